"""Synthetic record streams for the driver tests (a 16-transducer ring or a panning head)."""

from __future__ import annotations

import math
from collections.abc import Iterator

from sonarloc.io.logfile import (
    InitRecord,
    OdomRecord,
    Record,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
)


def ring_rig() -> RigRecord:
    return RigRecord(tuple(SensorMount(i, 0.2 * math.cos(i * math.pi / 8),
                                       0.2 * math.sin(i * math.pi / 8), i * 22.5)
                           for i in range(16)))


def ring_stream(duration_s: float = 1.0, dt_s: float = 0.005, pan: bool = False,
                seed: int = 1) -> Iterator[Record]:
    """rig, init, then odom at 1/(4 dt), a ping every dt (every 7th without echo), truth."""
    yield ring_rig()
    yield InitRecord(0.0, 0.0, 0.0, 0.0, 0.05, 2.0)
    k = 0
    while k * dt_s <= duration_s:
        t = k * dt_s
        if k % 4 == 0:
            yield OdomRecord(t, 0.3 * t, 0.01 * t * t, 10.0 * t - 5.0)
            yield TruthRecord(t, 0.3 * t, 0.0, 10.0 * t)
        tof = None if k % 7 == 3 else 3000.0 + 37.3 * ((k * seed) % 101)
        yield TofRecord(t, k % 16, tof, (-40.0 + (k % 161) * 0.5) if pan else None)
        k += 1


def device_records(stream: list[Record]) -> list[Record]:
    """The records a module sends (no init/truth)."""
    return [r for r in stream if r.type in ("rig", "odom", "tof")]


def drain(sim, drv, quiet_s: float = 1.0, limit_s: float = 30.0) -> list:
    """Everything a driver delivers until the module has finished and the line is quiet."""
    import time

    from sonarloc.errors import DeviceTimeoutError

    got: list = []
    end = time.monotonic() + limit_s
    quiet_since = None
    while time.monotonic() < end:
        try:
            rec = drv.read(timeout=0.05)
        except DeviceTimeoutError:
            if not sim.wait(0):
                continue
            now = time.monotonic()
            quiet_since = quiet_since or now
            if now - quiet_since >= quiet_s:
                return got
            continue
        if rec is None:
            return got
        quiet_since = None
        got.append(rec)
    raise AssertionError(f"stream did not end within {limit_s} s ({len(got)} records)")
