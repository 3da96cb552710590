import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.errors import MapError
from sonarloc.maps import build_map, load_map, map_from_geojson, map_to_geojson, save_map
from sonarloc.world.scene import Scene
from tests.conftest import MAPS, REPO


def fc(*features):
    return {"type": "FeatureCollection", "features": list(features)}


def feat(geom_type, coords, **props):
    return {"type": "Feature", "properties": props,
            "geometry": {"type": geom_type, "coordinates": coords}}


def test_example_maps_load():
    fig5 = load_map(MAPS / "paper_fig5.geojson")
    kinds = [r.kind for r in fig5.reflectors]
    assert kinds[:3] == ["pole", "plane", "rod"]
    assert kinds[3:] == ["edge", "edge"]  # the plane's free ends
    pole, plane, rod = fig5.reflectors[:3]
    assert pole.radius_m == pytest.approx(0.0445) and rod.radius_m == pytest.approx(0.004)
    # reflecting-surface ranges and bearings of the paper's Fig. 5 scene
    assert math.hypot(pole.geometry.x, pole.geometry.y) - pole.radius_m == pytest.approx(1.4615,
                                                                                        abs=1e-5)
    bearing = math.degrees(math.atan2(pole.geometry.y, pole.geometry.x))
    assert bearing == pytest.approx(-17, abs=1e-4)
    assert plane.geometry.distance(shapely.Point(0, 0)) == pytest.approx(1.5, abs=1e-5)
    assert plane.geometry.length == pytest.approx(1.0, abs=1e-5)
    assert math.hypot(rod.geometry.x, rod.geometry.y) - rod.radius_m == pytest.approx(1.4715,
                                                                                     abs=1e-5)
    room = load_map(MAPS / "room.geojson")
    assert room.route is not None and room.route.length > 10
    counts = {k: sum(r.kind == k for r in room.reflectors) for k in
              ("wall", "pole", "rod", "corner", "edge")}
    assert counts["pole"] >= 2 and counts["rod"] >= 2 and counts["wall"] >= 6
    assert counts["corner"] >= 4 and counts["edge"] >= 4


def test_polygon_vertices_are_corners_inside_edges_outside():
    # L-shaped room: (2, 2) is a reflex vertex of the room (an edge seen from inside)
    m = map_from_geojson(fc(feat("Polygon", [[[0, 0], [4, 0], [4, 4], [2, 4], [2, 2], [0, 2],
                                              [0, 0]]], kind="wall")))
    at = {(r.geometry.x, r.geometry.y, r.kind): r for r in m.reflectors
          if r.kind in ("corner", "edge")}
    assert len(at) == 12  # each of the 6 vertices is a corner from one side, edge from the other
    c = at[(0.0, 0.0, "corner")]
    assert c.cone_rad is not None
    assert c.kappa_us == pytest.approx(0.15) and at[(0.0, 0.0, "edge")].kappa_us > 1.0


def test_polygon_ring_without_its_closing_position_is_the_closed_ring():
    # a Polygon's rings are closed walls (FORMATS section 3): a ring that does not repeat
    # its start (RFC 7946 asks for it; hand-written maps forget it) is read as closed
    square = [[0, 0], [4, 0], [4, 4], [0, 4]]

    def walls(ring):
        m = map_from_geojson(fc(feat("Polygon", [ring], kind="wall")))
        return sorted((r.kind, tuple(map(tuple, np.round(r.geometry.coords, 9))))
                      for r in m.reflectors)

    closed = walls(square + [square[0]])
    assert walls(square) == closed
    assert sum(kind == "wall" for kind, _ in closed) == 4


def test_vertices_property_and_explicit_corner_override():
    wall = feat("LineString", [[0, 0], [2, 0], [2, 2]], kind="wall", vertices="corner")
    m = map_from_geojson(fc(wall))
    assert [r.kind for r in m.reflectors] == ["wall", "wall", "corner"]  # free ends dropped
    m = map_from_geojson(fc(feat("LineString", [[0, 0], [2, 0], [2, 2]], kind="wall",
                                 vertices="none")))
    assert [r.kind for r in m.reflectors] == ["wall", "wall"]
    # an explicit corner at the vertex replaces the derived one and keeps its cone
    m = map_from_geojson(fc(feat("LineString", [[0, 0], [2, 0], [2, 2]], kind="wall"),
                            feat("Point", [2.0, 0.005], kind="corner", kappa_us=0.3, id="c")))
    corners = [r for r in m.reflectors if r.kind == "corner"]
    assert len(corners) == 1 and corners[0].kappa_us == 0.3 and corners[0].cone_rad is not None
    # nearly straight vertices reflect nothing
    m = map_from_geojson(fc(feat("LineString", [[0, 0], [2, 0], [4, 0.1]], kind="wall",
                                 vertices="corner")))
    assert [r.kind for r in m.reflectors] == ["wall", "wall"]


@pytest.mark.parametrize(
    ("obj", "match"),
    [
        ({"type": "Feature"}, "FeatureCollection, got 'Feature'"),
        ([1, 2], "FeatureCollection, got 'list'"),
        ({"type": "FeatureCollection"}, "`features` list"),
        (fc({"type": "Feature", "properties": {"kind": "pole"}}), "feature 0: has no geometry"),
        (fc(feat("Point", [0, 0], kind="pole"), "x"), "feature 1: must be a GeoJSON Feature"),
        (fc(feat("MultiPoint", [[0, 0]], kind="pole")), "feature 0: geometry type 'MultiPoint'"),
        (fc(feat("Point", [0, 0])), "feature 0: missing property `kind`"),
        (fc(feat("Point", [0, 0], kind="tree")), "feature 0: unknown kind 'tree'"),
        (fc(feat("Point", [0, 0], kind="pole"), feat("Polygon", [[[0, 0], [1, 0], [1, 1],
                                                                   [0, 0]]], kind="pole")),
         "feature 1: unknown kind 'pole' for a Polygon"),
        (fc(feat("Point", [0, 0], kind="pole", radius_m=-0.1)), "feature 0: `radius_m`.*-0.1"),
        (fc(feat("Point", [0, 0], kind="pole", kappa_us=0)), "feature 0: `kappa_us`"),
        (fc(feat("Point", [0, 0], kind="rod", radius_m=1e-300)), "feature 0: `radius_m` must be 0"),
        (fc(feat("Point", [0, 0], kind="corner", radius_m=0.1)), "feature 0: a corner has no"),
        (fc(feat("Point", [0, float("nan")], kind="pole")), "feature 0: coordinates must be"),
        (fc(feat("Point", [0, float("inf")], kind="rod")), "feature 0: coordinates must be finite"),
        (fc(feat("Point", [0], kind="rod")), "feature 0: a position must be"),
        (fc(feat("Point", [0, 0], kind="rod"), feat("LineString", [[0, 0], [1, 1], [1, 0],
                                                                    [0, 1]], kind="wall")),
         "feature 1: wall LineString intersects itself"),
        (fc(feat("LineString", [[0, 0], [0, 0], [1, 0]], kind="wall")),
         "feature 0: zero-length segment"),
        (fc(feat("LineString", [[0, 0]], kind="wall")), "feature 0: bad LineString"),
        (fc(feat("Polygon", [[[0, 0], [2, 2], [2, 0], [0, 2], [0, 0]]], kind="wall")),
         "feature 0: invalid Polygon"),
        (fc(feat("Polygon", [[[0, 0], [0, 1], [1, 0]], []], kind="wall")),
         "feature 0: Polygon ring 1 needs at least 3 positions"),
        (fc(feat("LineString", [[0, 0], [1, 0]], kind="wall", vertices="some")),
         "feature 0: `vertices`"),
        (fc(feat("Point", [0, 0], kind="pole", id="a"), feat("Point", [1, 0], kind="rod", id="a")),
         "feature 1: duplicate id 'a'"),
        # ids become labels (FeatureMap, fit association): 1 and "1" shared one, and an
        # id "f1" the label of feature 1 without id
        (fc(feat("Point", [0, 0], kind="pole", id=1), feat("Point", [1, 0], kind="rod", id="1")),
         "feature 1: duplicate id '1' \\(also feature 0 as 1: the same label\\)"),
        (fc(feat("Point", [0, 0], kind="pole", id="f1"), feat("Point", [1, 0], kind="rod")),
         "feature 0: id 'f1' is the label of feature 1, which has no id"),
        # a reflector too weak to echo by orders of magnitude (1e308 overflowed the
        # simulator's delays)
        # a feature's position SD, which the Localizer uses (it was ignored when bad)
        (fc(feat("Point", [0, 0], kind="pole", sd_m=-0.001)), "feature 0: `sd_m` must be"),
        (fc(feat("LineString", [[0, 0], [1, 0]], kind="wall", sd_m="2 mm")),
         "feature 0: `sd_m` must be a non-negative number of metres, got '2 mm'"),
        # its SD relative to the map frame, which the Localizer uses instead where given
        (fc(feat("Point", [0, 0], kind="pole", sd_m=0.1),
            feat("Point", [1, 0], kind="rod", sd_m=0.1, sd_rel_m=-0.002)),
         "feature 1: `sd_rel_m` must be a non-negative number of metres, got -0.002"),
        (fc(feat("LineString", [[0, 0], [1, 0]], kind="wall", sd_rel_m=math.nan)),
         "feature 0: `sd_rel_m` must be a non-negative number of metres, got nan"),
        (fc(feat("LineString", [[0, 0], [1, 0]], kind="wall", sd_rel_m=True)),
         "feature 0: `sd_rel_m` must be"),
        (fc(feat("Point", [0, 0], kind="pole", kappa_us=1e308)),
         "feature 0: `kappa_us` must be at most 1e\\+06 us"),
        # a repeated position is a wall of no direction (a LineString's was refused)
        (fc(feat("Polygon", [[[0, 0], [4, 0], [4, 0], [4, 4], [0, 0]]], kind="wall")),
         "feature 0: zero-length segment at vertex 1 of Polygon ring 0"),
        (fc(feat("Polygon", [[[0, 0], [4, 0], [4, 4], [0, 4], [0, 0]],
                             [[1, 1], [2, 1], [2, 2], [2, 2], [1, 1]]], kind="wall")),
         "feature 0: zero-length segment at vertex 2 of Polygon ring 1"),
        (fc(feat("LineString", [], kind="wall")), "feature 0: bad LineString: needs at least 2"),
        # coordinates and radii that overflow the geometry (the kappa of a 1e300 m pole
        # was NaN)
        (fc(feat("Point", [1e300, 0], kind="pole")), "feature 0: coordinates must be metres"),
        (fc(feat("LineString", [[-1.5e308, 0], [1.5e308, 0]], kind="wall")),
         "feature 0: coordinates must be metres within"),
        (fc(feat("Point", [0, 0], kind="pole", radius_m=1e300)),
         "feature 0: `radius_m` must be at most"),
        # a map in degrees
        ({**fc(feat("Point", [13.4, 52.5], kind="pole")),
          "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}},
         "`crs` 'urn:ogc:def:crs:OGC:1.3:CRS84' is longitude/latitude"),
        ({**fc(), "crs": {"type": "name", "properties": {"name": "EPSG:4326"}}},
         "longitude/latitude"),
    ],
)
def test_bad_maps_name_the_feature(obj, match):
    with pytest.raises(MapError, match=match):
        map_from_geojson(obj)


def test_load_map_errors_name_the_file(tmp_path):
    with pytest.raises(MapError, match="cannot open map"):
        load_map(tmp_path / "missing.geojson")
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection",\n "features": [}')
    with pytest.raises(MapError, match="bad.geojson: not JSON \\(line 2"):
        load_map(bad)
    bad.write_text(json.dumps(fc(feat("Point", [0, 0], kind="tree"))))
    with pytest.raises(MapError, match="bad.geojson: feature 0: unknown kind"):
        load_map(bad)
    bad.write_text("[" * 100_000 + "]" * 100_000)  # deeper than json's recursion
    with pytest.raises(MapError, match="bad.geojson: not a map \\(JSON nested too deeply"):
        load_map(bad)
    # a byte-order mark (some editors write one) is no part of the JSON
    bad.write_text("\ufeff" + json.dumps(fc(feat("Point", [0, 0], kind="pole"))), encoding="utf-8")
    assert [r.kind for r in load_map(bad).reflectors] == ["pole"]


def test_odd_but_sound_maps_load():
    # a z is dropped, also where positions with and without one mix (shapely refused
    # the mix); a projected CRS is metres
    m = map_from_geojson({**fc(feat("LineString", [[0, 0, 1.5], [2, 0], [2, 2, 0.0]],
                                    kind="wall", vertices="none")),
                          "crs": {"type": "name",
                                  "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}}})
    assert [list(r.geometry.coords) for r in m.reflectors] == [[(0, 0), (2, 0)], [(2, 0), (2, 2)]]
    assert not m.features[0].geometry.has_z
    # a room with a box as the polygon's hole: every ring is walls; seen from the room,
    # a box corner is an edge, a room corner a corner
    m = map_from_geojson(fc(feat("Polygon", [[[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]],
                                             [[2, 1], [3, 1], [3, 2], [2, 2], [2, 1]]],
                                 kind="wall")))
    assert sum(r.kind == "wall" for r in m.reflectors) == 8
    scene = Scene(m)
    for (x, y, yaw_deg), kind in [((1.7, 0.7, 45.0), "edge"), ((5.0, 3.0, 45.0), "corner")]:
        cand = scene.candidates(x, y, math.radians(yaw_deg))
        kinds = {m.reflectors[i].kind for i, th in zip(cand.reflector, cand.theta_rad,
                                                        strict=True) if abs(th) < 0.01}
        assert kinds == {kind}, (x, y, kinds)


coord = st.floats(-50, 50, allow_nan=False).map(lambda v: round(v, 3))
point_feature = st.builds(
    lambda xy, kind, r, k: feat("Point", list(xy), kind=kind,
                                **({"radius_m": r} if kind not in ("corner", "edge") else {}),
                                **({"kappa_us": k} if k else {})),
    st.tuples(coord, coord), st.sampled_from(["pole", "rod", "point", "corner", "edge"]),
    st.one_of(st.just(0.0), st.floats(1e-3, 1)), st.one_of(st.none(), st.floats(0.01, 20)))
wall_feature = st.builds(
    lambda x, y, dx, dy, kind: feat("LineString", [[x, y], [x + dx, y + dy]], kind=kind),
    coord, coord, st.floats(0.1, 5).map(lambda v: round(v, 3)),
    st.floats(-5, 5).map(lambda v: round(v, 3)), st.sampled_from(["wall", "plane", "route"]))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.one_of(point_feature, wall_feature), max_size=8))
def test_save_load_round_trip(tmp_path_factory, features):
    m = map_from_geojson(fc(*features))
    path = tmp_path_factory.mktemp("maps") / "m.geojson"
    save_map(m, path)
    back = load_map(path)
    assert map_to_geojson(back) == map_to_geojson(m)
    assert len(back.reflectors) == len(m.reflectors)
    for a, b in zip(m.reflectors, back.reflectors, strict=True):
        assert a.kind == b.kind and a.kappa_us == b.kappa_us and a.radius_m == b.radius_m
        assert a.geometry.equals_exact(b.geometry, 1e-12)


def test_query_sector_matches_geometry(rng):
    pts = rng.uniform(-10, 10, (300, 2))
    features = [feat("Point", p.tolist(), kind="pole", radius_m=0.05) for p in pts[:200]]
    features += [feat("LineString", [p.tolist(), (p + rng.uniform(-1, 1, 2)).tolist()],
                      kind="wall", vertices="none") for p in pts[200:]]
    m = map_from_geojson(fc(*features))
    for _ in range(20):
        x, y = rng.uniform(-8, 8, 2)
        yaw, r, h = rng.uniform(-np.pi, np.pi), rng.uniform(1, 6), rng.uniform(0.1, 1.0)
        got = set(m.query_sector(x, y, yaw, r, h).tolist())
        # reference: exact disc-sector membership by sampling each reflector densely
        for i, refl in enumerate(m.reflectors):
            g = refl.geometry
            if g.geom_type == "Point":
                a = np.linspace(0, 2 * np.pi, 64)
                s = np.c_[g.x + refl.radius_m * np.cos(a), g.y + refl.radius_m * np.sin(a)]
            else:
                s = np.array([g.interpolate(f, normalized=True).coords[0]
                              for f in np.linspace(0, 1, 200)])
            d = np.hypot(s[:, 0] - x, s[:, 1] - y)
            ang = np.abs((np.arctan2(s[:, 1] - y, s[:, 0] - x) - yaw + np.pi) % (2 * np.pi)
                         - np.pi)
            inside = np.any((d < r * 0.999) & (ang < h * 0.999))
            if inside:
                assert i in got, (i, refl)
        far = [i for i in got if m.reflectors[i].geometry.distance(shapely.Point(x, y)) > r * 1.01]
        assert not far
    with pytest.raises(ValueError, match="max_range_m"):
        m.query_sector(0, 0, 0, -1.0, 0.3)


def test_build_map_accepts_programmatic_features():
    m = map_from_geojson(fc(feat("Point", [1, 2], kind="pole", radius_m=0.05)))
    again = build_map(m.features)
    assert again.reflectors == m.reflectors


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(allow_nan=True)
    | st.sampled_from(["pole", "wall", "rod", "route", "Point", "Feature", "x"]),
    lambda children: st.lists(children, max_size=5)
    | st.dictionaries(st.sampled_from(["type", "kind", "coordinates", "geometry", "properties",
                                       "radius_m", "kappa_us", "id", "vertices", "features"]),
                      children, max_size=5),
    max_leaves=25)
geometries = st.fixed_dictionaries({
    "type": st.sampled_from(["Point", "LineString", "Polygon", "MultiPoint", "Nope"]),
    "coordinates": json_values
    | st.lists(st.floats(-10, 10), min_size=2, max_size=2)
    | st.lists(st.lists(st.floats(-10, 10), min_size=2, max_size=2), max_size=5)
    | st.lists(st.lists(st.lists(st.integers(-3, 3), min_size=2, max_size=2), max_size=6),
               max_size=2)})
features = st.fixed_dictionaries(
    {"type": st.just("Feature"), "geometry": geometries | json_values,
     "properties": st.fixed_dictionaries(
         {"kind": st.sampled_from(list(("pole", "rod", "corner", "edge", "point", "wall",
                                        "plane", "route", "x"))) | json_values},
         optional={"radius_m": json_values | st.floats(-1, 1),
                   "kappa_us": json_values | st.floats(-1, 5),
                   "id": json_values, "vertices": json_values | st.sampled_from(
                       ["auto", "corner", "edge", "none"])}) | json_values})


@settings(max_examples=300, deadline=None)
@given(st.one_of(json_values, st.fixed_dictionaries(
    {"type": st.just("FeatureCollection"),
     "features": st.lists(features | json_values, max_size=4)})))
def test_garbage_maps_give_map_or_maperror(obj):
    try:
        m = map_from_geojson(obj)
    except MapError as err:
        assert str(err)
        return
    for r in m.reflectors:  # what loads is sound
        assert r.kappa_us > 0 and r.radius_m >= 0 and not r.geometry.is_empty


def test_save_map_replaces_the_file_whole_or_not_at_all(tmp_path):
    # written into a temporary file beside it and renamed over it: a crash or a full
    # disk mid-write leaves the previous map, not a truncated file a robot then loads
    room = load_map(MAPS / "room.geojson")
    path = tmp_path / "map.geojson"
    path.write_text("previous map\n", encoding="utf-8")
    path.chmod(0o640)
    save_map(room, path)
    assert map_to_geojson(load_map(path)) == map_to_geojson(room)
    assert path.stat().st_mode & 0o777 == 0o640          # the replaced file's permissions
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.geojson"]
    fresh = tmp_path / "new.geojson"
    save_map(room, fresh)
    assert fresh.stat().st_mode & 0o777 == 0o644
    # a disk that fills up mid-write (a file size limit, in a process of its own): the
    # previous map stays whole (it was truncated, then cut off), no partial file is left
    code = ("import resource, signal, sys; from sonarloc.maps import load_map, save_map; "
            "m = load_map(sys.argv[1]); signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            "resource.setrlimit(resource.RLIMIT_FSIZE, (500, 500)); save_map(m, sys.argv[2])")
    before = path.read_bytes()
    proc = subprocess.run([sys.executable, "-c", code, str(MAPS / "room.geojson"), str(path)],
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode != 0 and "File too large" in proc.stderr, proc.stderr
    assert path.read_bytes() == before and len(before) > 500
    # a target that cannot be replaced (a directory): an error, nothing left behind
    (tmp_path / "dir.geojson").mkdir()
    with pytest.raises(OSError):
        save_map(room, tmp_path / "dir.geojson")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.geojson", "map.geojson",
                                                          "new.geojson"]
