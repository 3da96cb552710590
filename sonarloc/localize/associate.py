"""Data association: which map feature did an observation come from?

Candidates are the features of the observation's type that can echo toward the
transducer (corners from inside their angle, edges from outside and close by, walls
whose perpendicular foot lies on the segment). For each, the squared Mahalanobis
distance of the wrapped innovation, ``d2 = nuᵀ S⁻¹ nu`` with ``S = H P Hᵀ + R``, and,
when both strengths are known, a reflecting-strength term on log(kappa):
``dk2 = (ln k_obs - ln k_map)² / (var_obs / k_obs² + kappa_log_sd²)``.

Gate: ``d2 <= chi2.ppf(gate_probability, dof)`` from ``scipy.stats`` (default 99 %).
How strength enters (``kappa_mode``):

* ``"weigh"`` (default): the gate is on position alone (dof 2: 9.21); strength weighs
  the gated candidates through a robust likelihood, a mixture of the Gaussian in
  ``dk`` with probability ``kappa_outlier_prob`` of a strength fit that says nothing
  (uniform over ``KAPPA_LOG_SPAN``). A wrong kappa cannot reject a good position
  match, but a right one tells a pole from a rod 5 cm away.
* ``"gate"``: ``d2 + dk2`` against dof 3 (11.34); strength can reject.
* ``"off"``: position only.

Ambiguity: among the gated candidates the best must hold at least
``min_match_probability`` (default 0.95) of the likelihood
``exp(-d2/2) / sqrt(det S)`` (times the strength term); otherwise the observation is
rejected as ambiguous rather than risk a wrong update.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.localize import ekf
from sonarloc.localize.ekf import Feature, Gaussian, Observation
from sonarloc.localize.features import FeatureMap

AssocStatus = Literal["matched", "no_candidate", "gated", "ambiguous"]
KappaMode = Literal["weigh", "gate", "off"]

#: Width (natural-log units) of the uniform "says nothing" part of the strength term.
KAPPA_LOG_SPAN = 8.0


@dataclass(frozen=True)
class AssociationConfig:
    """Association settings (see the module docstring).

    ``kappa_log_sd``: how far (in natural log) a map feature's strength may differ from
    a fitted one (0.5: a factor 1.65). ``wall_margin_m``: how far beyond a wall
    segment's ends its perpendicular foot may lie. ``max_range_m``: farthest candidate.
    """

    gate_probability: float = ekf.GATE_PROBABILITY
    min_match_probability: float = 0.95
    kappa_mode: KappaMode = "weigh"
    kappa_log_sd: float = 0.5
    kappa_outlier_prob: float = 0.1
    wall_margin_m: float = 0.2
    max_range_m: float = 6.0

    def __post_init__(self) -> None:
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"`gate_probability` must be in (0, 1), got "
                             f"{self.gate_probability!r}")
        if not 0.5 <= self.min_match_probability <= 1.0:
            raise ValueError(f"`min_match_probability` must be in [0.5, 1], got "
                             f"{self.min_match_probability!r}")
        if self.kappa_mode not in ("weigh", "gate", "off"):
            raise ValueError(f"`kappa_mode` must be weigh, gate or off, got {self.kappa_mode!r}")
        if not 0.0 <= self.kappa_outlier_prob < 1.0:
            raise ValueError(f"`kappa_outlier_prob` must be in [0, 1), got "
                             f"{self.kappa_outlier_prob!r}")
        for name in ("kappa_log_sd", "wall_margin_m", "max_range_m"):
            v = getattr(self, name)
            if not (v >= 0 and not math.isnan(v)):
                raise ValueError(f"`{name}` must be non-negative, got {v!r}")


@dataclass(frozen=True)
class Association:
    """Outcome of :func:`associate`.

    ``status``: ``matched`` (``feature`` / ``kind`` / ``index`` say which), ``no_candidate``
    (nothing of that type can echo from there), ``gated`` (candidates, none inside the
    gate) or ``ambiguous`` (several inside, none clearly best). ``d2``: best squared
    Mahalanobis distance (with the strength term), ``dof`` and ``gate`` it was held to,
    ``n_gated`` candidates inside the gate, ``probability`` the best one's share.
    """

    status: AssocStatus
    kind: Literal["point", "wall"] | None = None
    index: int = -1
    feature: Feature | None = None
    d2: float = math.inf
    dof: int = 2
    gate: float = math.inf
    n_gated: int = 0
    probability: float = 0.0

    @property
    def matched(self) -> bool:
        return self.status == "matched"


def _candidates_d2(state: Gaussian, obs: Observation, feats: Feature
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(N,) d2 and log det S of one observation against N same-kind features."""
    z_pred, h = ekf.measure(state.mean, obs, feats)
    nu = ekf.innovation(obs.z, z_pred, obs.angle_index)
    s = h @ state.cov @ np.swapaxes(h, -1, -2) + ekf.measurement_cov(state.mean, obs, feats)
    s = 0.5 * (s + np.swapaxes(s, -1, -2))
    # positive definite, finite and not numerically singular (correlation of its two
    # components below 1 - 5e-13): a belief of 1e150 m made solve raise "Singular matrix"
    with np.errstate(over="ignore", invalid="ignore"):
        det = s[..., 0, 0] * s[..., 1, 1] - s[..., 0, 1] * s[..., 1, 0]
        good = (det > 1e-12 * s[..., 0, 0] * s[..., 1, 1]) & (s[..., 0, 0] > 0) \
            & np.isfinite(det) & np.all(np.isfinite(nu), axis=-1)
    s_safe = np.where(good[..., None, None], s, np.eye(2))
    sol = np.linalg.solve(s_safe, nu[..., None])[..., 0]
    d2 = np.where(good, np.einsum("...i,...i->...", nu, sol), np.inf)
    return d2, np.log(np.where(good, det, 1.0))


def associate(state: Gaussian, obs: Observation, fmap: FeatureMap,
              config: AssociationConfig = AssociationConfig()) -> Association:
    """Pick the map feature an observation came from, or say why none.

    Parameters
    ----------
    state : Gaussian (unbatched) belief of the pose the observation refers to.
    obs : Observation (``point``, ``line`` or ``range_bearing``).
    fmap : the map's features.
    config : gate, ambiguity and strength settings.
    """
    sensor_xy = se2.transform_points(state.mean, obs.sensor[:2])
    groups: list[tuple[Literal["point", "wall"], NDArray[np.int64], Feature, NDArray[np.float64]]]
    groups = []
    ranged = obs.kind in ("range_bearing", "range_axis")
    if (obs.kind == "point" or ranged) and fmap.n_points:
        idx = np.flatnonzero(fmap.points_visible_from(sensor_xy, config.max_range_m))
        if idx.size:
            groups.append(("point", idx, Feature("point", fmap.point_xy[idx],
                                                 fmap.point_radius_m[idx]),
                           fmap.point_kappa_us[idx]))
    if (obs.kind == "line" or ranged) and fmap.n_walls:
        if obs.kind == "range_axis":
            yaw = float(state.mean[2] + obs.sensor[2])
            idx = np.flatnonzero(fmap.walls_hit_by_ray(sensor_xy, yaw, config.wall_margin_m,
                                                       config.max_range_m))
        else:
            idx = np.flatnonzero(fmap.walls_facing(sensor_xy, config.wall_margin_m,
                                                   config.max_range_m))
        if idx.size:
            groups.append(("wall", idx, Feature("wall", fmap.wall_line[idx]),
                           fmap.wall_kappa_us[idx]))
    if not groups:
        return Association("no_candidate")
    use_kappa = config.kappa_mode != "off" and not ranged \
        and math.isfinite(obs.kappa_us) and obs.kappa_us > 0
    dof = 3 if use_kappa and config.kappa_mode == "gate" else 2
    gate = ekf.chi2_gate(dof, config.gate_probability)
    kinds: list[Literal["point", "wall"]] = []
    index: list[NDArray[np.int64]] = []
    d2s: list[NDArray[np.float64]] = []
    loglik: list[NDArray[np.float64]] = []
    for kind, idx, feats, kap in groups:
        d2, logdet = _candidates_d2(state, obs, feats)
        ll = -0.5 * d2 - 0.5 * logdet
        if use_kappa:
            known = np.isfinite(kap) & (kap > 0)
            var_obs = obs.kappa_var_us2 / obs.kappa_us**2 \
                if math.isfinite(obs.kappa_var_us2) else 0.0
            var = var_obs + config.kappa_log_sd**2
            dk2 = np.where(known, (math.log(obs.kappa_us) - np.log(np.where(known, kap, 1.0)))
                           ** 2 / var, 0.0)
            if config.kappa_mode == "gate":
                d2 = d2 + dk2
                ll = ll - 0.5 * dk2 - 0.5 * math.log(var)
            else:
                eps = config.kappa_outlier_prob
                dens = (1 - eps) * np.exp(-0.5 * dk2) / math.sqrt(2 * math.pi * var) \
                    + eps / KAPPA_LOG_SPAN
                ll = ll + np.where(known, np.log(dens), 0.0)
        kinds += [kind] * len(idx)
        index.append(idx)
        d2s.append(d2)
        loglik.append(ll)
    all_d2 = np.concatenate(d2s)
    all_ll = np.concatenate(loglik)
    all_idx = np.concatenate(index)
    inside = all_d2 <= gate
    best = int(np.argmin(all_d2))
    if not np.any(inside):
        return Association("gated", d2=float(all_d2[best]), dof=dof, gate=gate)
    ll = np.where(inside, all_ll, -np.inf)
    best = int(np.argmax(ll))
    share = float(1.0 / np.sum(np.exp(ll[inside] - ll[best])))
    n_gated = int(np.sum(inside))
    kind = kinds[best]
    i = int(all_idx[best])
    if share < config.min_match_probability:
        return Association("ambiguous", kind, i, None, float(all_d2[best]), dof, gate, n_gated,
                           share)
    feature = fmap.point(i) if kind == "point" else fmap.wall(i)
    return Association("matched", kind, i, feature, float(all_d2[best]), dof, gate, n_gated,
                       share)
