"""Odometry error inside a segment: its share of a landmark's covariance.

A segment taken while the robot moves is fitted with the transducer poses that odometry
gives, relative to the segment's reference (last-echo) pose. Those relative poses are
not exact: over the path driven within the segment the odometry's heading drifts
(unequal wheel scale, wheel noise), so earlier readings sit on a slightly bent path
and look along slightly wrong axes. The fit's own covariance (TOF jitter, detection)
does not know this; for walls seen over a metre of driving the error it causes is
several times the jitter's (benchmarks/results/fit_quality.md).

Model: an unknown path-curvature error ``c`` [rad/m], constant over the segment, with
SD ``curvature_sd_deg_per_m``. A reading at chord distance ``d_i`` from the reference
position then has its heading off by ``c d_i`` and its position rotated about the
reference by ``c d_i / 2`` (the arc's chord turns by half the arc's angle). The fit's
sensitivity ``s = d params / d c`` is the implicit-function derivative of its optimum,
``s = -H^-1 dg/dc``: ``H`` the Fisher matrix at the fit, ``dg/dc`` the change of the
objective's gradient there when the poses are bent by a small ``c`` (two evaluations of
the fit's own objective, batched, no refit); ``s s^T sigma_c^2`` is added to the
covariance. (Until session 9 ``s`` came from refitting the bent segments from the fit:
that refit stops as soon as its Newton decrement is below the fit's tolerance, which a
bend small enough to be linear often is at once, so ``s`` was 0 for ~1 in 12 moving
segments and off by up to ~8x for others; the derivative is within ~10 % of a tightly
converged central difference for most, docs/FITTING.md, at ~1/9 of the cost.)

The default ``sigma_c`` is calibrated on the world simulator's default odometry (0.2 %
wheel-scale difference, 3 mm/sqrt(m) wheel noise, 0.4 m wheelbase: 0.3 deg/m systematic
drift, ~0.6 deg/sqrt(m) random): reported SD / actual error of walls from a ring16 drive
near 1 (bench_fit_quality, part 4; one short segment's range is the exception, where the
random heading walk outweighs the curvature). For poses that
are exact (simulator truth, a stationary pan) use 0; a pan has no motion and gets
nothing anyway.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit.lsq import BatchFit, FitConfig, SegmentBatch, _covariance, _evaluate_s2, _take

Array = NDArray[np.float64]

CURVATURE_SD_DEG_PER_M = 1.0
"""Default SD of the odometry's path-curvature error within a segment [deg/m]."""

_EPS = 1e-3   # rad/m: the bend of the finite difference dg/dc (linear regime)


def bend(batch: SegmentBatch, c: float) -> SegmentBatch:
    """The batch with every reading's pose relative to its reference bent by curvature
    error ``c`` [rad/m] (heading ``c d``, position rotated by ``c d / 2``)."""
    def one(px: Array, py: Array, yaw: Array) -> tuple[Array, Array, Array]:
        d = np.hypot(px, py)
        a = 0.5 * c * d
        ca, sa = np.cos(a), np.sin(a)
        return px * ca - py * sa, px * sa + py * ca, yaw + c * d

    px, py, yaw = one(batch.px, batch.py, batch.yaw)
    npx, npy, nyaw = one(batch.ne_px, batch.ne_py, batch.ne_yaw)
    return SegmentBatch(px, py, yaw, batch.tof_us, batch.valid, npx, npy, nyaw,
                        batch.ne_valid, batch.ref_xy, batch.ref_yaw, batch.ref_t_s)


def odometry_covariance(batch: SegmentBatch, fit: BatchFit, cfg: FitConfig,
                        curvature_sd_deg_per_m: float = CURVATURE_SD_DEG_PER_M) -> Array:
    """Covariance (B, 3, 3) of the local ``(r, phi, kappa)`` from odometry curvature error.

    ``fit``: the segments' fits (one kind and tier). Zero for segments without motion or
    when ``curvature_sd_deg_per_m`` is 0.
    """
    B = batch.size
    out = np.zeros((B, 3, 3))
    sd = math.radians(curvature_sd_deg_per_m)
    if sd <= 0.0 or B == 0:
        return out
    moving = np.flatnonzero(np.max(np.hypot(batch.px, batch.py) * batch.valid, axis=1) > 0.02)
    if moving.size == 0:
        return out
    sub = _take(batch, moving)
    fit = fit.take(moving)
    # the objective the fit minimised (its echoes, and the detection terms unless the
    # method is one of the echoes-only ones; see lsq._refine_any)
    c = cfg if cfg.method == "full" else replace(cfg, detection=False)
    y = np.where(fit.used, sub.tof_us - 0.5 * cfg.module.count_period_us, 0.0)
    _, g0, H, _, _ = _evaluate_s2(fit.kind, fit.tier, fit.local, sub, y, fit.used, None, c)
    _, g1, _, _, _ = _evaluate_s2(fit.kind, fit.tier, fit.local, bend(sub, _EPS), y, fit.used,
                                  None, c)
    s = -np.einsum("bij,bj->bi", _covariance(H), g1 - g0) / _EPS
    s = np.where(np.isfinite(s), s, 0.0)
    out[moving] = sd * sd * s[:, :, None] * s[:, None, :]
    return out
