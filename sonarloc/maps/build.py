"""Map building: landmarks fitted along a logged drive, clustered and merged into a map.

Every reading of the log gets the pose of its transducer in ``map`` -- from a pose
track (``sonarloc localize ... --out POSES.csv``, interpolated to the reading's time),
or from the odometry anchored at the log's ``init`` pose (dead reckoning: it drifts).
The fitting stage's segmenter and fitter (``sonarloc.fit``) turn the readings into
landmarks in ``map``; the builder merges them across passes:

* **walls**: line fits whose (rho, alpha) agree within ``wall_gate_m`` /
  ``wall_gate_deg`` and whose extents (the normal-incidence points of their echoes)
  overlap or nearly touch (``wall_gap_m``) are one wall. Its (rho, alpha) is the
  information-weighted mean of the fits (fit covariance plus, with a pose track, the
  pose covariance carried through), its extent the span of the echo points. Walls that
  nearly meet (ends within ``join_m`` of their lines' intersection, beyond both ends)
  are extended to meet there; clusters on one line with overlapping extents are merged,
  and a wall parallel within ``shadow_m`` of a wall seen twice as often over the same
  stretch is dropped as a biased duplicate.
* **points**: point fits within ``point_gate_m`` of a cluster's predicted reflecting
  point are one reflector (strength is not used to split clusters: fitted kappas
  scatter widely; the cluster keeps their median). A cylinder reflects at its
  surface point facing the transducer, ``q = c + R u``: the builder solves the linear
  least squares for the centre ``c`` and radius ``R`` (with a zero-mean prior of SD
  ``radius_prior_sd_m`` on R, so R shrinks to 0 when the viewing directions do not
  spread). The kind follows radius, then strength: R >= ``pole_radius_m`` is a
  ``pole``; otherwise plane-strength (kappa near 0.15 us) is a ``corner``, near 0.67 us
  a ``point``, near 2.68 us a ``rod`` (``edge`` when within 0.3 m of a built wall's
  end). Clusters that converge within ``point_gate_m`` of each other are merged.

Clusters seen fewer than ``min_observations`` times are dropped (spikes, ghosts). Every
feature carries its uncertainty: ``sd_m`` (largest position SD; for walls the SD of
rho), walls also ``sd_alpha_deg``, plus ``n_obs`` and the merged ``kappa_us``.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import InitRecord, LogStats, OdomRecord, RigRecord, TofRecord, iter_log
from sonarloc.io.posescsv import PoseTrack
from sonarloc.maps.geojson import Map, map_from_geojson
from sonarloc.physics import constants

Array = NDArray[np.float64]

_KIND_KAPPA = {"corner": constants.KAPPA_US["corner"], "pole": constants.KAPPA_US["pole"],
               "rod": constants.KAPPA_US["rod"]}


@dataclass(frozen=True)
class BuildConfig:
    """Settings of the map builder (see the module docstring)."""

    point_gate_m: float = 0.10
    wall_gate_m: float = 0.08
    wall_gate_deg: float = 6.0
    wall_gap_m: float = 0.6
    join_m: float = 1.0
    shadow_m: float = 0.3
    min_observations: int = 4
    radius_prior_sd_m: float = 0.03
    pole_radius_m: float = 0.015
    statuses: tuple[str, ...] = ("ok", "flat")
    segment_max_readings: int = 30
    edge_near_wall_m: float = 0.3
    speed_of_sound_mps: float | None = None

    def __post_init__(self) -> None:
        for name in ("point_gate_m", "wall_gate_m", "wall_gate_deg", "pole_radius_m", "shadow_m",
                     "wall_gap_m", "join_m", "radius_prior_sd_m", "edge_near_wall_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if not (isinstance(self.min_observations, int) and self.min_observations >= 1):
            raise ValueError(f"`min_observations` must be a positive integer, got "
                             f"{self.min_observations!r}")


@dataclass
class _PointCluster:
    """Normal equations of q_i = c + R u_i (unknowns c_x, c_y, R), plus strength."""

    normal: Array
    rhs: Array
    n: int = 0
    log_kappas: deque[float] = field(default_factory=lambda: deque(maxlen=255))
    _solution: Array | None = None
    _cov: Array | None = None

    def add(self, q: Array, cov: Array, u: Array, log_kappa: float) -> None:
        a = np.array([[1.0, 0.0, u[0]], [0.0, 1.0, u[1]]])
        w = np.linalg.solve(cov, a)  # C⁻¹ A
        self.normal += a.T @ w
        self.rhs += w.T @ q
        self.n += 1
        self.log_kappas.append(log_kappa)
        self._solution = None

    def absorb(self, other: _PointCluster, prior_info: float) -> None:
        """Merge another cluster's observations (its radius prior is not counted twice)."""
        self.normal += other.normal
        self.normal[2, 2] -= prior_info
        self.rhs += other.rhs
        self.n += other.n
        self.log_kappas.extend(other.log_kappas)
        self._solution = None

    def solve(self) -> tuple[Array, Array]:
        """(c_x, c_y, R) and its covariance; R >= 0 (refitted with R = 0 if negative)."""
        if self._solution is None:
            # 3x3 information, well conditioned by the prior on R
            cov = np.asarray(np.linalg.inv(self.normal), dtype=float)
            sol = cov @ self.rhs
            if sol[2] < 0:
                cov = np.zeros((3, 3))
                cov[:2, :2] = np.linalg.inv(self.normal[:2, :2])
                sol = np.array([*(cov[:2, :2] @ self.rhs[:2]), 0.0])
            self._solution = sol
            self._cov = cov
        assert self._cov is not None
        return self._solution, self._cov

    @property
    def log_kappa(self) -> float:
        """Median of the fitted log strengths (fits of kappa scatter widely)."""
        return float(np.median(np.asarray(self.log_kappas)))

    def predict(self, u: Array) -> Array:
        sol, _ = self.solve()
        return sol[:2] + sol[2] * u


@dataclass
class _WallCluster:
    """Information-form mean of (rho, alpha) near ``alpha_ref``, and the extent."""

    alpha_ref: float
    info: Array
    rhs: Array
    t_min: float = math.inf
    t_max: float = -math.inf
    n: int = 0
    log_kappas: deque[float] = field(default_factory=lambda: deque(maxlen=255))
    zwz: float = 0.0

    def scatter(self) -> float:
        """Chi-square per degree of freedom of the member fits about the merged line."""
        if self.n < 2:
            return math.nan
        m, _ = self.mean()
        return max(self.zwz - float(m @ self.info @ m), 0.0) / (2 * (self.n - 1))

    def aligned(self, rho: float, alpha: float) -> Array:
        """(rho, alpha) expressed with alpha near ``alpha_ref`` (rho may turn negative)."""
        d = float(se2.wrap_angle(alpha - self.alpha_ref))
        if abs(d) > math.pi / 2:
            return np.array([-rho, self.alpha_ref + float(se2.wrap_angle(d + math.pi))])
        return np.array([rho, self.alpha_ref + d])

    def mean(self) -> tuple[Array, Array]:
        cov = np.asarray(np.linalg.inv(self.info), dtype=float)
        return cov @ self.rhs, cov

    def direction(self) -> Array:
        m, _ = self.mean()
        return np.array([-math.sin(m[1]), math.cos(m[1])])

    def project(self, xy: Array) -> Array:
        return np.asarray(xy, dtype=float) @ self.direction()


@dataclass(frozen=True)
class BuiltFeature:
    """One feature of a built map (map frame)."""

    kind: str
    coords: Array          # (2,) point or (2, 2) wall ends
    kappa_us: float
    sd_m: float
    n_obs: int
    radius_m: float = 0.0
    sd_alpha_deg: float = math.nan

    def geojson(self, fid: str) -> dict[str, Any]:
        geom: dict[str, Any]
        props: dict[str, Any] = {"kind": self.kind, "id": fid,
                                 "kappa_us": round(self.kappa_us, 4),
                                 "sd_m": round(self.sd_m, 5), "n_obs": self.n_obs}
        if self.kind == "wall":
            props["sd_alpha_deg"] = round(self.sd_alpha_deg, 4)
            props["vertices"] = "none"  # corners are explicit points; free ends are not edges
            geom = {"type": "LineString",
                    "coordinates": [[round(float(v), 5) for v in p] for p in
                                    self.coords.tolist()]}
        else:
            if self.kind in ("pole", "rod", "point"):
                props["radius_m"] = round(self.radius_m, 5)
            geom = {"type": "Point",
                    "coordinates": [round(float(v), 5) for v in self.coords.tolist()]}
        return {"type": "Feature", "properties": props, "geometry": geom}


class MapBuilder:
    """Clusters landmarks (in ``map``) across passes; :meth:`features` merges them."""

    def __init__(self, config: BuildConfig | None = None) -> None:
        self.config = config or BuildConfig()
        self.points: list[_PointCluster] = []
        self.walls: list[_WallCluster] = []
        self.stats: Counter[str] = Counter()

    def add(self, lm: Landmark, view_xy: Array, pose: Array | None = None,
            pose_cov: Array | None = None, feet: Array | None = None) -> str:
        """Add one landmark in ``map``.

        ``view_xy``: (2,) where the transducer saw it from (mean echo position);
        ``pose`` / ``pose_cov``: base_link pose at the reference time and its covariance
        (carried into the landmark's covariance); ``feet``: (k, 2) normal-incidence points
        of a wall's echoes (its extent). Returns what happened: ``point``, ``wall`` (joined
        or new) or the reason it was skipped.
        """
        cfg = self.config
        if lm.status.value not in cfg.statuses:
            self.stats[f"skipped_{lm.status.value}"] += 1
            return f"skipped_{lm.status.value}"
        p = np.asarray(lm.params, dtype=float)
        cov = np.asarray(lm.cov, dtype=float)[:2, :2].copy()
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(cov)) and p[2] > 0):
            self.stats["skipped_bad"] += 1
            return "skipped_bad"
        if pose is not None and pose_cov is not None and np.all(np.isfinite(pose_cov)):
            cov = cov + _pose_jacobian(lm.kind, p, pose) @ pose_cov @ \
                _pose_jacobian(lm.kind, p, pose).T
        cov = cov + np.eye(2) * 1e-8
        log_k = math.log(p[2])
        if lm.kind == "point":
            self._add_point(p[:2], cov, np.asarray(view_xy, dtype=float), log_k)
            return "point"
        self._add_wall(p[0], p[1], cov, feet, log_k)
        return "wall"

    def _add_point(self, q: Array, cov: Array, view: Array, log_k: float) -> None:
        cfg = self.config
        v = view - q
        u = v / max(float(np.hypot(*v)), 1e-9)
        best, best_d = None, math.inf
        for c in self.points:
            d = float(np.hypot(*(c.predict(u) - q)))
            if d < best_d:
                best, best_d = c, d
        if best is None or best_d > cfg.point_gate_m:
            prior = np.zeros((3, 3))
            prior[2, 2] = 1.0 / cfg.radius_prior_sd_m**2
            best = _PointCluster(prior, np.zeros(3))
            self.points.append(best)
            self.stats["point_clusters"] += 1
        best.add(q, cov, u, log_k)
        self.stats["points"] += 1

    def _add_wall(self, rho: float, alpha: float, cov: Array, feet: Array | None,
                  log_k: float) -> None:
        cfg = self.config
        f = np.zeros((0, 2)) if feet is None else np.asarray(feet, dtype=float).reshape(-1, 2)
        best, best_score = None, math.inf
        mid = f.mean(axis=0) if len(f) else None
        for c in self.walls:
            m, _ = c.mean()
            z = c.aligned(rho, alpha)
            dalpha = abs(z[1] - m[1])
            # offset between the lines where this fit's echoes were (not at the origin)
            drho = abs(z[0] - m[0]) if mid is None else \
                abs(float(mid @ [math.cos(m[1]), math.sin(m[1])]) - m[0])
            if drho > cfg.wall_gate_m or dalpha > math.radians(cfg.wall_gate_deg):
                continue
            if len(f) and math.isfinite(c.t_min):
                t = c.project(f)
                if t.max() < c.t_min - cfg.wall_gap_m or t.min() > c.t_max + cfg.wall_gap_m:
                    continue
            score = drho / cfg.wall_gate_m + dalpha / math.radians(cfg.wall_gate_deg)
            if score < best_score:
                best, best_score = c, score
        if best is None:
            best = _WallCluster(alpha, np.zeros((2, 2)), np.zeros(2))
            self.walls.append(best)
            self.stats["wall_clusters"] += 1
        z = best.aligned(rho, alpha)
        w = np.linalg.inv(cov)
        best.info += w
        best.rhs += w @ z
        best.zwz += float(z @ w @ z)
        best.n += 1
        best.log_kappas.append(log_k)
        if len(f):
            t = best.project(f)
            best.t_min = min(best.t_min, float(t.min()))
            best.t_max = max(best.t_max, float(t.max()))
        self.stats["walls"] += 1

    def features(self) -> list[BuiltFeature]:
        """The merged map features (clusters with at least ``min_observations``)."""
        cfg = self.config
        walls: list[BuiltFeature] = []
        for c in _merge_walls(self.walls, cfg):
            if c.n < cfg.min_observations or not math.isfinite(c.t_min):
                continue
            m, cov = c.mean()
            rho, alpha = float(m[0]), float(m[1])
            n = np.array([math.cos(alpha), math.sin(alpha)])
            d = np.array([-n[1], n[0]])
            ends = np.array([rho * n + c.t_min * d, rho * n + c.t_max * d])
            if c.t_max - c.t_min < 1e-3:
                continue
            walls.append(BuiltFeature("wall", ends, math.exp(float(np.median(c.log_kappas))),
                                      math.sqrt(cov[0, 0]), c.n,
                                      sd_alpha_deg=math.degrees(math.sqrt(cov[1, 1]))))
        walls = _join_walls(_drop_shadowed(walls, cfg), cfg.join_m)
        points: list[BuiltFeature] = []
        wall_ends = np.array([w.coords for w in walls]).reshape(-1, 2)
        prior_info = 1.0 / cfg.radius_prior_sd_m**2
        for pc in _merge_points(self.points, cfg.point_gate_m, prior_info):
            if pc.n < cfg.min_observations:
                continue
            sol, cov = pc.solve()
            kappa = math.exp(pc.log_kappa)
            radius = float(sol[2])
            centre = sol[:2]
            if radius >= cfg.pole_radius_m:
                kind = "pole"  # a resolved radius says cylinder, whatever kappa says
            else:
                kind = min(_KIND_KAPPA, key=lambda k: abs(math.log(_KIND_KAPPA[k]) - pc.log_kappa))
                near_end = bool(len(wall_ends)) and float(
                    np.min(np.hypot(*(wall_ends - centre).T))) < cfg.edge_near_wall_m
                if kind == "pole":
                    kind = "point"
                elif kind == "rod" and near_end:
                    kind = "edge"
            if kind in ("corner", "edge"):
                radius = 0.0
            sd = math.sqrt(float(np.max(np.linalg.eigvalsh(cov[:2, :2]))))
            points.append(BuiltFeature(kind, centre, kappa, sd, pc.n, radius))
        return walls + points

    def geojson(self) -> dict[str, Any]:
        """The built map as a GeoJSON FeatureCollection (FORMATS.md section 3)."""
        feats = []
        counts: Counter[str] = Counter()
        for f in self.features():
            counts[f.kind] += 1
            feats.append(f.geojson(f"{f.kind}-{counts[f.kind]}"))
        return {"type": "FeatureCollection", "features": feats}

    def to_map(self) -> Map:
        return map_from_geojson(self.geojson())


def _drop_shadowed(walls: list[BuiltFeature], cfg: BuildConfig) -> list[BuiltFeature]:
    """Drop a wall running parallel within ``shadow_m`` of a wall seen at least twice as
    often, over an overlapping stretch: a biased duplicate (one wall cannot be seen
    through another)."""
    keep = []
    for i, w in enumerate(walls):
        a0, a1 = w.coords
        d = a1 - a0
        length = float(np.hypot(*d))
        shadowed = False
        for j, o in enumerate(walls):
            if j == i or o.n_obs < 2 * w.n_obs:
                continue
            b0, b1 = o.coords
            e = b1 - b0
            lo = float(np.hypot(*e))
            if abs(d[0] * e[1] - d[1] * e[0]) > math.sin(math.radians(cfg.wall_gate_deg)) \
                    * length * lo:
                continue
            n = np.array([-e[1], e[0]]) / lo
            if max(abs(float((a0 - b0) @ n)), abs(float((a1 - b0) @ n))) > cfg.shadow_m:
                continue
            t = sorted(float((p - b0) @ e) / lo for p in (a0, a1))
            if t[1] > 0 and t[0] < lo:  # overlapping stretch
                shadowed = True
                break
        if not shadowed:
            keep.append(w)
    return keep


def _merge_walls(clusters: list[_WallCluster], cfg: BuildConfig) -> list[_WallCluster]:
    """Merge wall clusters on the same line whose extents overlap or nearly touch."""
    out: list[_WallCluster] = []
    for c in sorted(clusters, key=lambda c: -c.n):
        if not math.isfinite(c.t_min):
            out.append(c)
            continue
        m, _ = c.mean()
        n = np.array([math.cos(m[1]), math.sin(m[1])])
        d = np.array([-n[1], n[0]])
        ends = np.array([m[0] * n + c.t_min * d, m[0] * n + c.t_max * d])
        for o in out:
            if not math.isfinite(o.t_min):
                continue
            om, _ = o.mean()
            z = o.aligned(float(m[0]), float(m[1]))
            mid = ends.mean(axis=0)
            offset = abs(float(mid @ [math.cos(om[1]), math.sin(om[1])]) - om[0])
            if offset > cfg.wall_gate_m or abs(z[1] - om[1]) > math.radians(cfg.wall_gate_deg):
                continue
            t = o.project(ends)
            if t.max() < o.t_min - cfg.wall_gap_m or t.min() > o.t_max + cfg.wall_gap_m:
                continue
            # express c's information in o's (rho, alpha) branch: flip the sign of rho if
            # the normals point opposite ways
            flip = abs(float(se2.wrap_angle(m[1] - om[1]))) > math.pi / 2
            j = np.diag([-1.0, 1.0]) if flip else np.eye(2)
            o.info += j @ c.info @ j
            o.rhs += j @ c.info @ z
            o.zwz += c.zwz
            o.n += c.n
            o.log_kappas.extend(c.log_kappas)
            o.t_min = min(o.t_min, float(t.min()))
            o.t_max = max(o.t_max, float(t.max()))
            break
        else:
            out.append(_WallCluster(c.alpha_ref, c.info.copy(), c.rhs.copy(), c.t_min, c.t_max,
                                    c.n, deque(c.log_kappas, maxlen=255), c.zwz))
    return out


def _merge_points(clusters: list[_PointCluster], gate_m: float, prior_info: float
                  ) -> list[_PointCluster]:
    """Merge clusters whose centres ended up within ``gate_m`` (split early in a drive)."""
    out: list[_PointCluster] = []
    for c in sorted(clusters, key=lambda c: -c.n):
        centre = c.solve()[0][:2]
        for o in out:
            if float(np.hypot(*(o.solve()[0][:2] - centre))) <= gate_m:
                o.absorb(c, prior_info)
                break
        else:
            merged = _PointCluster(c.normal.copy(), c.rhs.copy(), c.n, deque(c.log_kappas,
                                                                             maxlen=255))
            out.append(merged)
    return out


def _pose_jacobian(kind: str, p: Array, pose: Array) -> Array:
    """d(landmark xy or rho/alpha in map) / d(base_link pose), (2, 3)."""
    if kind == "point":
        return np.array([[1.0, 0.0, -(p[1] - pose[1])], [0.0, 1.0, p[0] - pose[0]]])
    a = p[1]
    return np.array([[math.cos(a), math.sin(a), -pose[0] * math.sin(a) + pose[1] * math.cos(a)],
                     [0.0, 0.0, 1.0]])


def _join_walls(walls: list[BuiltFeature], join_m: float) -> list[BuiltFeature]:
    """Extend wall ends that nearly meet (within ``join_m`` of both lines' intersection,
    which must lie beyond both ends: walls are only lengthened, never cut)."""
    ends = [w.coords.copy() for w in walls]
    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            a0, a1 = ends[i]
            b0, b1 = ends[j]
            da, db = a1 - a0, b1 - b0
            cross = da[0] * db[1] - da[1] * db[0]
            na, nb = float(np.hypot(*da)), float(np.hypot(*db))
            if abs(cross) < math.sin(math.radians(30)) * na * nb:
                continue  # near parallel
            s = ((b0[0] - a0[0]) * db[1] - (b0[1] - a0[1]) * db[0]) / cross
            x = a0 + s * da
            ia = int(np.argmin(np.hypot(*(ends[i] - x).T)))
            ib = int(np.argmin(np.hypot(*(ends[j] - x).T)))
            beyond_a = float((x - ends[i][1 - ia]) @ (ends[i][ia] - ends[i][1 - ia])) >= \
                float(np.sum((ends[i][ia] - ends[i][1 - ia]) ** 2)) - 1e-9
            beyond_b = float((x - ends[j][1 - ib]) @ (ends[j][ib] - ends[j][1 - ib])) >= \
                float(np.sum((ends[j][ib] - ends[j][1 - ib]) ** 2)) - 1e-9
            if beyond_a and beyond_b and np.hypot(*(ends[i][ia] - x)) <= join_m \
                    and np.hypot(*(ends[j][ib] - x)) <= join_m:
                ends[i][ia] = x
                ends[j][ib] = x
    return [BuiltFeature(w.kind, e, w.kappa_us, w.sd_m, w.n_obs, w.radius_m, w.sd_alpha_deg)
            for w, e in zip(walls, ends, strict=True)]


# --------------------------------------------------------------------------- from a log


class _Track:
    """base_link pose (and covariance) in ``map`` at any time, by interpolation."""

    def __init__(self, t: Array, poses: Array, cov: Array | None) -> None:
        self.t = t
        self.poses = poses
        self.cov = cov

    def at(self, t_s: float) -> tuple[Array, Array | None]:
        i = int(np.searchsorted(self.t, t_s, "right"))
        if i <= 0:
            return self.poses[0], None if self.cov is None else self.cov[0]
        if i >= len(self.t):
            return self.poses[-1], None if self.cov is None else self.cov[-1]
        span = self.t[i] - self.t[i - 1]
        f = 0.0 if span <= 0 else (t_s - self.t[i - 1]) / span
        pose = se2.interpolate(self.poses[i - 1], self.poses[i], f)
        cov = None if self.cov is None else (1 - f) * self.cov[i - 1] + f * self.cov[i]
        return pose, cov


@dataclass
class BuildResult:
    """A built map with what went into it."""

    builder: MapBuilder
    log: LogStats
    landmarks: int = 0
    readings: int = 0
    skipped: Counter[str] = field(default_factory=Counter)

    def geojson(self) -> dict[str, Any]:
        return self.builder.geojson()

    def summary(self) -> str:
        feats = self.builder.features()
        kinds = Counter(f.kind for f in feats)
        parts = [f"log: {self.log.summary()}", f"{self.readings} readings",
                 f"{self.landmarks} landmarks fitted",
                 "map: " + (", ".join(f"{v} {k}" for k, v in sorted(kinds.items())) or "empty")]
        st = {k: v for k, v in self.builder.stats.items() if k.startswith("skipped")}
        st.update(self.skipped)
        if st:
            parts.append("skipped: " + ", ".join(f"{k} {v}" for k, v in sorted(st.items())))
        return "; ".join(parts)


def _readings(source: str | Path | IO[str], stats: LogStats, poses: PoseTrack | None,
              skipped: Counter[str]) -> Iterator[tuple[float, int, float, Array, Array | None,
                                                      Array, float]]:
    """Yield (t, sensor, tof_us, transducer pose in map, base pose cov, base pose, c)."""
    mounts: dict[int, Array] = {}
    c_mps = 343.0
    init: Array | None = None
    odom_first: Array | None = None
    track = None
    if poses is not None:
        track = _Track(np.asarray(poses.t_s, float),
                       np.stack([poses.x_m, poses.y_m, poses.yaw_rad], axis=-1),
                       None if np.any(np.isnan(poses.cov)) else np.asarray(poses.cov))
    odo_t: list[float] = []
    odo_p: list[Array] = []
    pending: list[TofRecord] = []

    def odom_at(t: float) -> Array:
        i = bisect.bisect_right(odo_t, t)
        if i <= 0:
            return odo_p[0]
        if i >= len(odo_t):
            return odo_p[-1]
        span = odo_t[i] - odo_t[i - 1]
        return se2.interpolate(odo_p[i - 1], odo_p[i], 0.0 if span <= 0 else
                               (t - odo_t[i - 1]) / span)

    def emit(r: TofRecord) -> tuple[float, int, float, Array, Array | None, Array, float]:
        mount = mounts[r.sensor]
        if r.pan_deg is not None:
            mount = mount + np.array([0.0, 0.0, math.radians(r.pan_deg)])
        cov = None
        if track is not None:
            base, cov = track.at(r.t_s)
        else:
            first = odom_first if odom_first is not None else odo_p[0]
            rel = se2.between(first, odom_at(r.t_s))
            base = se2.compose(init, rel) if init is not None else rel
        tof = math.nan if r.tof_us is None else float(r.tof_us)
        return r.t_s, r.sensor, tof, se2.compose(base, mount), cov, base, c_mps

    for rec in iter_log(source, stats):
        if isinstance(rec, RigRecord):
            mounts = {m.id: np.array([m.x_m, m.y_m, math.radians(m.yaw_deg)])
                      for m in rec.sensors}
            c_mps = rec.speed_of_sound_mps
        elif isinstance(rec, InitRecord):
            if init is None:
                init = np.array([rec.x_m, rec.y_m, math.radians(rec.yaw_deg)])
        elif isinstance(rec, OdomRecord):
            p = np.array([rec.x_m, rec.y_m, math.radians(rec.yaw_deg)])
            if odom_first is None:
                odom_first = p
            if odo_t and rec.t_s < odo_t[-1]:
                skipped["odom_time_backwards"] += 1
                continue
            odo_t.append(rec.t_s)
            odo_p.append(p)
            if len(odo_t) > 4096:  # only recent odometry is needed: keep memory flat
                del odo_t[:2048]
                del odo_p[:2048]
            ready = [r for r in pending if r.t_s <= rec.t_s]
            pending = [r for r in pending if r.t_s > rec.t_s]
            for r in ready:
                yield emit(r)
        elif isinstance(rec, TofRecord):
            if rec.sensor not in mounts:
                skipped["tof_unknown_sensor" if mounts else "tof_before_rig"] += 1
                continue
            if track is not None:
                yield emit(rec)
            elif odom_first is None:
                skipped["tof_before_odom"] += 1
            else:
                pending.append(rec)
    if odom_first is not None:
        for r in pending:
            yield emit(r)


def build_from_log(source: str | Path | IO[str], poses: PoseTrack | None = None,
                   config: BuildConfig | None = None) -> BuildResult:
    """Build a map from a log (FORMATS.md section 4), streaming.

    Parameters
    ----------
    source : the log.
    poses : base_link poses in ``map`` (a pose CSV, e.g. from ``sonarloc localize``);
        None: odometry anchored at the log's ``init`` pose (or at the origin).
    config : builder settings.
    """
    from sonarloc.fit.landmarks import fit_segments
    from sonarloc.fit.lsq import FitConfig
    from sonarloc.fit.segment import Segmenter, SegmenterConfig
    from sonarloc.physics.tof import ModuleParams

    cfg = config or BuildConfig()
    stats = LogStats()
    result = BuildResult(MapBuilder(cfg), stats)
    seg: Segmenter | None = None
    fit_cfg: FitConfig | None = None
    ref_cov: dict[float, tuple[Array, Array | None]] = {}
    for t, sensor, tof, pose, cov, base, c_mps in _readings(source, stats, poses, result.skipped):
        if seg is None or fit_cfg is None:
            fit_cfg = FitConfig(module=ModuleParams(c_mps=cfg.speed_of_sound_mps or c_mps))
            seg = Segmenter(SegmenterConfig(max_readings=cfg.segment_max_readings),
                            fit_cfg.module)
        result.readings += 1
        if math.isfinite(tof):
            ref_cov[t] = (base, cov)
            if len(ref_cov) > 20000:
                for k in list(ref_cov)[:10000]:
                    del ref_cov[k]
        closed = seg.push(t, float(pose[0]), float(pose[1]), float(pose[2]), tof, sensor)
        if closed:
            _add_segments(result, closed, fit_segments(closed, fit_cfg), ref_cov)
    if seg is not None and fit_cfg is not None:
        closed = seg.flush()
        if closed:
            _add_segments(result, closed, fit_segments(closed, fit_cfg), ref_cov)
    return result


def _add_segments(result: BuildResult, segments: list[Any], landmarks: list[Landmark],
                  ref_cov: dict[float, tuple[Array, Array | None]]) -> None:
    if len(segments) != len(landmarks):  # pragma: no cover - fit_segments is one per segment
        raise RuntimeError("fit_segments returned a different number of landmarks")
    for s, lm in zip(segments, landmarks, strict=True):
        result.landmarks += 1
        r = s.readings
        echo = np.isfinite(r.tof_us)
        view = np.array([np.mean(r.x_m[echo]), np.mean(r.y_m[echo])]) if echo.any() else \
            np.array(lm.ref_pose[:2])
        base, cov = ref_cov.get(lm.ref_t_s, (None, None))
        feet = None
        if lm.kind == "line":
            n = np.array([math.cos(lm.params[1]), math.sin(lm.params[1])])
            xy = np.stack([r.x_m[echo], r.y_m[echo]], axis=-1)
            feet = xy + (lm.params[0] - xy @ n)[:, None] * n
        result.builder.add(lm, view, base, cov, feet)
