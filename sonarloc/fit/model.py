"""The fitter's forward model: geometry, beam delay and detection, with derivatives.

A landmark is parametrised *locally*, as seen from the segment's reference pose
(the transducer position of its last echo): ``r`` [m] the distance to the reflecting
point (point) or to the wall (line), ``phi`` [rad] the frame angle of the direction
to the reflecting point or of the wall normal, ``kappa`` [us] the reflector strength
tau/A0. Reading ``i`` of the transducer at ``(px_i, py_i)`` (relative to the reference
position, metres) with axis direction ``yaw_i`` (frame angle, radians) then sees

* point: ``R_i = |r u(phi) - p_i|``, off-axis ``theta_i = angle(r u(phi) - p_i) - yaw_i``;
* line:  ``R_i = r - p_i . u(phi)``, off-axis ``theta_i = phi - yaw_i``;

and reports ``Tm_i = 2 R_i / c + delay(kappa, theta_i)`` plus jitter and counting.
The delay is ``kappa * g(theta)`` with ``g = 1 / rel_amp`` (Gaussian or piston beam;
paper eq. 3). The echo is detected while ``kappa * g / G <= L`` for a log-normal
amplitude gain ``G`` (SD ``sigma_a`` of log G); this gives the detection probability
used for no-echo readings and the mean delay of detected echoes (a truncated
log-normal mean). A stationary pan (all ``p_i = 0``) is the special case where point
and line coincide.

All functions broadcast over leading batch axes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import j1, jv, log_ndtr, ndtr

from sonarloc.physics.tof import ModuleParams

Array = NDArray[np.float64]

TIERS = ("gauss", "piston", "waveform")
"""Model tiers the fitter can use: ``gauss`` (eq. 3, Gaussian main lobe), ``piston``
(eq. 3 with nulls and side lobes), ``waveform`` (piston beam and the simulated 6500
module's threshold crossing: ripple jumps, late weak echoes; also the model of the
simulator's ``auto`` tier, which agrees with it within 1 us)."""

KINDS = ("point", "line")

BEAMS = {"gauss": "gauss", "piston": "piston", "waveform": "piston"}
"""The beam pattern of each tier (``waveform``: the piston beam): tiers with the same
beam have the same :func:`beam_delay_factor`."""

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_TWO_PI = 2.0 * np.pi
_G_MAX = 1e12
"""Largest beam delay factor 1/rel_amp (nulls, the back of the transducer)."""


def wrap_angle(a: ArrayLike) -> Array:
    """Angle(s) wrapped to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    w = np.remainder(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def _wrap_fast(a: Array) -> Array:
    """Angle(s) wrapped to [-pi, pi] (hot paths; -pi and pi both allowed)."""
    if a.size == 0 or (a.max() <= np.pi and a.min() >= -np.pi):
        return a
    return a - _TWO_PI * np.rint(a * (1.0 / _TWO_PI))


def range_angle(kind: str, r: Array, phi: Array, px: Array, py: Array, yaw: Array
                ) -> tuple[Array, Array]:
    """Range [m] and off-axis angle [rad] of moving readings, as :func:`geometry`
    computes them (the same numbers), without its derivatives: what a bracket's nodes
    need. Inputs as :func:`geometry`'s, float arrays; the range of a line has the
    broadcast shape of ``phi`` and the positions."""
    c, s = np.cos(phi), np.sin(phi)
    if kind == "line":
        return r - (px * c + py * s), _wrap_fast(phi - yaw)
    qx = r * c - px
    qy = r * s - py
    return np.sqrt(qx * qx + qy * qy), _wrap_fast(np.arctan2(qy, qx) - yaw)


@dataclass(frozen=True)
class Geometry:
    """Range and off-axis angle of each reading with their derivatives by (r, phi).

    Every field has the broadcast shape of the inputs, (..., n).
    """

    R: Array
    theta: Array
    dR_dr: Array
    dR_dphi: Array
    dtheta_dr: Array
    dtheta_dphi: Array
    moving: bool = True
    """False when all readings were taken at the reference position (derivatives
    ``dR_dr = 1, dR_dphi = 0, dtheta_dr = 0, dtheta_dphi = 1``)."""


def geometry(kind: str, r: ArrayLike, phi: ArrayLike, px: ArrayLike, py: ArrayLike,
             yaw: ArrayLike, moving: bool | None = None) -> Geometry:
    """Range [m] and off-axis angle [rad] of readings for a local landmark (r, phi).

    Parameters
    ----------
    kind : ``"point"`` or ``"line"``.
    r, phi : (..., 1) local landmark parameters (broadcast against the readings).
    px, py, yaw : (..., n) transducer positions relative to the reference position [m]
        and axis directions [rad, frame].
    moving : whether any position is nonzero, if the caller knows (saves the check).
    """
    r = np.asarray(r, dtype=float)
    phi = np.asarray(phi, dtype=float)
    px = np.asarray(px, dtype=float)
    py = np.asarray(py, dtype=float)
    yaw = np.asarray(yaw, dtype=float)
    if kind not in KINDS:
        raise ValueError(f"`kind` must be 'point' or 'line', got {kind!r}")
    if moving is None:
        moving = bool(px.any() or py.any())
    if kind == "line" or not moving:
        # walls, and points seen from one spot (stationary pan): theta = phi - yaw
        theta = _wrap_fast(phi - yaw)
        if moving:
            c, s = np.cos(phi), np.sin(phi)
            R = r - (px * c + py * s)
            dR_dphi = px * s - py * c
        else:
            R = np.broadcast_to(r, theta.shape)
            dR_dphi = np.zeros(())
        shape = np.broadcast_shapes(np.shape(R), theta.shape)
        one, zero = np.ones(()), np.zeros(())
        b = [_broadcast(a, shape) for a in (R, theta, one, dR_dphi, zero, one)]
        return Geometry(b[0], b[1], b[2], b[3], b[4], b[5], moving=moving)
    c, s = np.cos(phi), np.sin(phi)
    qx = r * c - px
    qy = r * s - py
    R2 = qx * qx + qy * qy
    R = np.sqrt(R2)
    safe = np.maximum(R, 1e-9)
    bearing = np.arctan2(qy, qx)
    # dq/dr = u, dq/dphi = r u_perp
    dR_dr = (qx * c + qy * s) / safe
    dR_dphi = r * (-qx * s + qy * c) / safe
    inv = 1.0 / np.maximum(R2, 1e-18)
    dtheta_dr = (qx * s - qy * c) * inv
    dtheta_dphi = r * (qx * c + qy * s) * inv
    theta = _wrap_fast(bearing - yaw)
    shape = np.broadcast_shapes(R.shape, theta.shape)
    b = [_broadcast(a, shape) for a in (R, theta, dR_dr, dR_dphi, dtheta_dr, dtheta_dphi)]
    return Geometry(b[0], b[1], b[2], b[3], b[4], b[5], moving=True)


def _broadcast(a: Array, shape: tuple[int, ...]) -> Array:
    """``np.broadcast_to(a, shape)``, or ``a`` itself where it has that shape already (the
    call costs ~10 us, and a moving fit's model pass makes several: ~0.2 s of a moving
    ring's 300 s drive's fit stage)."""
    return a if a.shape == shape else np.broadcast_to(a, shape)


def beam_delay_factor(theta: ArrayLike, tier: str, params: ModuleParams,
                      derivative: bool = True) -> tuple[Array, Array, Array]:
    """Delay factor g(theta) = 1 / rel_amp(theta), dg/dtheta [1/rad] and ln g.

    ``gauss``: exp(theta^2 / 2 sigma^2); ``piston``: 1 / (2 J1(x) / x)^2 with
    x = pi d sin(theta) / lambda. Capped at 1e12 (nulls, |theta| > 90 deg).
    Without ``derivative`` the second array is ``g`` again.
    """
    t = np.asarray(theta, dtype=float)
    if tier == "gauss":
        inv_s2 = 1.0 / np.deg2rad(params.sigma_deg) ** 2
        e = np.minimum(0.5 * t * t * inv_s2, np.log(_G_MAX))
        g = np.exp(e)
        dg = np.where(e < np.log(_G_MAX), g * t * inv_s2, 0.0) if derivative else g
        return g, dg, e
    if BEAMS.get(tier) == "piston":
        return _piston_table(params.diameter_m, params.carrier_hz, params.c_mps).lookup(
            t, derivative)
    raise ValueError(f"`tier` must be one of {', '.join(TIERS)}; got {tier!r}")


def beam_log_factor(theta: ArrayLike, tier: str, params: ModuleParams,
                    derivative: bool = True, want_g: bool = True
                    ) -> tuple[Array, Array, Array]:
    """g = 1 / rel_amp(theta), d ln g / d theta [1/rad] and ln g (the fitter's form).

    As :func:`beam_delay_factor` (``dg = g * dlng``); ``d ln g / d theta`` is 0 where g
    is capped. Without ``derivative`` the second array is ``ln g``; without ``want_g``
    the first is ``ln g`` too (no exponential computed).
    """
    t = np.asarray(theta, dtype=float)
    if tier == "gauss":
        inv_s2 = 1.0 / np.deg2rad(params.sigma_deg) ** 2
        cap = np.log(_G_MAX)
        e = np.minimum((0.5 * inv_s2) * (t * t), cap)
        g = np.exp(e) if want_g else e
        if not derivative:
            return g, e, e
        dlng = t * inv_s2
        if e.size and e.max() >= cap:       # capped (far off-axis): flat
            dlng[e >= cap] = 0.0
        return g, dlng, e
    if BEAMS.get(tier) == "piston":
        return _piston_table(params.diameter_m, params.carrier_hz, params.c_mps).lookup_log(
            t, derivative, want_g)
    raise ValueError(f"`tier` must be one of {', '.join(TIERS)}; got {tier!r}")


def piston_delay_factor_exact(theta: ArrayLike, params: ModuleParams
                              ) -> tuple[Array, Array, Array]:
    """g = 1 / (2 J1(x) / x)^2, dg/dtheta and ln g from the Bessel functions (reference)."""
    t = np.asarray(theta, dtype=float)
    k = np.pi * params.diameter_m * params.carrier_hz / params.c_mps
    x = k * np.sin(t)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)
    d = np.where(small, 1.0 - x * x / 8.0, 2.0 * j1(xs) / xs)
    a = d * d
    ok = (np.abs(t) < 0.5 * np.pi) & (a > 1.0 / _G_MAX)
    g = np.where(ok, 1.0 / np.where(ok, a, 1.0), _G_MAX)
    dd_dx = np.where(small, -x / 4.0, -2.0 * jv(2, xs) / xs)
    da = 2.0 * d * dd_dx * k * np.cos(t)
    return g, np.where(ok, -da * g * g, 0.0), np.log(g)


@dataclass(frozen=True, eq=False)
class _HermiteTable:
    """ln g(|theta|) and its derivative on a uniform grid; cubic Hermite in between."""

    step: float
    f: Array
    df: Array

    def lookup(self, theta: Array, derivative: bool) -> tuple[Array, Array, Array]:
        u = np.abs(theta) * (1.0 / self.step)
        n = self.f.size - 1
        i = np.minimum(u.astype(np.intp), n - 1)
        s = u - i
        f0, f1 = self.f[i], self.f[i + 1]
        d0, d1 = self.df[i] * self.step, self.df[i + 1] * self.step
        s2 = s * s
        lng = f0 + s2 * (3.0 - 2.0 * s) * (f1 - f0) + s * (1.0 - s) * ((1.0 - s) * d0 - s * d1)
        beyond = u >= n
        lng = np.where(beyond, np.log(_G_MAX), lng)
        g = np.exp(lng)
        if not derivative:
            return g, g, lng
        dlng = ((6.0 * s * (1.0 - s)) * (f1 - f0) + (1.0 - s) * (1.0 - 3.0 * s) * d0
                + s * (3.0 * s - 2.0) * d1) / self.step
        dg = np.where(beyond, 0.0, g * dlng * np.sign(theta))
        return g, dg, lng


    @functools.cached_property
    def coef(self) -> Array:
        """(n, 4) power-basis coefficients of each interval's cubic in s (same curve)."""
        return _hermite_coef(self.f, self.df * self.step)

    def lookup_log(self, theta: Array, derivative: bool, want_g: bool
                   ) -> tuple[Array, Array, Array]:
        """(g, d ln g / d theta, ln g) as :func:`beam_log_factor` returns them (one row
        gather and Horner's rule: the fitter's hot path)."""
        u = np.abs(theta) * (1.0 / self.step)
        coef = self.coef
        n = coef.shape[0]
        i = np.minimum(u.astype(np.intp), n - 1)
        s = u - i
        c = np.take(coef, i, axis=0)
        c1, c2, c3 = c[..., 1], c[..., 2], c[..., 3]
        lng = c[..., 0] + s * (c1 + s * (c2 + s * c3))
        beyond = u >= n
        lng = np.where(beyond, np.log(_G_MAX), lng)
        g = np.exp(lng) if want_g else lng
        if not derivative:
            return g, lng, lng
        dlng = (c1 + s * (2.0 * c2 + 3.0 * s * c3)) * (1.0 / self.step)
        return g, np.where(beyond, 0.0, dlng * np.sign(theta)), lng

    @functools.cached_property
    def coef32(self) -> NDArray[np.float32]:
        """:attr:`coef` in float32 (the float32 passes; rows are gathered whole: one
        row gather costs less than one gather of a column)."""
        return _readonly32(self.coef)

    def lookup_log32(self, theta: NDArray[np.floating[Any]], derivative: bool = True,
                     ddiv: float = 1.0
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None, bool]:
        """ln g and d ln g / d theta / ``ddiv`` (None without ``derivative``) in float32
        (the fitter's float32 passes), and whether any angle lies beyond the table (ln g
        capped there, slope 0). The same cubic as :meth:`lookup_log`. Float64 angles
        are placed in their intervals in float64 (ln g then within float32 rounding of
        the float64 one, also next to the nulls, where ln g changes by ~1e5 per rad);
        float32 angles in float32 (the position in the interval rounded to ~1e-7 of the
        table index: a bracket's precision)."""
        f32 = np.float32
        coef = self.coef32
        n = coef.shape[0]
        u = np.abs(theta)
        u *= u.dtype.type(1.0 / self.step)
        i = u.astype(np.intp)
        beyond = bool(i.size) and int(i.max()) >= n
        far = None
        if beyond:
            far = i >= n
            np.minimum(i, n - 1, out=i)
        if u.dtype == f32:
            s = u
            s -= i.astype(f32)                         # position in the interval
        else:
            u -= i
            s = u.astype(f32)
        lng, dlng = _cubic32(np.take(coef, i, axis=0), s, derivative)
        if dlng is not None:
            dlng *= np.copysign(f32(1.0 / (self.step * ddiv)), theta)
        if far is not None:
            lng[far] = f32(np.log(_G_MAX))
            if dlng is not None:
                dlng[far] = 0.0
        return lng, dlng, beyond


def _readonly32(coef: Array) -> NDArray[np.float32]:
    """A read-only float32 copy of a table's coefficients."""
    out = coef.astype(np.float32)
    out.setflags(write=False)
    return out


def _cubic32(c: NDArray[np.float32], s: NDArray[np.float32], derivative: bool
             ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """The cubic c0 + c1 s + c2 s^2 + c3 s^3 of each entry's coefficient row ``c``
    (..., >= 4) at its position ``s`` in the interval, and its derivative by s (None
    without ``derivative``), by Horner's rule in float32 (the tables' float32 lookups)."""
    a1, a2, a3 = c[..., 1], c[..., 2], c[..., 3]
    d = None
    if derivative:
        d = a3 * (np.float32(3.0) * s)
        d += np.float32(2.0) * a2
        d *= s
        d += a1
    v = a3 * s
    v += a2
    v *= s
    v += a1
    v *= s
    v += c[..., 0]
    return v, d


def _hermite_coef(f: Array, d: Array) -> Array:
    """Coefficients (n, 4) of the cubic Hermite interpolant through values ``f`` (n+1)
    with slopes ``d`` (n+1, per unit of the local coordinate s in [0, 1])."""
    f0, f1, d0, d1 = f[:-1], f[1:], d[:-1], d[1:]
    coef = np.stack([f0, d0, 3.0 * (f1 - f0) - 2.0 * d0 - d1, 2.0 * (f0 - f1) + d0 + d1],
                    axis=1)
    coef.setflags(write=False)
    return coef


@functools.lru_cache(maxsize=16)
def _piston_table(diameter_m: float, carrier_hz: float, c_mps: float) -> _HermiteTable:
    """The piston delay factor tabulated once per transducer (Bessel functions are slow)."""
    params = ModuleParams(diameter_m=diameter_m, carrier_hz=carrier_hz, c_mps=c_mps)
    step = 2.5e-4
    th = np.arange(0.0, 0.5 * np.pi, step)
    g, dg, lng = piston_delay_factor_exact(th, params)
    dlng = np.where(g < _G_MAX, dg / g, 0.0)
    f, df = np.append(lng, np.log(_G_MAX)), np.append(dlng, 0.0)
    f.setflags(write=False)
    df.setflags(write=False)
    return _HermiteTable(step, f, df)


def sigma_a(params: ModuleParams) -> float:
    """SD of the log echo amplitude used by the detection model (at least 0.05)."""
    return max(float(params.amplitude_fluctuation), 0.05)


def detection_z(kappa: ArrayLike, log_g: ArrayLike, params: ModuleParams) -> Array:
    """Standardised log delay margin z = ln(kappa g / L) / sigma_a, from ln g.

    P(no echo) = Phi(z), P(echo) = Phi(-z).
    """
    lk = np.log(np.maximum(np.asarray(kappa, float), 1e-300))
    return (lk + np.asarray(log_g, float) - np.log(params.detection_limit_us)) / sigma_a(params)


_Z_HIGH = 7.0
_Z_FAST = 30.0     # below, P(echo) = Phi(-z) > 1e-198: no underflow in ndtr
_Z_LOW = -10.0


def probit_terms(v: ArrayLike, want_info: bool = True) -> tuple[Array, Array, Array]:
    """log Phi(v), its derivative phi(v)/Phi(v), and the Bernoulli Fisher information.

    The general reference form; the fitter's hot path uses :func:`echo_terms` and
    :func:`noecho_terms`, which tests check against this.

    The information of an event of probability Phi(v) per unit v^2 is
    phi(v)^2 / (Phi(v) Phi(-v)). Exact (``scipy.special.log_ndtr``) for -10 < v < 7;
    beyond, Phi(v) = 1 to 2e-12, or the asymptotic series of the Mills ratio (relative
    error < 1e-9), which keeps the cost of batch fits low.
    """
    v = np.asarray(v, dtype=float)
    logp = np.zeros(v.shape)
    mills = np.zeros(v.shape)
    info = np.zeros(v.shape)
    mid = (v > _Z_LOW) & (v < _Z_HIGH)
    low = v <= _Z_LOW
    if low.any():
        vl = v[low]
        inv2 = 1.0 / (vl * vl)
        # Phi(v) ~ phi(v)/|v| * sum_k (-1)^k (2k-1)!! / v^2k
        series = np.ones_like(vl)
        term = np.ones_like(vl)
        for k in range(1, 9):
            term = -term * (2 * k - 1) * inv2
            series = series + term
        logp[low] = -0.5 * vl * vl - np.log(-vl) - _LOG_SQRT_2PI + np.log(series)
        mills[low] = -vl / series
    if mid.any():
        vm = v[mid]
        lp = log_ndtr(vm)
        lpdf = -0.5 * vm * vm - _LOG_SQRT_2PI
        logp[mid] = lp
        mills[mid] = np.exp(lpdf - lp)
        if want_info:
            info[mid] = np.exp(2.0 * lpdf - lp - log_ndtr(-vm))
    return logp, mills, info


@dataclass(frozen=True)
class EchoTerms:
    """Detection-model terms of detected echoes (shape of the inputs).

    ``log_p``: log P(echo) = log Phi(-z); ``dlogp_dz``: its derivative by z;
    ``info``: Bernoulli (expected) information per unit z^2; ``curv``: the observed
    curvature d^2(-log P)/dz^2 (larger than ``info`` for unlikely echoes);
    ``delay``: mean delay of a detected echo [us]; ``ddelay_du``: its derivative by
    the eq. 3 delay u = kappa g; ``delay_var``: the delay's variance [us^2] (amplitude
    fluctuation; the reading adds jitter and counting).
    """

    log_p: Array
    dlogp_dz: Array
    info: Array
    curv: Array
    delay: Array
    ddelay_du: Array
    delay_var: Array


def echo_terms(kappa: ArrayLike, g: ArrayLike, z: ArrayLike | None, params: ModuleParams,
               want_info: bool = True, tier: str = "gauss") -> EchoTerms:
    """Mean delay and detection terms of detected echoes in one pass (the fit's hot path).

    ``z`` = :func:`detection_z`; None = no detection model (untruncated mean, P = 1).
    Exact where z > -7; deeper inside the arc P(echo) = 1 and the truncation vanish
    to 1e-12 and the constants are used. ``tier="waveform"``: the delay moments of the
    simulated module (:func:`waveform_delay_table`) instead of eq. 3's.
    """
    s = sigma_a(params)
    u = np.asarray(kappa, float) * np.asarray(g, float)
    scale = np.exp(0.5 * s * s)
    zeros = np.zeros(u.shape)
    if z is None:
        if tier == "waveform":
            m, dm, var = waveform_delay_table(params).lookup(u)
            return EchoTerms(zeros, zeros, zeros, zeros, m, dm, var)
        d = u * scale
        return EchoTerms(zeros, zeros, zeros, zeros, d, np.full(u.shape, scale), (s * d) ** 2)
    zf: Array = _broadcast(np.asarray(z, dtype=float), u.shape)
    act = zf > -_Z_HIGH
    n_act = int(np.count_nonzero(act))
    waveform = tier == "waveform"
    act_idx: NDArray[np.bool_] | None = act
    if 4 * n_act >= zf.size:
        # mostly near the arc edge: all at once (deeper inside clipped to z = -7, where
        # the terms are within 1e-10 of the constants) rather than masked
        if n_act < zf.size:
            zf = np.maximum(zf, -_Z_HIGH)
        log_p, m0, curv, ratio, dratio = _echo_core(zf, s, waveform)
        act_idx = None
    else:
        log_p, dlogp_, curv, ratio, dratio = (np.zeros(u.shape), np.zeros(u.shape),
                                              np.zeros(u.shape), np.ones(u.shape),
                                              np.zeros(u.shape))
        m0 = dlogp_
        if n_act:
            za = zf[act]
            lp_a, m0_a, curv_a, ratio_a, dratio_a = _echo_core(za, s, waveform)
            log_p[act], m0[act], curv[act] = lp_a, m0_a, curv_a
            if not waveform:
                ratio[act], dratio[act] = ratio_a, dratio_a
    dlogp = -m0
    info = np.zeros(u.shape)
    if want_info and n_act:
        l0 = log_p if act_idx is None else log_p[act_idx]
        za = zf if act_idx is None else zf[act_idx]
        lpdf = -0.5 * za ** 2 - _LOG_SQRT_2PI
        with np.errstate(divide="ignore"):
            lq = np.log(-np.expm1(l0))        # log Phi(z), accurate for all z
        if act_idx is None:
            info = np.exp(2.0 * lpdf - l0 - lq)
        else:
            info[act_idx] = np.exp(2.0 * lpdf - l0 - lq)
    if waveform:
        m, dm, var = waveform_delay_table(params).lookup(u)
        return EchoTerms(log_p, dlogp, info, curv, m, dm, var)
    d = u * (scale * ratio)
    return EchoTerms(log_p, dlogp, info, curv, d, scale * (ratio + dratio / s), (s * d) ** 2)


def _echo_core(z: Array, s: float, waveform: bool
               ) -> tuple[Array, Array, Array, Array, Array]:
    """log Phi(-z), phi(z)/Phi(-z), the curvature of -log Phi(-z), and (not for the
    waveform tier) the truncation ratio Phi(-z-s)/Phi(-z) and its derivative by z."""
    # Phi and phi directly (ndtr costs half of log_ndtr) where Phi(-z) is far from
    # underflow; the log form for the rest (z > 30: echoes the model cannot explain)
    p0 = ndtr(-z)                                   # P(echo)
    inv_p0 = 1.0 / np.maximum(p0, 1e-300)
    with np.errstate(divide="ignore"):
        l0 = np.log(p0)
    lpdf = -0.5 * z * z - _LOG_SQRT_2PI
    m0 = np.exp(lpdf) * inv_p0                      # phi(z) / Phi(-z)
    far = z > _Z_FAST
    any_far = bool(far.any())
    if any_far:
        l0[far] = log_ndtr(-z[far])
        m0[far] = np.exp(lpdf[far] - l0[far])
    curv = m0 * (m0 - z)
    if waveform:
        return l0, m0, curv, m0, m0
    zs = z + s
    ratio = ndtr(-zs) * inv_p0                      # Phi(-z-s) / Phi(-z)
    m1 = np.exp(-0.5 * zs * zs - _LOG_SQRT_2PI) * inv_p0
    if any_far:
        ratio[far] = np.exp(log_ndtr(-zs[far]) - l0[far])
        m1[far] = np.exp(-0.5 * zs[far] ** 2 - _LOG_SQRT_2PI - l0[far])
    return l0, m0, curv, ratio, ratio * m0 - m1


@dataclass(frozen=True, eq=False)
class _DelayTable:
    """Moments of a detected echo's delay against x = ln u on a uniform grid."""

    x0: float
    dx: float
    mean: Array
    dmean_dx: Array
    var: Array
    small_scale: float

    @functools.cached_property
    def coef(self) -> Array:
        """(n, 6): the mean's cubic in s (power basis) and the variance's line, per
        interval."""
        c = _hermite_coef(self.mean, self.dmean_dx * self.dx)
        out = np.concatenate([c, self.var[:-1, None], np.diff(self.var)[:, None]], axis=1)
        out.setflags(write=False)
        return out

    def lookup(self, u: Array) -> tuple[Array, Array, Array]:
        """Mean delay, its derivative by u, and the delay variance at eq. 3 delays u."""
        x = np.log(np.maximum(u, 1e-300))
        coef = self.coef
        n = coef.shape[0]
        t = (x - self.x0) * (1.0 / self.dx)
        below = t < 0.0
        tc = np.clip(t, 0.0, n)
        i = np.minimum(tc.astype(np.intp), n - 1)
        s = tc - i
        c = np.take(coef, i, axis=0)
        c1, c2, c3 = c[..., 1], c[..., 2], c[..., 3]
        m = c[..., 0] + s * (c1 + s * (c2 + s * c3))
        dm_dx = (c1 + s * (2.0 * c2 + 3.0 * s * c3)) * (1.0 / self.dx)
        dm_dx = np.where(t > n, 0.0, dm_dx)
        var = c[..., 4] + s * c[..., 5]
        # below the table (u < 1e-3 us) the module is eq. 3 with a log-normal gain
        if below.any():
            m = np.where(below, u * self.small_scale, m)
            dm_du = np.where(below, self.small_scale, dm_dx / np.maximum(u, 1e-300))
            var = np.where(below, (0.25 * u) ** 2, var)
        else:
            dm_du = dm_dx / np.maximum(u, 1e-300)
        return m, dm_du, var

    @functools.cached_property
    def coef32(self) -> NDArray[np.float32]:
        """:attr:`coef` in float32 (the float32 passes; rows are gathered whole)."""
        return _readonly32(self.coef)

    def lookup_log32(self, x: NDArray[np.float32], derivative: bool = True
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None,
                                NDArray[np.float32]]:
        """Mean delay, its derivative by x = ln u (None without ``derivative``) and the
        delay variance at float32 ``x`` (the fitter's float32 passes: ``ln u = ln kappa +
        ln g`` needs no logarithm there), in float32; the same curves as :meth:`lookup`
        (d mean / d u = (d mean / d x) / u)."""
        f32 = np.float32
        coef = self.coef32
        n = coef.shape[0]
        t = x - f32(self.x0)
        t *= f32(1.0 / self.dx)
        below = bool(t.size) and float(t.min()) < 0.0
        above = bool(t.size) and float(t.max()) > n
        tc = np.clip(t, f32(0.0), f32(n)) if below or above else t.copy()
        i = tc.astype(np.intp)
        np.minimum(i, n - 1, out=i)
        s = tc
        s -= i.astype(f32)
        c = np.take(coef, i, axis=0)
        m, dm = _cubic32(c, s, derivative)
        if dm is not None:
            dm *= f32(1.0 / self.dx)
            if above:
                dm[t > n] = 0.0
        var = c[..., 5] * s
        var += c[..., 4]
        # below the table (u < 1e-3 us) the module is eq. 3 with a log-normal gain
        if below:
            lo = t < 0.0
            u = np.exp(x[lo])
            m[lo] = u * f32(self.small_scale)
            var[lo] = (f32(0.25) * u) ** 2
            if dm is not None:
                dm[lo] = m[lo]                         # d (u c) / d ln u = u c
        return m, dm, var


@functools.lru_cache(maxsize=8)
def waveform_delay_table(params: ModuleParams) -> _DelayTable:
    """Mean, derivative and variance of the waveform tier's delay given detection.

    For an eq. 3 delay u (median over the amplitude gain), the reading's delay is
    W(u / G) (:func:`sonarloc.physics.waveform.crossing_delay_us`) with log-normal G,
    detected when u / G is below the detection limit. Its moments are kernel sums over
    a fixed grid of v = u / G (finest towards the limit, where W climbs steeply), so
    they are smooth in u and the derivative is exact; computed once per module.
    """
    from sonarloc.physics.waveform import crossing_delay_us, waveform_template

    s = sigma_a(params)
    peak = float(waveform_template(params).running_max[-1])
    top = np.log(peak)
    span = np.log(peak / 1e-3)
    edges = np.unique(top - np.concatenate([[span], np.geomspace(span, 1e-9, 2500), [0.0]]))
    y = 0.5 * (edges[1:] + edges[:-1])
    dy = np.diff(edges)
    W = crossing_delay_us(np.exp(y), params)
    W = np.where(np.isfinite(W), W, 0.0)
    x = np.linspace(np.log(1e-3), np.log(params.detection_limit_us) + 6.0 * s, 512)
    # the kernel k = exp(-a^2 / 2) dy, a = (x - y) / s, and its derivative by x,
    # -a / s k, with their W-weighted sums; in place (each (512, 2500) temporary costs
    # as much as the arithmetic), the same operations as the plain expressions
    a = np.subtract(x[:, None], y[None, :])
    a /= s
    k = np.multiply(a, -0.5)
    k *= a
    np.exp(k, out=k)
    k *= dy
    kw = k * W
    D, N = k.sum(1), kw.sum(1)
    kw *= W
    E2 = kw.sum(1)
    dk = np.negative(a, out=a)
    dk /= s
    dk *= k
    Dp = dk.sum(1)
    dk *= W
    Np = dk.sum(1)
    mean = N / D
    dmean = (Np * D - N * Dp) / (D * D)
    var = np.maximum(E2 / D - mean * mean, 0.0)
    for arr in (mean, dmean, var):
        arr.setflags(write=False)
    return _DelayTable(float(x[0]), float(x[1] - x[0]), mean, dmean, var,
                       float(np.exp(0.5 * s * s)))


def noecho_terms(z: ArrayLike, want_info: bool = True
                 ) -> tuple[Array, Array, Array, Array]:
    """log P(no echo) = log Phi(z), its derivative by z, the Bernoulli (expected)
    information and the observed curvature d^2(-log P)/dz^2.

    Exact where z < 7; beyond, P = 1 to 1.3e-12 and the constants are used.
    """
    z = np.asarray(z, dtype=float)
    act = z < _Z_HIGH
    n_act = int(np.count_nonzero(act))
    if 4 * n_act >= z.size:
        # mostly near the arc: all at once (beyond clipped to z = 7, where the terms are
        # within 1e-10 of the constants) rather than masked
        za = z if n_act == z.size else np.minimum(z, _Z_HIGH)
        n_act = z.size
    else:
        za = z[act]
    # Phi directly (half the cost of log_ndtr) where it is far from underflow
    p = ndtr(za)
    with np.errstate(divide="ignore"):
        lp = np.log(p)
    lpdf = -0.5 * za * za - _LOG_SQRT_2PI
    low = za < -_Z_FAST
    if low.any():
        lp[low] = log_ndtr(za[low])
    m = np.exp(lpdf - lp)
    cv = m * (za + m)
    info_a = None
    if want_info:
        with np.errstate(divide="ignore"):
            lq = np.log(-np.expm1(lp))
        info_a = np.exp(2.0 * lpdf - lp - lq)
    if n_act == z.size:
        return lp, m, info_a if info_a is not None else np.zeros(z.shape), cv
    log_p = np.zeros(z.shape)
    dlogp = np.zeros(z.shape)
    info = np.zeros(z.shape)
    curv = np.zeros(z.shape)
    if n_act:
        log_p[act], dlogp[act], curv[act] = lp, m, cv
        if info_a is not None:
            info[act] = info_a
    return log_p, dlogp, info, curv


def mean_delay(kappa: ArrayLike, g: ArrayLike, params: ModuleParams,
               z: ArrayLike | None = None, tier: str = "gauss") -> tuple[Array, Array]:
    """Mean threshold delay [us] of a *detected* echo and its derivative by u = kappa g.

    With a log-normal gain the eq. 3 delay is u / G; its mean is u exp(s^2/2) and, given
    detection (delay <= L, pass the detection margin ``z``), the truncated mean
    u exp(s^2/2) Phi(-z - s) / Phi(-z). (The ``delay`` fields of :func:`echo_terms`,
    the same numbers, without its detection terms: the waveform tier's delay table holds
    the truncation at the detection limit already, so it does not need ``z``.)
    """
    et = echo_terms(kappa, g, None if tier == "waveform" else z, params, want_info=False,
                    tier=tier)
    return et.delay, et.ddelay_du


def tof_variance_us2(delay_us: ArrayLike, params: ModuleParams,
                     delay_var: ArrayLike | None = None) -> Array:
    """Variance [us^2] of a reading with mean delay ``delay_us``: jitter model + counting.

    ``jitter_sd_us(delay)^2 + period^2 / 12`` with :func:`sonarloc.physics.jitter_sd_us`
    written out (no square root) because it runs in the fitter's inner loop; with
    ``delay_var`` (a model's own delay variance, e.g. the waveform tier's), the timing
    jitter, that variance and counting.
    """
    base = params.jitter_sd_us ** 2 + params.count_period_us ** 2 / 12.0
    if delay_var is not None:
        return base + np.asarray(delay_var, dtype=float)
    d = np.asarray(delay_us, dtype=float)
    a = params.amplitude_fluctuation
    return base + (a * a) * (d * d)


def us_per_m(params: ModuleParams) -> float:
    """Round-trip microseconds per metre of range, 2e6 / c."""
    return 2e6 / params.c_mps


def module_reach_m(module: ModuleParams) -> tuple[float, float]:
    """Ranges [m] outside which a fitted landmark cannot be one the module measured:
    half the range its blanking hides (no echo is reported before ``blanking_us``; a
    fit's range sits somewhat below its echoes' at the arc's edges, not by half) and
    twice its maximum range (an echo from beyond it is too weak to be detected).

    TOFs recorded in milliseconds, a timeout count reported as an echo, or a module
    other than the one configured put the fit there (without these bounds such fits
    were ``OK``: a pole 1 mm away, the fit's range bound, from a pan logged in ms; a
    wall 1715 m away from readings of 1e7 us: tests/fit/test_fit_fuzz.py); the
    two-reflector fit's landmarks are held to the same bounds."""
    blank_m = module.blanking_us / us_per_m(module)
    return 0.5 * blank_m, 2.0 * module.max_range_m


def to_frame(kind: str, local: ArrayLike, local_cov: ArrayLike, ref_xy: ArrayLike
             ) -> tuple[Array, Array, Array]:
    """Frame parameters and covariance from local (r, phi, kappa).

    Parameters
    ----------
    kind : ``"point"`` or ``"line"``.
    local : (..., 3) ``(r [m], phi [rad], kappa [us])`` seen from ``ref_xy``.
    local_cov : (..., 3, 3) their covariance.
    ref_xy : (..., 2) reference transducer position in the frame [m].

    Returns
    -------
    params : (..., 3) ``(x_m, y_m, kappa_us)`` (point) or ``(rho_m, alpha_rad, kappa_us)``
        (line, ``rho >= 0``, alpha in (-pi, pi]).
    cov : (..., 3, 3) covariance of ``params``.
    jac : (..., 3, 3) d params / d local.
    """
    p = np.asarray(local, dtype=float)
    C = np.asarray(local_cov, dtype=float)
    ref = np.asarray(ref_xy, dtype=float)
    r, phi, kap = p[..., 0], p[..., 1], p[..., 2]
    c, s = np.cos(phi), np.sin(phi)
    J = np.zeros(p.shape[:-1] + (3, 3))
    J[..., 2, 2] = 1.0
    if kind == "point":
        out = np.stack([ref[..., 0] + r * c, ref[..., 1] + r * s, kap], axis=-1)
        J[..., 0, 0], J[..., 0, 1] = c, -r * s
        J[..., 1, 0], J[..., 1, 1] = s, r * c
    elif kind == "line":
        rho = r + ref[..., 0] * c + ref[..., 1] * s
        flip = rho < 0
        sign = np.where(flip, -1.0, 1.0)
        alpha = wrap_angle(np.where(flip, phi + np.pi, phi))
        out = np.stack([np.abs(rho), alpha, kap], axis=-1)
        J[..., 0, 0] = sign
        J[..., 0, 1] = sign * (-ref[..., 0] * s + ref[..., 1] * c)
        J[..., 1, 1] = 1.0
    else:
        raise ValueError(f"`kind` must be 'point' or 'line', got {kind!r}")
    cov = J @ C @ np.swapaxes(J, -1, -2)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    return out, cov, J


_SF_DEGREE = 9
"""Degree of the polynomial of :func:`log_sf32` (error of log erfc < 3e-7, float32's)."""

_LOG_ERFC_POLY = (
    0.00033377548741319484, -0.0002079289176496348, -0.0020488139472272134,
    0.0017765992797309745, 0.008703864001330795, -0.00987378730693407,
    -0.04687490055170361, 0.047343109384155854, 0.6726422179287886, -0.6717940761316655)
"""The coefficients of :func:`log_sf32`: :func:`fit_log_erfc_poly`'s result, as
constants (the fit's least squares cost every process that fits ~40 ms CPU with
OpenBLAS's default threads, as a library user's may run, 2 ms with one thread;
tests/fit/test_fit_model.py checks these are its result)."""


def fit_log_erfc_poly(degree: int = _SF_DEGREE) -> tuple[float, ...]:
    """Power-basis coefficients (highest first) of ``p(v)``, ``v = 2 t - 1``,
    ``t = 1 / (1 + a / 2)``, with ``log erfc(a) = log t - a^2 + p(v)`` for ``a >= 0``.

    A least-squares Chebyshev fit at 4000 Chebyshev nodes of t in (0, 1]
    (``log erfcx(a) - log t`` is smooth there, tending to ``-log(2 sqrt(pi))`` as
    a -> inf), converted to powers of v (coefficients below 1 in size: Horner's rule
    is stable)."""
    from numpy.polynomial import chebyshev as cheb
    from scipy.special import erfcx

    t = 0.5 + 0.5 * np.cos(np.pi * (np.arange(4000) + 0.5) / 4000)
    t = t[t > 1e-6]
    a = 2.0 / t - 2.0
    c = cheb.chebfit(2.0 * t - 1.0, np.log(erfcx(a)) - np.log(t), degree)
    return tuple(float(v) for v in cheb.cheb2poly(c)[::-1])


_LOG_ERFC_POLY32 = tuple(np.float32(c) for c in _LOG_ERFC_POLY)
_SQRT_HALF32 = np.float32(np.sqrt(0.5))
_LN2_32 = np.float32(np.log(2.0))


def log_sf32(z: NDArray[np.float32]) -> NDArray[np.float32]:
    """log Phi(-z) (the log survival function of the standard normal) in float32,
    branch-free, for any z (no underflow: the upper tail from its log form).

    ``scipy.special.ndtr`` branches on the argument (erf or erfc, two rational
    approximations) and costs 10-45 ns per element on arrays mixing both sides of
    ~0.7; this is ~40 float32 array operations (a few ns). Absolute error below 2e-7
    in log Phi(-z) and relative error below 2e-7 in Phi(-z) (float32 rounding); tested
    against ``scipy.special.log_ndtr``.
    """
    # (constants: Python floats, or float32 for numpy's own scalars: a Python float
    # meets a float32 array as float32, NEP 50, and costs no scalar of its own per call)
    a = np.abs(z) * _SQRT_HALF32                       # erfc argument |z| / sqrt 2
    t = 1.0 / (1.0 + 0.5 * a)
    v = 2.0 * t - 1.0
    c0, *coef = _LOG_ERFC_POLY32
    acc = v * c0                                       # Horner's rule from c0 v
    for c in coef[:-1]:
        acc += c
        acc *= v
    acc += coef[-1]
    le = np.log(t)
    a *= a
    le -= a
    le += acc                                          # log erfc(|z| / sqrt 2)
    # z >= 0: log(erfc / 2); z < 0: log(1 - erfc / 2); both finite for every z, so a
    # blend by 0/1 weights (exact: one term is 0) replaces a masked select (which
    # costs more than all of the above on mixed signs)
    neg = (z < 0).astype(np.float32)
    lo = np.log(1.0 - 0.5 * np.exp(le))               # abs. error < 6e-8 (as log1p)
    lo *= neg
    le -= _LN2_32
    le *= 1.0 - neg
    le += lo
    return le


def mills_ratio32(z: NDArray[np.float32], log_sf: NDArray[np.float32]
                  ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The Mills ratio m = phi(z) / Phi(-z) and its excess m - z (m (m - z) is m's
    derivative by z, the curvature of -log Phi(-z)) in float32, from ``log_sf`` =
    :func:`log_sf32` of z: m = exp(-z^2 / 2 - log sqrt(2 pi) - log Phi(-z)), m - z their
    difference below :data:`Z_CF`; from there on up, where m - z ~ 1/z is a small
    difference of large numbers (the exponent's rounding, ~z^2 1e-7 of m: at z = 90,
    an echo far beyond the model's detection limit while a fit explores, m - z to
    ~100 %), :func:`mills_excess_cf32` and m = z + (m - z)."""
    f32 = np.float32
    m = np.exp(f32(-0.5) * z * z - f32(_LOG_SQRT_2PI) - log_sf)
    h = m - z
    far = np.flatnonzero(z >= f32(Z_CF))
    if far.size:
        zf = np.take(z, far)
        hf = mills_excess_cf32(zf)
        np.put(h, far, hf)
        np.put(m, far, zf + hf)
    return m, h


Z_CF = 4.0
"""From here on up the Mills ratio's excess m - z is :func:`mills_excess_cf32`'s."""


def mills_excess_cf32(z: NDArray[np.float32]) -> NDArray[np.float32]:
    """m - z of the Mills ratio m = phi(z) / Phi(-z) for z >= :data:`Z_CF` in float32:
    the continued fraction 1 / (z + 2 / (z + 3 / (z + ...))) with 10 terms (relative
    error < 3e-7 there)."""
    t = z.copy()
    for k in range(10, 1, -1):
        t = z + np.float32(k) / t
    return np.float32(1.0) / t
