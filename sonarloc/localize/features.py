"""The map as the filter sees it: arrays of point features and wall segments.

Built from a :class:`sonarloc.maps.geojson.Map` (its reflectors: walls/planes as
segments; poles, rods, points, corners and edges as points) or directly from arrays.
All coordinates are metres/radians in ``map``. Queries are vectorised over features.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2
from sonarloc.localize.ekf import Feature
from sonarloc.physics import constants

if TYPE_CHECKING:  # pragma: no cover
    from sonarloc.maps.geojson import Map

Array = NDArray[np.float64]

POINT_KINDS = ("pole", "rod", "point", "corner", "edge")
WALL_KINDS = ("wall", "plane")

#: Edges (convex vertices) echo only close by; beyond this they are not candidates.
EDGE_RANGE_M = 2.0 * constants.EDGE_MAX_RANGE_M


@dataclass(frozen=True)
class FeatureMap:
    """Point features and wall segments of a map.

    Attributes
    ----------
    point_xy : (P, 2) centres [m]; point_radius_m : (P,); point_kappa_us : (P,) (NaN =
        unknown); point_kind : P kind names; point_cone_rad : (P, 2) directions of the two
        walls meeting at a corner/edge vertex (NaN: seen from everywhere);
        point_id : P labels.
    wall_ends : (W, 2, 2) segment end points [m]; wall_line : (W, 2) (rho, alpha) of the
        infinite line (rho >= 0 from the map origin); wall_kappa_us : (W,); wall_kind,
        wall_id : W labels.
    point_sd_m, wall_sd_m : (P,), (W,) SD of each feature's position [m] as the map file
        gives it (NaN: not given): its ``sd_rel_m`` property (the SD relative to the map
        frame) where given, else its ``sd_m`` (``map build`` writes both; docs/MAPS.md):
        the map error :class:`~sonarloc.localize.localizer.Localizer` adds to the
        readings of one update (``LocalizerConfig.map_sd_m``). The Localizer estimates
        the pose in the map's frame, so an error of that frame, which all the features
        share, is not an error of a feature there.
    """

    point_xy: Array
    point_radius_m: Array
    point_kappa_us: Array
    point_kind: tuple[str, ...]
    point_cone_rad: Array
    point_id: tuple[str, ...]
    wall_ends: Array
    wall_line: Array
    wall_kappa_us: Array
    wall_kind: tuple[str, ...]
    wall_id: tuple[str, ...]
    point_sd_m: Array = field(default_factory=lambda: np.zeros(0))
    wall_sd_m: Array = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        # not given (or not one per feature): unknown
        for name, n in (("point_sd_m", len(self.point_xy)), ("wall_sd_m", len(self.wall_ends))):
            if np.shape(getattr(self, name)) != (n,):
                object.__setattr__(self, name, np.full(n, np.nan))

    @classmethod
    def build(cls, points: ArrayLike = (), walls: ArrayLike = (),
              *, point_radius_m: ArrayLike | None = None, point_kappa_us: ArrayLike | None = None,
              point_kind: tuple[str, ...] | None = None, point_cone_rad: ArrayLike | None = None,
              point_id: tuple[str, ...] | None = None, wall_kappa_us: ArrayLike | None = None,
              wall_kind: tuple[str, ...] | None = None, wall_id: tuple[str, ...] | None = None,
              point_sd_m: ArrayLike | None = None, wall_sd_m: ArrayLike | None = None
              ) -> FeatureMap:
        """A map from point centres (P, 2) and wall segments (W, 2, 2); defaults: kind
        ``point`` / ``wall``, radius 0, kappa from the kind's default, ids ``p<i>`` / ``w<i>``,
        position SDs unknown (NaN).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        ends = np.asarray(walls, dtype=float).reshape(-1, 2, 2)
        n_p, n_w = len(pts), len(ends)
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(ends))):
            raise ValueError("`points` and `walls` must be finite")
        seg = np.hypot(*(ends[:, 1] - ends[:, 0]).T)
        if np.any(seg < 1e-9):
            raise ValueError(f"`walls` has a zero-length segment at index {int(np.argmin(seg))}")
        pk = point_kind or ("point",) * n_p
        wk = wall_kind or ("wall",) * n_w
        if len(pk) != n_p or len(wk) != n_w:
            raise ValueError("`point_kind` / `wall_kind` must have one entry per feature")
        for k in pk:
            if k not in POINT_KINDS:
                raise ValueError(f"`point_kind` must be one of {POINT_KINDS}, got {k!r}")
        for k in wk:
            if k not in WALL_KINDS:
                raise ValueError(f"`wall_kind` must be one of {WALL_KINDS}, got {k!r}")

        def arr(v: ArrayLike | None, default: Array, n: int, name: str) -> Array:
            a = default if v is None else np.asarray(v, dtype=float)
            if a.shape != (n,):
                raise ValueError(f"`{name}` must have shape ({n},), got {a.shape}")
            return a

        radius = arr(point_radius_m, np.zeros(n_p), n_p, "point_radius_m")
        if np.any(radius < 0):
            raise ValueError("`point_radius_m` must be non-negative")
        pkap = arr(point_kappa_us, np.array([constants.KAPPA_US[k] for k in pk]), n_p,
                   "point_kappa_us")
        wkap = arr(wall_kappa_us, np.array([constants.KAPPA_US[k] for k in wk]), n_w,
                   "wall_kappa_us")
        cone = np.full((n_p, 2), np.nan) if point_cone_rad is None else \
            np.asarray(point_cone_rad, dtype=float).reshape(n_p, 2)
        psd = arr(point_sd_m, np.full(n_p, np.nan), n_p, "point_sd_m")
        wsd = arr(wall_sd_m, np.full(n_w, np.nan), n_w, "wall_sd_m")
        if np.any(psd < 0) or np.any(wsd < 0):
            raise ValueError("`point_sd_m` and `wall_sd_m` must be non-negative (NaN: unknown)")
        return cls(pts, radius, pkap, tuple(pk), cone,
                   tuple(point_id or (f"p{i}" for i in range(n_p))), ends, _lines(ends), wkap,
                   tuple(wk), tuple(wall_id or (f"w{i}" for i in range(n_w))), psd, wsd)

    @classmethod
    def from_map(cls, world_map: Map) -> FeatureMap:
        """Features from a loaded GeoJSON map's reflectors (segments and points)."""
        pts, radius, pkap, pkind, cones, pid, psd = [], [], [], [], [], [], []
        ends, wkap, wkind, wid, wsd = [], [], [], [], []
        for i, ref in enumerate(world_map.reflectors):
            sd = _sd_m(world_map, ref.feature)
            label = str(ref.id if ref.id is not None else f"f{ref.feature}")
            if ref.kind in WALL_KINDS or ref.kind in ("corner", "edge"):
                label += f":{ref.part}"  # segment / vertex index within the feature
            if ref.kind in WALL_KINDS:
                coords = np.asarray(ref.geometry.coords, dtype=float)[:2, :2]
                ends.append(coords)
                wkap.append(ref.kappa_us)
                wkind.append(ref.kind)
                wid.append(label)
                wsd.append(sd)
            elif ref.kind in POINT_KINDS:
                pts.append((ref.geometry.x, ref.geometry.y))
                radius.append(ref.radius_m)
                pkap.append(ref.kappa_us)
                pkind.append(ref.kind)
                psd.append(sd)
                cones.append(ref.cone_rad if ref.cone_rad is not None else (math.nan, math.nan))
                pid.append(label)
            else:  # pragma: no cover - the map validates kinds
                raise ValueError(f"reflector {i}: unknown kind {ref.kind!r}")
        return cls.build(np.array(pts).reshape(-1, 2), np.array(ends).reshape(-1, 2, 2),
                         point_radius_m=np.array(radius), point_kappa_us=np.array(pkap),
                         point_kind=tuple(pkind), point_cone_rad=np.array(cones).reshape(-1, 2),
                         point_id=tuple(pid), wall_kappa_us=np.array(wkap),
                         wall_kind=tuple(wkind), wall_id=tuple(wid), point_sd_m=np.array(psd),
                         wall_sd_m=np.array(wsd))

    def sd_m(self, kind: str | None, index: int) -> float:
        """Position SD [m] of feature ``index`` of ``kind`` (``point`` / ``wall``) as the
        map gives it (NaN: not given)."""
        return float(self.point_sd_m[index] if kind == "point" else self.wall_sd_m[index])

    @property
    def n_points(self) -> int:
        return len(self.point_xy)

    @property
    def n_walls(self) -> int:
        return len(self.wall_ends)

    def point(self, i: int) -> Feature:
        """Point feature ``i`` for :func:`sonarloc.localize.ekf.update`."""
        return Feature("point", self.point_xy[i], float(self.point_radius_m[i]))

    def wall(self, i: int) -> Feature:
        """Wall ``i`` (its infinite line) for :func:`sonarloc.localize.ekf.update`."""
        return Feature("wall", self.wall_line[i])

    def points_visible_from(self, xy: ArrayLike, max_range_m: float = math.inf
                            ) -> NDArray[np.bool_]:
        """(..., P) which point features can echo towards positions ``xy`` (..., 2) in
        ``map``.

        Corners are seen only from inside the angle between their walls, edges from
        outside it and within :data:`EDGE_RANGE_M`; all within ``max_range_m``.
        """
        p = np.asarray(xy, dtype=float)[..., None, :]
        d = p - self.point_xy
        dist = np.hypot(d[..., 0], d[..., 1])
        ok = dist <= max_range_m + self.point_radius_m
        has_cone = ~np.isnan(self.point_cone_rad[:, 0])
        if np.any(has_cone):
            phi = np.arctan2(d[..., 1], d[..., 0])
            a1, a2 = self.point_cone_rad[:, 0], self.point_cone_rad[:, 1]
            # inside the (< 180 deg) angle between the two wall directions
            half = 0.5 * se2.wrap_angle(a2 - a1)
            mid = a1 + half
            inside = np.abs(se2.wrap_angle(phi - mid)) < np.abs(half)
            kinds = np.array(self.point_kind, dtype=object)
            corner = (kinds == "corner") & has_cone
            edge = (kinds == "edge") & has_cone
            ok &= ~(corner & ~inside) & ~(edge & inside)
        edges = np.array([k == "edge" for k in self.point_kind], dtype=bool)
        ok &= ~edges | (dist <= EDGE_RANGE_M)
        return np.asarray(ok)

    def walls_facing(self, xy: ArrayLike, margin_m: float = 0.2,
                     max_range_m: float = math.inf) -> NDArray[np.bool_]:
        """(..., W) walls whose foot of the perpendicular from ``xy`` (..., 2) lies on the
        segment (extended by ``margin_m`` at both ends) within ``max_range_m``: where a
        specular echo can come from.
        """
        p = np.asarray(xy, dtype=float)[..., None, :]
        a, b = self.wall_ends[:, 0], self.wall_ends[:, 1]
        ab = b - a
        length = np.hypot(ab[:, 0], ab[:, 1])
        t = np.sum((p - a) * ab, axis=-1) / length
        dist = np.abs(ab[:, 0] * (p[..., 1] - a[:, 1]) - ab[:, 1] * (p[..., 0] - a[:, 0])) \
            / length
        return np.asarray((t >= -margin_m) & (t <= length + margin_m) & (dist <= max_range_m))


    def walls_hit_by_ray(self, xy: ArrayLike, yaw_rad: float, margin_m: float = 0.2,
                         max_range_m: float = math.inf) -> NDArray[np.bool_]:
        """(W,) walls that a ray from ``xy`` along ``yaw_rad`` meets (segments extended by
        ``margin_m`` at both ends) within ``max_range_m``."""
        p = np.asarray(xy, dtype=float)
        d = np.array([math.cos(yaw_rad), math.sin(yaw_rad)])
        a, b = self.wall_ends[:, 0], self.wall_ends[:, 1]
        ab = b - a
        length = np.hypot(ab[:, 0], ab[:, 1])
        u = ab / length[:, None]
        a_ext = a - margin_m * u
        ab_ext = ab + 2 * margin_m * u
        den = d[0] * ab_ext[:, 1] - d[1] * ab_ext[:, 0]
        ok = np.abs(den) > 1e-12
        den_s = np.where(ok, den, 1.0)
        ap = a_ext - p
        t = (ap[:, 0] * ab_ext[:, 1] - ap[:, 1] * ab_ext[:, 0]) / den_s  # along the ray
        s = (ap[:, 0] * d[1] - ap[:, 1] * d[0]) / den_s  # along the segment, 0..1
        return np.asarray(ok & (t > 0) & (t <= max_range_m) & (s >= 0) & (s <= 1))


def _lines(ends: Array) -> Array:
    """(rho >= 0, alpha) of the infinite lines through segments (W, 2, 2)."""
    if len(ends) == 0:
        return np.zeros((0, 2))
    d = ends[:, 1] - ends[:, 0]
    alpha = np.arctan2(d[:, 0], -d[:, 1])  # normal = direction rotated by -90 deg
    rho = ends[:, 0, 0] * np.cos(alpha) + ends[:, 0, 1] * np.sin(alpha)
    alpha = np.where(rho < 0, alpha + math.pi, alpha)
    return np.stack([np.abs(rho), se2.wrap_angle(alpha)], axis=-1)


def _sd_m(world_map: Map, feature: int) -> float:
    """The position SD of source feature ``feature`` in the map's frame: its
    ``sd_rel_m`` property, else its ``sd_m`` (NaN when neither is a non-negative finite
    number)."""
    if not 0 <= feature < len(world_map.features):
        return math.nan
    props = world_map.features[feature].properties
    for name in ("sd_rel_m", "sd_m"):
        v = props.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        v = float(v)
        if math.isfinite(v) and v >= 0:
            return v
    return math.nan
