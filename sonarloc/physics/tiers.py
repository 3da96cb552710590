"""Model tiers: the cheapest model that explains a reading, and which one was used.

* ``gauss``    eq. 3 with the Gaussian main lobe (no side lobes, no ripple);
* ``piston``   eq. 3 with the piston pattern (nulls and side lobes);
* ``waveform`` the simulated ranging module (ripple jumps, decreasing slope) driven by
               the piston pattern (:mod:`sonarloc.physics.waveform`);
* ``auto``     per echo, the cheapest of the three that is accurate for it.

Every tier draws the same random amplitude gain per echo (log-normal, SD
``amplitude_fluctuation``), so for one seed the tiers differ only by their model.
All tiers detect an echo exactly when ``kappa / (a * gain) <= detection_limit_us``
for their amplitude ``a``; the waveform tier is calibrated to that (its processed
signal peaks at the limit).

The ``auto`` rule (per echo, with ``s = kappa/gain`` the strength of this echo):

1. *No echo in any tier* if even the largest piston amplitude at this or any larger
   angle (the side-lobe envelope) cannot reach the threshold: recorded as ``gauss``.
2. *Gaussian* where |theta| <= theta_g(s): the largest angle up to which the Gaussian
   eq. 3 delay stays within ``GAUSS_TOLERANCE_US`` of the piston one,
   ``s * |1/a_gauss - 1/a_piston| <= tol`` at every smaller angle. Strong reflectors
   get up to about 12 deg (never the first null, 13.7 deg); weak ones stop earlier
   (pole 7.5 deg, rod 5.6 deg at unit gain).
3. *Piston* elsewhere (outside the Gaussian's valid region, side lobes of strong
   reflectors), and for echoes whose Gaussian delay is within ``GAUSS_TOLERANCE_US``
   of ``u_w`` (they are re-evaluated with the piston pattern).
4. *Waveform* where the piston eq. 3 delay ``u`` exceeds ``u_w``: the largest delay up
   to which the waveform tier agrees with eq. 3 within ``WAVEFORM_TOLERANCE_US``
   (3.37 us for the default module: the end of the first half cycle of the
   processed echo). Beyond it the waveform tier changes the answer (ripple jumps,
   late weak echoes), so it is used.

The decisions cost two table look-ups per echo at one grid index (tables on a
uniform 0.01 deg grid, built once per :class:`ModuleParams`); the Gaussian pattern
is computed for every echo (it is the cheapest), the piston pattern only outside
the Gaussian's region, the waveform only for weak echoes. The piston pattern and the
waveform crossing are table look-ups too, so every tier costs about the same per
echo (benchmarks/results/physics.md); ``auto`` buys the waveform's fidelity (within
1 us, same detections) with eq. 3-exact readings where eq. 3 is accurate, and the
per-echo record of which model mattered.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from sonarloc.physics.beam import gaussian_echo, piston_echo, piston_one_way
from sonarloc.physics.tof import ModuleParams
from sonarloc.physics.waveform import crossing_delay_us, eq3_agreement_limit_us


class Tier(enum.IntEnum):
    """Model tier codes (small ints so per-reading tier arrays stay compact)."""

    GAUSS = 0
    PISTON = 1
    WAVEFORM = 2
    AUTO = 3

    @classmethod
    def parse(cls, name: str | Tier) -> Tier:
        """Tier from its name (case-insensitive) or a :class:`Tier`."""
        if isinstance(name, Tier):
            return name
        try:
            return cls[str(name).upper()]
        except KeyError:
            raise ValueError(
                f"`tier` must be one of gauss, piston, waveform, auto; got {name!r}"
            ) from None

    @property
    def label(self) -> str:
        return self.name.lower()


GAUSS_TOLERANCE_US = 0.5
"""Largest noise-free delay error [us] for which ``auto`` accepts the Gaussian beam
(a quarter of the 2 us count, a tenth of the 5 us jitter)."""

WAVEFORM_TOLERANCE_US = 0.5
"""Largest difference [us] between waveform and eq. 3 delays that ``auto`` ignores."""

_THETA_STEP_RAD = np.deg2rad(0.01)
_SIN_STEP = 1e-4


@dataclass(frozen=True, eq=False)
class AutoTables:
    """Precomputed tables of the tiers for one :class:`ModuleParams`.

    ``mismatch`` and ``envelope`` live on the grid theta_i = i * theta_step_rad,
    0 <= theta_i <= pi/2; ``piston_one_way`` on the grid sin(theta) = j * sin_step.

    Attributes
    ----------
    mismatch : (n,) largest |1/a_gauss - 1/a_piston| at any angle up to theta_(i+1)
        (non-decreasing; infinite from the piston's first null on). A reflector of
        strength s may use the Gaussian at |theta| <= theta_i if s * mismatch[i] <= tol.
    envelope : (n,) largest echo amplitude (piston or Gaussian) at theta_i or any
        larger angle (non-increasing): nothing weaker than ``limit * envelope`` is
        detectable there.
    piston_one_way : (m + 1,) one-way piston pattern 2 J1(x)/x at sin(theta) = j *
        sin_step; linear interpolation of it, squared, gives the echo pattern within
        2e-7 (faster than evaluating J1).
    piston_slope : (m + 1,) increment of ``piston_one_way`` to the next node.
    waveform_from_us : u_w, eq. 3 delay beyond which the waveform tier is used.
    theta_step_rad, sin_step : grid spacings.
    """

    mismatch: NDArray[np.float64]
    envelope: NDArray[np.float64]
    piston_one_way: NDArray[np.float64]
    piston_slope: NDArray[np.float64]
    waveform_from_us: float
    theta_step_rad: float
    sin_step: float


@functools.lru_cache(maxsize=16)
def auto_tables(params: ModuleParams = ModuleParams(),
                waveform_tolerance_us: float = WAVEFORM_TOLERANCE_US) -> AutoTables:
    """Build (once per argument set) the tables behind the tiers and the auto decisions."""
    if not (np.isfinite(waveform_tolerance_us) and waveform_tolerance_us > 0):
        raise ValueError(
            f"`waveform_tolerance_us` must be positive, got {waveform_tolerance_us!r}")
    theta = np.arange(int(np.ceil(np.pi / 2 / _THETA_STEP_RAD)) + 1) * _THETA_STEP_RAD
    a_g = gaussian_echo(theta, params.sigma_deg)
    a_p = piston_echo(theta, params.diameter_m, params.carrier_hz, params.c_mps)
    tiny = 1e-300
    inv_g = 1.0 / np.maximum(a_g, tiny)
    inv_p = np.where(a_p > tiny, 1.0 / np.maximum(a_p, tiny), np.inf)
    worst = np.maximum.accumulate(np.abs(inv_g - inv_p))
    mismatch = np.append(worst[1:], np.inf)  # next node up: safe for |theta| in a cell
    envelope = np.maximum.accumulate(np.maximum(a_p, a_g)[::-1])[::-1]
    n_sin = int(round(1.0 / _SIN_STEP))
    sin_grid = np.minimum(np.arange(n_sin + 1) * _SIN_STEP, 1.0)
    one_way = piston_one_way(np.arcsin(sin_grid), params.diameter_m, params.carrier_hz,
                             params.c_mps)
    slope = np.append(np.diff(one_way), 0.0)
    for arr in (mismatch, envelope, one_way, slope):
        arr.setflags(write=False)
    return AutoTables(mismatch, envelope, one_way, slope,
                      eq3_agreement_limit_us(params, waveform_tolerance_us),
                      _THETA_STEP_RAD, _SIN_STEP)


def tabulated_piston_echo(theta_rad: ArrayLike,
                          params: ModuleParams = ModuleParams()) -> NDArray[np.float64]:
    """The piston echo pattern from the table the tiers use (within 2e-7 of
    :func:`~sonarloc.physics.beam.piston_echo`). Shape of ``theta_rad``."""
    return _piston_fast(np.asarray(theta_rad, dtype=float), auto_tables(params))


def _piston_fast(theta: NDArray[np.float64], tables: AutoTables) -> NDArray[np.float64]:
    x = np.sin(theta, out=np.empty_like(theta))
    np.abs(x, out=x)
    x *= 1.0 / tables.sin_step  # at most the last node, whose slope is 0
    j = x.astype(np.intp)
    x -= j
    x *= tables.piston_slope[j]
    x += tables.piston_one_way[j]
    x *= x
    return x


def gauss_valid_rad(kappa_us: ArrayLike, params: ModuleParams = ModuleParams(),
                    tolerance_us: float = GAUSS_TOLERANCE_US) -> NDArray[np.float64]:
    """Largest off-axis angle up to which the Gaussian eq. 3 delay is within tolerance.

    For a reflector of strength ``kappa_us`` (unit gain), the Gaussian delay
    kappa/a_gauss differs from the piston delay kappa/a_piston by at most
    ``tolerance_us`` at every angle up to the returned one (0.01 deg grid, rounded
    down). Shape of ``kappa_us``; never beyond the piston's first null.

    Examples
    --------
    >>> round(float(np.rad2deg(gauss_valid_rad(0.67))), 2)
    7.47
    """
    kap = _check_kappa(kappa_us)
    if not (np.isfinite(tolerance_us) and tolerance_us > 0):
        raise ValueError(f"`tolerance_us` must be positive, got {tolerance_us!r}")
    tables = auto_tables(params)
    n = np.searchsorted(tables.mismatch, tolerance_us / kap, side="right")
    return np.asarray((n - 1) * tables.theta_step_rad, dtype=float)


def max_detection_angle_rad(kappa_us: ArrayLike, params: ModuleParams = ModuleParams(),
                            gain_sd: float = 4.0) -> NDArray[np.float64]:
    """Largest off-axis angle at which any tier can detect a reflector of this strength.

    Allows an amplitude gain of ``exp(gain_sd * amplitude_fluctuation)``; uses the
    piston side lobes and the Gaussian. 0 where nothing is detectable. Shape of
    ``kappa_us``. Useful to prune candidate reflectors before modelling echoes.
    """
    kap = _check_kappa(kappa_us)
    if not (np.isfinite(gain_sd) and gain_sd >= 0):
        raise ValueError(f"`gain_sd` must be non-negative, got {gain_sd!r}")
    tables = auto_tables(params)
    env = tables.envelope
    need = kap / (params.detection_limit_us * np.exp(gain_sd * params.amplitude_fluctuation))
    # env is non-increasing: n grid angles still reach `need`, so detection ends before
    # the n-th grid angle (rounded up to it).
    n = np.searchsorted(-env, -need, side="right")
    return np.minimum(n * tables.theta_step_rad, np.pi / 2)


def echo_delays_us(
    theta_rad: ArrayLike,
    kappa_us: ArrayLike,
    tier: Tier | str,
    rng: np.random.Generator,
    params: ModuleParams = ModuleParams(),
) -> tuple[NDArray[np.float64], NDArray[np.int8]]:
    """Random threshold delays of echoes and the tier that produced each.

    Parameters
    ----------
    theta_rad : (...,) off-axis angle of each echo (transducer axis to reflecting point).
    kappa_us : (...,) reflector strength tau/A0 [us], broadcast with ``theta_rad``.
    tier : model tier, or ``auto``.
    rng : source of the amplitude fluctuation (one normal draw per echo).

    Returns
    -------
    delay_us : (...,) delay after the arrival To [us]; NaN where the echo is not detected.
    tier_used : (...,) :class:`Tier` code per echo (never ``AUTO``).
    """
    t = Tier.parse(tier)
    theta_b, kap_b = np.broadcast_arrays(np.asarray(theta_rad, float),
                                         np.asarray(kappa_us, float))
    shape = theta_b.shape
    theta = theta_b.reshape(-1)
    bad = np.isnan(theta)
    if bad.any():
        where = tuple(int(i) for i in np.unravel_index(int(np.argmax(bad)), shape))
        raise ValueError(f"`theta_rad` must not be NaN, got nan at index {where}")
    kap = _check_kappa(kap_b).reshape(-1)
    gain = rng.standard_normal(theta.size)
    gain *= params.amplitude_fluctuation
    s = np.exp(gain, out=gain)
    np.divide(kap, s, out=s)  # s = kappa / gain: this echo's threshold delay on the axis
    limit = params.detection_limit_us
    if t is Tier.GAUSS:
        delay = _eq3(s / gaussian_echo(theta, params.sigma_deg), limit)
    elif t is Tier.AUTO:
        delay, used = _auto(theta, s, params)
        return delay.reshape(shape), used.reshape(shape)
    else:
        with np.errstate(divide="ignore"):
            u = s / _piston_fast(theta, auto_tables(params))
        delay = _eq3(u, limit) if t is Tier.PISTON else crossing_delay_us(u, params)
    return delay.reshape(shape), np.full(shape, int(t), dtype=np.int8)


class DelayMoments(NamedTuple):
    """Distribution of an echo's threshold delay over the amplitude fluctuation.

    Attributes
    ----------
    p_detect : (...,) probability that the echo is detected.
    mean_us : (...,) mean delay after To given detection [us]; NaN where p_detect = 0.
    sd_us : (...,) SD of the delay given detection [us]; NaN where p_detect = 0.
    """

    p_detect: NDArray[np.float64]
    mean_us: NDArray[np.float64]
    sd_us: NDArray[np.float64]


def delay_moments_us(
    theta_rad: ArrayLike, kappa_us: ArrayLike, tier: Tier | str = Tier.AUTO,
    params: ModuleParams = ModuleParams(), n_nodes: int = 161,
) -> DelayMoments:
    """Detection probability, mean and SD of the threshold delay in a tier.

    Detection needs a gain above kappa / (a * detection_limit_us), so p_detect is
    exact (normal tail); the moments given detection are a trapezoid quadrature on
    ``n_nodes`` log-gain values over the detected part of [-6, 6] SD, crowded towards
    the detection edge (mean within about 1 % of Monte Carlo with the default). A reading
    adds to the delay the timing jitter (SD ``jitter_sd_us``, mean 0) and the counter
    (mean +count_period/2, SD count_period/sqrt(12)): reading = To + delay + those.
    Use it as a forward model for fits in the tier the data came from.

    Parameters
    ----------
    theta_rad, kappa_us : (...,) off-axis angle and reflector strength, broadcast.

    Examples
    --------
    >>> m = delay_moments_us(0.0, 0.67)
    >>> round(float(m.p_detect), 3), round(float(m.mean_us), 2)
    (1.0, 0.69)
    """
    t = Tier.parse(tier)
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, int) or n_nodes < 3:
        raise ValueError(f"`n_nodes` must be an integer >= 3, got {n_nodes!r}")
    theta_b, kap_b = np.broadcast_arrays(np.asarray(theta_rad, float),
                                         np.asarray(kappa_us, float))
    shape = theta_b.shape
    kap = _check_kappa(kap_b).reshape(-1)
    theta = theta_b.reshape(-1)
    tables = auto_tables(params)
    a = (gaussian_echo(theta, params.sigma_deg) if t is Tier.GAUSS
         else _piston_fast(theta, tables))
    limit = params.detection_limit_us
    sig = params.amplitude_fluctuation
    with np.errstate(divide="ignore"):
        log_need = np.log(kap / limit) - np.log(a)  # log of the smallest detected gain
    if sig > 0:
        p = special.ndtr(-log_need / sig)
        lo = np.clip(log_need / sig, -6.0, 6.0)
        # Nodes crowd towards the detection edge z = lo, where weak echoes cross ever
        # later (ripple jumps accumulate there): z = lo + (6 - lo) xi^3.
        xi = np.linspace(0.0, 1.0, n_nodes)
        z = lo[:, None] + (6.0 - lo)[:, None] * xi[None, :] ** 3
        w = np.exp(-0.5 * z * z) * (3.0 * xi * xi)[None, :]
        w[:, [0, -1]] *= 0.5
    else:
        p = (log_need <= 0).astype(float)
        z = np.zeros((theta.size, 1))
        w = np.ones_like(z)
    s = (kap[:, None] / np.exp(sig * z)).reshape(-1)
    th = np.repeat(theta, z.shape[1])
    if t is Tier.GAUSS:
        d = _eq3(s / gaussian_echo(th, params.sigma_deg), limit)
    elif t is Tier.AUTO:
        d, _ = _auto(th, s, params)
    else:
        with np.errstate(divide="ignore"):
            u = s / _piston_fast(th, tables)
        d = _eq3(u, limit) if t is Tier.PISTON else crossing_delay_us(u, params)
    d = d.reshape(z.shape)
    w = np.where(np.isnan(d), 0.0, w)
    d = np.where(np.isnan(d), 0.0, d)
    wsum = w.sum(axis=1)
    ok = (p > 0) & (wsum > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * d).sum(axis=1) / wsum
        var = (w * (d - mean[:, None]) ** 2).sum(axis=1) / wsum
    mean = np.where(ok, mean, np.nan)
    sd = np.where(ok, np.sqrt(np.maximum(var, 0.0)), np.nan)
    return DelayMoments(p.reshape(shape), mean.reshape(shape), sd.reshape(shape))


def _check_kappa(kappa_us: ArrayLike) -> NDArray[np.float64]:
    """``kappa_us`` as a float array; ValueError naming the first bad value."""
    kap = np.asarray(kappa_us, dtype=float)
    bad = ~(np.isfinite(kap) & (kap > 0))
    if bad.any():
        flat = int(np.argmax(bad.reshape(-1)))
        where = tuple(int(i) for i in np.unravel_index(flat, kap.shape))
        raise ValueError(f"`kappa_us` must be positive and finite, got "
                         f"{float(kap.reshape(-1)[flat])!r}"
                         + (f" at index {where}" if where else ""))
    return kap


def _eq3(u: NDArray[np.float64], limit: float) -> NDArray[np.float64]:
    return np.where(u <= limit, u, np.nan)


def _auto(theta: NDArray[np.float64], s: NDArray[np.float64],
          params: ModuleParams) -> tuple[NDArray[np.float64], NDArray[np.int8]]:
    tables = auto_tables(params)
    limit = params.detection_limit_us
    u_w = tables.waveform_from_us
    # One grid index per echo serves both decision tables: the node at or below |theta|
    # for the non-increasing envelope, the next one up (built into `mismatch`) for the
    # non-decreasing mismatch, so both err on the safe side.
    i = np.abs(theta)
    i *= 1.0 / tables.theta_step_rad
    i = np.minimum(i, tables.envelope.size - 1).astype(np.intp)
    dead = s > limit * tables.envelope[i]
    u = s / gaussian_echo(theta, params.sigma_deg)
    need_p = s * tables.mismatch[i] > GAUSS_TOLERANCE_US
    need_p |= u > u_w - GAUSS_TOLERANCE_US
    need_p &= ~dead
    u[dead] = np.inf
    idx_p = np.flatnonzero(need_p)
    used = np.zeros(theta.shape, dtype=np.int8)
    if idx_p.size:
        with np.errstate(divide="ignore"):
            u_p = s[idx_p] / _piston_fast(theta[idx_p], tables)
        u[idx_p] = u_p
        used[idx_p] = Tier.PISTON
        idx_w = idx_p[u_p > u_w]
    else:
        idx_w = idx_p
    delay = _eq3(u, limit)
    if idx_w.size:
        delay[idx_w] = crossing_delay_us(u[idx_w], params)
        used[idx_w] = Tier.WAVEFORM
    return delay, used
