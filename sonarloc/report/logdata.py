"""A log JSONL (FORMATS.md section 4) as arrays, for reports and plots.

Holds a whole log in memory (reports and plots look at all of it); streaming consumers
should use :func:`sonarloc.io.logfile.iter_log` directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from sonarloc.errors import LogFormatError
from sonarloc.io.logfile import (
    InitRecord,
    LogStats,
    OdomRecord,
    RigRecord,
    TofRecord,
    TruthRecord,
    iter_log,
)


@dataclass(frozen=True)
class LogData:
    """Arrays of a log: poses are (n, 4) (t_s, x_m, y_m, yaw_rad), yaw unwrapped.

    ``tof``: (m, 4) (t_s, sensor, tof_us or NaN for no echo, pan_rad or 0).
    """

    rig: RigRecord
    init: InitRecord | None
    odom: NDArray[np.float64]
    truth: NDArray[np.float64]
    tof: NDArray[np.float64]
    stats: LogStats

    @property
    def has_truth(self) -> bool:
        return len(self.truth) > 0

    def mounts(self) -> dict[int, tuple[float, float, float]]:
        """Sensor id -> mount (x_m, y_m, yaw_rad) in base_link."""
        return {s.id: (s.x_m, s.y_m, math.radians(s.yaw_deg)) for s in self.rig.sensors}


def _poses(rows: list[tuple[float, float, float, float]]) -> NDArray[np.float64]:
    a = np.array(rows, dtype=float).reshape(-1, 4)
    if len(a):
        a[:, 3] = np.unwrap(a[:, 3])
    return a


def load_log(source: str | Path | IO[str]) -> LogData:
    """Read a whole log; the first record must be ``rig``."""
    stats = LogStats()
    rig: RigRecord | None = None
    init: InitRecord | None = None
    odom: list[tuple[float, float, float, float]] = []
    truth: list[tuple[float, float, float, float]] = []
    tof: list[tuple[float, float, float, float]] = []
    for rec in iter_log(source, stats):
        if isinstance(rec, TofRecord):
            tof.append((rec.t_s, rec.sensor, math.nan if rec.tof_us is None else rec.tof_us,
                        math.radians(rec.pan_deg) if rec.pan_deg is not None else 0.0))
        elif isinstance(rec, OdomRecord):
            odom.append((rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg)))
        elif isinstance(rec, TruthRecord):
            truth.append((rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg)))
        elif isinstance(rec, InitRecord):
            init = init or rec
        elif isinstance(rec, RigRecord):
            rig = rig or rec
    if rig is None:
        raise LogFormatError(f"log {source if isinstance(source, (str, Path)) else ''} has no "
                             f"`rig` record ({stats.summary()})")
    return LogData(rig, init, _poses(odom), _poses(truth),
                   np.array(tof, dtype=float).reshape(-1, 4), stats)


def interpolate_track(track: NDArray[np.float64], t_s: NDArray[np.float64]
                      ) -> NDArray[np.float64]:
    """(m, 3) poses (x_m, y_m, yaw_rad) of a (n, 4) track at times ``t_s`` (clamped)."""
    t = np.asarray(t_s, dtype=float)
    if len(track) == 0:
        return np.full((len(t), 3), np.nan)
    return np.stack([np.interp(t, track[:, 0], track[:, i]) for i in (1, 2, 3)], -1)


def compose(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """a ⊕ b over (..., 3) planar poses (x, y, yaw): b given in a's frame."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1],
                     a[..., 1] + s * b[..., 0] + c * b[..., 1], a[..., 2] + b[..., 2]], -1)


def inverse(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """a⁻¹ over (..., 3) planar poses."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1],
                     -a[..., 2]], -1)


def transducer_poses(data: LogData, robot: NDArray[np.float64]) -> NDArray[np.float64]:
    """(m, 3) transducer poses of every tof reading, given robot poses (n, 4) in some frame.

    The robot pose is interpolated at each ping; the mount (and pan angle) is composed on.
    Readings of sensors missing from the rig are NaN.
    """
    mounts = data.mounts()
    sid = data.tof[:, 1].astype(int)
    m = np.array([mounts.get(int(i), (np.nan, np.nan, np.nan)) for i in sid],
                 dtype=float).reshape(-1, 3)
    m[:, 2] += data.tof[:, 3]
    return compose(interpolate_track(robot, data.tof[:, 0]), m)


def odometry_in_map(data: LogData) -> NDArray[np.float64]:
    """The odometry track moved into ``map`` so that it starts at the prior (or truth).

    Uses the ``init`` record, else the first truth pose; unchanged when neither exists.
    """
    if len(data.odom) == 0:
        return data.odom
    if data.init is not None:
        start = np.array([data.init.x_m, data.init.y_m, math.radians(data.init.yaw_deg)])
    elif data.has_truth:
        start = interpolate_track(data.truth, data.odom[:1, 0])[0]
    else:
        return data.odom
    T = compose(start, inverse(data.odom[0, 1:]))
    out = data.odom.copy()
    out[:, 1:] = compose(np.broadcast_to(T, (len(out), 3)), data.odom[:, 1:])
    return out
