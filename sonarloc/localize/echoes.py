"""Every reading of a fitted segment as a measurement: Kuc's forward model in the filter.

A fitted landmark summarises a segment's readings in the ``odom`` frame, so odometry
error inside the segment distorts it, and its (range, bearing) is only as good as the
fit. Once the fit has told *which* map feature the segment saw (data association), the
readings themselves can be fused: each one is a time of flight predicted from the map
feature and the robot pose by the forward model

    Tm_i = 2 r_i / c + delay(theta_i, kappa) + count bias,

``r_i`` the range from the transducer to the reflecting point (a wall's normal-incidence
point, a pole's surface), ``theta_i`` that point's angle off the transducer axis and
``delay`` the threshold delay of the ranging module (eq. 3, kappa·exp(theta²/2 sigma²),
with the piston pattern and waveform effects of :func:`sonarloc.physics.tiers.
delay_moments_us` where they matter). A conventional sonar filter takes ``c Tm / 2`` for
the range and is biased by the delay (millimetres off axis); here it is predicted, and
its derivative in ``theta`` carries bearing information.

All readings of a segment form one stacked update relative to ``base_link`` at the
segment's reference time. The transducer poses relative to that reference come from
odometry; their errors (the odometry increments' noise between each reading and the
reference, correlated because the increments nest) enter the measurement covariance
through the model's sensitivity to the transducer pose::

    R = diag(sd_i²) + G Σ_s Gᵀ

``sd_i``: timing jitter, the delay's spread (amplitude fluctuation) and counting;
``Σ_s``: the joint covariance of the relative transducer poses, stored in factored form
(``cov(s_i, s_j) = P_i V_j`` for readings i no later than j), so a 400-reading pan
segment costs O(n²) scalars, not O(n²) 3×3 blocks.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from sonarloc import se2
from sonarloc.localize import ekf
from sonarloc.localize.ekf import Feature, Gaussian, Innovation, OdomNoise
from sonarloc.physics.reflectors import ReflectorKind, kappa_at_range_us
from sonarloc.physics.tiers import (
    Tier,
    delay_moments_us,
    max_detection_angle_rad,
    tabulated_piston_echo,
)
from sonarloc.physics.tof import ModuleParams

Array = NDArray[np.float64]

#: Step of the central difference of the delay model in theta [rad].
_DTHETA_RAD = math.radians(0.05)


@functools.lru_cache(maxsize=8)
def _module(c_mps: float) -> ModuleParams:
    return ModuleParams(c_mps=c_mps)


def delay_model(theta_rad: ArrayLike, kappa_us: ArrayLike, c_mps: float = 343.0
                ) -> tuple[Array, Array, Array, Array]:
    """Mean threshold delay, its slope in theta, its SD and the detection probability.

    Interpolated in :class:`DelayTable` (within a few hundredths of a microsecond of
    :func:`delay_model_direct`, see its notes); evaluated directly where the table has
    no finite neighbours (the detection edge, strengths outside its range).

    Parameters
    ----------
    theta_rad : (n,) off-axis angle of the reflecting point [rad].
    kappa_us : (n,) reflector strength [us].
    c_mps : speed of sound (selects the module parameters).

    Returns
    -------
    mean_us, slope_us_per_rad, sd_us, p_detect : (n,) each; NaN where no echo is
        expected (beyond the detection arc).
    """
    return delay_table(float(c_mps)).lookup(theta_rad, kappa_us)


def delay_model_direct(theta_rad: ArrayLike, kappa_us: ArrayLike, c_mps: float = 343.0
                       ) -> tuple[Array, Array, Array, Array]:
    """:func:`delay_model` evaluated with :func:`~sonarloc.physics.tiers.delay_moments_us`
    (``auto`` tier, 41 quadrature nodes; slope a central difference over
    ``_DTHETA_RAD``). Same arguments and returns."""
    th = np.asarray(theta_rad, dtype=float)
    kap = np.broadcast_to(np.asarray(kappa_us, dtype=float), th.shape)
    params = _module(float(c_mps))
    grid = np.stack([th - _DTHETA_RAD, th, th + _DTHETA_RAD])
    m = delay_moments_us(grid, np.broadcast_to(kap, grid.shape), Tier.AUTO, params,
                         _DELAY_NODES)
    slope = (m.mean_us[2] - m.mean_us[0]) / (2 * _DTHETA_RAD)
    return m.mean_us[1], slope, m.sd_us[1], m.p_detect[1]


#: Reflector kinds whose strength grows with range (cylinders,
#: :func:`~sonarloc.physics.reflectors.kappa_at_range_us`); the others keep theirs.
_GROWING_KINDS = frozenset(k.value for k in ReflectorKind if k.is_cylinder)
#: Largest change of a reading's off-axis angle [rad] (0.03 deg) for which
#: :meth:`EchoObservation.linearize` keeps the delay model it has.
RELINEARIZE_RAD = 5e-4
#: Detection probability below which :func:`screen` does not take a reading as the
#: feature's (the belief puts it past the edge of the detection arc).
SCREEN_MIN_DETECT = 0.01
#: The detection screen trusts the belief's angle to a feature only while the belief is
#: this tight (position SD [m], yaw SD [rad]; the beam is ~12 deg to its first null):
#: a belief of metres or tens of degrees cannot say where its detection arc ends, and a
#: screen at its mean would drop readings by chance (a prior of 1e150 m then picked the
#: readings that took it to `tracking` on made-up data).
SCREEN_BELIEF_SD_M, SCREEN_BELIEF_SD_YAW = 0.5, math.radians(5.0)


def belief_is_tight(cov: ArrayLike) -> NDArray[np.bool_]:
    """(...) whether beliefs of covariance ``cov`` (..., 3, 3) are tight enough for the
    detection screen (:data:`SCREEN_BELIEF_SD_M`, :data:`SCREEN_BELIEF_SD_YAW`)."""
    c = np.asarray(cov, dtype=float)
    a, b, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 1]
    with np.errstate(invalid="ignore", over="ignore"):
        # the larger eigenvalue of the position block, in closed form (NaN or inf: not
        # tight, every comparison below being False)
        pos = 0.5 * (a + d) + np.sqrt((0.5 * (a - d)) ** 2 + b * b)
        return np.asarray((pos <= SCREEN_BELIEF_SD_M**2)
                          & (c[..., 2, 2] <= SCREEN_BELIEF_SD_YAW**2))
#: Quadrature nodes of the delay moments.
_DELAY_NODES = 41
#: Strength grid of :class:`DelayTable`: log-spaced, ``_KAPPA_PER_DECADE`` rows a
#: decade from ``_KAPPA_MIN_US`` to ``_KAPPA_MAX_US``.
_KAPPA_MIN_US, _KAPPA_MAX_US, _KAPPA_PER_DECADE = 1e-3, 1e3, 80
#: Detection of a row's strength is tabulated out to this many SDs of the gain.
_TABLE_GAIN_SD = 8.0
#: A table cell is interpolated only where the mean's second differences (in theta and
#: in log kappa) at its corners stay below this [us]: the delay is smooth there and the
#: bilinear interpolation within about half of it (0.015 us measured). Elsewhere (ripple
#: jumps of the waveform tier, tier switches, the detection edge) it is evaluated directly.
_SMOOTH_US = 0.03


class DelayTable:
    """The delay model (:func:`delay_model_direct`) tabulated over (|theta|, kappa).

    Rows on a log-spaced strength grid (:data:`_KAPPA_PER_DECADE` a decade), each built
    on first use over |theta| on the ``_DTHETA_RAD`` grid out to the row's detection
    arc: ``mean / kappa``, ``sd / kappa`` and the central-difference slope ``/ kappa``
    (exactly the direct slope at the nodes). Look-ups interpolate bilinearly in
    (|theta|, log kappa) and scale by kappa; the slope is odd in theta, the rest even.
    Dividing by kappa makes the eq. 3 part (delay proportional to kappa) exact in kappa;
    the tier switches and the waveform crossing leave interpolation errors of a few
    hundredths of a microsecond (tests/localize/test_echoes.py), against a 5 us timing
    jitter. The detection probability is computed directly (closed form, cheap).
    """

    def __init__(self, params: ModuleParams) -> None:
        self.params = params
        self._h = math.log(10.0) / _KAPPA_PER_DECADE
        self._ln_min = math.log(_KAPPA_MIN_US)
        self._n_rows = int(round(math.log(_KAPPA_MAX_US / _KAPPA_MIN_US) / self._h)) + 1
        self._width = int(math.ceil(math.pi / 2 / _DTHETA_RAD)) + 2
        shape = (self._n_rows, self._width)
        #: (row, |theta| node, 3): mean, slope and SD over kappa; NaN where undetected
        self._vals = np.full(shape + (3,), np.nan)
        #: (row, node): second difference of mean/kappa in |theta|
        self._curv = np.full(shape, np.nan)
        #: (row, node): the cell from this node to the next row and node is smooth
        self._cell_ok = np.zeros(shape, dtype=bool)
        self._row_built = np.zeros(self._n_rows, dtype=bool)
        #: (row,) detection arc [rad]: nothing at least as strong is detected beyond it
        self._arc = np.full(self._n_rows, np.inf)
        self._cells_done = np.zeros(self._n_rows, dtype=bool)

    def _build_row(self, j: int) -> None:
        kap = math.exp(self._ln_min + j * self._h)
        arc = float(max_detection_angle_rad(kap, self.params, _TABLE_GAIN_SD))
        n = min(int(arc / _DTHETA_RAD) + 3, self._width)
        if n < self._width:
            self._arc[j] = arc
        th = np.arange(-1, n + 1) * _DTHETA_RAD     # one node each side for the slope
        m = delay_moments_us(th, kap, Tier.AUTO, self.params, _DELAY_NODES)
        mean = m.mean_us
        self._curv[j, :n] = np.abs(mean[2:] - 2 * mean[1:-1] + mean[:-2]) / kap
        self._vals[j, :n, 0] = mean[1:-1] / kap
        self._vals[j, :n, 1] = (mean[2:] - mean[:-2]) / (2 * _DTHETA_RAD * kap)
        self._vals[j, :n, 2] = m.sd_us[1:-1] / kap
        self._row_built[j] = True

    def _ensure(self, rows: NDArray[np.intp]) -> None:
        """Build rows ``j - 1 .. j + 2`` of each row ``j`` of ``rows`` and the smoothness
        of the cells of ``rows`` (only those: strengths far apart leave the rows between
        them unbuilt)."""
        rows = np.unique(rows)
        rows = rows[~self._cells_done[rows]]
        if rows.size == 0:
            return
        for j in np.unique(rows[:, None] + np.arange(-1, 3)).tolist():
            if not self._row_built[j]:
                self._build_row(j)
        m = self._vals[:, :, 0]
        with np.errstate(invalid="ignore"):
            def node_curv(r: NDArray[np.intp]) -> Array:  # (len(r), width), NaN: rough
                in_kappa = np.abs(m[r - 1] - 2 * m[r] + m[r + 1])
                return np.maximum(in_kappa, self._curv[r])
            c = np.maximum(node_curv(rows), node_curv(rows + 1))
            c = np.maximum(c[:, :-1], c[:, 1:])
            kap_hi = np.exp(self._ln_min + (rows + 1) * self._h)[:, None]
            finite = np.asarray(np.isfinite(self._vals).all(axis=2))
            fin = finite[rows] & finite[rows + 1]
            fin = fin[:, :-1] & fin[:, 1:]
            self._cell_ok[rows, :-1] = np.asarray(fin & (c * kap_hi <= _SMOOTH_US))
        self._cells_done[rows] = True

    def moments(self, theta_rad: ArrayLike, kappa_us: ArrayLike
                ) -> tuple[Array, Array, Array]:
        """Mean [us], slope [us/rad] and SD [us] of the delay: ``theta_rad`` (n,)
        [rad] and ``kappa_us`` (n,) [us] broadcast (:func:`delay_model` without the
        detection probability)."""
        th = np.asarray(theta_rad, dtype=float)
        kap = np.broadcast_to(np.asarray(kappa_us, dtype=float), th.shape)
        shape = th.shape
        th, kap = th.reshape(-1), kap.reshape(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            a = np.abs(th) * (1.0 / _DTHETA_RAD)
            lk = (np.log(kap) - self._ln_min) * (1.0 / self._h)
            known = (lk >= 1) & (lk < self._n_rows - 2)
            inside = known & (a < self._width - 1)
        if not inside.all():
            a = np.where(inside, a, 0.0)
            lk = np.where(known, lk, 1.0)
        i = a.astype(np.intp)
        j = lk.astype(np.intp)
        if not self._cells_done[j].all():
            self._ensure(j)
        f = (a - i)[:, None]
        g = (lk - j)[:, None]
        flat = j * self._width + i
        v = self._vals.reshape(-1, 3)
        lo = v[flat] + f * (v[flat + 1] - v[flat])
        hi = v[flat + self._width] + f * (v[flat + self._width + 1] - v[flat + self._width])
        val = (lo + g * (hi - lo)) * kap[:, None]
        mean, slope, sd = val[:, 0], val[:, 1] * np.sign(th), val[:, 2]
        ok = inside & self._cell_ok.reshape(-1)[flat]
        if not ok.all():
            # beyond the detection arc of the weaker row: no echo (NaN), no evaluation
            with np.errstate(invalid="ignore"):
                dead = known & (np.abs(th) > self._arc[j])
            fall = np.flatnonzero(~ok & ~dead & np.isfinite(th) & np.isfinite(kap)
                                  & (kap > 0))
            mean[~ok] = slope[~ok] = sd[~ok] = np.nan
            if fall.size:
                dm, ds, dsd, _ = delay_model_direct(th[fall], kap[fall], self.params.c_mps)
                mean[fall], slope[fall], sd[fall] = dm, ds, dsd
        return mean.reshape(shape), slope.reshape(shape), sd.reshape(shape)

    def lookup(self, theta_rad: ArrayLike, kappa_us: ArrayLike
               ) -> tuple[Array, Array, Array, Array]:
        """:func:`delay_model` for this module (see :meth:`moments`), with the
        detection probability."""
        mean, slope, sd = self.moments(theta_rad, kappa_us)
        th = np.asarray(theta_rad, dtype=float)
        kap = np.broadcast_to(np.asarray(kappa_us, dtype=float), th.shape)
        return mean, slope, sd, self.p_detect(th, kap)

    def p_detect(self, th: Array, kap: Array) -> Array:
        """Detection probability of an echo of strength ``kap`` [us] from off-axis angle
        ``th`` [rad] (same shapes)."""
        a = tabulated_piston_echo(th, self.params)
        sig = self.params.amplitude_fluctuation
        with np.errstate(divide="ignore", invalid="ignore"):
            log_need = np.log(kap / self.params.detection_limit_us) - np.log(a)
        if sig > 0:
            return np.asarray(special.ndtr(-log_need / sig), dtype=float)
        return (log_need <= 0).astype(float)


@functools.lru_cache(maxsize=8)
def delay_table(c_mps: float = 343.0) -> DelayTable:
    """The (lazily filled) :class:`DelayTable` of the module at this speed of sound."""
    return DelayTable(_module(float(c_mps)))


def warm_up(point_kappa_us: ArrayLike, point_kind: Sequence[str], point_radius_m: ArrayLike,
            wall_kappa_us: ArrayLike, c_mps: float = 343.0,
            ranges_m: tuple[float, float] = (0.1, 8.0)) -> int:
    """Build the rows of the :func:`delay_table` that a map's features need: their
    strengths (a cylinder's grows with range) over ``ranges_m`` (first, last) [m]; rows
    are otherwise built by the first fusion that needs them (on the room drive the first
    fusion's call spent ~80 ms building the table). Returns the strengths looked up."""
    rng = np.geomspace(float(ranges_m[0]), float(ranges_m[1]), 32)
    kaps = [np.asarray(wall_kappa_us, dtype=float).reshape(-1)]
    radii = np.broadcast_to(np.asarray(point_radius_m, dtype=float), (len(point_kind),))
    for kap, kind, radius in zip(np.asarray(point_kappa_us, dtype=float).reshape(-1),
                                 point_kind, radii, strict=True):
        kaps.append(kappa_at_range_us(kap, kind, rng, radius) if kind in _GROWING_KINDS
                    else np.array([kap]))
    k = np.concatenate(kaps)
    k = k[np.isfinite(k) & (k > 0)]
    delay_table(float(c_mps)).moments(np.zeros(k.size), k)
    return int(k.size)


def reading_sd_us(delay_sd_us: ArrayLike, c_mps: float = 343.0) -> Array:
    """SD of a reading around its predicted mean: jitter, delay spread and counting."""
    p = _module(float(c_mps))
    return np.sqrt(p.jitter_sd_us**2 + np.asarray(delay_sd_us, dtype=float) ** 2
                   + p.count_period_us**2 / 12.0)


def relative_sensor_chain(base_ref: ArrayLike, base_at: ArrayLike, sensor_at: ArrayLike,
                          noise: OdomNoise) -> tuple[Array, Array, Array]:
    """Transducer poses relative to ``base_link`` at the reference time, with the
    factored joint covariance of their odometry errors.

    Parameters
    ----------
    base_ref : (..., 3) odometry pose of ``base_link`` at the reference time.
    base_at : (..., n, 3) odometry poses of ``base_link`` at the readings' times, in time
        order, none after the reference.
    sensor_at : (..., n, 3) odometry poses of the transducers at those times.
    noise : odometry increment noise model.

    Leading axes are a batch of segments (:mod:`sonarloc.localize.batchfuse` pads
    shorter ones at the start with copies of their first reading: a zero increment adds
    no noise, so the padding changes nothing).

    Returns
    -------
    rel : (..., n, 3) transducer poses in ``base_link`` at the reference time.
    p_fac, v_fac : (..., n, 3, 3) with ``cov(err s_i, err s_j) = p_fac[i] @ v_fac[j]``
        for i <= j (reading i no later than reading j).
    """
    ref = np.asarray(base_ref, dtype=float)
    base = np.asarray(base_at, dtype=float)
    if base.ndim == 1:
        base = base.reshape(-1, 3)
    sens = np.asarray(sensor_at, dtype=float).reshape(base.shape)
    ref_n = ref[..., None, :]
    b = se2.between(ref_n, base)                    # base at t_i in base at ref
    rel = se2.between(ref_n, sens)                  # transducer at t_i in base at ref
    # chain backwards from the reference: b_i = b_{i+1} ⊕ u_i, u_i = between(base_{i+1},
    # base_i), b_n = 0. The Jacobians of ⊕ in b_{i+1} are I + (W_i - W_{i+1}) e₃ᵀ with
    # W = (-y, x, 0) of b, so the chain's products telescope (as in ekf.predict_chain):
    # Σ_i = Σ_{k >= i} Φ_ik w_k Φ_ikᵀ, Φ_ik = I + (W_i - W_k) e₃ᵀ, w_k the noise of u_k
    # turned into the frame of b_{k+1}: suffix sums of w_k, qt_k W_k and qt_k W_k W_kᵀ.
    nxt = np.concatenate([base[..., 1:, :], np.broadcast_to(ref_n, ref_n.shape)], axis=-2)
    u = se2.between(nxt, base)
    d = np.hypot(u[..., 0], u[..., 1])
    turn = np.abs(u[..., 2])                        # wrapped by between
    qx = noise.along_var_per_m * d + noise.xy_var_per_rad * turn
    qy = noise.cross_var_per_m * d + noise.xy_var_per_rad * turn
    qt = noise.yaw_var_per_m * d + noise.yaw_var_per_rad * turn
    b_next = np.concatenate([b[..., 1:, :], np.zeros(b.shape[:-2] + (1, 3))], axis=-2)
    c, s = np.cos(b_next[..., 2]), np.sin(b_next[..., 2])
    wx, wy = -b[..., 1], b[..., 0]                  # W_i

    # suffix sums (over k >= i along the readings) of the nine chain quantities at once
    terms = np.stack([c * c * qx + s * s * qy, c * s * (qx - qy), s * s * qx + c * c * qy,
                      qt, qt * wx, qt * wy, qt * wx * wx, qt * wx * wy, qt * wy * wy])
    (a_xx, a_xy, a_yy, s0, s1x, s1y, s2xx, s2xy, s2yy) = \
        np.cumsum(terms[..., ::-1], axis=-1)[..., ::-1]
    sigma = np.empty(base.shape + (3,))
    sigma[..., 0, 0] = a_xx + s0 * wx * wx - 2.0 * wx * s1x + s2xx
    sigma[..., 0, 1] = sigma[..., 1, 0] = a_xy + s0 * wx * wy - wx * s1y - s1x * wy + s2xy
    sigma[..., 1, 1] = a_yy + s0 * wy * wy - 2.0 * wy * s1y + s2yy
    sigma[..., 0, 2] = sigma[..., 2, 0] = s0 * wx - s1x
    sigma[..., 1, 2] = sigma[..., 2, 1] = s0 * wy - s1y
    sigma[..., 2, 2] = s0
    # the error of s_i = b_i ⊕ mount_i: K_i δb_i, K_i = I + (W(rel_i) - W_i) e₃ᵀ; the
    # chain from the reference to b_i: A_i = I + W_i e₃ᵀ, so cov(s_i, s_j) = K_i A_i ·
    # A_j⁻¹ Σ_j K_jᵀ for i <= j
    p_fac = np.zeros(base.shape + (3,))
    p_fac[..., 0, 0] = p_fac[..., 1, 1] = p_fac[..., 2, 2] = 1.0
    p_fac[..., 0, 2], p_fac[..., 1, 2] = -rel[..., 1], rel[..., 0]      # K_i A_i
    a_inv = np.zeros_like(p_fac)
    a_inv[..., 0, 0] = a_inv[..., 1, 1] = a_inv[..., 2, 2] = 1.0
    a_inv[..., 0, 2], a_inv[..., 1, 2] = -wx, -wy
    k_t = np.zeros_like(p_fac)
    k_t[..., 0, 0] = k_t[..., 1, 1] = k_t[..., 2, 2] = 1.0
    k_t[..., 2, 0], k_t[..., 2, 1] = -rel[..., 1] - wx, rel[..., 0] - wy
    v_fac = a_inv @ sigma @ k_t
    return rel, p_fac, v_fac


def geometry(pose: Array, rel: Array, feature: Feature) -> tuple[Array, Array, Array, Array]:
    """Range, off-axis angle and their derivatives wrt the transducer pose in map.

    Returns range (n,), theta (n,), d range / d (x, y, psi) (n, 3), d theta / d (...)
    (n, 3), and the transducer poses in map ``(n, 3)`` via the caller.
    """
    t = se2.compose(pose, rel)
    px, py, psi = t[:, 0], t[:, 1], t[:, 2]
    n = len(t)
    dr = np.zeros((n, 3))
    dth = np.zeros((n, 3))
    if feature.kind == "point":
        c = np.asarray(feature.params, dtype=float)
        dx, dy = c[0] - px, c[1] - py
        dist2 = np.maximum(dx * dx + dy * dy, 1e-18)
        dist = np.sqrt(dist2)
        rng = dist - float(np.asarray(feature.radius_m))
        theta = se2.wrap_angle(np.arctan2(dy, dx) - psi)
        dr[:, 0], dr[:, 1] = -dx / dist, -dy / dist
        dth[:, 0], dth[:, 1] = dy / dist2, -dx / dist2
    else:
        rho, alpha = (float(v) for v in np.asarray(feature.params, dtype=float))
        ca, sa = math.cos(alpha), math.sin(alpha)
        signed = rho - px * ca - py * sa
        sign = np.where(signed < 0, -1.0, 1.0)
        rng = np.abs(signed)
        direction = alpha + np.where(signed < 0, math.pi, 0.0)
        theta = se2.wrap_angle(direction - psi)
        dr[:, 0], dr[:, 1] = -sign * ca, -sign * sa
    dth[:, 2] = -1.0
    return rng, theta, dr, dth


def feature_ranges(pose: ArrayLike, rel: ArrayLike, point_xy: ArrayLike, radius_m: ArrayLike,
                   wall_line: ArrayLike) -> tuple[Array, Array]:
    """Ranges from n transducers to P point features and W walls (perpendicular).

    ``pose`` (3,) base_link in map; ``rel`` (n, 3) transducers in base_link;
    ``point_xy`` (P, 2), ``radius_m`` (P,), ``wall_line`` (W, 2) (rho, alpha). Returns
    (P, n) and (W, n) ranges [m] (geometry only: no delay, no visibility).
    """
    t = se2.compose(np.asarray(pose, dtype=float), np.asarray(rel, dtype=float))
    c = np.asarray(point_xy, dtype=float).reshape(-1, 2)
    rp = np.hypot(c[:, None, 0] - t[None, :, 0], c[:, None, 1] - t[None, :, 1]) \
        - np.asarray(radius_m, dtype=float).reshape(-1, 1)
    w = np.asarray(wall_line, dtype=float).reshape(-1, 2)
    rw = np.abs(w[:, None, 0] - t[None, :, 0] * np.cos(w[:, None, 1])
                - t[None, :, 1] * np.sin(w[:, None, 1]))
    return rp, rw


@dataclass
class EchoObservation:
    """A segment's readings of one map feature, relative to ``base_link`` at ``t_s``.

    Attributes
    ----------
    z_m : (n,) readings as ranges ``c Tm / 2`` [m].
    rel : (n, 3) transducer poses in ``base_link`` at the reference time (odometry).
    p_fac, v_fac : (n, 3, 3) factored covariance of ``rel``'s errors
        (:func:`relative_sensor_chain`).
    kappa_us : strength used in the delay model (the map feature's at 1.5 m, else the
        fit's).
    feature : the associated map feature.
    kind : its reflector kind (``pole``, ``rod``, ``point``, ``corner``, ``edge``,
        ``wall``, ``plane``): a cylinder's strength grows with range
        (:func:`~sonarloc.physics.reflectors.kappa_at_range_us`), the others' does not.
    t_s : reference time.
    c_mps : speed of sound.
    lin_theta, lin_mean, lin_slope, lin_sd : (n,) the delay model linearised at the
        first evaluation (off-axis angle [rad], mean [us], slope [us/rad], SD [us]);
        re-used when the update is replayed on a slightly different belief.
    map_var_m2 : variance [m²] of the map feature's position, an error all the readings
        share: added to every element of R (a common range offset; exact for a wall's
        distance, for a point seen over the short arc of one segment nearly so).
    """

    z_m: Array
    rel: Array
    p_fac: Array
    v_fac: Array
    kappa_us: float
    feature: Feature
    t_s: float
    c_mps: float = 343.0
    kind: str = "wall"
    lin_theta: Array | None = None
    lin_mean: Array | None = None
    lin_slope: Array | None = None
    lin_sd: Array | None = None
    compressed: Compressed | None = None
    map_var_m2: float = 0.0
    #: the pose of the last :meth:`measure` and its result (pose, h, H, R)
    _measured: tuple[Array, Array, Array, Array] | None = field(
        default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.z_m)

    def subset(self, keep: NDArray[np.bool_]) -> EchoObservation:
        """The observation restricted to readings ``keep`` (n,) (linearisation and the
        last :meth:`measure` kept)."""
        def sel(a: Array | None) -> Array | None:
            return None if a is None else a[keep]
        out = EchoObservation(self.z_m[keep], self.rel[keep], self.p_fac[keep],
                              self.v_fac[keep], self.kappa_us, self.feature, self.t_s,
                              self.c_mps, self.kind, sel(self.lin_theta),
                              sel(self.lin_mean), sel(self.lin_slope), sel(self.lin_sd),
                              map_var_m2=self.map_var_m2)
        if self._measured is not None:
            x, h, hx, r = self._measured
            idx = np.flatnonzero(keep)
            out._measured = (x, h[idx], hx[idx], r[np.ix_(idx, idx)])
        return out

    def linearize(self, pose: ArrayLike) -> EchoObservation:
        """Evaluate the delay model at the off-axis angles seen from ``pose`` (3,).

        Kept as it is when no angle moved more than :data:`RELINEARIZE_RAD` from the
        stored linearisation (:meth:`measure` extrapolates it along its slope; the
        curvature term is below a thousandth of a microsecond there).
        """
        rng, theta, _, _ = geometry(np.asarray(pose, dtype=float), self.rel, self.feature)
        if self.lin_theta is not None and len(self.lin_theta) == len(theta) and \
                float(np.max(np.abs(se2.wrap_angle(theta - self.lin_theta)),
                             initial=0.0)) <= RELINEARIZE_RAD:
            return self
        mean, slope, sd = delay_table(float(self.c_mps)).moments(theta, self.kappa_at(rng))
        self.lin_theta, self.lin_mean, self.lin_slope, self.lin_sd = theta, mean, slope, sd
        self._measured = None
        return self

    def p_detect(self, pose: ArrayLike) -> Array:
        """(n,) probability that the feature is detected by each reading's transducer
        seen from ``pose`` (3,)."""
        rng, theta, _, _ = geometry(np.asarray(pose, dtype=float), self.rel, self.feature)
        return delay_table(float(self.c_mps)).p_detect(theta, self.kappa_at(rng))

    def kappa_at(self, range_m: Array) -> Array:
        """(n,) strength at the readings' ranges [us]."""
        if self.kind not in _GROWING_KINDS:   # walls, corners, edges: constant
            return np.full(np.shape(range_m), float(self.kappa_us))
        radius = float(np.asarray(self.feature.radius_m)) if self.feature.kind == "point" \
            else 0.0
        return kappa_at_range_us(self.kappa_us, self.kind, np.maximum(range_m, 1e-3), radius)

    def measure(self, pose: ArrayLike) -> tuple[Array, Array, Array]:
        """Predicted ranges (n,), Jacobian wrt the pose H (n, 3) and covariance R (n, n).

        The delay model is taken from the stored linearisation (see :meth:`linearize`).
        """
        if self.lin_theta is None or self.lin_mean is None or self.lin_slope is None \
                or self.lin_sd is None:
            self.linearize(pose)
        assert self.lin_theta is not None and self.lin_mean is not None
        assert self.lin_slope is not None and self.lin_sd is not None
        x = np.asarray(pose, dtype=float)
        if self._measured is not None and np.array_equal(self._measured[0], x):
            return self._measured[1], self._measured[2], self._measured[3]
        rng, theta, dr, dth = geometry(x, self.rel, self.feature)
        us_to_m = 0.5e-6 * self.c_mps
        bias_us = 0.5 * _module(float(self.c_mps)).count_period_us
        dtheta = se2.wrap_angle(theta - self.lin_theta)
        delay = self.lin_mean + self.lin_slope * dtheta
        h = rng + us_to_m * (delay + bias_us)
        dh_dt = dr + (us_to_m * self.lin_slope)[:, None] * dth   # wrt transducer pose in map
        # transducer pose in map T = x ⊕ rel: dT/dx, dT/drel
        jx, jrel = se2.compose_jacobians(x, self.rel)
        hx = np.einsum("ni,nij->nj", dh_dt, jx)
        g = np.einsum("ni,nij->nj", dh_dt, jrel)
        sd_m = us_to_m * reading_sd_us(self.lin_sd, self.c_mps)
        gp = np.einsum("ni,nij->nj", g, self.p_fac)
        gv = np.einsum("nij,nj->ni", self.v_fac, g)
        m = gp @ gv.T                       # m[i, j] = g_i P_i V_j g_j (valid for i <= j)
        upper = np.triu(m)
        r = upper + np.triu(m, 1).T + np.diag(sd_m**2)
        if self.map_var_m2 > 0:
            r = r + self.map_var_m2
        r = ekf.symmetrize(r)
        self._measured = (x.copy(), h, hx, r)
        return h, hx, r


@dataclass(frozen=True)
class Compressed:
    """A stacked readings update linearised once and reduced to at most 3 rows.

    Whitened by ``R = L Lᵀ`` and QR-factored, ``L⁻¹ H = Q Rq``: the update with
    ``(Qᵀ L⁻¹ nu, Rq, I)`` equals the n-row one with ``(nu, H, R)`` exactly, and the
    n-row squared Mahalanobis distance is the reduced one plus ``resid2``, the part of
    the whitened innovation outside ``Q``'s span. ``x0``: the pose linearised at.
    """

    x0: Array
    q_nu: Array    # (k,) Qᵀ L⁻¹ (z - h(x0))
    rq: Array      # (k, 3)
    resid2: float
    n: int


def compress(obs: EchoObservation, pose: ArrayLike) -> Compressed | None:
    """Linearise ``obs`` at ``pose`` and reduce it (None if R is not positive definite)."""
    x0 = np.asarray(pose, dtype=float).copy()
    h, hx, r = obs.measure(x0)
    nu = obs.z_m - h
    try:
        chol = np.linalg.cholesky(r)
    except np.linalg.LinAlgError:
        return None
    sol = np.linalg.solve(chol, np.column_stack([hx, nu]))  # L⁻¹ [H | nu]
    hw, nuw = sol[:, :3], sol[:, 3]
    q, rq = np.linalg.qr(hw, mode="reduced")
    q_nu = q.T @ nuw
    resid2 = max(float(nuw @ nuw - q_nu @ q_nu), 0.0)
    return Compressed(x0, q_nu, rq, resid2, len(nu))


#: Linearisations of a first update (iterated EKF), at most.
ITERATIONS = 3


def _reduced_update(state: Gaussian, c: Compressed) -> tuple[Gaussian, Innovation]:
    dx = state.mean - c.x0
    dx[2] = float(se2.wrap_angle(dx[2]))
    nu3 = c.q_nu - c.rq @ dx
    return ekf.kalman_update(state, nu3, c.rq, np.eye(len(nu3)))


def update(state: Gaussian, obs: EchoObservation, gate: float = math.inf
           ) -> tuple[Gaussian, Innovation]:
    """Stacked Kalman update of an unbatched belief with a segment's readings.

    Linearised at the first call's belief, relinearised at the updated mean up to
    :data:`ITERATIONS` times (iterated EKF), and kept (:class:`Compressed`): a replay of
    the same update on a slightly moved belief (a delayed observation fused before it)
    moves the prediction by ``H (x - x0)``, and costs a 3-row update.
    """
    last: tuple[Compressed, tuple[Gaussian, Innovation]] | None = None
    if obs.compressed is None:
        # iterated: relinearise (geometry and the delay model) at the updated mean, so a
        # first update from a belief degrees off does not trust a slope taken there
        x_lin = state.mean
        for _ in range(ITERATIONS):
            obs.linearize(x_lin)
            obs.compressed = compress(obs, x_lin)
            if obs.compressed is None:
                break
            last = (obs.compressed, _reduced_update(state, obs.compressed))
            moved = last[1][0].mean
            step = moved - x_lin
            step[2] = float(se2.wrap_angle(step[2]))
            x_lin = moved
            if abs(step[0]) + abs(step[1]) < 1e-5 and abs(step[2]) < 1e-5:
                break
    c = obs.compressed
    if c is None:
        h, hx, r = obs.measure(state.mean)
        return ekf.kalman_update(state, obs.z_m - h, hx, r, gate)
    new, innov = last[1] if last is not None and last[0] is c else _reduced_update(state, c)
    d2 = innov.d2 + c.resid2
    accepted = np.asarray(~innov.singular & (d2 <= gate))
    if not bool(accepted):
        new = state
    return new, Innovation(innov.nu, innov.S, d2, gate, accepted, innov.singular)


def screen(state: Gaussian, obs: EchoObservation, probability: float = 0.999,
           min_detect: float = SCREEN_MIN_DETECT) -> NDArray[np.bool_]:
    """(n,) readings consistent one by one with the belief: finite model, an angle the
    feature is detected from with probability at least ``min_detect``, and ``nu_i² /
    S_ii`` inside the chi-square(1) gate of ``probability``.

    A reading the belief says the feature would almost never give (its angle past the
    edge of the detection arc) is not one of the feature's at this belief: there the
    model's delay is conditional on a crossing that hardly happens, steep and ends at
    a cliff, so its slope would turn a few millimetres of range into a confident, wrong
    yaw (a pole seen 3.5 m away at the edge of the beam, the belief 2 deg off: 37 us of
    delay predicted where the truth gives 20 us).
    """
    h, hx, r = obs.measure(state.mean)
    nu = obs.z_m - h
    s = np.einsum("ni,ij,nj->n", hx, state.cov, hx) + np.diag(r)
    ok = np.isfinite(nu) & np.isfinite(s) & (s > 0)
    if min_detect > 0 and bool(belief_is_tight(state.cov)):
        ok &= obs.p_detect(state.mean) >= min_detect
    d2 = np.where(ok, nu**2 / np.where(ok, s, 1.0), np.inf)
    return np.asarray(ok & (d2 <= ekf.chi2_gate(1, probability)))


def ambiguous(state: Gaussian, obs: EchoObservation, rivals: Sequence[EchoObservation],
              probability: float = 0.999, min_detect: float = 0.5) -> NDArray[np.bool_]:
    """(n,) readings of ``obs`` that another map feature, nearer, explains as well.

    The module reports the *first* threshold crossing, so where two reflectors lie at
    nearly the same range (a wall's normal-incidence point next to its corner, seen by
    a beam sweeping along the wall) a segment's readings come from either, and the
    segmenter keeps them in one segment. A reading that also passes the per-reading
    screen (:func:`screen`, same ``probability``) of a rival feature (same readings,
    transducer poses and chain, that feature's geometry and strength) is the rival's
    when the rival predicts the earlier crossing and is detected there with
    probability at least ``min_detect``: fused as a reading of ``obs.feature`` it would
    pull the pose by the range difference, millimetres that the forward model's
    sub-millimetre SDs turn into a strong, wrong update. Where ``obs.feature`` predicts
    the earlier crossing the reading stays its own (the nearer reflector wins).

    Parameters
    ----------
    state : the belief the readings are screened against (mean (3,), cov (3, 3)).
    obs : the readings as measurements of the associated feature.
    rivals : the same readings as measurements of each other candidate feature.
    probability : chi-square(1) gate of the screen.
    min_detect : detection probability of the rival needed to claim a reading.
    """
    out = np.zeros(len(obs), dtype=bool)
    if not rivals:
        return out
    h_own, _, _ = obs.linearize(state.mean).measure(state.mean)
    for rival in rivals:
        if len(rival) != len(obs):
            raise ValueError(f"rival observation has {len(rival)} readings, `obs` has "
                             f"{len(obs)}")
        rival.linearize(state.mean)
        h, _, _ = rival.measure(state.mean)
        rng, theta, _, _ = geometry(np.asarray(state.mean, dtype=float), rival.rel,
                                    rival.feature)
        p_det = delay_table(float(rival.c_mps)).lookup(theta, rival.kappa_at(rng))[3]
        with np.errstate(invalid="ignore"):
            nearer = (h < h_own) & (p_det >= min_detect)
        out |= screen(state, rival, probability) & nearer
    return out
