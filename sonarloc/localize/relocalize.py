"""Global relocalization: where am I in the map, from the landmarks fitted recently?

When the filter is lost (its updates keep being rejected) or was started without a
pose prior, the EKF cannot help: its linearisation is only good near the truth. The
landmarks fitted over the last ``window_s`` of the drive are still mutually consistent
in ``odom`` (the odometry drifts slowly), so the question becomes: which rigid
transform ``map_to_odom`` (x, y, yaw of ``odom`` in ``map``) lays them onto the map?

1. **Observed landmarks.** Point fits that agree within ``cluster_m`` are one
   reflector (information-weighted mean, median strength, mean viewing direction);
   wall fits on one line (``cluster_deg``, ``cluster_m`` at their feet) are one wall,
   represented at the foot of the transducers' perpendicular (where the range was
   measured, so a heading error does not lever the offset). Each gets the fits'
   covariance plus a floor (``floor_m``, ``floor_deg``) and the odometry drift since it
   was seen (``drift_per_m`` times the path driven since).
2. **Hypotheses** from minimal matches, compatible in geometry and strength:
   two observed points against two map points at the same distance (within
   ``pair_tol_m`` plus their radii; log-strength within ``kappa_log_tol``); a point
   and a wall against a map point and a map wall at the same offset; two
   non-parallel walls against two map walls meeting at the same angle.
3. **Scores.** Every hypothesis is scored by all observed landmarks: each costs the
   squared Mahalanobis distance to its best map feature under that transform (a
   cylinder's fitted point is its surface point facing the transducer; corners only
   from inside their walls' angle; a wall's foot must lie on the map segment), capped
   at ``outlier_d2`` (an unexplained landmark: clutter, a bad fit). The cost is
   minus twice the log-likelihood of a Gaussian-plus-outlier model, up to a constant.
4. **Refinement.** The best hypotheses are refined by Gauss-Newton on their inliers
   (the covariance of the transform is the inverse of the normal matrix) and scored
   again.
5. **Decision.** The winner is accepted only if it explains at least ``min_inliers``
   landmarks, its covariance pins all three degrees of freedom (SD below ``max_sd_m``
   and ``max_sd_deg``), and every clearly different hypothesis (further than
   ``distinct_m`` / ``distinct_deg``) costs at least ``ambiguity_d2`` more (a
   likelihood ratio of ``exp(ambiguity_d2 / 2)``). Otherwise the result says why
   (``insufficient``, ``no_match`` or ``ambiguous`` with the rival poses) and nothing
   is guessed.

Translations (the SD test, distinctness, the hypotheses' 2 cm grid) are those of the
observed landmarks' centroid: the transform is solved between ``odom`` about that
centroid and ``map`` about its features' centre, so the outcome does not depend on
where either frame's origin lies (a 10 km drive's odometry, a map in UTM), and a
transform judged about ``odom``'s origin would not pin it once that origin is far off
(its translation SD grows by the distance times the yaw's SD).

The functional core is :func:`relocalize` (observed landmarks + map -> result); the
:class:`Relocalizer` keeps the recent fits and the odometry path length for the
:class:`~sonarloc.localize.localizer.Localizer`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.localize.features import EDGE_RANGE_M, FeatureMap, _lines

Array = NDArray[np.float64]
RelocStatus = Literal["found", "ambiguous", "insufficient", "no_match"]


@dataclass(frozen=True)
class RelocalizeConfig:
    """Settings of global relocalization (see the module docstring)."""

    window_s: float = 20.0
    cluster_m: float = 0.08
    cluster_deg: float = 6.0
    floor_m: float = 0.02
    floor_deg: float = 2.0
    drift_per_m: float = 0.03
    pair_tol_m: float = 0.06
    min_pair_m: float = 0.3
    min_wall_angle_deg: float = 25.0
    kappa_log_tol: float = 2.0
    kappa_log_sd: float = 1.0
    wall_margin_m: float = 0.3
    outlier_d2: float = 9.21
    min_landmarks: int = 3
    min_inliers: int = 4
    max_sd_m: float = 0.05
    max_sd_deg: float = 2.0
    distinct_m: float = 0.25
    distinct_deg: float = 10.0
    ambiguity_d2: float = 9.21
    max_hypotheses: int = 20000
    refine_top: int = 12
    statuses: tuple[str, ...] = ("ok", "flat")
    every_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("window_s", "cluster_m", "cluster_deg", "floor_m", "floor_deg",
                     "pair_tol_m", "min_pair_m", "min_wall_angle_deg", "kappa_log_tol",
                     "kappa_log_sd", "wall_margin_m", "outlier_d2", "max_sd_m", "max_sd_deg",
                     "distinct_m", "distinct_deg", "ambiguity_d2", "every_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if not (math.isfinite(self.drift_per_m) and self.drift_per_m >= 0):
            raise ValueError(f"`drift_per_m` must be non-negative, got {self.drift_per_m!r}")
        for name in ("min_landmarks", "min_inliers", "max_hypotheses", "refine_top"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"`{name}` must be a positive integer, got {v!r}")


@dataclass(frozen=True)
class ObservedPoint:
    """A point reflector seen recently, in ``odom``.

    ``xy`` (2,) m: fitted reflecting point; ``cov`` (2, 2) m²; ``view`` (2,): unit
    direction from the point towards the transducers; ``range_m``: mean distance to
    them; ``log_kappa``: median natural log of the fitted strength (us); ``n``: fits.
    """

    xy: Array
    cov: Array
    view: Array
    range_m: float
    log_kappa: float
    n: int


@dataclass(frozen=True)
class ObservedWall:
    """A wall seen recently, in ``odom``: the line through ``foot`` (2,) with normal
    angle ``alpha`` (rad); ``cov`` (2, 2) of (offset across the line at the foot [m],
    alpha [rad]); ``extent`` (2, 2): the outermost feet; ``n``: fits."""

    foot: Array
    alpha: float
    cov: Array
    extent: Array
    n: int


@dataclass(frozen=True)
class Relocalization:
    """Outcome of :func:`relocalize`.

    ``status``: ``found`` (``map_to_odom`` (3,) x, y, yaw of ``odom`` in ``map`` with
    covariance ``cov`` (3, 3)), ``ambiguous`` (``alternatives`` hold the rival
    transforms with their costs), ``insufficient`` (too few landmarks, or they do not pin
    the pose) or ``no_match``. ``reason`` says why in words. ``cost``: the winner's cost
    (sum of capped squared Mahalanobis distances); ``inliers`` of ``n_landmarks``;
    ``n_hypotheses`` scored.
    """

    status: RelocStatus
    reason: str
    map_to_odom: Array = field(default_factory=lambda: np.full(3, np.nan))
    cov: Array = field(default_factory=lambda: np.full((3, 3), np.nan))
    cost: float = math.inf
    inliers: int = 0
    n_landmarks: int = 0
    n_hypotheses: int = 0
    alternatives: tuple[tuple[Array, float, int], ...] = ()
    odom_origin: Array = field(default_factory=lambda: np.zeros(2))
    """(2,) m: the point of ``odom`` (the observed landmarks' centroid) about which the
    transform was solved; ``map_origin`` (2,) the point of ``map`` its local frame starts
    at; ``local`` (3,) and ``local_cov`` (3, 3) the transform between those local frames
    (``map - map_origin = R (odom - odom_origin) + local[:2]``). :meth:`pose_in_map`
    works from them: ``map_to_odom``'s translation and its covariance carry the lever
    of ``odom``'s origin (huge after a long drive or in UTM, x ~ 5e5 m)."""
    map_origin: Array = field(default_factory=lambda: np.zeros(2))
    local: Array | None = None
    local_cov: Array | None = None

    @property
    def found(self) -> bool:
        return self.status == "found"

    def pose_in_map(self, odom_pose: Array) -> tuple[Array, Array]:
        """base_link pose (3,) in ``map`` and its covariance (3, 3) at odometry pose
        ``odom_pose`` (3,) in ``odom`` (the transform's uncertainty carried through)."""
        q = np.asarray(odom_pose, dtype=float)
        if self.local is None or self.local_cov is None:
            pose = se2.compose(self.map_to_odom, q)
            ja, _ = se2.compose_jacobians(self.map_to_odom, q)
            return pose, ja @ self.cov @ ja.T
        # in the local frames: the offset from the solved-about point first (exact in any
        # frame), then the large origins added
        rel = np.array([q[0] - self.odom_origin[0], q[1] - self.odom_origin[1], q[2]])
        local_pose = se2.compose(self.local, rel)
        ja, _ = se2.compose_jacobians(self.local, rel)
        pose = np.array([self.map_origin[0] + local_pose[0],
                         self.map_origin[1] + local_pose[1], local_pose[2]])
        return pose, ja @ self.local_cov @ ja.T


# --------------------------------------------------------------------------- observations


@dataclass
class _PointAcc:
    q: list[Array] = field(default_factory=list)
    w: list[Array] = field(default_factory=list)
    u: list[Array] = field(default_factory=list)
    r: list[float] = field(default_factory=list)
    k: list[float] = field(default_factory=list)
    drift: list[float] = field(default_factory=list)


@dataclass
class _WallAcc:
    f: list[Array] = field(default_factory=list)
    a: list[float] = field(default_factory=list)
    w: list[Array] = field(default_factory=list)
    drift: list[float] = field(default_factory=list)


def observed_landmarks(fits: Sequence[tuple[Landmark, float]], config: RelocalizeConfig
                       ) -> tuple[list[ObservedPoint], list[ObservedWall]]:
    """Cluster recent fits (in ``odom``) into observed points and walls.

    ``fits``: (landmark, path length driven since its reference reading [m]) pairs.
    """
    cfg = config
    pts: list[_PointAcc] = []
    walls: list[_WallAcc] = []
    for lm, travel in fits:
        if lm.status.value not in cfg.statuses:
            continue
        p = np.asarray(lm.params, dtype=float)
        cov = np.asarray(lm.cov, dtype=float)[:2, :2]
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(cov)) and p[2] > 0):
            continue
        drift = (cfg.drift_per_m * max(travel, 0.0)) ** 2
        ref = np.asarray(lm.ref_pose[:2], dtype=float)
        if lm.kind == "point":
            q = p[:2]
            view_xy = lm.extra.get("view_xy")
            v = np.asarray(view_xy, dtype=float) if isinstance(view_xy, tuple) else ref
            u = v - q
            rng = float(np.hypot(*u))
            if rng < 1e-6:
                continue
            for pc in pts:
                if float(np.hypot(*(np.mean(pc.q, axis=0) - q))) <= cfg.cluster_m:
                    break
            else:
                pc = _PointAcc()
                pts.append(pc)
            pc.q.append(q)
            pc.w.append(np.asarray(np.linalg.inv(cov + np.eye(2) * 1e-10), dtype=float))
            pc.u.append(u / rng)
            pc.r.append(rng)
            pc.k.append(math.log(p[2]))
            pc.drift.append(drift)
        else:
            rho, alpha = float(p[0]), float(p[1])
            n = np.array([math.cos(alpha), math.sin(alpha)])
            foot = ref + (rho - float(ref @ n)) * n
            # (rho, alpha) about the origin -> (offset at the foot, alpha)
            j = np.array([[1.0, foot[0] * math.sin(alpha) - foot[1] * math.cos(alpha)],
                          [0.0, 1.0]])
            cf = j @ cov @ j.T
            for wc in walls:
                a0 = wc.a[0]
                d_a = float(se2.wrap_angle(alpha - a0))
                if abs(d_a) > math.pi / 2:
                    d_a = float(se2.wrap_angle(d_a + math.pi))
                n0 = np.array([math.cos(a0), math.sin(a0)])
                if abs(d_a) <= math.radians(cfg.cluster_deg) and \
                        abs(float((foot - wc.f[0]) @ n0)) <= cfg.cluster_m:
                    alpha = a0 + d_a
                    break
            else:
                wc = _WallAcc()
                walls.append(wc)
            wc.f.append(foot)
            wc.a.append(alpha)
            wc.w.append(np.linalg.inv(cf + np.eye(2) * 1e-12))
            wc.drift.append(drift)
    out_p = []
    for pc in pts:
        w = np.array(pc.w)
        cov = np.linalg.inv(w.sum(axis=0))
        q = cov @ np.einsum("kij,kj->i", w, np.array(pc.q))
        u = np.sum(np.array(pc.u), axis=0)
        u = u / max(float(np.hypot(*u)), 1e-12)
        cov = cov + np.eye(2) * (cfg.floor_m**2 + float(np.median(pc.drift)))
        out_p.append(ObservedPoint(q, cov, u, float(np.mean(pc.r)), float(np.median(pc.k)),
                                   len(pc.q)))
    out_w = []
    for wc in walls:
        a = np.array(wc.a, dtype=float)
        w = np.array(wc.w)
        alpha = float(np.sum(w[:, 1, 1] * a) / np.sum(w[:, 1, 1]))
        n = np.array([math.cos(alpha), math.sin(alpha)])
        d = np.array([-n[1], n[0]])
        f = np.array(wc.f)
        wd = w[:, 0, 0]
        off = float(np.sum(wd * (f @ n)) / np.sum(wd))
        t = f @ d
        foot = off * n + float(np.mean(t)) * d
        cov = np.linalg.inv(w.sum(axis=0))
        cov = cov + np.diag(np.array([cfg.floor_m**2 + float(np.median(wc.drift)),
                                      math.radians(cfg.floor_deg) ** 2]))
        extent = np.array([off * n + float(t.min()) * d, off * n + float(t.max()) * d])
        out_w.append(ObservedWall(foot, alpha, cov, extent, len(f)))
    return out_p, out_w


# --------------------------------------------------------------------------- hypotheses


def _rot(theta: Array) -> Array:
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _map_wall_arrays(fmap: FeatureMap) -> tuple[Array, Array, Array, Array]:
    """(W,) rho, (W,) alpha, (W, 2) start, (W, 2) unit direction, of the map walls."""
    ends = fmap.wall_ends
    d = ends[:, 1] - ends[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    return fmap.wall_line[:, 0], fmap.wall_line[:, 1], ends[:, 0], d / length[:, None]


def _hypotheses(points: list[ObservedPoint], walls: list[ObservedWall], fmap: FeatureMap,
                cfg: RelocalizeConfig) -> Array:
    """(H, 3) candidate transforms (tx, ty, theta) from minimal matches."""
    out: list[Array] = []
    cxy, crad = fmap.point_xy, fmap.point_radius_m
    ckap = np.log(fmap.point_kappa_us)
    n_m = fmap.n_points
    # -- two points against two map points
    if len(points) >= 2 and n_m >= 2:
        q = np.array([p.xy for p in points])
        lk = np.array([p.log_kappa for p in points])
        ia, ib = np.triu_indices(len(points), 1)
        d_o = np.hypot(*(q[ib] - q[ia]).T)
        keep = d_o >= cfg.min_pair_m
        ia, ib, d_o = ia[keep], ib[keep], d_o[keep]
        mi, mj = np.nonzero(~np.eye(n_m, dtype=bool))
        d_m = np.hypot(*(cxy[mj] - cxy[mi]).T)
        tol = cfg.pair_tol_m + crad[mi] + crad[mj]
        ok = np.abs(d_o[:, None] - d_m[None, :]) <= tol[None, :]

        def kappa_ok(lo: Array, lm: Array) -> NDArray[np.bool_]:
            return np.asarray(np.isnan(lm)[None, :] | (np.abs(lo[:, None] - lm[None, :])
                                                       <= cfg.kappa_log_tol))

        ok &= kappa_ok(lk[ia], ckap[mi]) & kappa_ok(lk[ib], ckap[mj])
        po, pm = np.nonzero(ok)
        if len(po):
            a, b, i, j = ia[po], ib[po], mi[pm], mj[pm]
            dv_o, dv_m = q[b] - q[a], cxy[j] - cxy[i]
            theta = np.arctan2(dv_m[:, 1], dv_m[:, 0]) - np.arctan2(dv_o[:, 1], dv_o[:, 0])
            mid_o = 0.5 * (q[a] + q[b])
            mid_m = 0.5 * (cxy[i] + cxy[j])
            t = mid_m - np.einsum("hij,hj->hi", _rot(theta), mid_o)
            out.append(np.column_stack([t, se2.wrap_angle(theta)]))
    n_w = fmap.n_walls
    if n_w:
        rho_m, alpha_m, _, _ = _map_wall_arrays(fmap)
        # both orientations of every map wall's normal
        alpha_m2 = np.concatenate([alpha_m, alpha_m + math.pi])
        rho_m2 = np.concatenate([rho_m, -rho_m])
        # -- a point and a wall against a map point and a map wall
        if points and walls and n_m:
            for w in walls:
                n_o = np.array([math.cos(w.alpha), math.sin(w.alpha)])
                theta = alpha_m2 - w.alpha  # (2W,)
                nm = np.stack([np.cos(alpha_m2), np.sin(alpha_m2)], -1)
                s_m = cxy @ nm.T - rho_m2[None, :]  # (P, 2W) map point offsets
                for p in points:
                    s_o = float((p.xy - w.foot) @ n_o)
                    ok = np.abs(s_m - s_o) <= cfg.pair_tol_m + crad[:, None]
                    ok &= np.isnan(ckap)[:, None] | (np.abs(p.log_kappa - ckap)[:, None]
                                                     <= cfg.kappa_log_tol)
                    pi, wk = np.nonzero(ok)
                    if len(pi):
                        th = theta[wk]
                        t = cxy[pi] - np.einsum("hij,j->hi", _rot(th), p.xy)
                        out.append(np.column_stack([t, se2.wrap_angle(th)]))
        # -- two non-parallel walls against two map walls
        if len(walls) >= 2 and n_w >= 2:
            min_ang = math.radians(cfg.min_wall_angle_deg)
            for a in range(len(walls)):
                for b in range(a + 1, len(walls)):
                    wa, wb = walls[a], walls[b]
                    dab = float(se2.wrap_angle(wb.alpha - wa.alpha))
                    if min(abs(dab), math.pi - abs(dab)) < min_ang:
                        continue
                    theta = alpha_m2 - wa.alpha  # (2W,) wall a -> each oriented map wall
                    pred = se2.wrap_angle(wb.alpha + theta)  # wall b's normal in map
                    diff = se2.wrap_angle(pred[:, None] - alpha_m2[None, :])  # (2W, 2W)
                    ka, kb = np.nonzero(np.abs(diff) <= math.radians(cfg.cluster_deg))
                    same = (ka % n_w) == (kb % n_w)
                    ka, kb = ka[~same], kb[~same]
                    if not len(ka):
                        continue
                    th = theta[ka]
                    na = np.stack([np.cos(alpha_m2[ka]), np.sin(alpha_m2[ka])], -1)
                    nb = np.stack([np.cos(alpha_m2[kb]), np.sin(alpha_m2[kb])], -1)
                    rot = _rot(th)
                    fa = np.einsum("hij,j->hi", rot, wa.foot)
                    fb = np.einsum("hij,j->hi", rot, wb.foot)
                    # n_a . t = rho_a - n_a . R f_a ; same for b
                    rhs = np.stack([rho_m2[ka] - np.sum(na * fa, -1),
                                    rho_m2[kb] - np.sum(nb * fb, -1)], -1)
                    mat = np.stack([na, nb], -2)
                    det = np.linalg.det(mat)
                    good = np.abs(det) > math.sin(min_ang) * 0.5
                    if not np.any(good):
                        continue
                    t = np.linalg.solve(mat[good], rhs[good][..., None])[..., 0]
                    out.append(np.column_stack([t, se2.wrap_angle(th[good])]))
    if not out:
        return np.zeros((0, 3))
    hyp = np.concatenate(out)
    # duplicates (one pose found by many matches): keep one per 2 cm / 1 deg cell
    key = np.column_stack([np.round(hyp[:, :2] / 0.02), np.round(hyp[:, 2] / math.radians(1))])
    _, first = np.unique(key, axis=0, return_index=True)
    hyp = hyp[np.sort(first)]
    if len(hyp) > cfg.max_hypotheses:
        rng = np.random.default_rng(0)
        hyp = hyp[np.sort(rng.choice(len(hyp), cfg.max_hypotheses, replace=False))]
    return hyp


# --------------------------------------------------------------------------- scores


@dataclass(frozen=True)
class _Scores:
    cost: Array        # (H,)
    inliers: Array     # (H,) int
    point_match: Array  # (H, Po) map point index, -1 = outlier
    wall_match: Array   # (H, Wo) oriented map wall index (0..2W-1), -1 = outlier


def _score(hyp: Array, points: list[ObservedPoint], walls: list[ObservedWall],
           fmap: FeatureMap, cfg: RelocalizeConfig) -> _Scores:
    """Cost of each transform (H, 3): capped squared Mahalanobis distances summed."""
    h = len(hyp)
    rot = _rot(hyp[:, 2])
    t = hyp[:, :2]
    cost = np.zeros(h)
    inl = np.zeros(h, dtype=int)
    pm = np.full((h, len(points)), -1)
    wm = np.full((h, len(walls)), -1)
    cap = cfg.outlier_d2
    if points and fmap.n_points:
        cxy, crad = fmap.point_xy, fmap.point_radius_m
        ckap = np.log(fmap.point_kappa_us)
        kinds = np.array(fmap.point_kind, dtype=object)
        cone = fmap.point_cone_rad
        has_cone = ~np.isnan(cone[:, 0])
        half = 0.5 * se2.wrap_angle(cone[:, 1] - cone[:, 0])
        mid = cone[:, 0] + half
        is_corner = (kinds == "corner") & has_cone
        is_edge = (kinds == "edge") & has_cone
        for k, p in enumerate(points):
            qm = np.einsum("hij,j->hi", rot, p.xy) + t            # (H, 2)
            um = np.einsum("hij,j->hi", rot, p.view)              # (H, 2)
            pred = cxy[None, :, :] + crad[None, :, None] * um[:, None, :]  # (H, P, 2)
            r = qm[:, None, :] - pred
            s = rot @ p.cov @ np.swapaxes(rot, -1, -2)            # (H, 2, 2)
            s_inv = np.linalg.inv(s)
            d2 = np.einsum("hpi,hij,hpj->hp", r, s_inv, r)
            dk = np.where(np.isnan(ckap), 0.0, (p.log_kappa - ckap) / cfg.kappa_log_sd)
            d2 = d2 + np.minimum(dk**2, 4.0)[None, :]
            # corners echo only into the angle between their walls, edges outside it
            phi = np.arctan2(um[:, 1], um[:, 0])
            inside = np.abs(se2.wrap_angle(phi[:, None] - mid[None, :])) < np.abs(half)[None, :]
            bad = (is_corner[None, :] & ~inside) | (is_edge[None, :] & inside)
            bad |= (kinds == "edge")[None, :] & (p.range_m > EDGE_RANGE_M)
            pm[:, k] = _best_within(np.where(bad, np.inf, d2), cap, cost, inl)
    elif points:
        cost += cap * len(points)
    if walls and fmap.n_walls:
        rho_m, alpha_m, start, dirs = _map_wall_arrays(fmap)
        length = np.hypot(*(fmap.wall_ends[:, 1] - fmap.wall_ends[:, 0]).T)
        alpha2 = np.concatenate([alpha_m, alpha_m + math.pi])
        rho2 = np.concatenate([rho_m, -rho_m])
        n2 = np.stack([np.cos(alpha2), np.sin(alpha2)], -1)     # (2W, 2)
        start2 = np.concatenate([start, start])
        dirs2 = np.concatenate([dirs, dirs])
        len2 = np.concatenate([length, length])
        for k, w in enumerate(walls):
            fm = np.einsum("hij,j->hi", rot, w.foot) + t          # (H, 2)
            am = w.alpha + hyp[:, 2]
            off = fm @ n2.T - rho2[None, :]                        # (H, 2W)
            da = se2.wrap_angle(am[:, None] - alpha2[None, :])
            s_inv = np.linalg.inv(w.cov)
            d2 = s_inv[0, 0] * off**2 + 2 * s_inv[0, 1] * off * da + s_inv[1, 1] * da**2
            # the observed extent must overlap the map segment (margin at both ends)
            ends = np.einsum("hij,ej->hei", rot, w.extent) + t[:, None, :]  # (H, 2, 2)
            along = np.einsum("hei,wi->hew", ends - 0.0, dirs2) - \
                np.einsum("wi,wi->w", start2, dirs2)[None, None, :]
            lo, hi = along.min(axis=1), along.max(axis=1)
            overlap = (hi >= -cfg.wall_margin_m) & (lo <= len2[None, :] + cfg.wall_margin_m)
            d2 = np.where(overlap & (np.abs(da) < math.pi / 2), d2, np.inf)
            wm[:, k] = _best_within(d2, cap, cost, inl)
    elif walls:
        cost += cap * len(walls)
    return _Scores(cost, inl, pm, wm)


def _best_within(d2: Array, cap: float, cost: Array, inl: Array) -> Array:
    """Per hypothesis (rows of ``d2``, (H, F) squared distances to the map features),
    the nearest feature if closer than ``cap``, else -1; adds the (capped) distance to
    ``cost`` and the match to the inlier count ``inl`` in place."""
    best = np.argmin(d2, axis=1)
    dbest = d2[np.arange(d2.shape[0]), best]
    good = dbest < cap
    cost += np.where(good, dbest, cap)
    inl += good
    return np.where(good, best, -1)


def _refine(x: Array, points: list[ObservedPoint], walls: list[ObservedWall],
            fmap: FeatureMap, cfg: RelocalizeConfig, iterations: int = 5
            ) -> tuple[Array, Array]:
    """Gauss-Newton on the inliers of transform ``x`` (3,); returns (x, cov (3, 3))."""
    x = np.asarray(x, dtype=float).copy()
    cov = np.full((3, 3), np.nan)
    for _ in range(iterations):
        sc = _score(x[None, :], points, walls, fmap, cfg)
        a = np.zeros((3, 3))
        g = np.zeros(3)
        rot = _rot(np.array(x[2]))
        drot = rot @ np.array([[0.0, -1.0], [1.0, 0.0]])
        for k, p in enumerate(points):
            i = int(sc.point_match[0, k])
            if i < 0:
                continue
            rad = float(fmap.point_radius_m[i])
            r = rot @ p.xy + x[:2] - fmap.point_xy[i] - rad * (rot @ p.view)
            j = np.zeros((2, 3))
            j[:, :2] = np.eye(2)
            j[:, 2] = drot @ p.xy - rad * (drot @ p.view)
            w = np.linalg.inv(rot @ p.cov @ rot.T)
            a += j.T @ w @ j
            g += j.T @ w @ r
        if walls and fmap.n_walls:
            rho_m, alpha_m, _, _ = _map_wall_arrays(fmap)
            alpha2 = np.concatenate([alpha_m, alpha_m + math.pi])
            rho2 = np.concatenate([rho_m, -rho_m])
            for k, wl in enumerate(walls):
                m = int(sc.wall_match[0, k])
                if m < 0:
                    continue
                nm = np.array([math.cos(alpha2[m]), math.sin(alpha2[m])])
                fm = rot @ wl.foot + x[:2]
                r = np.array([float(fm @ nm) - rho2[m],
                              float(se2.wrap_angle(wl.alpha + x[2] - alpha2[m]))])
                j = np.array([[nm[0], nm[1], float((drot @ wl.foot) @ nm)], [0.0, 0.0, 1.0]])
                w = np.linalg.inv(wl.cov)
                a += j.T @ w @ j
                g += j.T @ w @ r
        if np.linalg.matrix_rank(a, tol=1e-9 * max(float(np.trace(a)), 1e-30)) < 3:
            return x, np.full((3, 3), np.inf)
        step = np.linalg.solve(a, -g)
        x = x + step
        x[2] = float(se2.wrap_angle(x[2]))
        cov = np.linalg.inv(a)
        if np.all(np.abs(step) < 1e-7):
            break
    return x, 0.5 * (cov + cov.T)


def relocalize(points: Sequence[ObservedPoint], walls: Sequence[ObservedWall],
               fmap: FeatureMap, config: RelocalizeConfig | None = None) -> Relocalization:
    """Find ``map_to_odom`` from landmarks observed in ``odom`` (see the module docstring).

    Parameters
    ----------
    points, walls : observed landmarks in ``odom`` (:func:`observed_landmarks`).
    fmap : the map.
    config : settings.

    Returns
    -------
    Relocalization
        ``found`` with the transform and its covariance, or why not.
    """
    cfg = config or RelocalizeConfig()
    pts, wls = list(points), list(walls)
    n = len(pts) + len(wls)
    if n < cfg.min_landmarks:
        return Relocalization("insufficient", f"{n} landmark(s) seen recently, need "
                              f"{cfg.min_landmarks}", n_landmarks=n)
    # solved between local frames: odom about the landmarks' centroid, the map about its
    # features' centre, so that neither the hypotheses' grid, the distinctness test, the
    # translation's SD nor the Gauss-Newton lever depend on where either frame's origin
    # is (odometry after a long drive, a map in UTM: x ~ 5e5 m; docs/LOCALIZATION.md)
    o = np.mean([p.xy for p in pts] + [w.foot for w in wls], axis=0)
    m = _map_centre(fmap)
    pts = [replace(p, xy=p.xy - o) for p in pts]
    wls = [replace(w, foot=w.foot - o, extent=w.extent - o) for w in wls]
    fmap = _shifted_map(fmap, m)
    hyp = _hypotheses(pts, wls, fmap, cfg)
    if not len(hyp):
        return Relocalization("no_match", "no pair of observed landmarks matches a pair of "
                              "map features", n_landmarks=n)
    costs = np.empty(len(hyp))
    for s in range(0, len(hyp), 2000):
        costs[s:s + 2000] = _score(hyp[s:s + 2000], pts, wls, fmap, cfg).cost
    # refine the best few distinct hypotheses
    order = np.argsort(costs, kind="stable")
    chosen: list[Array] = []
    for k in order:
        if len(chosen) >= cfg.refine_top:
            break
        if all(not _same(hyp[k], c, cfg) for c in chosen):
            chosen.append(hyp[k])
    refined: list[tuple[Array, Array, float, int]] = []
    for x0 in chosen:
        x, cov = _refine(x0, pts, wls, fmap, cfg)
        sc = _score(x[None, :], pts, wls, fmap, cfg)
        refined.append((x, cov, float(sc.cost[0]), int(sc.inliers[0])))
    refined.sort(key=lambda r: r[2])
    # distinct results only (refinement can make two hypotheses converge)
    distinct: list[tuple[Array, Array, float, int]] = []
    for r in refined:
        if all(not _same(r[0], d[0], cfg) for d in distinct):
            distinct.append(r)
    best = distinct[0]
    x, cov, cost, inliers = best
    alts = tuple((_to_frames(d[0], d[1], o, m)[0], d[2], d[3]) for d in distinct[1:4])
    x_frame, cov_frame = _to_frames(x, cov, o, m)

    def result(status: RelocStatus, reason: str) -> Relocalization:
        return Relocalization(status, reason, x_frame, cov_frame, cost, inliers, n, len(hyp),
                              alts, o, m, x, cov)

    if inliers < cfg.min_inliers:
        return result("no_match", f"the best pose explains {inliers} of {n} landmarks, "
                      f"need {cfg.min_inliers}")
    sd_xy = math.sqrt(max(float(cov[0, 0]), float(cov[1, 1]))) if np.all(np.isfinite(cov)) \
        else math.inf
    sd_yaw = math.degrees(math.sqrt(float(cov[2, 2]))) if np.all(np.isfinite(cov)) else math.inf
    if not (sd_xy <= cfg.max_sd_m and sd_yaw <= cfg.max_sd_deg):
        return result("insufficient", f"the matched landmarks do not pin the pose "
                      f"(SD {sd_xy:.3f} m, {sd_yaw:.1f} deg)")
    if len(distinct) > 1 and distinct[1][2] - cost < cfg.ambiguity_d2:
        rival = distinct[1]
        return result(
            "ambiguous", f"{len([d for d in distinct if d[2] - cost < cfg.ambiguity_d2])} "
            f"poses explain the landmarks about as well (costs {cost:.1f} and "
            f"{rival[2]:.1f}, {inliers} and {rival[3]} of {n} landmarks): not guessing")
    margin = (distinct[1][2] - cost) if len(distinct) > 1 else math.inf
    return result("found", f"{inliers} of {n} landmarks matched, next best pose costs "
                  f"{margin:.1f} more")


def _map_centre(fmap: FeatureMap) -> Array:
    """(2,) the centre of the map's features' bounding box (zeros for an empty map)."""
    xy = np.concatenate([fmap.point_xy.reshape(-1, 2), fmap.wall_ends.reshape(-1, 2)])
    if not len(xy):
        return np.zeros(2)
    return 0.5 * (xy.min(axis=0) + xy.max(axis=0))


def _shifted_map(fmap: FeatureMap, origin: Array) -> FeatureMap:
    """``fmap`` with its positions relative to ``origin`` (2,) (directions unchanged)."""
    ends = fmap.wall_ends - origin
    return replace(fmap, point_xy=fmap.point_xy - origin, wall_ends=ends,
                   wall_line=_lines(ends))


def _to_frames(x: Array, cov: Array, o: Array, m: Array) -> tuple[Array, Array]:
    """The transform ``x`` (3,) between the local frames (odom about ``o``, map about
    ``m``) and its covariance as ``map_to_odom`` between the frames themselves:
    ``t = m + x[:2] - R o``."""
    c, s = math.cos(x[2]), math.sin(x[2])
    ro = np.array([c * o[0] - s * o[1], s * o[0] + c * o[1]])
    out = np.array([(m[0] - ro[0]) + x[0], (m[1] - ro[1]) + x[1], x[2]])
    if not np.all(np.isfinite(cov)):
        return out, cov.copy()
    j = np.eye(3)
    j[0, 2], j[1, 2] = ro[1], -ro[0]     # d(-R o)/d theta
    return out, j @ cov @ j.T


def _same(a: Array, b: Array, cfg: RelocalizeConfig) -> bool:
    return bool(np.hypot(*(a[:2] - b[:2])) < cfg.distinct_m and
                abs(float(se2.wrap_angle(a[2] - b[2]))) < math.radians(cfg.distinct_deg))


# --------------------------------------------------------------------------- the keeper


class Relocalizer:
    """Keeps the fits of the last ``window_s`` (in ``odom``) and the odometry path
    length, and runs :func:`relocalize` on them (bounded memory)."""

    def __init__(self, fmap: FeatureMap, config: RelocalizeConfig | None = None) -> None:
        self.fmap = fmap
        self.config = config or RelocalizeConfig()
        self._fits: deque[tuple[float, Landmark, float]] = deque(maxlen=4096)
        self._odom: deque[tuple[float, float]] = deque(maxlen=8192)  # (t, path length)
        self._last_xy: Array | None = None
        self._path = 0.0
        self.last_attempt_t = -math.inf
        self.attempts = 0
        self.last: Relocalization | None = None

    def on_odom(self, t_s: float, odom: Array) -> None:
        xy = np.asarray(odom[:2], dtype=float)
        if self._last_xy is not None:
            self._path += float(np.hypot(*(xy - self._last_xy)))
        self._last_xy = xy
        self._odom.append((t_s, self._path))
        self._trim(t_s)

    def add(self, lm: Landmark) -> None:
        self._fits.append((lm.ref_t_s, lm, self._path_at(lm.ref_t_s)))

    def clear(self) -> None:
        self._fits.clear()

    def forget_before(self, t_s: float) -> None:
        """Drop the fits whose reference reading is older than ``t_s``."""
        while self._fits and self._fits[0][0] < t_s:
            self._fits.popleft()

    def _path_at(self, t_s: float) -> float:
        for t, p in reversed(self._odom):
            if t <= t_s:
                return p
        return self._odom[0][1] if self._odom else self._path

    def _trim(self, now: float) -> None:
        horizon = now - self.config.window_s
        while self._fits and self._fits[0][0] < horizon:
            self._fits.popleft()
        while len(self._odom) > 1 and self._odom[1][0] < horizon:
            self._odom.popleft()

    def due(self, t_s: float) -> bool:
        return t_s - self.last_attempt_t >= self.config.every_s

    def solve(self, t_s: float) -> Relocalization:
        """Relocalize from the fits of the last ``window_s`` before ``t_s``."""
        self.last_attempt_t = t_s
        self.attempts += 1
        self._trim(t_s)
        fits = [(lm, self._path - p) for _, lm, p in self._fits]
        pts, wls = observed_landmarks(fits, self.config)
        self.last = relocalize(pts, wls, self.fmap, self.config)
        return self.last
