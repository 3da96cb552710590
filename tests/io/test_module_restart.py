"""A sonar module that restarts mid-stream (power glitch, watchdog, firmware update):
its clock starts again from zero, and the host's log must not go back in time."""

from __future__ import annotations

import random
import time

import pytest
from io_streams import drain, ring_stream

from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.protocol.records import ModuleClock


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
    assert clk.unwrap(0) == 10_100_000  # restarted, no host time: continues at the last
    assert clk.restarts == 2
    clk = ModuleClock()  # the 32-bit wrap is not a restart
    assert clk.unwrap(0xFFFF_FF00) == 0xFFFF_FF00
    assert clk.unwrap(0x10) == (1 << 32) + 0x10 and clk.restarts == 0
