"""A sonar module that restarts mid-stream (power glitch, watchdog, firmware update):
its clock starts again from zero, and the host's log must not go back in time."""

from __future__ import annotations

import os
import random
import select
import time
import tty

import pytest
from io_streams import drain, ring_stream

from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.base import Wakeup
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.protocol.framing import START, STOP, SerialDecoder, SerialEncoder
from sonarloc.io.protocol.messages import RequestRig, Start, Stop
from sonarloc.io.protocol.records import ModuleClock, messages_from_record


def _times(recs: list) -> list[float]:
    """Times of the readings (odom, tof) among ``recs``."""
    return [r.t_s for r in recs if r.type in ("odom", "tof")]


@pytest.mark.parametrize("link", ["tcp", "can"])
def test_a_restarted_module_continues_the_log_in_time(link) -> None:
    # Before: the records after the restart went back to t = 0 (a 3 s TCP session, then
    # the module restarted: "time went backwards 594 times" in the recorded log).
    first = list(ring_stream(duration_s=2.0))
    second = list(ring_stream(duration_s=0.5, seed=3))
    channel = f"restart-{random.random()}"
    if link == "tcp":
        sim1 = SimModule.on_tcp(first, rate=20.0)
        port = sim1.transport.port  # type: ignore[attr-defined]
    else:
        sim1 = SimModule.on_can(first, channel=channel, rate=20.0)
    with sim1, open_driver(sim1.url, **({"backoff_s": (0.02, 0.1)} if link == "tcp" else {})) \
            as drv:
        t_start = time.monotonic()
        got1 = drain(sim1, drv, quiet_s=0.2)
        sim1.close()  # the module goes down ...
        time.sleep(0.3)
        # ... and comes back with its clock at zero (and its sequence numbers)
        sim2 = (SimModule.on_tcp(second, port=port, rate=20.0) if link == "tcp" else
                SimModule.on_can(second, channel=channel, rate=20.0, wait_for_start=False))
        with sim2:
            got2 = drain(sim2, drv, quiet_s=0.2)
        elapsed = time.monotonic() - t_start
        counters = drv.counters()
    t1, t2 = _times(got1), _times(got2)
    assert len(t1) == sum(r.type in ("odom", "tof") for r in first)
    assert len(t2) == sum(r.type in ("odom", "tof") for r in second)
    assert t1 == sorted(t1) and t2 == sorted(t2)
    # after the last reading, by the outage as the host saw it (>= the 0.3 s of sleep)
    assert t1[-1] + 0.3 < t2[0] < t1[-1] + elapsed
    offset = t2[0] - _times(second)[0]
    assert t2 == pytest.approx([t + offset for t in _times(second)], abs=2e-6)
    assert counters["module_restarts"] == 1
    assert "module restarts 1" in drv.summary()


def test_clock_tells_a_restart_from_readings_out_of_order() -> None:
    clk = ModuleClock()
    assert clk.unwrap(5_000_000, 100.0) == 5_000_000
    assert clk.unwrap(4_900_000, 100.01) == 4_900_000  # 0.1 s out of order: no restart
    assert clk.restarts == 0
    assert clk.unwrap(5_100_000, 100.02) == 5_100_000
    assert clk.unwrap(0, 102.02) == 7_100_000  # restarted: on by the host's 2 s
    assert clk.unwrap(1000, 102.03) == 7_101_000
    assert clk.restarts == 1
    assert clk.unwrap(3_000_000) == 10_100_000  # no host time: the same offset
    assert clk.pending  # a jump of 2.9 s: held until the next reading follows it
    assert clk.unwrap(3_001_000) == 10_101_000 and clk.verdict is True
    assert clk.unwrap(0) == 10_101_000  # restarted, no host time: continues at the last
    assert clk.pending and clk.restarts == 1  # (a restart counts once the next follows)
    assert clk.unwrap(1000) == 10_102_000
    assert clk.restarts == 2 and clk.spikes == 0
    clk = ModuleClock()  # the 32-bit wrap is not a restart
    assert clk.unwrap(0xFFFF_FF00) == 0xFFFF_FF00
    assert clk.unwrap(0x10) == (1 << 32) + 0x10 and clk.restarts == 0


def test_wakeup_rule_with_the_clock_given() -> None:
    # Start again only after wake_s without the module, every wake_s while it stays
    # silent, never after the host's Stop (until its Start).
    w = Wakeup(2.0, now=100.0)
    assert not w.due(101.9) and w.due(102.0)  # silent since the host opened
    w.heard(101.0)  # a healthy stream: every frame moves the deadline
    assert not w.due(102.9) and w.due(103.0)
    w.heard(102.5)
    w.heard(102.0)  # a late callback does not move it back
    assert not w.due(104.4) and w.due(104.5)
    w.sent(Start(), 104.5)  # the wake-up itself: the next one wake_s later
    assert not w.due(106.4) and w.due(106.5)
    w.sent(RequestRig(), 110.0)  # other commands change nothing
    assert w.due(110.0)
    w.sent(Stop(), 110.0)  # the host wants silence
    assert not w.due(1e9)
    w.sent(Start(), 200.0)
    assert not w.due(201.9) and w.due(202.0)
    assert not Wakeup(None, 0.0).due(1e9)
    with pytest.raises(ValueError, match="wake_s"):
        Wakeup(0.0, 0.0)


def test_a_restarted_can_module_that_waits_for_start_is_started_again() -> None:
    # The module restarts and waits for a host's Start, as at power-up, saying nothing:
    # a serial host reconnects and sends Start, a CAN host has no link to lose and never
    # did: the recording went dead. The wake-up repeats until the module is heard, so it
    # does not matter whether the first one comes before the new module listens.
    first = list(ring_stream(duration_s=2.0))
    second = list(ring_stream(duration_s=0.5, seed=3))
    channel = f"wake-{random.random()}"
    with SimModule.on_can(first, channel=channel, rate=20.0) as sim1, \
            open_driver(sim1.url, wake_s=0.2) as drv:
        got1 = drain(sim1, drv, quiet_s=0.1)
        sim1.close()
        with SimModule.on_can(second, channel=channel, rate=20.0) as sim2:  # waits for Start
            got2 = drain(sim2, drv, quiet_s=0.1, limit_s=10.0)
        counters = drv.counters()
    t1, t2 = _times(got1), _times(got2)
    assert len(t1) == len(_times(first)) and len(t2) == len(_times(second))
    assert t1 == sorted(t1) and t2 == sorted(t2) and t1[-1] < t2[0]  # time goes on
    assert counters["wakeups"] >= 1 and counters["module_restarts"] == 1
    assert sim2.stats.commands >= 2  # its Start (and RequestRig) came from the wake-up


def _commands(master: int, dec: SerialDecoder, until: int | None, wait_s: float) -> list[int]:
    """Types of the host's packets read from a pty's master side within ``wait_s``, up to
    and including the first of type ``until`` (None: all that come)."""
    end = time.monotonic() + wait_s
    out: list[int] = []
    while time.monotonic() < end:
        if select.select([master], [], [], 0.02)[0]:
            out += [f.type for f in dec.feed_frames(os.read(master, 4096))]
            if until is not None and until in out:
                return out
    return out


def test_a_module_reset_behind_an_open_serial_port_is_started_again() -> None:
    # A USB adapter stays plugged in while the module's processor resets: the host's port
    # never fails, so it never reconnected and never sent Start again.
    master, slave = os.openpty()
    tty.setraw(slave)
    enc, host = SerialEncoder(), SerialDecoder()
    try:
        with open_driver(os.ttyname(slave), wake_s=0.2) as drv:
            assert START in _commands(master, host, START, 5.0)  # on connect
            wire = b"".join(enc.encode(m) for r in ring_stream(duration_s=0.05)
                            for m in messages_from_record(r))
            os.write(master, wire)  # the module streams, then resets (silence)
            assert drv.read(2.0) is not None
            assert START in _commands(master, host, START, 5.0)  # the wake-up
            assert drv.counters()["wakeups"] >= 1
            drv.send(Stop())  # the host stops it: silence is wanted now
            _commands(master, host, STOP, 5.0)  # (a wake-up may come before the Stop)
            assert _commands(master, host, None, 0.6) == []  # three wake_s: nothing
            drv.send(Start())
    finally:
        os.close(slave)
        os.close(master)


def test_the_first_odometry_after_a_module_restart_is_a_reset() -> None:
    """A restarted module's odometry begins again (at zero): its first odom record is
    flagged ``reset`` (a new odometry frame), no other."""
    from sonarloc.io.protocol.messages import Echo, Odom
    from sonarloc.io.protocol.records import RecordAssembler

    asm = RecordAssembler()
    out = []
    host = 100.0
    for k in range(5):  # the module's first life: 0.1 s apart, driving along x
        out += asm.push(Odom(1_000_000 + 100_000 * k, 1000 * k, 0, 0), host + 0.1 * k)
    # restarted: its clock and its odometry start again at zero
    out += asm.push(Echo(0, 0, 100), host + 2.0)
    out += asm.push(Odom(10_000, 0, 0, 0), host + 2.01)
    out += asm.push(Odom(110_000, 1000, 0, 0), host + 2.11)
    out += asm.flush()
    odoms = [r for r in out if r.type == "odom"]
    assert [r.reset for r in odoms] == [False] * 5 + [True, False]
    assert asm.clock.restarts == 1
    assert odoms[5].x_m == 0.0 and odoms[5].t_s > odoms[4].t_s
