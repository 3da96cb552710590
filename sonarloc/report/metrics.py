"""Trajectory errors against ground truth."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class TrackError:
    """Errors of a pose track against truth at the track's times.

    ``rmse_m``: RMS of the position error; ``yaw_rmse_deg``: RMS of the wrapped heading
    error; ``max_m``: largest position error; ``final_m``: position error at the end;
    ``n``: poses compared.
    """

    rmse_m: float
    yaw_rmse_deg: float
    max_m: float
    final_m: float
    n: int


def track_error(track: NDArray[np.float64], truth: NDArray[np.float64],
                t_from_s: float = -math.inf) -> TrackError:
    """Errors of ``track`` (n, 4: t_s, x_m, y_m, yaw_rad) against ``truth`` (m, 4).

    Truth is interpolated linearly at the track's times (in x, y and unwrapped yaw);
    poses outside the truth's time span, or before ``t_from_s``, are not compared.
    """
    track = np.asarray(track, dtype=float).reshape(-1, 4)
    truth = np.asarray(truth, dtype=float).reshape(-1, 4)
    if len(truth) == 0 or len(track) == 0:
        return TrackError(math.nan, math.nan, math.nan, math.nan, 0)
    t = track[:, 0]
    use = (t >= truth[0, 0]) & (t <= truth[-1, 0]) & (t >= t_from_s)
    if not use.any():
        return TrackError(math.nan, math.nan, math.nan, math.nan, 0)
    tr, tt = track[use], t[use]
    yaw_truth = np.unwrap(truth[:, 3])
    tx = np.interp(tt, truth[:, 0], truth[:, 1])
    ty = np.interp(tt, truth[:, 0], truth[:, 2])
    tyaw = np.interp(tt, truth[:, 0], yaw_truth)
    d = np.hypot(tr[:, 1] - tx, tr[:, 2] - ty)
    dyaw = np.angle(np.exp(1j * (tr[:, 3] - tyaw)))
    return TrackError(float(np.sqrt(np.mean(d ** 2))),
                      float(np.degrees(np.sqrt(np.mean(dyaw ** 2)))),
                      float(d.max()), float(d[-1]), int(use.sum()))
