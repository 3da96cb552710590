"""Map GeoJSON (FORMATS.md section 3): load, validate, save, and a spatial index.

A map is a GeoJSON FeatureCollection whose coordinates are metres in the ``map``
frame. Each feature becomes one or more elementary *reflectors*:

* Point ``pole`` / ``rod`` / ``point`` -> a cylinder of ``radius_m`` (0 = a point
  scatterer);
* Point ``corner`` / ``edge`` -> a vertex reflector (corner: plane strength; edge:
  weak, seen only within about 0.5 m);
* LineString ``wall`` / ``plane`` -> one specular plane per segment;
* Polygon ``wall`` -> every ring is a closed wall, one plane per segment.

Vertices where two wall segments meet become vertex reflectors (property
``vertices``, default ``"auto"``): seen from inside the angle between the two walls
(the concave side) the vertex is a ``corner``, seen from outside it is an ``edge``.
The free ends of an open wall are edges. ``"corner"`` / ``"edge"`` keep only that
half, ``"none"`` none. An explicit Point ``corner``/``edge`` feature within 1 cm of a
wall vertex replaces the derived reflector of its kind there (and keeps its viewing
side).
Nearly straight vertices (turn below 10 deg) reflect nothing.

Extension: a LineString with ``kind: "route"`` is a route for drives; the first one is
the map's default route (``Map.route``). Routes do not reflect.

Bad maps raise :class:`~sonarloc.errors.MapError` naming the feature index.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.geometry import LineString, Point, Polygon, mapping, shape
from shapely.geometry.base import BaseGeometry

from sonarloc.errors import MapError
from sonarloc.physics import reflectors as physics_reflectors

POINT_KINDS = ("pole", "rod", "corner", "edge", "point")
LINE_KINDS = ("wall", "plane", "route")
POLYGON_KINDS = ("wall",)
CYLINDER_KINDS = ("pole", "rod", "point")
VERTEX_KINDS = ("corner", "edge")
VERTEX_MODES = ("auto", "corner", "edge", "none")

STRAIGHT_TURN_DEG = 10.0
"""Wall vertices turning less than this are treated as straight (no vertex reflector)."""

MIN_RADIUS_M = 1e-6
"""Smallest non-zero cylinder radius accepted (thinner is no sonar reflector; use 0)."""

SNAP_M = 0.01
"""An explicit corner/edge Point this close to a wall vertex replaces the derived one."""

MAX_COORD_M = 1e8
"""Largest coordinate or radius accepted [m]: far beyond any map in metres (projected
coordinates such as UTM stay below 1e7 m); larger values overflow the geometry."""

MAX_KAPPA_US = 1e6
"""Largest reflecting strength accepted [us]: a reflector whose on-axis delay is this
many times the module's detection limit (12 us) never echoes; larger values (1e308)
overflowed the simulator's delays."""

LONLAT_CRS = re.compile(r"(CRS(84|83|27)|EPSG(:+|/0/)(4326|4269|4258|4979))$", re.IGNORECASE)
"""Names of longitude/latitude coordinate systems in an (old-style GeoJSON) ``crs``
member, e.g. ``urn:ogc:def:crs:OGC:1.3:CRS84``, ``EPSG:4326``: a map in degrees is
refused (map coordinates are metres)."""


def default_kappa_us(kind: str, radius_m: float = 0.0) -> float:
    """Default reflecting strength tau/A0 [us] at 1.5 m of a reflector kind and radius.

    :func:`sonarloc.physics.reflectors.default_kappa_us`: planes, walls, corners 0.15;
    edges 2.68; cylinders with a radius by the physics radius rule (the paper's 0.67 us
    for the 8.9 cm pole, 2.68 us for the 8 mm rod), without one 0.67 (pole, point) or
    2.68 (rod).
    """
    return float(physics_reflectors.default_kappa_us(kind, radius_m))


@dataclass(frozen=True)
class MapFeature:
    """One feature of a map as written in the file: geometry plus its properties.

    ``properties`` always holds ``kind``; other keys are kept verbatim so that a map
    round-trips through :func:`save_map` / :func:`load_map`.
    """

    geometry: BaseGeometry
    properties: Mapping[str, Any]

    @property
    def kind(self) -> str:
        return str(self.properties["kind"])


@dataclass(frozen=True)
class Reflector:
    """One elementary reflector of a map.

    Attributes
    ----------
    kind : ``wall``/``plane`` (a segment), ``pole``/``rod``/``point`` (a cylinder of
        ``radius_m``, 0 = point), ``corner``/``edge`` (a vertex).
    geometry : 2-point LineString for segments, Point (centre or vertex) otherwise.
    kappa_us : reflecting strength tau/A0 at the reference range 1.5 m (smaller =
        stronger); a cylinder's grows with range (physics ``kappa_at_range_us``).
    radius_m : cylinder radius (0 for other kinds).
    id : the feature's ``id`` property (None if absent).
    feature : index of the source feature in the FeatureCollection.
    part : segment index within the feature (vertex index for derived vertices).
    cone_rad : for vertex reflectors at a wall vertex, the directions of the two walls
        leaving the vertex; a corner is seen only from inside the (< 180 deg) angle
        between them, an edge only from outside. None: seen from everywhere.
    """

    kind: str
    geometry: BaseGeometry
    kappa_us: float
    radius_m: float = 0.0
    id: str | int | None = None
    feature: int = -1
    part: int = 0
    cone_rad: tuple[float, float] | None = None


@dataclass(frozen=True, eq=False)
class Map:
    """A validated map: its source features, reflectors, routes and a spatial index.

    Build one with :func:`load_map`, :func:`map_from_geojson` or :func:`build_map`.
    Immutable; equality and hash are by identity (usable as a cache key).
    """

    features: tuple[MapFeature, ...]
    reflectors: tuple[Reflector, ...]
    routes: tuple[LineString, ...] = ()
    _tree_geoms: tuple[BaseGeometry, ...] = field(default=(), repr=False, compare=False)

    @property
    def route(self) -> LineString | None:
        """The default route for drives (the first ``route`` feature), or None."""
        return self.routes[0] if self.routes else None

    @cached_property
    def tree(self) -> shapely.STRtree:
        """STRtree over the reflectors' shapes (segments, discs, vertices), by reflector index."""
        return shapely.STRtree(list(self._tree_geoms))

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(minx, miny, maxx, maxy) of all reflectors [m]."""
        if not self._tree_geoms:
            return (0.0, 0.0, 0.0, 0.0)
        b = shapely.total_bounds(np.asarray(self._tree_geoms, dtype=object))
        return (float(b[0]), float(b[1]), float(b[2]), float(b[3]))

    def __len__(self) -> int:
        return len(self.reflectors)

    def query_bounds(self, bounds: ArrayLike) -> NDArray[np.int64]:
        """Reflectors whose shape meets axis-aligned boxes (the coarse, fast query).

        Parameters
        ----------
        bounds : (K, 4) boxes ``minx, miny, maxx, maxy`` [m].

        Returns
        -------
        (2, n) int array of (box index, reflector index) pairs, sorted by box then
        reflector.
        """
        b = np.atleast_2d(np.asarray(bounds, dtype=float))
        if b.shape[-1] != 4:
            raise ValueError(f"`bounds` must have shape (K, 4), got {b.shape}")
        if not self.reflectors or b.shape[0] == 0:
            return np.zeros((2, 0), dtype=np.int64)
        boxes = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
        pairs = np.asarray(self.tree.query(boxes, predicate="intersects"), dtype=np.int64)
        order = np.lexsort((pairs[1], pairs[0]))
        return pairs[:, order]

    def query_sector(self, x_m: float, y_m: float, yaw_rad: float, max_range_m: float,
                     half_angle_rad: float) -> NDArray[np.int64]:
        """Reflectors that have some part inside a transducer's beam sector.

        The sector is centred on the transducer at (``x_m``, ``y_m``) with axis
        ``yaw_rad``, radius ``max_range_m`` and half-angle ``half_angle_rad``. Cost grows
        with what is near the beam, not with the map. This is a geometric query: which
        of these actually echo (normal incidence inside a segment, occlusion, corner
        side) is decided by :class:`sonarloc.world.scene.Scene`.

        Returns
        -------
        Sorted reflector indices (into ``self.reflectors``).
        """
        if not (math.isfinite(max_range_m) and max_range_m > 0):
            raise ValueError(f"`max_range_m` must be positive, got {max_range_m!r}")
        if not (math.isfinite(half_angle_rad) and half_angle_rad > 0):
            raise ValueError(f"`half_angle_rad` must be positive, got {half_angle_rad!r}")
        if not self.reflectors:
            return np.zeros(0, dtype=np.int64)
        sector = sector_polygon(x_m, y_m, yaw_rad, max_range_m, half_angle_rad)
        return np.sort(np.asarray(self.tree.query(sector, predicate="intersects"),
                                  dtype=np.int64))


def sector_polygon(x_m: float, y_m: float, yaw_rad: float, radius_m: float,
                   half_angle_rad: float, n_arc: int = 32) -> Polygon:
    """Polygon of a beam sector (a disc when the half-angle reaches pi).

    The arc is approximated from outside, so the polygon contains the true sector.
    """
    h = min(half_angle_rad, math.pi)
    n = max(2, int(math.ceil(n_arc * h / math.pi)))
    step = 2 * h / n
    r_out = radius_m / math.cos(step / 2)  # chords outside the arc
    ang = yaw_rad + np.linspace(-h, h, n + 1)
    mid = yaw_rad - h + step * (np.arange(n) + 0.5)
    xs = np.empty(2 * n + 1)
    ys = np.empty(2 * n + 1)
    xs[0::2] = x_m + radius_m * np.cos(ang)
    ys[0::2] = y_m + radius_m * np.sin(ang)
    xs[1::2] = x_m + r_out * np.cos(mid)
    ys[1::2] = y_m + r_out * np.sin(mid)
    if h >= math.pi:
        return Polygon(np.column_stack([xs, ys]))
    return Polygon(np.column_stack([np.r_[x_m, xs], np.r_[y_m, ys]]))


# --------------------------------------------------------------------------- parsing


def _fail(index: int, problem: str) -> MapError:
    return MapError(f"feature {index}: {problem}")


def _finite_number(value: Any) -> bool:
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and math.isfinite(value))


def _positions_xy(index: int, coords: Any, depth: int) -> Any:
    """Nested GeoJSON positions checked and cut to [x, y] (a z is dropped; positions
    with and without one may mix): depth 0 = one position."""
    if depth == 0:
        if not isinstance(coords, list) or len(coords) not in (2, 3):
            raise _fail(index, f"a position must be [x, y], got {coords!r:.60}")
        if not all(_finite_number(v) for v in coords):
            raise _fail(index, f"coordinates must be finite numbers, got {coords!r:.60}")
        if abs(coords[0]) > MAX_COORD_M or abs(coords[1]) > MAX_COORD_M:
            raise _fail(index, f"coordinates must be metres within ±{MAX_COORD_M:g}, "
                               f"got {coords!r:.60}")
        return coords[:2]
    if not isinstance(coords, list):
        raise _fail(index, f"`coordinates` must be a list, got {coords!r:.60}")
    return [_positions_xy(index, c, depth - 1) for c in coords]


def _parse_feature(index: int, obj: Any) -> MapFeature:
    if not isinstance(obj, dict) or obj.get("type") != "Feature":
        got = obj.get("type") if isinstance(obj, dict) else type(obj).__name__
        raise _fail(index, f"must be a GeoJSON Feature, got {got!r}")
    props = obj.get("properties")
    if props is None:
        props = {}
    if not isinstance(props, dict):
        raise _fail(index, "`properties` must be an object")
    geom = obj.get("geometry")
    if not isinstance(geom, dict):
        raise _fail(index, "has no geometry")
    gtype = geom.get("type")
    depth = {"Point": 0, "LineString": 1, "Polygon": 2}.get(str(gtype))
    if depth is None:
        raise _fail(index, f"geometry type {gtype!r} is not supported "
                           "(Point, LineString or Polygon)")
    coords = _positions_xy(index, geom.get("coordinates"), depth)
    if gtype == "LineString" and len(coords) < 2:
        raise _fail(index, f"bad LineString: needs at least 2 positions, got {len(coords)}")
    if gtype == "Polygon":
        # (a ring that does not repeat its start is closed, as a Polygon's rings are by
        # definition: FORMATS section 3 "its rings are walls", and earlier releases read
        # such files; RFC 7946 asks for the repeat, which writers usually give)
        for k, ring in enumerate(coords):
            if len(ring) < 3:
                raise _fail(index, f"Polygon ring {k} needs at least 3 positions, got {len(ring)}")
    try:
        geometry = shape({"type": gtype, "coordinates": coords})
    except Exception as err:  # shapely raises several types on bad coordinates
        raise _fail(index, f"bad {gtype} coordinates: {err}") from err
    return MapFeature(geometry, dict(props))


def _validate(index: int, feat: MapFeature) -> None:
    props = feat.properties
    if "kind" not in props:
        raise _fail(index, "missing property `kind`")
    kind = props["kind"]
    gtype = feat.geometry.geom_type
    allowed = {"Point": POINT_KINDS, "LineString": LINE_KINDS, "Polygon": POLYGON_KINDS}[gtype]
    if kind not in allowed:
        raise _fail(index, f"unknown kind {kind!r} for a {gtype} "
                           f"(expected one of {', '.join(allowed)})")
    if "kappa_us" in props and props["kappa_us"] is not None:
        k = props["kappa_us"]
        if not _finite_number(k) or k <= 0:
            raise _fail(index, f"`kappa_us` must be a positive number, got {k!r}")
        if k > MAX_KAPPA_US:
            raise _fail(index, f"`kappa_us` must be at most {MAX_KAPPA_US:g} us, got {k!r}")
    # the Localizer adds sd_rel_m (else sd_m) to the readings' variance
    for name in ("sd_m", "sd_rel_m"):
        if props.get(name) is not None:
            sd = props[name]
            if not _finite_number(sd) or not 0 <= sd <= MAX_COORD_M:
                raise _fail(index, f"`{name}` must be a non-negative number of metres, "
                                   f"got {sd!r}")
    if "id" in props and props["id"] is not None \
            and (isinstance(props["id"], bool) or not isinstance(props["id"], (str, int))):
        raise _fail(index, f"`id` must be a string or integer, got {props['id']!r}")
    if gtype == "Point":
        r = props.get("radius_m", 0.0)
        if r is None:
            r = 0.0
        if not _finite_number(r) or r < 0:
            raise _fail(index, f"`radius_m` must be a non-negative number, got {r!r}")
        if r > MAX_COORD_M:
            raise _fail(index, f"`radius_m` must be at most {MAX_COORD_M:g} m, got {r!r}")
        if 0 < r < MIN_RADIUS_M:
            raise _fail(index, f"`radius_m` must be 0 or at least {MIN_RADIUS_M:g} m, got {r!r}")
        if kind in VERTEX_KINDS and r != 0:
            raise _fail(index, f"a {kind} has no radius, got radius_m={r!r}")
        return
    if kind != "route" and "vertices" in props and props["vertices"] not in VERTEX_MODES:
        raise _fail(index, f"`vertices` must be one of {', '.join(VERTEX_MODES)}, "
                           f"got {props['vertices']!r}")
    if gtype == "LineString":
        _check_segments(index, feat.geometry, "the LineString")
        if not feat.geometry.is_simple:
            raise _fail(index, f"{kind} LineString intersects itself")
        return
    poly = feat.geometry
    if poly.is_empty or not poly.is_valid:
        reason = shapely.is_valid_reason(poly) if not poly.is_empty else "empty"
        raise _fail(index, f"invalid Polygon ({reason})")
    for k, ring in enumerate([poly.exterior, *poly.interiors]):
        _check_segments(index, ring, f"Polygon ring {k}")


def _check_segments(index: int, chain: BaseGeometry, what: str) -> None:
    """Refuse a zero-length segment (a repeated position): a wall of no direction. (A
    LineString has at least 2 positions here, a ring at least 4.)"""
    short = np.hypot(*np.diff(np.asarray(chain.coords), axis=0).T) < 1e-9
    if short.any():
        raise _fail(index, f"zero-length segment at vertex {int(np.argmax(short))} of {what}")


def _ring_coords(geom: BaseGeometry) -> list[NDArray[np.float64]]:
    """Vertex chains of a wall: one per ring (closed, last == first) or the line."""
    if geom.geom_type == "Polygon":
        rings = [geom.exterior, *geom.interiors]
        return [np.asarray(r.coords, dtype=float) for r in rings]
    return [np.asarray(geom.coords, dtype=float)]


def _props_kappa(props: Mapping[str, Any], kind: str, radius_m: float = 0.0) -> float:
    k = props.get("kappa_us")
    return float(k) if k is not None else default_kappa_us(kind, radius_m)


def build_map(features: Sequence[MapFeature]) -> Map:
    """Validate features and derive the map's reflectors and routes.

    Raises
    ------
    MapError
        naming the feature index and the problem.
    """
    # ids as the labels they become (FeatureMap, fit association): 1 and "1" are one
    # label, and a feature without id is labelled f<index>
    ids: dict[str, tuple[int, Any]] = {}
    for i, feat in enumerate(features):
        _validate(i, feat)
        fid = feat.properties.get("id")
        if fid is not None:
            if str(fid) in ids:
                j, other = ids[str(fid)]
                same = "" if other == fid else f" as {other!r}: the same label"
                raise _fail(i, f"duplicate id {fid!r} (also feature {j}{same})")
            ids[str(fid)] = (i, fid)
    for i, feat in enumerate(features):
        if feat.properties.get("id") is None and f"f{i}" in ids:
            j, fid = ids[f"f{i}"]
            raise _fail(j, f"id {fid!r} is the label of feature {i}, which has no id")

    reflectors: list[Reflector] = []
    tree_geoms: list[BaseGeometry] = []
    routes: list[LineString] = []
    derived: list[tuple[float, float, str, float, Reflector]] = []
    explicit_vertex: list[int] = []  # positions in `reflectors` of explicit corner/edge

    for i, feat in enumerate(features):
        props, kind, geom = feat.properties, feat.kind, feat.geometry
        fid = props.get("id")
        if kind == "route":
            routes.append(geom)
            continue
        if geom.geom_type == "Point":
            r = float(props.get("radius_m") or 0.0)
            ref = Reflector(kind, geom, _props_kappa(props, kind, r), r, fid, i)
            if kind in VERTEX_KINDS:
                explicit_vertex.append(len(reflectors))
            reflectors.append(ref)
            tree_geoms.append(geom.buffer(r, quad_segs=4) if r > 0 else geom)
            continue
        kappa = _props_kappa(props, kind)
        mode = props.get("vertices", "auto")
        part = 0
        for chain in _ring_coords(geom):
            closed = bool(np.allclose(chain[0], chain[-1]))
            for j in range(len(chain) - 1):
                seg = LineString(chain[j:j + 2])
                reflectors.append(Reflector(kind, seg, kappa, 0.0, fid, i, part))
                tree_geoms.append(seg)
                part += 1
            if mode == "none":
                continue
            # vertex reflectors: interior vertices (all of them on a closed ring)
            n = len(chain) - 1 if closed else len(chain)
            for j in range(n):
                v = chain[j]
                if closed or 0 < j < n - 1:
                    prev = chain[j - 1] if j > 0 else chain[-2]
                    nxt = chain[j + 1]
                    a1 = math.atan2(prev[1] - v[1], prev[0] - v[0])
                    a2 = math.atan2(nxt[1] - v[1], nxt[0] - v[0])
                    opening = abs((a2 - a1 + math.pi) % (2 * math.pi) - math.pi)
                    if opening > math.pi - math.radians(STRAIGHT_TURN_DEG):
                        continue
                    cone: tuple[float, float] | None = (a1, a2)
                    kinds: tuple[str, ...] = ("corner", "edge") if mode == "auto" else (mode,)
                else:  # free end of an open wall
                    cone = None
                    kinds = ("edge",) if mode in ("auto", "edge") else ()
                for vk in kinds:
                    ref = Reflector(vk, Point(v), default_kappa_us(vk), 0.0, fid, i, j, cone)
                    derived.append((float(v[0]), float(v[1]), vk, 0.0, ref))

    # explicit corner/edge points at a wall vertex replace the derived ones there
    for pos in explicit_vertex:
        ex = reflectors[pos]
        px, py = ex.geometry.x, ex.geometry.y
        near = [d for d in derived
                if d[2] == ex.kind and math.hypot(d[0] - px, d[1] - py) <= SNAP_M]
        if not near:
            continue
        cones = [d[4].cone_rad for d in near if d[4].cone_rad is not None]
        reflectors[pos] = Reflector(ex.kind, ex.geometry, ex.kappa_us, 0.0, ex.id, ex.feature,
                                    ex.part, cones[0] if cones else None)
        derived = [d for d in derived if d not in near]
    for d in derived:
        reflectors.append(d[4])
        tree_geoms.append(d[4].geometry)
    return Map(tuple(features), tuple(reflectors), tuple(routes), tuple(tree_geoms))


def map_from_geojson(obj: Any) -> Map:
    """A :class:`Map` from a parsed GeoJSON object (a FeatureCollection).

    Raises
    ------
    MapError
        if it is not a FeatureCollection or a feature is bad (names the feature index).
    """
    if not isinstance(obj, dict) or obj.get("type") != "FeatureCollection":
        got = obj.get("type") if isinstance(obj, dict) else type(obj).__name__
        raise MapError(f"a map must be a GeoJSON FeatureCollection, got {got!r}")
    crs = obj.get("crs")
    name = crs.get("properties") if isinstance(crs, dict) else None
    name = name.get("name") if isinstance(name, dict) else None
    if isinstance(name, str) and LONLAT_CRS.search(name.strip()):
        raise MapError(f"the map's `crs` {name!r:.80} is longitude/latitude: map "
                       "coordinates are metres in a local frame (FORMATS.md section 3)")
    feats = obj.get("features")
    if not isinstance(feats, list):
        raise MapError("FeatureCollection needs a `features` list")
    return build_map([_parse_feature(i, f) for i, f in enumerate(feats)])


def load_map(path: str | Path) -> Map:
    """Read and validate a map GeoJSON file.

    Raises
    ------
    MapError
        if the file cannot be read or parsed, or a feature is bad.
    """
    try:  # a byte-order mark (some editors write one) is not part of the JSON
        text = Path(path).read_text(encoding="utf-8-sig")
    except OSError as err:
        raise MapError(f"cannot open map {path}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise MapError(f"map {path} is not UTF-8 text") from err
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as err:
        raise MapError(f"map {path}: not JSON (line {err.lineno}: {err.msg})") from err
    except RecursionError:
        raise MapError(f"map {path}: not a map (JSON nested too deeply)") from None
    try:
        return map_from_geojson(obj)
    except MapError as err:
        raise MapError(f"map {path}: {err}") from None


def map_to_geojson(world_map: Map) -> dict[str, Any]:
    """The FeatureCollection of a map's source features (derived reflectors are not written)."""
    return {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature", "properties": dict(f.properties),
             "geometry": _geometry_json(f.geometry)}
            for f in world_map.features
        ],
    }


def _geometry_json(geom: BaseGeometry) -> dict[str, Any]:
    obj = mapping(geom)

    def lists(c: Any) -> Any:
        return [lists(x) for x in c] if isinstance(c, (list, tuple)) and c \
            and isinstance(c[0], (list, tuple)) else [float(v) for v in c]

    return {"type": obj["type"], "coordinates": lists(obj["coordinates"])}


def save_map(world_map: Map, path: str | Path) -> None:
    """Write a map as GeoJSON (:func:`write_geojson`)."""
    write_geojson(map_to_geojson(world_map), path)


def write_geojson(obj: dict[str, Any], path: str | Path) -> None:
    """Write a FeatureCollection ``obj`` to ``path``, one feature per line (readable
    diffs), atomically: into a temporary file beside it, renamed over it once complete,
    so a crash or a full disk leaves the previous map whole instead of a truncated one."""
    lines = [json.dumps(f, separators=(", ", ": ")) for f in obj["features"]]
    body = ",\n".join("  " + line for line in lines)
    text = '{"type": "FeatureCollection", "features": [\n' + body + "\n]}\n"
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp",
                               dir=target.parent if str(target.parent) else ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
        # the permissions of the file replaced, or a new file's usual ones (mkstemp's
        # are the owner's only)
        os.chmod(tmp, target.stat().st_mode & 0o7777 if target.exists() else 0o644)
        os.replace(tmp, target)
    except BaseException:
        os.unlink(tmp)
        raise
