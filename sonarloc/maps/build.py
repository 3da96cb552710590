"""Map building: landmarks fitted along a logged drive, clustered and merged into a map.

Every reading of the log gets the pose of its transducer in ``map`` -- from a pose
track (``sonarloc localize ... --out POSES.csv``, interpolated to the reading's time),
or from the odometry anchored at the log's ``init`` pose (dead reckoning: it drifts),
then, by default (``method="slam"``), corrected by graph SLAM: the robot poses and the
landmarks estimated together from the odometry and the landmark fits
(:mod:`sonarloc.maps.slam`), and the fits re-placed with the optimized poses.
The fitting stage's segmenter and fitter (``sonarloc.fit``) turn the readings into
landmarks in ``map``; the builder merges them across passes:

* **walls**: line fits whose (rho, alpha) agree within ``wall_gate_m`` /
  ``wall_gate_deg`` and whose extents (the normal-incidence points of their echoes)
  overlap or nearly touch (``wall_gap_m``) are one wall. Its line is fitted through the
  member fits' *feet* (where the transducers' perpendiculars met each fitted line; total
  least squares, outliers beyond 3 robust SDs dropped): a pose's yaw error rotates a
  fitted line about its foot, so the feet stay on the wall while the fits' (rho, alpha)
  do not. Its extent is the span of the inlier feet. Walls that nearly meet (ends within
  ``join_m`` of their lines' intersection, beyond both ends) are extended to meet
  there; clusters on one line with overlapping extents are merged, a wall parallel
  within ``shadow_m`` of a wall seen twice as often over the same stretch is dropped as
  a biased duplicate, and a wall shorter than ``short_wall_m`` seen fewer than twice
  ``min_observations`` times is dropped (corner echoes fitted as a line).
* **points**: point fits within ``point_gate_m`` of a cluster's predicted reflecting
  point are one reflector (strength is not used to split clusters: fitted kappas
  scatter widely; the cluster keeps their median). A cylinder reflects at its
  surface point facing the transducer, ``q = c + R u``: the builder solves the linear
  least squares for the centre ``c`` and radius ``R`` (with a zero-mean prior of SD
  ``radius_prior_sd_m`` on R, so R shrinks to 0 when the viewing directions do not
  spread). The kind: within ``corner_gate_m`` of a vertex where two built walls meet,
  ``corner`` if seen from inside the walls' angle, ``edge`` if from outside; otherwise
  R >= ``pole_radius_m`` (and more than plane strength) is a ``pole``; otherwise
  plane-strength (kappa near 0.15 us) is a ``corner``, near 0.67 us a ``point``, near
  2.68 us a ``rod`` (``edge`` when within ``edge_near_wall_m`` of a built wall's end).
  Corners and edges are placed by the fit with R = 0 (a vertex has no radius). A point
  on a built wall (within ``on_wall_m`` of its line, further than ``end_gate_m`` from
  its ends) is dropped: a wall echo fitted as a point. (A vertex at a wall's end
  echoes like the wall beside it, so the wall's feet run past the vertex: its echo
  from a transducer whose foot is 7 cm past it, 2 m away, is only 1.2 mm longer.)
  Clusters that converge within ``point_gate_m`` of each other are merged.

Clusters seen fewer than ``min_observations`` times, or in fewer than ``min_visits``
separate passes (observations more than ``visit_gap_s`` apart), are dropped (spikes,
ghosts). Every feature carries its uncertainty: ``sd_m`` (a point's largest position
SD; a wall's SD across its line at the worse of its ends, from the feet's scatter and
its direction's SD), walls also ``sd_alpha_deg``, plus ``n_obs``, ``n_visits`` and the
merged ``kappa_us``. A point's own part is scaled by the fit's reduced chi-square when
above 1 (sightings scattering beyond their stated SDs). The poses' errors are in it:
a pose track's covariance as each sighting's own error; without a track, the dead
reckoning's covariance (the ``init`` prior carried along the odometry with
``odom_noise``), an error the sightings share, kept whole (:class:`_Drift`); with SLAM,
the optimized poses' marginal covariances, the same way. A SLAM build also writes
``sd_rel_m``: the same SD from the poses' covariances relative to the map frame (the
error of the frame itself, which all features share, taken out:
:func:`sonarloc.maps.slam._pose_marginals`); the Localizer uses it instead of ``sd_m``.
A dead-reckoned build writes none (its drift is the map's shape error: given the
``init`` pose it is honest in that pose's frame but not after the map's best rigid
alignment, docs/MAPS.md).
"""

from __future__ import annotations

import bisect
import math
import time
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import InitRecord, LogStats, OdomRecord, RigRecord, TofRecord, iter_log
from sonarloc.io.posescsv import PoseTrack
from sonarloc.io.scancsv import TimeoutWatch
from sonarloc.localize.ekf import OdomNoise, predict_lists
from sonarloc.localize.localizer import DEFAULT_ODOM_NOISE, in_odom_gap
from sonarloc.localize.odomframe import OdomJoiner, check_odom_reset_settings
from sonarloc.maps.geojson import Map, map_from_geojson
from sonarloc.maps.slam import (
    Observation,
    OdomTrace,
    SlamConfig,
    SlamResult,
    optimize,
    transform_with_cov,
)
from sonarloc.physics import constants

Array = NDArray[np.float64]

_MAX_FEET = 3000

_KIND_KAPPA = {"corner": constants.KAPPA_US["corner"], "pole": constants.KAPPA_US["pole"],
               "rod": constants.KAPPA_US["rod"]}
#: log strength halfway (geometrically) between a corner's and a pole's
_LOG_CORNER_SPLIT = 0.5 * (math.log(_KIND_KAPPA["corner"]) + math.log(_KIND_KAPPA["pole"]))


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
    corner_gate_m: float = 0.05
    on_wall_m: float = 0.03
    end_gate_m: float = 0.12
    visit_gap_s: float = 10.0
    short_wall_m: float = 0.5
    min_visits: int = 1
    speed_of_sound_mps: float | None = None
    odom_gap_s: float = 1.0  # readings inside a longer gap of a moving robot's poses: skipped
    #: odometry increment noise of a build without poses (dead reckoning): its drift's
    #: covariance, propagated along the log, goes into the features' ``sd_m``
    odom_noise: OdomNoise = field(default_factory=lambda: DEFAULT_ODOM_NOISE)
    # an odometry increment implying more is a jump, taken as a reset (as the Localizer's
    # LocalizerConfig.odom_max_speed_mps / odom_max_yaw_rate_rad_s; math.inf: never)
    odom_max_speed_mps: float = 5.0
    odom_max_yaw_rate_rad_s: float = 10.0
    #: a module that logs its timeout as a reading: readings at or above this [us] are
    #: no echo, counted in ``BuildResult.timeouts`` (as ``LocalizerConfig.max_tof_us``);
    #: None: every reading as logged (the summary says when they look like timeouts)
    max_tof_us: float | None = None
    #: across a reset or jump the motion is unknown: the dead reckoning's covariance
    #: grows by these SDs (as LocalizerConfig.odom_reset_sd_m / odom_reset_sd_deg)
    odom_reset_sd_m: float = 0.1
    odom_reset_sd_deg: float = 5.0
    #: without a pose track: ``slam`` (poses and landmarks estimated together,
    #: :mod:`sonarloc.maps.slam`; falls back to the odometry with a reason) or
    #: ``odometry`` (dead reckoning alone)
    method: str = "slam"
    #: settings of the SLAM (its gates and radius prior are this config's)
    slam: SlamConfig = field(default_factory=SlamConfig)

    def __post_init__(self) -> None:
        if self.method not in BUILD_METHODS:
            raise ValueError(f"`method` must be one of {', '.join(BUILD_METHODS)}, got "
                             f"{self.method!r}")
        for name in ("point_gate_m", "wall_gate_m", "wall_gate_deg", "pole_radius_m", "shadow_m",
                     "wall_gap_m", "join_m", "radius_prior_sd_m", "edge_near_wall_m",
                     "corner_gate_m", "on_wall_m", "end_gate_m", "visit_gap_s",
                     "short_wall_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if self.max_tof_us is not None and not (math.isfinite(self.max_tof_us)
                                                and self.max_tof_us > 0):
            raise ValueError(f"`max_tof_us` must be a positive number of microseconds or "
                             f"None, got {self.max_tof_us!r}")
        if not self.odom_gap_s > 0:  # math.inf allowed: no gaps
            raise ValueError(f"`odom_gap_s` must be positive, got {self.odom_gap_s!r}")
        check_odom_reset_settings(self.odom_max_speed_mps, self.odom_max_yaw_rate_rad_s,
                                  self.odom_reset_sd_m, self.odom_reset_sd_deg)
        if not (isinstance(self.min_observations, int) and self.min_observations >= 1):
            raise ValueError(f"`min_observations` must be a positive integer, got "
                             f"{self.min_observations!r}")


BUILD_METHODS = ("slam", "odometry")
"""How :func:`build_from_log` places the readings without a pose track."""


@dataclass
class _Visits:
    """Time intervals in which a cluster was observed (gaps > ``gap_s`` start a new one)."""

    spans: list[list[float]] = field(default_factory=list)

    def add(self, t_s: float, gap_s: float) -> None:
        if not math.isfinite(t_s):
            return
        for sp in self.spans[-2:]:
            if sp[0] - gap_s <= t_s <= sp[1] + gap_s:
                sp[0], sp[1] = min(sp[0], t_s), max(sp[1], t_s)
                return
        self.spans.append([t_s, t_s])
        if len(self.spans) > 1 and t_s < self.spans[-2][0]:
            self.spans.sort()

    def merged(self, other: _Visits, gap_s: float) -> _Visits:
        out: list[list[float]] = []
        for sp in sorted(self.spans + other.spans):
            if out and sp[0] <= out[-1][1] + gap_s:
                out[-1][1] = max(out[-1][1], sp[1])
            else:
                out.append(list(sp))
        return _Visits(out)

    def __len__(self) -> int:
        return len(self.spans)


@dataclass
class _Drift:
    """Weighted mean of the sightings' dead-reckoning covariances (2, 2), each mapped
    into the landmark's parameters (x, y or rho, alpha).

    The odometry's drift is an error the sightings share (every later pose carries all
    of the drift before it), so it does not average down over sightings: the weighted
    mean of their covariances, not the covariance divided by their number, bounds the
    error the drift leaves in a weighted mean of them (for any correlation between them).
    """

    total: Array = field(default_factory=lambda: np.zeros((2, 2)))
    weight: float = 0.0

    def add(self, cov: Array, weight: float) -> None:
        self.total += weight * cov
        self.weight += weight

    def merged(self, other: _Drift, flip: bool = False) -> _Drift:
        j = np.diag([-1.0, 1.0]) if flip else np.eye(2)
        return _Drift(self.total + j @ other.total @ j, self.weight + other.weight)

    def cov(self) -> Array:
        return self.total / self.weight if self.weight > 0 else np.zeros((2, 2))


@dataclass
class _PointCluster:
    """Normal equations of q_i = c + R u_i (unknowns c_x, c_y, R), plus strength."""

    normal: Array
    rhs: Array
    n: int = 0
    log_kappas: deque[float] = field(default_factory=lambda: deque(maxlen=255))
    _solution: Array | None = None
    _cov: Array | None = None
    u_sum: Array = field(default_factory=lambda: np.zeros(2))
    visits: _Visits = field(default_factory=_Visits)
    #: sum of q_i' C_i⁻¹ q_i (for the fit's chi-square)
    zwz: float = 0.0
    drift: _Drift = field(default_factory=lambda: _Drift())
    #: the drift relative to the map frame (its common error taken out; :class:`_Drift`)
    drift_rel: _Drift = field(default_factory=lambda: _Drift())
    #: Σ Aᵢᵀ Cᵢ⁻¹ Fᵢ Cᵢ⁻¹ Aᵢ (+ the prior), Fᵢ the fit's own covariance (Cᵢ less the
    #: drift): the middle of the sandwich covariance of the fit's own error
    middle: Array | None = None

    def __post_init__(self) -> None:
        if self.middle is None:
            self.middle = self.normal.copy()

    def mean_view(self) -> Array:
        """(2,) mean unit direction from the reflector towards the transducers."""
        return self.u_sum / max(float(np.hypot(*self.u_sum)), 1e-12)

    def solve_point(self) -> tuple[Array, Array]:
        """Centre (2,) and covariance (2, 2) of a point reflector (radius fixed at 0)."""
        cov = np.asarray(np.linalg.inv(self.normal[:2, :2]), dtype=float)
        return cov @ self.rhs[:2], cov

    def add(self, q: Array, cov: Array, u: Array, log_kappa: float,
            fit_cov: Array | None = None) -> None:
        """One sighting ``q`` (2,) of covariance ``cov`` (its weight), of which
        ``fit_cov`` (default: all) is its own error, the rest shared drift."""
        a = np.array([[1.0, 0.0, u[0]], [0.0, 1.0, u[1]]])
        w = np.linalg.solve(cov, a)  # C⁻¹ A
        self.normal += a.T @ w
        assert self.middle is not None
        self.middle += a.T @ w if fit_cov is None else w.T @ fit_cov @ w
        self.rhs += w.T @ q
        self.zwz += float(q @ np.linalg.solve(cov, q))
        self.n += 1
        self.log_kappas.append(log_kappa)
        self.u_sum += u
        self._solution = None

    def absorb(self, other: _PointCluster, prior_info: float, gap_s: float) -> None:
        """Merge another cluster's observations (its radius prior is not counted twice)."""
        self.normal += other.normal
        self.normal[2, 2] -= prior_info
        assert self.middle is not None and other.middle is not None
        self.middle += other.middle
        self.middle[2, 2] -= prior_info
        self.rhs += other.rhs
        self.zwz += other.zwz
        self.drift = self.drift.merged(other.drift)
        self.drift_rel = self.drift_rel.merged(other.drift_rel)
        self.n += other.n
        self.log_kappas.extend(other.log_kappas)
        self.u_sum += other.u_sum
        self.visits = self.visits.merged(other.visits, gap_s)
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

    def fit_cov(self, radius: bool) -> Array:
        """(2, 2) covariance of the centre from the sightings' own errors (the drift
        they share left out): of the solution with the radius ``radius``, else of the
        point with R = 0."""
        assert self.middle is not None
        if radius:
            n_inv = np.linalg.inv(self.normal)
            return np.asarray((n_inv @ self.middle @ n_inv)[:2, :2], dtype=float)
        n_inv = np.linalg.inv(self.normal[:2, :2])
        return np.asarray(n_inv @ self.middle[:2, :2] @ n_inv, dtype=float)

    def chi2_per_dof(self, radius: bool) -> float:
        """Reduced chi-square of the sightings about the solution (with the radius
        ``radius``, else the point with R = 0); NaN without degrees of freedom."""
        if radius:
            sol, _ = self.solve()
            chi2, dof = self.zwz - float(sol @ self.rhs), 2 * self.n - 3
        else:
            centre, _ = self.solve_point()
            chi2, dof = self.zwz - float(centre @ self.rhs[:2]), 2 * self.n - 2
        return max(chi2, 0.0) / dof if dof > 0 else math.nan

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
    #: (foot_x, foot_y, weight) of the member fits' echo extents (ends and middle), the
    #: most recent ``_MAX_FEET`` kept (memory stays bounded over long logs)
    feet: deque[tuple[float, float, float]] = field(
        default_factory=lambda: deque(maxlen=_MAX_FEET))
    visits: _Visits = field(default_factory=_Visits)
    #: dead-reckoning covariance of (rho, alpha), in this cluster's branch
    drift: _Drift = field(default_factory=lambda: _Drift())
    #: the same relative to the map frame (its common error taken out)
    drift_rel: _Drift = field(default_factory=lambda: _Drift())

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
    n_visits: int = 0
    #: a wall's across-line variance [m²] at a point p on it: ``c0 + c1 t + c2 t²`` with
    #: t = p · d [m] along the unit direction d = (dx, dy): (c0, c1, c2, dx, dy)
    offset_var: tuple[float, float, float, float, float] | None = None
    #: the SD [m] relative to the map frame (``sd_m`` less the error all features share,
    #: the map frame's own against the world: see the module docstring); NaN: not known
    sd_rel_m: float = math.nan
    #: a wall's ``offset_var`` relative to the map frame
    offset_var_rel: tuple[float, float, float, float, float] | None = None

    def end_sd(self, ends: Array) -> float:
        """A wall's SD [m] across its line at the worse of its ends ``ends`` (2, 2)."""
        return self.sd_m if self.offset_var is None else _end_sd(self.offset_var, ends)

    def end_sd_rel(self, ends: Array) -> float:
        """:meth:`end_sd` relative to the map frame (``sd_rel_m``)."""
        return self.sd_rel_m if self.offset_var_rel is None else \
            _end_sd(self.offset_var_rel, ends)

    def geojson(self, fid: str) -> dict[str, Any]:
        geom: dict[str, Any]
        props: dict[str, Any] = {"kind": self.kind, "id": fid,
                                 "kappa_us": round(self.kappa_us, 4),
                                 "sd_m": round(self.sd_m, 5), "n_obs": self.n_obs,
                                 "n_visits": self.n_visits}
        if math.isfinite(self.sd_rel_m):
            props["sd_rel_m"] = round(self.sd_rel_m, 5)
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


def _offset_var(sd_rho: float, sd_alpha: float, t_c: float, d: Array, drift: Array
                ) -> tuple[float, float, float, float, float]:
    """A wall's across-line variance at t (:attr:`BuiltFeature.offset_var`): the fit's
    (``sd_rho`` at the feet's centroid ``t_c``, the direction's ``sd_alpha`` about it)
    plus the drift's (rho, alpha) covariance ``drift`` (2, 2) at the origin:
    offset(t) = d_rho - t d_alpha; ``d`` (2,) the unit direction."""
    return (sd_rho**2 + t_c**2 * sd_alpha**2 + float(drift[0, 0]),
            -2.0 * t_c * sd_alpha**2 - 2.0 * float(drift[0, 1]),
            sd_alpha**2 + float(drift[1, 1]), float(d[0]), float(d[1]))


def _end_sd(offset_var: tuple[float, float, float, float, float], ends: Array) -> float:
    """SD [m] across a wall's line at the worse of ``ends`` (2, 2), from its across-line
    variance ``c0 + c1 t + c2 t²`` (:attr:`BuiltFeature.offset_var`)."""
    c0, c1, c2, dx, dy = offset_var
    t = np.asarray(ends, dtype=float) @ np.array([dx, dy])
    return float(np.sqrt(np.max(np.maximum(c0 + c1 * t + c2 * t**2, 0.0))))


class MapBuilder:
    """Clusters landmarks (in ``map``) across passes; :meth:`features` merges them.

    ``origin`` (2,) m: the builder works in ``map`` shifted by ``-origin``: :meth:`add`
    takes landmarks, views, poses and feet in that frame, :meth:`features` and
    :meth:`geojson` give ``map`` coordinates. :func:`build_from_log` puts it at the
    first reading's robot position, so that the walls' (rho, alpha) information and
    the vague-landmark test are formed near the data whatever the map frame's origin
    (a wall's rho about an origin 5e6 m away, as in UTM, has an SD of 5e6 m times its
    alpha's: every wall was skipped as vague there).
    """

    def __init__(self, config: BuildConfig | None = None,
                 origin: tuple[float, float] | Array = (0.0, 0.0)) -> None:
        self.config = config or BuildConfig()
        self.points: list[_PointCluster] = []
        self.walls: list[_WallCluster] = []
        self.stats: Counter[str] = Counter()
        self.origin = np.asarray(origin, dtype=float).reshape(2).copy()
        #: whether a sighting gave its drift relative to the map frame (:meth:`add`'s
        #: ``drift_rel_cov``): the features then carry ``sd_rel_m``
        self.frame_relative = False
        if not np.all(np.isfinite(self.origin)):
            raise ValueError(f"`origin` must be two finite numbers, got {origin!r}")

    def add(self, lm: Landmark, view_xy: Array, pose: Array | None = None,
            pose_cov: Array | None = None, feet: Array | None = None,
            drift_cov: Array | None = None, drift_rel_cov: Array | None = None) -> str:
        """Add one landmark in ``map``.

        ``view_xy``: (2,) where the transducer saw it from (mean echo position);
        ``pose`` / ``pose_cov``: base_link pose at the reference time and its covariance
        (carried into the landmark's covariance, an error of this sighting alone);
        ``feet``: (k, 2) normal-incidence points of a wall's echoes (its extent);
        ``drift_cov``: (3, 3) covariance of the pose's dead-reckoning drift (with
        ``pose``), an error shared with the other sightings of the feature: it weights
        this sighting and is kept whole in the feature's ``sd_m`` (:class:`_Drift`);
        ``drift_rel_cov``: (3, 3) the part of it relative to the map frame (the error
        all the map's features share taken out), kept whole in the feature's
        ``sd_rel_m`` (written once any sighting of the build gave it; a sighting
        without it counts its whole ``drift_cov`` there).
        Returns what happened: ``point``, ``wall`` (joined or new) or the reason it was
        skipped.
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
        if self._vague(lm.kind, cov):  # (the drift does not make a fit vague)
            self.stats["skipped_vague"] += 1
            return "skipped_vague"
        drift = np.zeros((2, 2))
        drift_rel = drift
        if pose is not None and drift_cov is not None and np.all(np.isfinite(drift_cov)):
            jac = _pose_jacobian(lm.kind, p, pose)
            drift = jac @ np.asarray(drift_cov, dtype=float) @ jac.T
            cov = cov + drift
            drift_rel = drift
            if drift_rel_cov is not None and np.all(np.isfinite(drift_rel_cov)):
                drift_rel = jac @ np.asarray(drift_rel_cov, dtype=float) @ jac.T
                self.frame_relative = True
        log_k = math.log(p[2])
        if lm.kind == "point":
            self._add_point(p[:2], cov, np.asarray(view_xy, dtype=float), log_k, lm.ref_t_s,
                            drift, drift_rel)
            return "point"
        self._add_wall(p[0], p[1], cov, feet, log_k, lm.ref_t_s, drift, drift_rel)
        return "wall"

    VAGUE_GATES = 10.0
    """A landmark whose SD of x or y (rho or alpha) exceeds this many of its gates
    (``point_gate_m``; ``wall_gate_m``, ``wall_gate_deg``) is skipped (:meth:`_vague`)."""

    def _vague(self, kind: str, cov: Array) -> bool:
        """A landmark its fit cannot place: an SD of x or y beyond :attr:`VAGUE_GATES`
        point gates (of rho or alpha, wall gates: 0.8 m, 60 deg by default), or a
        covariance not positive definite. It adds no information, only a count. A `FLAT`
        wall driven past at one angle can leave rho and alpha undetermined together (SDs
        of 7e7 m, correlation 1: inverting that covariance stopped the builder). On
        that log (bench_localize's map building, seed 200, true poses)
        8 of 304 points and 8 of 227 walls are this vague; 20 and 32 have an SD beyond
        one gate, kept (their weight is small)."""
        cfg = self.config
        gate = ((cfg.point_gate_m, cfg.point_gate_m) if kind == "point"
                else (cfg.wall_gate_m, math.radians(cfg.wall_gate_deg)))
        var = np.diag(cov) / (self.VAGUE_GATES * np.asarray(gate)) ** 2
        return bool(var.max() > 1.0 or np.linalg.eigvalsh(cov)[0] <= 0.0)

    def _add_point(self, q: Array, cov: Array, view: Array, log_k: float,
                   t_s: float, drift: Array, drift_rel: Array) -> None:
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
        best.add(q, cov, u, log_k, cov - drift)
        # weighted as the fit weights it (its information, as a scalar)
        best.drift.add(drift, 2.0 / float(np.trace(cov)))
        best.drift_rel.add(drift_rel, 2.0 / float(np.trace(cov)))
        best.visits.add(t_s, cfg.visit_gap_s)
        self.stats["points"] += 1

    def _add_wall(self, rho: float, alpha: float, cov: Array, feet: Array | None,
                  log_k: float, t_s: float, drift: Array, drift_rel: Array) -> None:
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
        # the line goes through the feet, each fit weighted by its echoes
        flip = np.diag([-1.0, 1.0]) if abs(float(se2.wrap_angle(alpha - best.alpha_ref))) > \
            math.pi / 2 else np.eye(2)
        best.drift.add(flip @ drift @ flip, float(max(len(f), 1)))
        best.drift_rel.add(flip @ drift_rel @ flip, float(max(len(f), 1)))
        w = np.linalg.inv(cov)
        best.info += w
        best.rhs += w @ z
        best.zwz += float(z @ w @ z)
        best.n += 1
        best.log_kappas.append(log_k)
        best.visits.add(t_s, cfg.visit_gap_s)
        if len(f):
            t = best.project(f)
            best.t_min = min(best.t_min, float(t.min()))
            best.t_max = max(best.t_max, float(t.max()))
            # the fit's extent as three weighted points on its own line: where the
            # transducers' perpendiculars met it (accurate across the wall whatever the
            # pose's yaw error, which only slides them along it)
            tf = f @ np.array([-math.sin(alpha), math.cos(alpha)])
            w_each = len(f) / 3.0
            for k in (int(np.argmin(tf)), int(np.argmax(tf))):
                best.feet.append((float(f[k, 0]), float(f[k, 1]), w_each))
            mean = f.mean(axis=0)
            best.feet.append((float(mean[0]), float(mean[1]), w_each))
        self.stats["walls"] += 1

    def features(self) -> list[BuiltFeature]:
        """The merged map features (clusters with at least ``min_observations``), in
        ``map`` (:attr:`origin` added back)."""
        o = self.origin
        if not o.any():
            return self._features()
        return [replace(f, coords=f.coords + o) for f in self._features()]

    def _features(self) -> list[BuiltFeature]:
        """:meth:`features` in the builder's frame (``map`` less :attr:`origin`)."""
        cfg = self.config
        walls: list[BuiltFeature] = []
        for c in _merge_walls(self.walls, cfg):
            if c.n < cfg.min_observations or not math.isfinite(c.t_min) or \
                    len(c.visits) < cfg.min_visits:
                continue
            line = _robust_line(c)
            if line is None:
                continue
            rho, alpha, t_min, t_max, sd_rho, sd_alpha, t_c = line
            n = np.array([math.cos(alpha), math.sin(alpha)])
            d = np.array([-n[1], n[0]])
            ends = np.array([rho * n + t_min * d, rho * n + t_max * d])
            if t_max - t_min < 1e-3 or (t_max - t_min < cfg.short_wall_m and
                                        c.n < 2 * cfg.min_observations):
                self.stats["dropped_short_wall"] += 1
                continue  # short and rarely seen: corner/edge echoes fitted as a line
            # across-line variance at t: the fit's (sd_rho at the feet's centroid t_c, the
            # direction's sd_alpha about it) plus the drift's (rho, alpha) at the origin:
            # offset(t) = d_rho - t d_alpha
            dr = c.drift.cov()
            fit = (sd_rho, sd_alpha, t_c, d)
            offset_var_rel = _offset_var(*fit, c.drift_rel.cov()) if self.frame_relative \
                else None
            proto = BuiltFeature("wall", ends, math.exp(float(np.median(c.log_kappas))),
                                 sd_rho, c.n, n_visits=len(c.visits),
                                 offset_var=_offset_var(*fit, dr),
                                 sd_alpha_deg=math.degrees(math.sqrt(sd_alpha**2 +
                                                                     float(dr[1, 1]))),
                                 offset_var_rel=offset_var_rel)
            walls.append(_with_ends(proto, ends))
        walls = _join_walls(_drop_shadowed(walls, cfg), cfg.join_m)
        vertices = _wall_vertices(walls, cfg.corner_gate_m)
        points: list[BuiltFeature] = []
        wall_ends = np.array([w.coords for w in walls]).reshape(-1, 2)
        prior_info = 1.0 / cfg.radius_prior_sd_m**2
        for pc in _merge_points(self.points, cfg.point_gate_m, prior_info,
                                   cfg.visit_gap_s):
            if pc.n < cfg.min_observations or len(pc.visits) < cfg.min_visits:
                continue
            sol, _ = pc.solve()
            kappa = math.exp(pc.log_kappa)
            radius = float(sol[2])
            centre = sol[:2]
            if _inside_wall(centre, walls, cfg):
                self.stats["dropped_on_wall"] += 1
                continue  # a wall's echo fitted as a point: nothing stands inside a wall
            vertex = _vertex_kind(centre, pc.mean_view(), vertices, cfg.corner_gate_m)
            if vertex is not None:
                kind = vertex  # where two built walls meet: their corner (or edge)
            elif radius >= cfg.pole_radius_m and pc.log_kappa > _LOG_CORNER_SPLIT:
                kind = "pole"  # a resolved radius says cylinder (unless plane-strength)
            else:
                kind = min(_KIND_KAPPA, key=lambda k: abs(math.log(_KIND_KAPPA[k]) - pc.log_kappa))
                near_end = bool(len(wall_ends)) and float(
                    np.min(np.hypot(*(wall_ends - centre).T))) < cfg.edge_near_wall_m
                if kind == "pole":
                    kind = "point"
                elif kind == "rod" and near_end:
                    kind = "edge"
            if kind in ("corner", "edge"):
                # a vertex reflects at one point, whatever the direction: no radius
                radius = 0.0
                centre, _ = pc.solve_point()
            # the sightings' scatter beyond their stated SDs widens the fit's covariance;
            # the drift they share is kept whole on top
            chi2 = pc.chi2_per_dof(radius > 0.0)
            scale = chi2 if math.isfinite(chi2) and chi2 > 1.0 else 1.0
            own = scale * pc.fit_cov(radius > 0.0)
            sd = math.sqrt(float(np.max(np.linalg.eigvalsh(own + pc.drift.cov()))))
            sd_rel = math.sqrt(float(np.max(np.linalg.eigvalsh(own + pc.drift_rel.cov())))) \
                if self.frame_relative else math.nan
            points.append(BuiltFeature(kind, centre, kappa, sd, pc.n, radius,
                                       n_visits=len(pc.visits), sd_rel_m=sd_rel))
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


def _robust_line(c: _WallCluster
                 ) -> tuple[float, float, float, float, float, float, float] | None:
    """(rho, alpha, t_min, t_max, sd_rho, sd_alpha, t_c) of a wall cluster's line,
    fitted through its member fits' feet (total least squares, outliers beyond 3 robust
    SDs dropped), extent from the inlier feet; None if nothing is left. ``sd_rho`` is the
    line's SD across itself at ``t_c``, where the inlier feet's centroid lies along it
    (t = p · d, d = (-sin alpha, cos alpha)).

    A fit's feet are where the transducer's perpendicular met its line: a yaw error of
    the pose slides them along the wall but hardly moves them across it, so a line
    through the feet of many fits is far less sensitive to pose yaw errors than the
    mean of their (rho, alpha). With feet spread over less than 0.2 m the direction
    comes from the information-weighted mean instead.
    """
    m_info, cov_info = c.mean()
    if not c.feet:
        return None
    f = np.array(c.feet, dtype=float)
    xy, w = f[:, :2], f[:, 2]
    keep = np.ones(len(f), dtype=bool)
    alpha = float(m_info[1])
    sigma = 0.0
    for _ in range(6):
        ww = w[keep]
        mean = (ww @ xy[keep]) / ww.sum()
        r = xy[keep] - mean
        scatter = (r * ww[:, None]).T @ r / ww.sum()
        evals, evecs = np.linalg.eigh(scatter)
        along = float(np.sqrt(max(evals[1], 0.0)))
        if along >= 0.2:
            nrm = evecs[:, 0]
            a = math.atan2(nrm[1], nrm[0])
            # keep the normal on the side of the information mean's
            alpha = a if abs(float(se2.wrap_angle(a - m_info[1]))) <= math.pi / 2 else \
                float(se2.wrap_angle(a + math.pi))
        nrm = np.array([math.cos(alpha), math.sin(alpha)])
        res = (xy - mean) @ nrm
        sigma = max(1.4826 * float(np.median(np.abs(res[keep]))), 0.002)
        new_keep = np.abs(res) <= 3.0 * sigma
        if new_keep.sum() < 2 or np.array_equal(new_keep, keep):
            keep = new_keep if new_keep.sum() >= 2 else keep
            break
        keep = new_keep
    ww = w[keep]
    mean = (ww @ xy[keep]) / ww.sum()
    nrm = np.array([math.cos(alpha), math.sin(alpha)])
    d = np.array([-nrm[1], nrm[0]])
    rho = float(mean @ nrm)
    t = xy[keep] @ d
    n_fits = max(int(keep.sum()) // 3, 1)
    spread = float(np.sqrt(np.mean((t - t.mean()) ** 2)))
    sd_rho = sigma / math.sqrt(n_fits)
    sd_alpha = sigma / (math.sqrt(n_fits) * spread) if spread >= 0.2 else \
        math.sqrt(float(cov_info[1, 1]))
    return rho, alpha, float(t.min()), float(t.max()), sd_rho, sd_alpha, float(mean @ d)


def _wall_vertices(walls: list[BuiltFeature], gate_m: float) -> list[tuple[Array, Array, Array]]:
    """Where two built walls meet: (vertex (2,), unit direction along wall 1 away from
    it, the same along wall 2), for every pair with an end within ``gate_m`` of the
    other's end."""
    out = []
    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            a, b = walls[i].coords, walls[j].coords
            dist = np.hypot(*(a[:, None, :] - b[None, :, :]).transpose(2, 0, 1))
            ia, ib = np.unravel_index(int(np.argmin(dist)), dist.shape)
            if dist[ia, ib] > gate_m:
                continue
            v = 0.5 * (a[ia] + b[ib])
            da = a[1 - ia] - a[ia]
            db = b[1 - ib] - b[ib]
            da = da / max(float(np.hypot(*da)), 1e-12)
            db = db / max(float(np.hypot(*db)), 1e-12)
            if abs(float(da[0] * db[1] - da[1] * db[0])) < math.sin(math.radians(10)):
                continue  # (nearly) straight on: no vertex
            out.append((v, da, db))
    return out


def _vertex_kind(centre: Array, view: Array, vertices: list[tuple[Array, Array, Array]],
                 gate_m: float) -> str | None:
    """``corner`` if ``centre`` is within ``gate_m`` of a wall vertex and was seen from
    inside the angle between its walls (``view``: mean direction towards the
    transducers), ``edge`` if seen from outside it, None when no vertex is near."""
    best, best_d = None, gate_m
    for v, da, db in vertices:
        dist = float(np.hypot(*(centre - v)))
        if dist <= best_d:
            best, best_d = (da, db), dist
    if best is None:
        return None
    da, db = best
    # inside the (< 180 deg) angle spanned by da and db: on the same side of each as
    # the other
    cross = lambda p, q: float(p[0] * q[1] - p[1] * q[0])  # noqa: E731
    inside = cross(da, view) * cross(da, db) > 0 and cross(db, view) * cross(db, da) > 0
    return "corner" if inside else "edge"


def _inside_wall(centre: Array, walls: list[BuiltFeature], cfg: BuildConfig) -> bool:
    """True if ``centre`` lies on a built wall (within ``on_wall_m`` of its line) away
    from its ends (further than ``end_gate_m`` inside: a vertex reflects at the end, and
    the wall's feet run past it. Measured in benchmarks/bench_localize.py's map building
    (room, ring16, localized poses): a corner 7 cm inside its wall's built end, which
    a gate of ``corner_gate_m`` dropped)."""
    for w in walls:
        a, b = w.coords
        d = b - a
        length = float(np.hypot(*d))
        u = d / length
        t = float((centre - a) @ u)
        off = abs(float((centre - a) @ np.array([-u[1], u[0]])))
        if off <= cfg.on_wall_m and cfg.end_gate_m < t < length - cfg.end_gate_m:
            return True
    return False


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
            o.drift = o.drift.merged(c.drift, flip)
            o.drift_rel = o.drift_rel.merged(c.drift_rel, flip)
            o.n += c.n
            o.log_kappas.extend(c.log_kappas)
            o.feet.extend(c.feet)
            o.visits = o.visits.merged(c.visits, cfg.visit_gap_s)
            o.t_min = min(o.t_min, float(t.min()))
            o.t_max = max(o.t_max, float(t.max()))
            break
        else:
            out.append(_WallCluster(c.alpha_ref, c.info.copy(), c.rhs.copy(), c.t_min, c.t_max,
                                    c.n, deque(c.log_kappas, maxlen=255), c.zwz,
                                    deque(c.feet, maxlen=_MAX_FEET),
                                    _Visits([list(v) for v in c.visits.spans]),
                                    c.drift.merged(_Drift()), c.drift_rel.merged(_Drift())))
    return out


def _merge_points(clusters: list[_PointCluster], gate_m: float, prior_info: float,
                  gap_s: float) -> list[_PointCluster]:
    """Merge clusters whose centres ended up within ``gate_m`` (split early in a drive)."""
    out: list[_PointCluster] = []
    for c in sorted(clusters, key=lambda c: -c.n):
        centre = c.solve()[0][:2]
        for o in out:
            if float(np.hypot(*(o.solve()[0][:2] - centre))) <= gate_m:
                o.absorb(c, prior_info, gap_s)
                break
        else:
            merged = _PointCluster(c.normal.copy(), c.rhs.copy(), c.n, deque(c.log_kappas,
                                                                             maxlen=255))
            merged.u_sum = c.u_sum.copy()
            merged.visits = _Visits([list(v) for v in c.visits.spans])
            merged.zwz = c.zwz
            merged.middle = None if c.middle is None else c.middle.copy()
            merged.drift = c.drift.merged(_Drift())
            merged.drift_rel = c.drift_rel.merged(_Drift())
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
    return [_with_ends(w, e) for w, e in zip(walls, ends, strict=True)]


def _with_ends(wall: BuiltFeature, ends: Array) -> BuiltFeature:
    """``wall`` with its ends moved to ``ends`` (2, 2) and its ``sd_m`` the SD across
    its line at the worse of them (a yaw error moves a long wall's far end most)."""
    return BuiltFeature(wall.kind, ends, wall.kappa_us, wall.end_sd(ends), wall.n_obs,
                        wall.radius_m, wall.sd_alpha_deg, wall.n_visits, wall.offset_var,
                        wall.end_sd_rel(ends), wall.offset_var_rel)


# --------------------------------------------------------------------------- from a log


class _Track:
    """base_link pose (and covariance) in ``map`` at any time within the track, by
    interpolation (outside it there is no pose: :meth:`covers`)."""

    def __init__(self, t: Array, poses: Array, cov: Array | None) -> None:
        if len(t) == 0:
            raise ValueError("`poses` has no pose")
        self.t = t
        self.poses = poses
        self.cov = cov

    def covers(self, t_s: float) -> bool:
        return bool(self.t[0] <= t_s <= self.t[-1])

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
    notes: list[str] = field(default_factory=list)
    odom_travel_m: float = 0.0
    """Distance the odometry travelled over the log (its drift grows with it)."""
    odom_turn_deg: float = 0.0
    """Heading change the odometry summed over the log, degrees."""
    odom_resets: int = 0
    """Odom records flagged ``reset`` (the odometry restarted): not taken as motion."""
    odom_jumps: int = 0
    """Odometry increments faster than ``BuildConfig.odom_max_speed_mps`` /
    ``odom_max_yaw_rate_rad_s``: taken as resets."""
    method: str = "odometry"
    """How the readings were placed: ``poses`` (a pose track), ``slam`` (odometry
    corrected by SLAM) or ``odometry`` (dead reckoning; also where SLAM fell back)."""
    slam: SlamResult | None = None
    """What the SLAM did (``ok`` False: why it fell back), None if it did not run."""
    cpu_s: float = 0.0
    """CPU time of the build [s]."""
    timeouts: int = 0
    """Readings at or above ``BuildConfig.max_tof_us``, taken as no echo."""

    def geojson(self) -> dict[str, Any]:
        return self.builder.geojson()

    def summary(self) -> str:
        feats = self.builder.features()
        kinds = Counter(f.kind for f in feats)
        parts = [f"method: {self.method}", f"log: {self.log.summary()}",
                 f"{self.readings} readings",
                 f"{self.landmarks} landmarks fitted",
                 "map: " + (", ".join(f"{v} {k}" for k, v in sorted(kinds.items())) or "empty")]
        for n, what in ((self.odom_resets, "odometry resets"),
                        (self.odom_jumps, "odometry jumps"),
                        (self.timeouts, "timeouts taken as no echo")):
            if n:
                parts.append(f"{n} {what}")
        if self.slam is not None and self.slam.ok:
            parts.append(self.slam.summary())
        return "; ".join(parts + self.skipped_summary() + self.notes)

    def skipped_summary(self) -> list[str]:
        """``["skipped: NAME COUNT, ..."]`` (readings, records, landmarks), or ``[]``."""
        st = {k: v for k, v in self.builder.stats.items() if k.startswith("skipped")}
        st.update(self.skipped)
        return ["skipped: " + ", ".join(f"{k} {v}" for k, v in sorted(st.items()))] if st else []


def _in_gap(times: Sequence[float] | Array, poses: Sequence[Array] | Array, t_s: float,
            gap_s: float) -> bool:
    """Whether ``t_s`` lies inside a gap of the pose track (the Localizer's rule,
    :func:`~sonarloc.localize.localizer.in_odom_gap`)."""
    i = bisect.bisect_right(times, t_s)
    return 0 < i < len(times) and in_odom_gap(t_s, times[i - 1], poses[i - 1], times[i],
                                              poses[i], gap_s)


def _readings(source: str | Path | IO[str], poses: PoseTrack | None, result: BuildResult,
              gap_s: float = math.inf, odom_noise: OdomNoise = DEFAULT_ODOM_NOISE,
              joiner: OdomJoiner | None = None, reset_cov: Array | None = None,
              trace: OdomTrace | None = None
              ) -> Iterator[tuple[float, int, float, Array, Array | None, Array, float] | None]:
    """Yield (t, sensor, tof_us, transducer pose in map, base pose cov, base pose, c),
    and None where the odometry restarted (the segments open then are to be closed).

    Odometry is joined across resets and jumps (``joiner``, default limits:
    :class:`~sonarloc.localize.odomframe.OdomJoiner`), counted in ``result``: the
    increment across one is not taken as motion, and readings placed by odometry between
    the record before it and it are skipped (``tof_across_odom_reset``).

    The base pose's covariance is the pose track's (None if it has none), or without a
    track the dead reckoning's: the ``init`` record's prior (none without one: the map
    frame is the first odometry pose) carried along the odometry, each increment adding
    ``odom_noise`` (:func:`~sonarloc.localize.ekf.predict`), and ``reset_cov`` across a
    reset or jump (the motion across it is unknown), interpolated between odometry
    records.

    A reading without a pose is counted in ``result.skipped``, never given a made-up
    one: outside the pose track (``tof_outside_poses``; pose rows whose time went
    backwards are dropped, ``poses_time_backwards``), before the first odometry or
    after the last (``tof_before_odom``, ``tof_after_last_odom``), inside a gap longer
    than ``gap_s`` of the poses (or odometry) while the robot moved
    (``tof_in_odom_gap``). Odometry is anchored
    at the first ``init`` record, or at the origin without one (``result.notes`` says
    so); an ``init`` after readings were placed is skipped (``init_after_readings``):
    one map frame for all of them.

    ``trace``: if given, every odometry record is appended to it (joined pose, restart),
    and its ``init`` / ``init_cov`` set from the ``init`` record.
    """
    skipped = result.skipped
    anchored = False  # readings placed by odometry: the map frame is fixed
    mounts: dict[int, Array] = {}
    c_mps = 343.0
    init: Array | None = None
    odom_first: Array | None = None
    track = None
    if poses is not None:
        # a row older than one before it is localize's row for an odom record whose time
        # went backwards (the estimate of the later time): no pose of its time
        t = np.asarray(poses.t_s, float)
        keep = t >= np.fmax.accumulate(t)
        if not keep.all():
            skipped["poses_time_backwards"] += int(np.count_nonzero(~keep))
        cov = np.asarray(poses.cov)[keep]
        track = _Track(t[keep], np.stack([poses.x_m, poses.y_m, poses.yaw_rad], axis=-1)[keep],
                       None if np.any(np.isnan(cov)) else cov)
    odo_t: list[float] = []
    odo_p: list[Array] = []
    odo_c: list[Array] = []  # covariance of the pose relative to the first odometry
    odo_reset: list[bool] = []
    rel_mean: list[float] = [0.0, 0.0, 0.0]
    rel_cov: list[list[float]] = [[0.0] * 3 for _ in range(3)]
    init_cov = np.zeros((3, 3))
    pending: list[TofRecord] = []
    joiner = joiner if joiner is not None else OdomJoiner()

    def around(t: float) -> tuple[int, int, float]:
        """The odometry records either side of ``t`` and the fraction of the way from
        the first to the second (the first or the last record alone outside them)."""
        i = bisect.bisect_right(odo_t, t)
        if i <= 0:
            return 0, 0, 0.0
        if i >= len(odo_t):
            return -1, -1, 0.0
        span = odo_t[i] - odo_t[i - 1]
        return i - 1, i, 0.0 if span <= 0 else (t - odo_t[i - 1]) / span

    def odom_at(t: float) -> Array:
        a, b, f = around(t)
        return odo_p[a] if a == b else se2.interpolate(odo_p[a], odo_p[b], f)

    def odom_cov_at(t: float) -> Array:
        a, b, f = around(t)
        return (1 - f) * odo_c[a] + f * odo_c[b]

    def emit(r: TofRecord) -> Iterator[tuple[float, int, float, Array, Array | None, Array,
                                              float]]:
        """The reading placed, or nothing where it lies inside a gap of the poses that
        the robot moved across (counted: a pose interpolated over it is a guess)."""
        nonlocal anchored
        times, track_poses = (track.t, track.poses) if track is not None else (odo_t, odo_p)
        if track is None:
            i = bisect.bisect_right(odo_t, r.t_s)
            if 0 < i < len(odo_t) and odo_reset[i] and r.t_s > odo_t[i - 1]:
                skipped["tof_across_odom_reset"] += 1   # no pose between the two records
                return
        if _in_gap(times, track_poses, r.t_s, gap_s):
            skipped["tof_in_odom_gap"] += 1
            return
        mount = mounts[r.sensor]
        if r.pan_deg is not None:
            mount = mount + np.array([0.0, 0.0, math.radians(r.pan_deg)])
        cov = None
        if track is not None:
            base, cov = track.at(r.t_s)
        else:
            anchored = True
            first = odom_first if odom_first is not None else odo_p[0]
            rel = se2.between(first, odom_at(r.t_s))
            cov = odom_cov_at(r.t_s)
            if init is not None:
                j_init, j_rel = se2.compose_jacobians(init, rel)
                cov = j_init @ init_cov @ j_init.T + j_rel @ cov @ j_rel.T
            base = se2.compose(init, rel) if init is not None else rel
        tof = math.nan if r.tof_us is None else float(r.tof_us)
        yield r.t_s, r.sensor, tof, se2.compose(base, mount), cov, base, c_mps

    for rec in iter_log(source, result.log):
        if isinstance(rec, RigRecord):
            mounts = {m.id: np.array([m.x_m, m.y_m, math.radians(m.yaw_deg)])
                      for m in rec.sensors}
            c_mps = rec.speed_of_sound_mps
        elif isinstance(rec, InitRecord):
            if init is None and anchored:
                skipped["init_after_readings"] += 1
            elif init is None:
                init = np.array([rec.x_m, rec.y_m, math.radians(rec.yaw_deg)])
                init_cov = np.diag([rec.sd_xy_m**2, rec.sd_xy_m**2,
                                    math.radians(rec.sd_yaw_deg) ** 2])
                if trace is not None:
                    trace.init, trace.init_cov = init.copy(), init_cov.copy()
        elif isinstance(rec, OdomRecord):
            raw = (rec.x_m, rec.y_m, math.radians(rec.yaw_deg))
            if odo_t and rec.t_s < odo_t[-1]:
                skipped["odom_time_backwards"] += 1
                continue
            restart = joiner.restart(rec.t_s, raw, rec.reset)
            p = np.array(joiner.join(rec.t_s, raw, restart))
            if odom_first is None:
                odom_first = p
            if restart is not None:
                if restart == "reset":
                    result.odom_resets += 1
                else:
                    result.odom_jumps += 1
                if reset_cov is not None:  # the motion across it is unknown
                    rel_cov = (np.array(rel_cov) + reset_cov).tolist()
                yield None
            if odo_p:
                step = se2.between(odo_p[-1], p)
                result.odom_travel_m += math.hypot(step[0], step[1])
                result.odom_turn_deg += abs(math.degrees(step[2]))
                rel_mean, rel_cov = predict_lists(rel_mean, rel_cov, step.tolist(), odom_noise)
            odo_t.append(rec.t_s)
            odo_p.append(p)
            odo_c.append(np.array(rel_cov))
            odo_reset.append(restart is not None)
            if trace is not None:
                trace.t.append(rec.t_s)
                trace.p.append(p)
                trace.restart.append(restart is not None)
            if len(odo_t) > 4096:  # only recent odometry is needed: keep memory flat
                del odo_t[:2048]
                del odo_p[:2048]
                del odo_c[:2048]
                del odo_reset[:2048]
            ready = [r for r in pending if r.t_s <= rec.t_s]
            pending = [r for r in pending if r.t_s > rec.t_s]
            for r in ready:
                yield from emit(r)
        elif isinstance(rec, TofRecord):
            if rec.sensor not in mounts:
                skipped["tof_unknown_sensor" if mounts else "tof_before_rig"] += 1
                continue
            if track is not None:
                if track.covers(rec.t_s):
                    yield from emit(rec)
                else:  # extrapolating the track would build from made-up poses
                    skipped["tof_outside_poses"] += 1
            elif odom_first is None:
                skipped["tof_before_odom"] += 1
            else:
                pending.append(rec)
    for r in pending:  # those at the last odometry's time came after it in the log
        if r.t_s <= odo_t[-1]:
            yield from emit(r)
        else:
            skipped["tof_after_last_odom"] += 1
    if anchored and init is None:
        result.notes.append("no init record: the map frame is the first odometry pose")
    if anchored and result.odom_travel_m >= DRIFT_NOTE_TRAVEL_M:
        # a map from odometry alone holds the odometry's drift (on a 60 s lap of the
        # room: walls tilted and doubled, and a localizer using it got lost)
        result.notes.append(
            f"poses from odometry alone over {result.odom_travel_m:.1f} m and "
            f"{result.odom_turn_deg:.0f} deg: its drift is in the map (--poses POSES.csv "
            f"from `sonarloc localize LOG --map MAP --out POSES.csv` keeps it out)")


DRIFT_NOTE_TRAVEL_M = 5.0
"""Odometry travel [m] from which a map built without poses says its drift is in it
(a few metres of wheel odometry drift by centimetres and degrees)."""


def build_from_log(source: str | Path | IO[str], poses: PoseTrack | None = None,
                   config: BuildConfig | None = None, method: str | None = None
                   ) -> BuildResult:
    """Build a map from a log (FORMATS.md section 4), streaming.

    Parameters
    ----------
    source : the log.
    poses : base_link poses in ``map`` (a pose CSV, e.g. from ``sonarloc localize``);
        None: the odometry anchored at the log's ``init`` pose (or at the origin),
        corrected by SLAM or not (``method``).
    config : builder settings.
    method : without ``poses``: ``slam`` (poses and landmarks estimated together from
        the odometry and the landmark fits, :mod:`sonarloc.maps.slam`; a log it cannot
        correct falls back to the odometry, ``result.notes`` says why) or ``odometry``
        (dead reckoning alone); default ``config.method``. Not with ``poses``. SLAM
        keeps the accepted fits and the odometry of the whole log in memory (a few
        kilobytes per fit, a hundred bytes per odometry record; the rest streams).

    Returns
    -------
    BuildResult; ``method`` says which ran (``poses``, ``slam`` or ``odometry``),
    ``slam`` what the SLAM did (None if it did not run).
    """
    from sonarloc.fit.landmarks import fit_segments
    from sonarloc.fit.lsq import FitConfig
    from sonarloc.fit.segment import Segmenter, SegmenterConfig
    from sonarloc.physics.tof import ModuleParams

    cfg = config or BuildConfig()
    if method is not None and method not in BUILD_METHODS:
        raise ValueError(f"`method` must be one of {', '.join(BUILD_METHODS)}, got {method!r}")
    if poses is not None and method is not None:
        raise ValueError(f"`method` ({method!r}) is for a build without `poses`: with a pose "
                         "track the readings are placed by it")
    how = "poses" if poses is not None else (method or cfg.method)
    t_cpu = time.process_time()
    result = BuildResult(MapBuilder(cfg), LogStats(), method=how)
    seg: Segmenter | None = None
    fit_cfg: FitConfig | None = None
    ref_cov: dict[float, tuple[Array, Array | None]] = {}
    drift = poses is None  # dead reckoning: an error the sightings share
    joiner = OdomJoiner(cfg.odom_max_speed_mps, cfg.odom_max_yaw_rate_rad_s)
    reset_cov = np.diag([cfg.odom_reset_sd_m**2, cfg.odom_reset_sd_m**2,
                         math.radians(cfg.odom_reset_sd_deg) ** 2])
    trace = OdomTrace() if how == "slam" else None
    observations: list[Observation] | None = [] if how == "slam" else None
    # readings are fitted and clustered relative to the first reading's robot position
    # (MapBuilder.origin): the same map, shifted, whatever the map frame's origin
    shift = np.zeros(3)
    watch = TimeoutWatch()   # a module's timeouts logged as echoes?

    def add(closed: list[Any]) -> None:
        assert fit_cfg is not None
        _add_segments(result, closed, fit_segments(closed, fit_cfg), ref_cov, drift,
                      observations)

    for item in _readings(source, poses, result, cfg.odom_gap_s, cfg.odom_noise, joiner,
                          reset_cov, trace):
        if item is None:  # the odometry restarted: close the segments open across it
            if seg is not None and fit_cfg is not None and poses is None:
                closed = seg.flush()
                if closed:
                    add(closed)
            continue
        t, sensor, tof, pose, cov, base, c_mps = item
        if seg is None or fit_cfg is None:
            fit_cfg = FitConfig(module=ModuleParams(c_mps=cfg.speed_of_sound_mps or c_mps))
            seg = Segmenter(SegmenterConfig(max_readings=cfg.segment_max_readings),
                            fit_cfg.module)
            shift[:2] = base[:2]
            result.builder.origin = shift[:2].copy()
        pose, base = pose - shift, base - shift
        result.readings += 1
        if cfg.max_tof_us is not None and tof >= cfg.max_tof_us:
            tof = math.nan
            result.timeouts += 1
        else:
            watch.push_one(tof)
        if math.isfinite(tof):
            ref_cov[t] = (base, cov)
            if len(ref_cov) > 20000:
                for k in list(ref_cov)[:10000]:
                    del ref_cov[k]
        closed = seg.push(t, float(pose[0]), float(pose[1]), float(pose[2]), tof, sensor)
        if closed:
            add(closed)
    if seg is not None and fit_cfg is not None:
        closed = seg.flush()
        if closed:
            add(closed)
    advice = watch.advice() if cfg.max_tof_us is None else None
    if advice is not None:
        result.notes.append(advice)
    if trace is not None and observations is not None:
        _slam(result, cfg, trace, observations, shift, reset_cov)
    result.cpu_s = time.process_time() - t_cpu
    return result


def _slam(result: BuildResult, cfg: BuildConfig, trace: OdomTrace,
          observations: list[Observation], shift: Array, reset_cov: Array) -> None:
    """Optimize the poses with the landmark fits (:func:`sonarloc.maps.slam.optimize`)
    and rebuild the map from the fits placed with them; or keep the dead reckoning's
    map and say why."""
    scfg = replace(cfg.slam, point_gate_m=cfg.point_gate_m, wall_gate_m=cfg.wall_gate_m,
                   wall_gate_deg=cfg.wall_gate_deg, wall_gap_m=cfg.wall_gap_m,
                   radius_prior_sd_m=cfg.radius_prior_sd_m)
    if not trace.t:
        slam = SlamResult(ok=False, reason="no odometry")
    else:
        first = trace.init if trace.init is not None else np.zeros(3)
        slam = optimize(observations, trace, first - shift, trace.init_cov, cfg.odom_noise,
                        reset_cov, scfg, cfg.visit_gap_s)
    result.slam = slam
    if not slam.ok:
        result.method = "odometry"
        result.notes.append(f"SLAM fell back to the odometry: {slam.reason}")
        return
    builder = MapBuilder(cfg, result.builder.origin)
    for k, o in enumerate(observations):
        i = int(slam.obs_node[k])
        pose = slam.node_pose[i]
        lm = o.landmark
        z, c2 = transform_with_cov(o.kind, pose, o.z, o.cov)
        params = np.array([z[0], z[1], lm.params[2]])
        cov3 = np.array(lm.cov, dtype=float, copy=True)
        cov3[:2, :2] = c2
        cov3[:2, 2] = cov3[2, :2] = 0.0  # (kappa's correlation is not used by the builder)
        placed = replace(lm, params=params, cov=cov3)
        feet = se2.transform_points(pose, o.feet) if o.kind == "line" else None
        builder.add(placed, se2.transform_points(pose, o.view), pose, None, feet,
                    drift_cov=slam.node_cov[i], drift_rel_cov=slam.node_cov_rel[i])
    result.builder = builder
    result.notes = [n for n in result.notes if not n.startswith("poses from odometry alone")]


def _add_segments(result: BuildResult, segments: list[Any], landmarks: list[Landmark],
                  ref_cov: dict[float, tuple[Array, Array | None]], drift: bool,
                  observations: list[Observation] | None = None) -> None:
    """Add the fitted landmarks; the poses' covariance in ``ref_cov`` is the dead
    reckoning's drift if ``drift`` (shared by the sightings), else each pose's own.
    The landmarks added are appended to ``observations`` (if given) as seen from their
    base pose (for the SLAM)."""
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
        if drift:
            what = result.builder.add(lm, view, base, None, feet, drift_cov=cov)
        else:
            what = result.builder.add(lm, view, base, cov, feet)
        if observations is not None and base is not None and what in ("point", "wall"):
            observations.append(_observation(lm, view, base, feet))


def _observation(lm: Landmark, view: Array, base: Array, feet: Array | None) -> Observation:
    """A landmark fit in ``map`` as seen from the base pose ``base`` (its fit's own
    covariance carried into base_link)."""
    kind = "point" if lm.kind == "point" else "line"
    z, c2 = transform_with_cov(kind, se2.inverse(base), np.asarray(lm.params[:2], dtype=float),
                               np.asarray(lm.cov, dtype=float)[:2, :2])
    f = np.zeros((0, 2)) if feet is None else se2.inverse_transform_points(base, feet)
    return Observation(kind, lm.ref_t_s,
                       np.asarray(base, dtype=float).copy(), z, c2,
                       se2.inverse_transform_points(base, view), f, lm)
