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
covariance. (Not a refit of the bent segments: that refit stops as soon as its Newton
decrement is below the fit's tolerance, which a bend small enough to be linear often is
at once, so ``s`` came out 0 for ~1 in 12 moving segments and off by up to ~8x for
others; the derivative is within ~10 % of a tightly converged central difference for
most, docs/FITTING.md, at ~1/9 of the cost.)

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
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit import model as M
from sonarloc.fit.lsq import (
    BatchFit,
    FitConfig,
    SegmentBatch,
    _covariance,
    _evaluate_s2,
    _solve_pivoted,
    _take,
    tof_jacobian_at,
)
from sonarloc.fit.select import runs_z

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
    return _curvature_share(batch, fit, cfg, curvature_sd_deg_per_m)[0]


def odometry_terms(batch: SegmentBatch, fit: BatchFit, travel: Array, cfg: FitConfig,
                   curvature_sd_deg_per_m: float = CURVATURE_SD_DEG_PER_M, arm_m: float = 0.0
                   ) -> tuple[Array, Array, Array, Array]:
    """:func:`odometry_covariance` and :func:`odometry_chi2` (its chi-square, covariance
    and runs statistic) of the same fits, the Fisher matrix at the fit evaluated once
    for both."""
    cov, fisher = _curvature_share(batch, fit, cfg, curvature_sd_deg_per_m)
    chi2, walk, runs = odometry_chi2(batch, fit, travel, cfg, curvature_sd_deg_per_m, fisher,
                                     arm_m)
    return cov, chi2, walk, runs


def _curvature_share(batch: SegmentBatch, fit: BatchFit, cfg: FitConfig,
                     curvature_sd_deg_per_m: float) -> tuple[Array, Array]:
    """:func:`odometry_covariance` and the Fisher matrix (B, 3, 3) at the fit of the
    moving segments it evaluated (zero for the others)."""
    B = batch.size
    out = np.zeros((B, 3, 3))
    fisher = np.zeros((B, 3, 3))
    sd = math.radians(curvature_sd_deg_per_m)
    if sd <= 0.0 or B == 0:
        return out, fisher
    moving = np.flatnonzero(np.max(np.hypot(batch.px, batch.py) * batch.valid, axis=1) > 0.02)
    if moving.size == 0:
        return out, fisher
    c = _objective(cfg)
    for rows, sub in _by_width(batch, moving):
        wd = sub.valid.shape[1]
        used = fit.used[rows, :wd]
        y = np.where(used, sub.tof_us - 0.5 * cfg.module.count_period_us, 0.0)
        p = fit.local[rows]
        _, g0, H, _, _ = _evaluate_s2(fit.kind, fit.tier, p, sub, y, used, None, c)
        _, g1, _, _, _ = _evaluate_s2(fit.kind, fit.tier, p, bend(sub, _EPS), y, used, None, c)
        s = -np.einsum("bij,bj->bi", _covariance(H), g1 - g0) / _EPS
        s = np.where(np.isfinite(s), s, 0.0)
        out[rows] = sd * sd * s[:, :, None] * s[:, None, :]
        fisher[rows] = H
    return out, fisher


PROFILE_CHUNK = 64
"""Segments per chunk of the odometry terms (:func:`_by_width`)."""


def _by_width(batch: SegmentBatch, rows: NDArray[np.int64]
              ) -> Iterator[tuple[NDArray[np.int64], SegmentBatch]]:
    """Segments ``rows`` of ``batch`` in chunks of :data:`PROFILE_CHUNK` of similar
    widths, each chunk with its segments cut to its widest (echo and no-echo columns):
    the odometry terms' arrays are (b, ..., Nd), most segments far narrower than a
    batch's widest (a moving ring's 300 s drive: 23,000 echoes in 563 segments padded
    to 300 columns)."""
    def extent(mask: NDArray[np.bool_]) -> NDArray[np.int64]:
        """Columns up to each row's last true one (no-echo columns may have holes)."""
        if mask.shape[1] == 0:
            return np.zeros(mask.shape[0], dtype=np.int64)
        return np.where(mask.any(1), mask.shape[1] - np.argmax(mask[:, ::-1], axis=1), 0)

    wd_all, wn_all = extent(batch.valid[rows]), extent(batch.ne_valid[rows])
    order = np.argsort(wd_all + wn_all, kind="stable")
    for k in range(0, order.size, PROFILE_CHUNK):
        j = order[k:k + PROFILE_CHUNK]
        yield rows[j], _take(batch, rows[j], max(int(wd_all[j].max()), 1),
                             int(wn_all[j].max()))


def _objective(cfg: FitConfig) -> FitConfig:
    """The settings of the objective the fit minimised (its echoes, and the detection
    terms unless the method is one of the echoes-only ones; see lsq._refine_any), in
    float64: the curvature's share is a difference of two gradients over a small bend,
    which a float32 pass's rounding (~1e-6 of the terms) would move by ~1e-5 (and with
    it, by the batch's padding, a segment's share with the batch it sits in)."""
    return replace(cfg, float32=False,
                   detection=cfg.detection and cfg.method == "full")


# --- the odometry's random pose error: the status test and the covariance -----------

WHEEL_NOISE_M_PER_SQRT_M = 0.003
"""Wheel-travel noise of the simulator's default odometry [m/sqrt(m) per wheel]
(:class:`sonarloc.world.robot.OdometryModel`)."""

WHEELBASE_M = 0.4
"""Wheelbase of the simulator's default drive [m] (:class:`sonarloc.world.robot.DriveParams`)."""

HEADING_WALK_RAD2_PER_M = 2.0 * WHEEL_NOISE_M_PER_SQRT_M ** 2 / WHEELBASE_M ** 2
"""Heading random walk of that odometry [rad^2 per m of travel]: the two wheels' travel
errors are independent, the heading error their difference over the wheelbase (about
(0.61 deg)^2 per metre)."""

ALONG_WALK_M2_PER_M = WHEEL_NOISE_M_PER_SQRT_M ** 2 / 2.0
"""Along-track random walk of that odometry [m^2 per m of travel]: the mean of the two
wheels' travel errors (about (2.1 mm)^2 per metre)."""

WALK_TERMS = 10
"""Terms of each random walk's Karhunen-Loeve expansion (the first four carry 95 % of a
Brownian path's variance at its end, ten 98 %; the path's shape in between needs more:
on a moving ring's 300 s drive, benchmarks/bench_fit.py section 4, 4 -> 10 terms left
118 -> 106 segments ``UNRESOLVED``; 24 terms gained one more)."""


def travel_from_start(seg: NDArray[np.int64], t_s: Array, x_m: Array, y_m: Array,
                        sensor: NDArray[np.int64], n_segments: int) -> Array:
    """Distance travelled [m] from each segment's first reading to each reading (flat
    readings sorted by segment, each segment in time order).

    Odometry errors grow with the distance the wheels travelled, not with the chord
    to the reference (a segment of a ring's drive may span a turn, its path several
    times its chord). A ring's consecutive readings come from transducers whose mounts
    differ, so the travel is the segment's mean speed (each transducer's path between
    its own consecutive readings, over their time) times the time from its start."""
    order = np.lexsort((t_s, sensor, seg))
    same = (seg[order][1:] == seg[order][:-1]) & (sensor[order][1:] == sensor[order][:-1])
    step = np.hypot(np.diff(x_m[order]), np.diff(y_m[order]))
    dt = np.diff(t_s[order])
    s_seg = seg[order][1:][same]
    dist = np.bincount(s_seg, step[same], minlength=n_segments)
    time = np.bincount(s_seg, dt[same], minlength=n_segments)
    speed = np.where(time > 0.0, dist / np.maximum(time, 1e-12), 0.0)
    start = np.full(n_segments, np.inf)
    np.minimum.at(start, seg, t_s)
    return speed[seg] * (t_s - start[seg])


def ring_arm(t_s: Array, x_m: Array, y_m: Array, yaw_rad: Array, sensor: NDArray[np.int64]
             ) -> float:
    """How far behind its transducers [m] the robot's centre lies, from readings of
    different transducers taken at the same time (a ring firing several at once): the
    least-squares distance along their axes to a common point; 0 without such readings
    (one transducer: its lever arm shows only through rotation)."""
    order = np.lexsort((sensor, t_s))
    t, k = t_s[order], sensor[order]
    pair = np.flatnonzero((t[1:] == t[:-1]) & (k[1:] != k[:-1]))
    if pair.size == 0:
        return 0.0
    a, b = order[pair], order[pair + 1]
    dux = np.cos(yaw_rad[a]) - np.cos(yaw_rad[b])
    duy = np.sin(yaw_rad[a]) - np.sin(yaw_rad[b])
    den = float(np.sum(dux * dux + duy * duy))
    if den < 1e-9:
        return 0.0
    arm = float(np.sum((x_m[a] - x_m[b]) * dux + (y_m[a] - y_m[b]) * duy)) / den
    return arm if math.isfinite(arm) and arm > 0.0 else 0.0


def _walk_modes(s: Array, length: Array, n: int) -> tuple[Array, Array]:
    """The first ``n`` modes of a unit-intensity Brownian path on [0, length] started at 0
    (Karhunen-Loeve), each (b, n, Nd): their values at ``s`` (b, Nd) and their
    derivatives by ``s`` (``length`` (b, 1))."""
    half = (np.arange(n) + 0.5)[None, :, None] * math.pi
    ws = half * (s / length)[:, None, :]
    amp = np.sqrt(2.0 * length)[:, :, None] / half
    return amp * np.sin(ws), np.sqrt(2.0 / length)[:, :, None] * np.cos(ws)


def odometry_chi2(batch: SegmentBatch, fit: BatchFit, travel: Array, cfg: FitConfig,
                  curvature_sd_deg_per_m: float = CURVATURE_SD_DEG_PER_M,
                  fisher: Array | None = None, arm_m: float = 0.0
                  ) -> tuple[Array, Array, Array]:
    """TOF chi-square of moving segments with the odometry's pose error profiled out (B,),
    the random walks' share of the covariance of the local ``(r, phi, kappa)``
    (B, 3, 3) and the runs statistic of the residuals left (B,; NaN where not moving).

    ``travel`` (B, Nd): distance travelled from each echo to the reference (from
    :func:`travel_from_start`). Relative to the reference, odometry bends the path by a
    heading error growing along it. Model: a constant curvature error (SD
    ``curvature_sd_deg_per_m``, as in :func:`odometry_covariance`) plus random walks of
    the heading and of the distance driven, with the intensities of the world
    simulator's default odometry (:data:`HEADING_WALK_RAD2_PER_M`,
    :data:`ALONG_WALK_M2_PER_M`: derived from its wheel noise and wheelbase, not fitted
    to any result) times ``(curvature_sd_deg_per_m / CURVATURE_SD_DEG_PER_M)^2``, so 0
    means exact poses. A reading's heading is off by the heading error where it was
    taken; its position by the path from it on to the reference (the robot's centre,
    ``arm_m`` behind each transducer: :func:`ring_arm`), each element turned by the
    heading error there and stretched by the distance's, plus its lever arm turned
    (:class:`_Path`; not the chord to the reference turned by the mean heading error
    and stretched along itself: that is exact for a straight path only, and a ring's
    segments turn by 20-180 deg). Each walk is expanded in :data:`WALK_TERMS`
    Karhunen-Loeve modes with standard-normal weights.

    With ``A`` the whitened TOF sensitivities to the weights (the model's pose
    Jacobian at the fit) and ``J`` the fit's whitened TOF Jacobian, the chi-square
    returned is the fit's less the drop of ``min ||e - J^T dp - A^T w||^2 + ||w||^2``
    when the weights ``w`` join the parameter step ``dp`` (``e`` the standardised
    residuals; linearised at the fit): what is left when the path may bend as the
    odometry's error does. The correlated walk, not the constant curvature, is most of
    the misfit of a single reflector seen over a metre or more (docs/FITTING.md).

    The walks also move the fit: ``S = H^-1 J A^T``, ``H`` the Fisher matrix of the
    objective the fit minimised (as in :func:`odometry_covariance`), adds ``S S^T`` to
    the covariance (the curvature's weight left out: that share is
    :func:`odometry_covariance`'s). Segments without motion keep ``fit.chi2`` and get no
    share. ``fisher``: that Fisher matrix (B, 3, 3) where known (:func:`odometry_terms`),
    else evaluated here.
    """
    chi2 = fit.chi2.copy()
    out_cov = np.zeros((batch.size, 3, 3))
    runs = np.full(batch.size, np.nan)
    sd = math.radians(curvature_sd_deg_per_m)
    if sd <= 0.0 or batch.size == 0:
        return chi2, out_cov, runs
    used = fit.used
    moving = np.flatnonzero(np.max(np.hypot(batch.px, batch.py) * used, axis=1) > 0.02)
    if moving.size == 0:
        return chi2, out_cov, runs
    scale = sd / math.radians(CURVATURE_SD_DEG_PER_M)
    for rows, sub in _by_width(batch, moving):
        wd = sub.valid.shape[1]
        c2, cv, z = _walk_profile(fit, rows, cfg, None if fisher is None else fisher[rows],
                                  _Path(sub, travel[rows, :wd], arm_m, scale, sd))
        good = np.isfinite(c2) & np.all(np.isfinite(cv), axis=(1, 2))
        chi2[rows[good]] = np.maximum(c2[good], 0.0)
        out_cov[rows[good]] = cv[good]
        runs[rows[good]] = z[good]
    return chi2, out_cov, runs


def _walk_profile(fit: BatchFit, rows: NDArray[np.int64], cfg: FitConfig,
                  fisher: Array | None, path: _Path) -> tuple[Array, Array, Array]:
    """:func:`odometry_chi2` of segments ``rows`` (``path`` of theirs, cut to their
    widest: :func:`_by_width`): the chi-square, the walks' covariance and the runs
    statistic."""
    sub = path.sub
    wd = sub.valid.shape[1]
    used = fit.used[rows, :wd]
    u = used.astype(float)
    e = fit.resid[rows, :wd] * u
    p = fit.local[rows]
    geo, G = _system(fit.kind, fit.tier, p, sub, u, path, cfg)
    N = _normal(G)
    b = np.matmul(G, e[:, :, None])[..., 0]
    step = _solve_pivoted(N, b)
    # the chi-square's drop when the weights join the fit's parameters (the fit's own
    # linear step, which the detection terms and kappa's prior kept it from, taken out)
    alone = np.einsum("bi,bi->b", b[:, :3], _solve_pivoted(N[:, :3, :3], b[:, :3]))
    left_chi2 = fit.chi2[rows] - np.einsum("bi,bi->b", b, step) + alone
    left = (e - np.matmul(step[:, None, :], G)[:, 0]) * u
    # the fit's linear response to the walks' weights, -H^-1 dg (H the Fisher matrix of
    # the objective it minimised, as in odometry_covariance; not the curvature's weight:
    # that share is odometry_covariance's)
    if fisher is None:
        y = np.where(used, sub.tof_us - 0.5 * cfg.module.count_period_us, 0.0)
        _, _, H, _, _ = _evaluate_s2(fit.kind, fit.tier, p, sub, y, used, None,
                                     _objective(cfg))
    else:   # :func:`_curvature_share`'s (its moving segments include these)
        H = fisher
    S = np.einsum("bij,bjk->bik", _covariance(H), N[:, :3, 4:])     # (b, 3, m - 1)
    cov = np.einsum("bik,bjk->bij", S, S)
    # the runs statistic of the residuals left when the path may bend so, in order of the
    # off-axis angle as the fit's own runs test reads them (select.overlap_check): the
    # walk itself puts a moving segment's residuals in blocks
    order = np.argsort(np.where(u > 0.0, geo.theta, np.inf), axis=1)
    z = runs_z(np.take_along_axis(left > 0.0, order, axis=1), used.sum(1))
    return left_chi2, cov, z


class _Path:
    """The odometry's error fields along the path of segments' echoes (time order, up to
    the reference, the last echo), one per weight of the profile: ``heads`` (b, 1 + K,
    Nd) heading errors (0 at the reference) of the constant curvature and of the
    heading's random walk, ``rates`` (b, K, Nd) rates at which the distance driven is off
    (per metre) of the distance's walk (K = :data:`WALK_TERMS`); and the path itself:
    the robot's centre (``arm_m`` behind each transducer) and its elements between
    consecutive echoes."""

    def __init__(self, sub: SegmentBatch, travel: Array, arm_m: float, scale: float,
                 sd: float) -> None:
        self.sub = sub
        valid = sub.valid
        s = np.maximum(travel, np.hypot(sub.px, sub.py)) * valid
        length = np.maximum(np.max(s, axis=1, keepdims=True), 1e-9)
        qh = math.sqrt(HEADING_WALK_RAD2_PER_M) * scale
        qa = math.sqrt(ALONG_WALK_M2_PER_M) * scale
        # the walks' modes: the heading's values, the distance's derivatives
        val, rate = _walk_modes(s, length, WALK_TERMS)
        self.heads = np.concatenate([(sd * s)[:, None, :], qh * val], axis=1)
        self.rates = qa * rate
        self.lever = (arm_m * np.cos(sub.yaw), arm_m * np.sin(sub.yaw))
        self.steps = tuple(np.where(valid[:, 1:], np.diff(q - lq, axis=1), 0.0)[:, None, :]
                           for q, lq in zip((sub.px, sub.py), self.lever, strict=True))

    def onward(self, f: Array) -> tuple[Array, Array]:
        """Sums over the path's elements from each echo on to the reference of ``f`` (at
        the elements' middles; (b, m, Nd)) times the element."""
        fm = 0.5 * (f[..., :-1] + f[..., 1:])
        out = []
        for st in self.steps:
            g = fm * st
            v = np.zeros(f.shape)
            v[..., :-1] = g.sum(-1, keepdims=True) - np.cumsum(g, axis=-1) + g
            out.append(v)
        return out[0], out[1]

    def turned(self) -> tuple[Array, Array]:
        """Each echo's position error (linear) from each heading error field: the path on
        to the reference turned by it, and the lever arm turned."""
        hx, hy = self.onward(self.heads)
        lx, ly = (q[:, None, :] for q in self.lever)
        return hy - self.heads * ly, -hx + self.heads * lx

    def stretched(self) -> tuple[Array, Array]:
        """Each echo's position error (linear) from each distance rate field: the
        centre's path on to the reference stretched by it."""
        ax, ay = self.onward(self.rates)
        return -ax, -ay


def _system(kind: str, tier: str, p: Array, sub: SegmentBatch, u: Array, path: _Path,
            cfg: FitConfig) -> tuple[M.Geometry, Array]:
    """The geometry at the fits ``p`` (at the poses of ``sub``) and the whitened TOF
    sensitivities (b, 3 + m, Nd) to the parameters and to the weights of ``path``'s
    error fields, the curvature's first (the model's pose Jacobian times the fields'
    pose errors), used echoes only."""
    mod = cfg.module
    tau = M.us_per_m(mod)
    r, phi, K = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    geo = M.geometry(kind, r, phi, sub.px, sub.py, sub.yaw, moving=True)
    g, dg, lng = M.beam_delay_factor(geo.theta, tier, mod)
    z = M.detection_z(K, lng, mod) if cfg.detection else None
    J, et, tof_sd = tof_jacobian_at(geo, K, g, dg, z, tier, mod)
    a = et.ddelay_du * K * dg                         # d mean TOF / d theta
    # pose Jacobian of the mean TOF (whitened, used echoes only)
    c, s = np.cos(phi), np.sin(phi)
    if kind == "line":
        dx, dy = -tau * c + 0.0 * sub.px, -tau * s + 0.0 * sub.py
    else:
        qx, qy = r * c - sub.px, r * s - sub.py
        R2 = np.maximum(qx * qx + qy * qy, 1e-18)
        Rr = np.sqrt(R2)
        dx = -tau * qx / Rr + a * qy / R2
        dy = -tau * qy / Rr - a * qx / R2
    w = u / tof_sd
    dx, dy = (dx * w)[:, None], (dy * w)[:, None]
    hx, hy = path.turned()
    ax, ay = path.stretched()
    return geo, np.concatenate([J * u[:, None, :],
                                dx * hx + dy * hy + (-a * w)[:, None] * path.heads,
                                dx * ax + dy * ay], axis=1)


def _normal(G: Array) -> Array:
    """Normal matrix of the profile: ``G G^T`` with the weights' standard-normal prior."""
    N = np.matmul(G, G.transpose(0, 2, 1))
    N[:, 3:, 3:] += np.eye(G.shape[1] - 3)[None]
    N[:, :3, :3] += 1e-9 * np.eye(3)[None]
    return N
