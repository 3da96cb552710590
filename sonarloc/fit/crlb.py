"""Cramér–Rao bound of landmark fits for any scan geometry.

For readings y_i = m_i(p) + e_i with e_i ~ N(0, s_i^2) the Fisher information is
J = sum_i grad m_i grad m_i^T / s_i^2 and any unbiased estimate has cov >= J^-1
(PHYSICS.md, estimation notes). Here every planned reading contributes what the
fitter's likelihood (:mod:`sonarloc.fit.lsq`) gets from it, in expectation:

* its TOF, if an echo comes back (probability P(echo)), with the detected echo's
  mean and variance of the fitter's model;
* with ``detection=True`` (as the fitter by default), the echo/no-echo event itself
  (Bernoulli information phi(z)^2 / (Phi(z) Phi(-z)) grad z grad z^T), which is what
  pins the arc's edges.

``detection=False`` gives the TOF-only bound (the one quoted in PHYSICS.md: about
0.30 deg plane, 0.36 deg pole, 0.47 deg rod for a -40..40 deg pan at 0.3 deg).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.fit import model as M
from sonarloc.fit.lsq import FitConfig

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Bound:
    """Cramér–Rao bound of one or many planned scans (leading batch axes ``...``).

    ``cov_local`` (..., 3, 3): bound on (range_m, bearing_rad, kappa_us) seen from the
    reference pose; ``cov`` (..., 3, 3): on the frame parameters (x_m, y_m, kappa_us) or
    (rho_m, alpha_rad, kappa_us); ``n_echo`` (...,): expected number of echoes.
    """

    kind: str
    cov_local: Array
    cov: Array
    n_echo: Array

    @property
    def range_sd_m(self) -> Array:
        return np.sqrt(self.cov_local[..., 0, 0])

    @property
    def bearing_sd_rad(self) -> Array:
        return np.sqrt(self.cov_local[..., 1, 1])

    @property
    def kappa_sd_us(self) -> Array:
        return np.sqrt(self.cov_local[..., 2, 2])


def local_params(kind: str, params: ArrayLike, ref_xy: ArrayLike) -> Array:
    """Frame parameters (..., 3) to local (r, phi, kappa) seen from ``ref_xy`` (..., 2)."""
    p = np.asarray(params, dtype=float)
    ref = np.asarray(ref_xy, dtype=float)
    if kind == "point":
        dx, dy = p[..., 0] - ref[..., 0], p[..., 1] - ref[..., 1]
        return np.stack([np.hypot(dx, dy), np.arctan2(dy, dx), p[..., 2]], axis=-1)
    if kind == "line":
        c, s = np.cos(p[..., 1]), np.sin(p[..., 1])
        d = p[..., 0] - (ref[..., 0] * c + ref[..., 1] * s)
        phi = np.where(d >= 0, p[..., 1], p[..., 1] + np.pi)
        return np.stack([np.abs(d), M.wrap_angle(phi), p[..., 2]], axis=-1)
    raise ValueError(f"`kind` must be 'point' or 'line', got {kind!r}")


def fisher_information(kind: str, local: ArrayLike, px: ArrayLike, py: ArrayLike,
                       yaw: ArrayLike, config: FitConfig | None = None, tier: str = "gauss",
                       detection: bool = True) -> tuple[Array, Array]:
    """Expected Fisher information (..., 3, 3) of local (r, phi, kappa) and E[#echoes].

    Parameters
    ----------
    kind : ``"point"`` or ``"line"``.
    local : (..., 3) (r [m], phi [rad], kappa [us]) seen from the reference position.
    px, py, yaw : (..., n) planned transducer positions relative to the reference [m]
        and axis directions [rad].
    tier : model tier of the fitter (``gauss``, ``piston`` or ``waveform``).
    detection : include the information of the echo/no-echo events (and, like the
        fitter with ``FitConfig.detection``, model detected delays as truncated at the
        detection limit); False: the TOF-only bound of eq. 3 with untruncated delays.
    """
    cfg = replace(config or FitConfig(), detection=detection)
    mod = cfg.module
    lp = np.asarray(local, dtype=float)
    r, phi, K = lp[..., 0:1], lp[..., 1:2], lp[..., 2:3]
    geo = M.geometry(kind, r, phi, px, py, yaw)
    g, dg, lng = M.beam_delay_factor(geo.theta, tier, mod)
    z = M.detection_z(K, lng, mod)
    et = M.echo_terms(K, g, z if cfg.detection else None, mod, tier=tier)
    delay, ddu = et.delay, et.ddelay_du
    s2 = M.tof_variance_us2(delay, mod, et.delay_var if tier == "waveform" else None)
    tau = M.us_per_m(mod)
    Jm = np.stack([tau * geo.dR_dr + ddu * K * dg * geo.dtheta_dr,
                   tau * geo.dR_dphi + ddu * K * dg * geo.dtheta_dphi,
                   np.broadcast_to(ddu * g, geo.theta.shape)], axis=-1)
    p_echo = np.exp(M.echo_terms(K, g, z, mod, want_info=False).log_p)
    F = np.einsum("...n,...nk,...nl->...kl", p_echo / s2, Jm, Jm)
    if detection:
        sa = M.sigma_a(mod)
        dlng = np.where(g < 1e11, dg / g, 0.0)
        dz = np.stack([dlng * geo.dtheta_dr, dlng * geo.dtheta_dphi,
                       np.broadcast_to(1.0 / K, g.shape)], axis=-1) / sa
        F = F + np.einsum("...n,...nk,...nl->...kl", M.noecho_terms(z)[2], dz, dz)
    return F, p_echo.sum(-1)


def crlb(kind: str, params: ArrayLike, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
         config: FitConfig | None = None, tier: str = "gauss", detection: bool = True,
         ref_index: int = -1) -> Bound:
    """Cramér–Rao bound of a landmark fitted from readings at the given transducer poses.

    Parameters
    ----------
    kind : ``"point"`` or ``"line"``.
    params : (..., 3) the landmark in the frame: (x_m, y_m, kappa_us) or (rho_m,
        alpha_rad, kappa_us).
    x_m, y_m, yaw_rad : (..., n) planned transducer poses in the frame (a pan from one
        spot, a ring on a moving robot, ...), every ping, echo or not.
    config : the fitter's settings (module: speed of sound, jitter, detection limit).
    tier : ``gauss``, ``piston`` or ``waveform`` (see :data:`sonarloc.fit.model.TIERS`).
    detection : include what echo/no-echo events say (the fitter uses it).
    ref_index : the reading whose position is the reference of range and bearing
        (the fitter uses the segment's last echo).

    Examples
    --------
    >>> import numpy as np
    >>> yaw = np.deg2rad(np.arange(-40, 40.01, 0.3))
    >>> b = crlb("point", [1.5, 0.0, 0.67], 0.0 * yaw, 0.0 * yaw, yaw, detection=False)
    >>> round(float(np.rad2deg(b.bearing_sd_rad)), 2)
    0.37
    """
    if kind not in M.KINDS:
        raise ValueError(f"`kind` must be 'point' or 'line', got {kind!r}")
    if tier not in M.TIERS:
        raise ValueError(f"`tier` must be one of {', '.join(M.TIERS)}; got {tier!r}")
    x, y, yaw = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x_m, y_m, yaw_rad)))
    if x.ndim == 0 or x.shape[-1] == 0:
        raise ValueError("`x_m`, `y_m`, `yaw_rad` must hold at least one pose")
    p = np.asarray(params, dtype=float)
    if p.shape[-1] != 3:
        raise ValueError(f"`params` must end in 3 values, got shape {p.shape}")
    ref = np.stack([x[..., ref_index], y[..., ref_index]], axis=-1)
    local = local_params(kind, p, ref)
    F, n_echo = fisher_information(kind, local, x - ref[..., 0:1], y - ref[..., 1:2], yaw,
                                   config, tier, detection)
    cov_local = _inverse(F)
    with np.errstate(invalid="ignore"):
        _, cov, _ = M.to_frame(kind, local, cov_local, ref)
    cov = np.where(np.isnan(cov), np.inf, cov)
    return Bound(kind, cov_local, cov, n_echo)


def _inverse(F: Array) -> Array:
    """Inverse of symmetric information matrices; inf variance where singular."""
    Fs = 0.5 * (F + np.swapaxes(F, -1, -2))
    w, V = np.linalg.eigh(Fs)
    tiny = np.maximum(np.abs(w).max(axis=-1, keepdims=True) * 1e-15, 1e-300)
    inv = np.where(w > tiny, 1.0 / np.where(w > tiny, w, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        out = np.einsum("...ij,...j,...kj->...ik", V, inv, V)
    # an unidentifiable direction leaves inf on the diagonal (and NaN off it)
    return np.where(np.isnan(out), np.inf, out)
