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


def test_a_restarted_can_module_that_waits_for_start_is_started_again() -> None:
    # A module comes back from a restart waiting for the host's Start, as at power-up.
    # A serial host reconnects and sends it; a CAN host never did: the recording ended.
    first = list(ring_stream(duration_s=2.0))
    second = list(ring_stream(duration_s=0.5, seed=3))
    channel = f"wake-{random.random()}"
    with SimModule.on_can(first, channel=channel, rate=20.0) as sim1, \
            open_driver(sim1.url, wake_s=0.3) as drv:
        got1 = drain(sim1, drv, quiet_s=0.2)
        sim1.close()
        with SimModule.on_can(second, channel=channel, rate=20.0) as sim2:  # waits for Start
            got2 = drain(sim2, drv, quiet_s=0.2, limit_s=5.0)
        counters = drv.counters()
    assert len(_times(got1)) == len(_times(first))
    assert len(_times(got2)) == len(_times(second))
    assert counters["wakeups"] >= 1 and counters["module_restarts"] == 1


def test_a_silent_serial_module_is_sent_start_again() -> None:
    # The module's processor resets behind a USB adapter that stays plugged in: the
    # host's port never fails, so it never reconnected and never sent Start again.
    import os
    import tty

    from sonarloc.io.protocol.framing import START, SerialDecoder, SerialEncoder
    from sonarloc.io.protocol.messages import Start, Stop

    master, slave = os.openpty()
    tty.setraw(slave)
    host_side = SerialDecoder()

    def commands(wait_s: float) -> list[int]:
        import select
        end = time.monotonic() + wait_s
        out: list[int] = []
        while time.monotonic() < end and not out:
            if select.select([master], [], [], 0.05)[0]:
                out += [f.type for f in host_side.feed_frames(os.read(master, 4096))]
        return out

    try:
        with open_driver(os.ttyname(slave), wake_s=0.3) as drv:
            assert START in commands(1.0)  # on connect
            os.write(master, SerialEncoder().encode(Stop()))  # data, then the reset
            t = time.monotonic()
            assert START in commands(2.0)  # again, after 0.3 s of silence
            assert 0.25 < time.monotonic() - t < 1.5
            drv.send(Stop())  # the host stopped it: silence is wanted, no Start
            commands(0.1)
            assert commands(0.8) == []
            drv.send(Start())
            assert drv.counters()["wakeups"] >= 1
    finally:
        os.close(slave)
        os.close(master)
