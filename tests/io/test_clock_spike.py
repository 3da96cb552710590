"""One reading with a wrong time (a corrupted or spiked clock value) must cost that reading,
not shift the rest of the log; a real jump of the module's clock is still followed."""

from __future__ import annotations

import dataclasses

import pytest
from io_streams import drain, ring_stream

from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.logfile import OdomRecord, Record, TofRecord
from sonarloc.io.protocol.records import ModuleClock, RecordAssembler, messages_from_record


def _readings(recs: list) -> list[Record]:
    return [r for r in recs if r.type in ("odom", "tof")]


def test_clock_drops_a_spike_and_follows_a_jump() -> None:
    clk = ModuleClock()
    for k in range(3):
        assert clk.unwrap(10_000_000 + k * 1000) == 10_000_000 + k * 1000
    # one reading 10 min ahead, the next back on time: that one alone was wrong
    assert clk.unwrap(610_003_000) == 610_003_000 and clk.pending
    assert clk.unwrap(10_004_000) == 10_004_000
    assert clk.verdict is False and clk.spikes == 1 and not clk.pending
    # 1 h ahead: beyond half the 32-bit wrap, it looks like a step back of 11.6 min
    assert clk.unwrap((10_005_000 + 3_600_000_000) % (1 << 32)) and clk.pending
    assert clk.unwrap(10_006_000) == 10_006_000 and clk.spikes == 2 and clk.restarts == 0
    # a step back (a restart's zero) with the next reading back on time: also a spike
    clk.unwrap(5_000)
    assert clk.unwrap(10_007_000) == 10_007_000 and clk.spikes == 3 and clk.restarts == 0
    # the module's clock really moved on 10 min: the next reading follows, both are kept
    assert clk.unwrap(610_008_000) == 610_008_000 and clk.pending
    assert clk.unwrap(610_009_000) == 610_009_000 and clk.verdict is True
    assert clk.spikes == 3 and clk.restarts == 0
    # within 1 s either way: readings slightly out of order, placed at once
    assert clk.unwrap(609_100_000) == 609_100_000 and not clk.pending
    # a jump at the end of the stream: nothing contradicts it, it is kept
    clk.unwrap(700_000_000)
    assert clk.flush() is True and clk.last == 700_000_000 and clk.flush() is None


def test_assembler_holds_a_jumped_reading_until_the_next_one() -> None:
    asm = RecordAssembler()

    def push(rec: Record) -> list[Record]:
        return [r for m in messages_from_record(rec) for r in asm.push(m)]

    a, b = TofRecord(1.0, 0, 100.0), OdomRecord(1.01, 0.5, 0.0, 0.0)
    assert push(a) == [a] and push(b) == [b]
    assert push(TofRecord(3601.02, 1, 200.0)) == []  # held back
    c = TofRecord(1.03, 2, 300.0)
    assert push(c) == [c] and asm.clock.spikes == 1  # the spike is gone, c comes at once
    d, e = TofRecord(601.04, 3, 400.0), TofRecord(601.05, 4, 500.0)
    assert push(d) == [] and push(e) == [d, e]  # a real jump: held, then both in order
    f = TofRecord(1200.0, 5, 600.0)
    assert push(f) == [] and asm.flush() == [f] and asm.flush() == []


def _spiked(spike_s: float, genuine: bool) -> tuple[list[Record], list[float]]:
    """ring_stream with the reading at 1 s moved by ``spike_s`` (``genuine``: it and every
    later record), and the times a host should log (without the spiked reading)."""
    recs = list(ring_stream(duration_s=2.0))
    k = next(i for i, r in enumerate(recs) if r.type == "tof" and r.t_s >= 1.0)
    if genuine:
        recs[k:] = [dataclasses.replace(r, t_s=r.t_s + spike_s) for r in recs[k:]]
        want = [r.t_s for r in _readings(recs)]
    else:
        want = [r.t_s for r in _readings(recs[:k] + recs[k + 1:])]
        recs[k] = dataclasses.replace(recs[k], t_s=recs[k].t_s + spike_s)
    return recs, want


@pytest.mark.parametrize("link", ["tcp", "candump"])
@pytest.mark.parametrize(("spike_s", "genuine"), [(3600.0, False), (600.0, False),
                                                  (-600.0, False), (600.0, True)])
def test_one_spiked_time_costs_one_reading(link, spike_s, genuine, tmp_path) -> None:
    # Before: every reading after a spike of +1 h, +10 min or -10 min was shifted (250
    # of 502, by 695 s or 600 s) and a module restart counted; now the spiked reading
    # alone is dropped and counted, and a real jump of the clock is still followed.
    recs, want = _spiked(spike_s, genuine)
    if link == "tcp":
        with SimModule.on_tcp(recs, rate=None) as sim, open_driver(sim.url) as drv:
            got = drain(sim, drv, quiet_s=0.2)
            counters = drv.counters()
    else:
        path = tmp_path / "spiked.log"
        SimModule.to_candump(recs, path).run()
        with open_driver(f"candump:{path}") as drv:
            got = list(drv.records(timeout=2.0))
            counters = drv.counters()
    assert [r.t_s for r in _readings(got)] == pytest.approx(want, abs=1e-6)
    assert counters["clock_spikes"] == (0 if genuine else 1)
    assert counters["module_restarts"] == 0
