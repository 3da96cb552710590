import io
import math
import re

import numpy as np
import pytest

from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.io.logfile import LogWriter, TruthRecord, iter_log
from sonarloc.io.posescsv import PoseTrack, read_poses_csv, write_poses_csv
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.replay import replay_log
from sonarloc.maps.build import BuildConfig, MapBuilder, build_from_log
from sonarloc.maps.compare import feature_errors
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records
from tests.conftest import MAPS

ROOM = MAPS / "room.geojson"


def point_lm(q, sd=0.002, kappa=0.67, status=FitStatus.OK):
    cov = np.diag([sd**2, sd**2, 0.01])
    return Landmark("point", np.array([q[0], q[1], kappa]), cov, 1.0, 0.0, 10, 0.0,
                    (0.0, 0.0, 0.0), status)


def line_lm(rho, alpha, sd=0.002, sd_a=0.003, kappa=0.15):
    cov = np.diag([sd**2, sd_a**2, 0.001])
    return Landmark("line", np.array([rho, alpha, kappa]), cov, 1.0, 0.0, 10, 0.0,
                    (0.0, 0.0, 0.0))


def test_cylinder_centre_and_radius_from_several_directions(rng):
    c, r = np.array([2.0, 1.0]), 0.0445
    b = MapBuilder()
    for ang in np.linspace(-2.5, 2.5, 40):
        u = np.array([math.cos(ang), math.sin(ang)])
        view = c + 1.5 * u
        q = c + r * u + rng.normal(0, 0.002, 2)
        assert b.add(point_lm(q), view) == "point"
    (f,) = b.features()
    assert f.kind == "pole"
    assert np.hypot(*(f.coords - c)) < 0.002
    assert f.radius_m == pytest.approx(r, abs=0.003)
    assert f.n_obs == 40 and 0 < f.sd_m < 0.002


def test_point_seen_from_one_side_has_no_radius(rng):
    b = MapBuilder()
    for _ in range(10):
        b.add(point_lm(np.array([1.0, 1.0]) + rng.normal(0, 0.001, 2), kappa=0.15),
              np.array([0.0, 1.0]))
    (f,) = b.features()
    assert f.kind == "corner" and f.radius_m == 0.0
    assert np.hypot(*(f.coords - [1.0, 1.0])) < 0.002


def test_walls_merge_across_passes_and_spurious_clusters_drop(rng):
    b = MapBuilder(BuildConfig(min_observations=3))
    for k in range(12):  # a wall y = 3 seen in pieces along x from 0 to 6
        x0 = 0.5 * k
        feet = np.array([[x0, 3.0], [x0 + 0.5, 3.0]])
        b.add(line_lm(3.0 + rng.normal(0, 0.002), math.pi / 2 + rng.normal(0, 0.003)),
              np.array([x0, 2.0]), feet=feet)
    b.add(point_lm([5.0, 5.0]), np.array([4.0, 4.0]))  # seen once: dropped
    b.add(point_lm([1.0, 1.0], status=FitStatus.PARTIAL), np.array([0.0, 0.0]))
    feats = b.features()
    assert [f.kind for f in feats] == ["wall"]
    ends = feats[0].coords
    assert np.allclose(sorted(ends[:, 0]), [0.0, 6.0], atol=0.01)
    assert np.allclose(ends[:, 1], 3.0, atol=0.01)
    assert b.stats["skipped_partial"] == 1
    m = b.to_map()
    assert [r.kind for r in m.reflectors] == ["wall"]  # vertices "none": no edges at the ends


def test_walls_are_extended_to_meet_at_corners():
    b = MapBuilder(BuildConfig(min_observations=1))
    b.add(line_lm(0.0, -math.pi / 2), np.array([1.0, 1.0]),
          feet=np.array([[0.6, 0.0], [3.0, 0.0]]))
    b.add(line_lm(4.0, 0.0), np.array([3.0, 1.0]), feet=np.array([[4.0, 0.5], [4.0, 3.0]]))
    walls = [f for f in b.features() if f.kind == "wall"]
    corner = np.array([4.0, 0.0])
    assert all(np.min(np.hypot(*(w.coords - corner).T)) < 1e-9 for w in walls)
    # the far ends stay where the echoes were
    assert any(np.allclose(w.coords, [[0.6, 0.0], [4.0, 0.0]]) or
               np.allclose(w.coords, [[4.0, 0.0], [0.6, 0.0]]) for w in walls)


def test_corner_at_wall_meeting_is_a_corner_without_radius(rng):
    # two walls meeting at (4, 0); a corner reflector there seen from inside the angle,
    # its fits scattered so that a cylinder fit would find a small radius
    b = MapBuilder(BuildConfig(min_observations=3))
    for k in range(6):
        b.add(line_lm(0.0, -math.pi / 2), np.array([1.0 + 0.4 * k, 1.0]),
              feet=np.array([[0.6 + 0.5 * k, 0.0], [1.0 + 0.5 * k, 0.0]]))
        b.add(line_lm(4.0, 0.0), np.array([3.0, 0.5 + 0.4 * k]),
              feet=np.array([[4.0, 0.4 + 0.5 * k], [4.0, 0.8 + 0.5 * k]]))
    vertex = np.array([4.0, 0.0])
    for ang in np.linspace(math.radians(100), math.radians(170), 12):
        u = np.array([math.cos(ang), math.sin(ang)])
        q = vertex + 0.012 * u + rng.normal(0, 0.001, 2)  # biased towards the viewer
        b.add(point_lm(q, kappa=0.4), vertex + 2.0 * u)
    (c,) = [f for f in b.features() if f.kind != "wall"]
    assert c.kind == "corner" and c.radius_m == 0.0
    # point fit with R = 0: the mean of the fits, not a cylinder centre behind them
    assert np.hypot(*(c.coords - vertex)) < 0.015


def test_point_on_a_wall_is_dropped_and_short_rare_walls_too(rng):
    b = MapBuilder(BuildConfig(min_observations=3))
    for k in range(8):
        b.add(line_lm(3.0, math.pi / 2), np.array([0.5 * k, 2.0]),
              feet=np.array([[0.5 * k, 3.0], [0.5 * k + 0.5, 3.0]]))
    for _ in range(5):  # a wall echo fitted as a weak point in the middle of the wall
        b.add(point_lm(np.array([2.0, 3.0]) + rng.normal(0, 0.002, 2), kappa=7.0),
              np.array([2.0, 2.0]))
    for _ in range(5):  # the same near the wall's end (20 cm: not where a vertex reflects)
        b.add(point_lm(np.array([3.8, 3.0]) + rng.normal(0, 0.002, 2), kappa=9.0),
              np.array([3.5, 2.0]))
    for _ in range(4):  # a short, rarely seen line: corner echoes fitted as a wall
        b.add(line_lm(6.0, 0.3), np.array([5.0, 0.0]),
              feet=np.array([[6.0, 1.0], [6.0, 1.2]]))
    feats = b.features()
    assert [f.kind for f in feats] == ["wall"]
    assert b.stats["dropped_on_wall"] == 2 and b.stats["dropped_short_wall"] == 1


def test_wall_line_from_feet_is_insensitive_to_pose_yaw_errors(rng):
    # each fit's line is rotated about its foot by a yaw error (1 deg SD, reported far
    # smaller): the feet stay on the wall, so the built wall does too
    b = MapBuilder(BuildConfig(min_observations=3))
    for k in range(30):
        x0 = 0.2 * k
        foot = np.array([x0 + 0.1, 3.0])
        err = rng.normal(0, math.radians(1.0))
        alpha = math.pi / 2 + err
        n = np.array([math.cos(alpha), math.sin(alpha)])
        rho = float(foot @ n)
        d = np.array([-n[1], n[0]])
        feet = np.array([foot - 0.1 * d, foot + 0.1 * d])
        b.add(line_lm(rho, alpha, sd=0.001, sd_a=0.0005), np.array([x0 + 0.1, 1.5]), feet=feet)
    (w,) = b.features()
    assert max(abs(w.coords[:, 1] - 3.0)) < 0.004
    assert w.sd_alpha_deg < 0.2


@pytest.fixture(scope="module")
def room_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("build")
    log = d / "room.jsonl"
    with LogWriter(log) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=116.0, seed=7))
    truth = [r for r in iter_log(log) if isinstance(r, TruthRecord)]
    n = len(truth)
    track = PoseTrack(np.array([r.t_s for r in truth]), np.array([r.x_m for r in truth]),
                      np.array([r.y_m for r in truth]), np.radians([r.yaw_deg for r in truth]),
                      np.zeros((n, 3, 3)))
    poses = d / "truth.csv"
    write_poses_csv(poses, track)
    built = d / "built.geojson"
    result = build_from_log(log, read_poses_csv(poses))
    built.write_text(__import__("json").dumps(result.geojson()))
    return d, log, poses, built


def _line_distance(p, seg):
    a, b = seg
    d = b - a
    n = np.array([-d[1], d[0]]) / np.hypot(*d)
    return abs((p - a) @ n)


@pytest.mark.slow    # (the 116 s drive of its fixture: 16-26 s of the suite)
def test_built_map_recovers_the_room_within_2cm(room_run):
    d, log, poses, out = room_run
    built_map = load_map(out)
    built = FeatureMap.from_map(built_map)
    true = FeatureMap.from_map(load_map(ROOM))
    assert built.n_walls >= 5
    for ends in built.wall_ends:  # no ghost walls: both ends of each on a true wall's line
        err = min(max(_line_distance(p, seg) for p in ends) for seg in true.wall_ends)
        assert err < 0.02
    cyl = [i for i, k in enumerate(true.point_kind) if k in ("pole", "rod")]
    for i in cyl:  # every pole and rod found, centre within 2 cm
        d_c = np.hypot(*(built.point_xy - true.point_xy[i]).T)
        assert d_c.min() < 0.02, (true.point_id[i], d_c.min())
    for p, k in zip(built.point_xy, built.point_kind, strict=True):
        # nothing made up: every point within 2 cm of a true reflector of its kind
        d_t = np.hypot(*(true.point_xy - p).T)
        assert d_t.min() < 0.02
        assert k in {true.point_kind[j] for j in np.nonzero(d_t < 0.02)[0]}, (p, k)
    corners = [p for p, k in zip(built.point_xy, built.point_kind, strict=True) if k == "corner"]
    assert len(corners) >= 4  # the room's corners, each at a true vertex (checked above)


@pytest.mark.slow
def test_built_map_works_in_localize(room_run):
    d, log, poses, out = room_run
    fmap = FeatureMap.from_map(load_map(out))
    truth = {r.t_s: r for r in iter_log(log) if isinstance(r, TruthRecord)}
    head = io.StringIO("".join(line for line, _ in zip(open(log, encoding="utf-8"),
                                                       range(9000), strict=False)))
    errors = []

    def check(rec, est):
        if rec.t_s > 5.0:
            t = truth[rec.t_s]
            errors.append(math.hypot(est.x_m - t.x_m, est.y_m - t.y_m))

    result = replay_log(head, fmap, on_estimate=check)
    assert result.localizer.stats.accepted > 50
    assert np.sqrt(np.mean(np.square(errors))) < 0.02
    assert result.last is not None and result.last.status == "tracking"


def test_build_cli_from_odometry_and_bad_input(run_cli, tmp_path):
    text = io.StringIO()
    with LogWriter(text) as w:   # (a lap's first 20 s: the room_run fixture is slow)
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=20.0, seed=7))
    lines = text.getvalue().splitlines()
    bad = tmp_path / "bad.jsonl"
    bad.write_text("\n".join(lines[:50] + ["garbage", '{"type": "sonar"}'] + lines[50:]) + "\n")
    out = tmp_path / "m.geojson"
    proc = run_cli("map", "build", str(bad), "--out", str(out), check=True)
    assert "line 51" in proc.stderr and "sonar" in proc.stderr
    assert "landmarks fitted" in proc.stderr
    assert re.search(r"poses from odometry alone over \d+\.\d m and \d+ deg: its drift is "
                     r"in the map \(--poses POSES.csv from `sonarloc localize", proc.stderr)
    map_from_geojson(__import__("json").loads(out.read_text()))
    proc = run_cli("map", "build", str(bad), "--poses", str(tmp_path / "none.csv"), "--out",
                   str(out))
    assert proc.returncode == 2 and "none.csv" in proc.stderr
    proc = run_cli("map", "build", str(bad))
    assert proc.returncode == 2 and "--out" in proc.stderr


def test_builder_memory_is_bounded():
    b = MapBuilder()
    for k in range(3000):
        b.add(point_lm([1.0, 1.0], kappa=0.5 + (k % 7) * 0.1), np.array([0.0, 1.0]))
    assert len(b.points) == 1 and len(b.points[0].log_kappas) <= 255
    result = build_from_log(io.StringIO(""))
    assert result.readings == 0 and result.builder.features() == []


@pytest.mark.parametrize(("end_gate_m", "kept"), [(BuildConfig.end_gate_m, True), (0.05, False)])
def test_vertex_just_inside_a_walls_built_end_is_kept(rng, end_gate_m, kept):
    # the wall's feet run 7 cm past the vertex at its end (the vertex echoes like the
    # wall beside it): the vertex is no wall echo fitted as a point
    b = MapBuilder(BuildConfig(min_observations=3, end_gate_m=end_gate_m))
    for k in range(8):
        b.add(line_lm(3.0, math.pi / 2), np.array([0.5 * k, 2.0]),
              feet=np.array([[0.5 * k, 3.0], [0.5 * k + 0.5, 3.0]]))
    for _ in range(5):
        b.add(point_lm(np.array([3.93, 3.0]) + rng.normal(0, 0.002, 2), kappa=0.15),
              np.array([3.0, 2.0]))
    kinds = sorted(f.kind for f in b.features())
    assert (len(kinds) == 2) == kept, kinds
    assert b.stats["dropped_on_wall"] == (0 if kept else 1)


def test_a_landmark_its_fit_cannot_place_is_skipped_not_fatal():
    # a FLAT wall driven past at one angle (bench_localize's map building, seed 200):
    # rho and alpha undetermined together, SDs of 7e7 m at correlation 1; the builder
    # inverted that covariance and stopped
    v = 5.74206347e15
    cov = np.array([[v, v, 28.36], [v, v, 28.36], [28.36, 28.36, 1.15e-3]])
    flat = Landmark("line", np.array([7.9997, 0.0, 0.05]), cov, 1.0, 0.0, 28, 0.0,
                    (6.472, 1.0, 0.0), FitStatus.FLAT)
    b = MapBuilder(BuildConfig(min_observations=1))
    assert b.add(flat, np.array([6.5, 1.0]), feet=np.array([[8.0, 0.9], [8.0, 1.1]])) == \
        "skipped_vague"
    wide = point_lm([1.0, 1.0], sd=1.5)              # SD 15 gates: nowhere in particular
    assert b.add(wide, np.array([0.0, 1.0])) == "skipped_vague"
    assert b.add(point_lm([1.0, 1.0], sd=0.2), np.array([0.0, 1.0])) == "point"   # 2 gates
    assert b.stats["skipped_vague"] == 2 and len(b.features()) == 1


def _normalized_errors(feats, world, gate_m=0.5):
    """error / sd_m of every built feature matched to a true one, and the errors."""
    pairs = feature_errors(feats, world, gate_m)
    return np.array([e / f.sd_m for f, e in pairs]), np.array([e for _, e in pairs])


def test_odometry_only_build_states_its_drift():
    # 25 s of the room from odometry alone, from an exact init: the drift moves the
    # features by up to 12 cm; each one's sd_m covers its error (stated 1-3 mm before)
    world = load_map(ROOM)
    text = io.StringIO()
    with LogWriter(text) as w:
        w.write_all(simulate_records(world, ring16(), duration_s=25.0, seed=7,
                                     init_sd_xy_m=0.0, init_sd_yaw_deg=0.0))
    res = build_from_log(io.StringIO(text.getvalue()))
    feats = res.builder.features()
    # (no sd_rel_m: the dead reckoning's drift is the map's shape error; docs/MAPS.md)
    assert all(math.isnan(f.sd_rel_m) for f in feats)
    assert not any("sd_rel_m" in f["properties"] for f in res.geojson()["features"])
    z, errs = _normalized_errors(feats, world)
    assert len(z) >= 8 and errs.max() > 0.05   # matched, and the drift is there
    assert z.max() < 3.0, np.round(z, 1)
    assert 0.05 < np.mean(z**2) < 3.0          # not made honest by being vast either


def _drifting_point_sightings(b, n, drift_sd, fit_sd, q, rng):
    cov = np.diag([drift_sd**2, drift_sd**2, 0.0])
    for k in range(n):
        view = q + np.array([-1.0, 0.2 * (k % 5 - 2)])
        b.add(point_lm(q + rng.normal(0, fit_sd, 2), sd=fit_sd, kappa=0.15), view,
              pose=np.array([*view, 0.0]), drift_cov=cov)


def test_shared_drift_is_kept_whole_over_sightings(rng):
    # 5 cm of drift shared by every sighting: 100 sightings do not make it 5 mm
    for n in (5, 100):
        b = MapBuilder(BuildConfig(min_observations=3))
        _drifting_point_sightings(b, n, 0.05, 0.002, np.array([2.0, 1.0]), rng)
        (f,) = b.features()
        assert f.sd_m == pytest.approx(0.05, rel=0.05), n
    # as a pose's own covariance (localized poses) it does average down
    b = MapBuilder(BuildConfig(min_observations=3))
    for k in range(100):
        view = np.array([1.0, 1.0 + 0.02 * k])
        b.add(point_lm(np.array([2.0, 1.0]) + rng.normal(0, 0.002, 2)), view,
              pose=np.array([*view, 0.0]), pose_cov=np.diag([0.05**2, 0.05**2, 0.0]))
    (f,) = b.features()
    assert f.sd_m < 0.01


def test_point_sd_grows_with_scatter_beyond_the_stated_sds(rng):
    # fits stating 1 mm that scatter by 5 mm: the SD of their mean is 5 mm / sqrt(n)
    b = MapBuilder(BuildConfig(min_observations=3))
    n = 50
    for _ in range(n):
        b.add(point_lm(np.array([1.0, 1.0]) + rng.normal(0, 0.005, 2), sd=0.001,
                       kappa=0.15), np.array([0.0, 1.0]))
    (f,) = b.features()
    assert f.sd_m == pytest.approx(0.005 / math.sqrt(n), rel=0.3)
    b = MapBuilder(BuildConfig(min_observations=3))   # scatter within the SDs: unchanged
    for _ in range(n):
        b.add(point_lm(np.array([1.0, 1.0]) + rng.normal(0, 0.0005, 2), sd=0.001,
                       kappa=0.15), np.array([0.0, 1.0]))
    (f,) = b.features()
    assert f.sd_m == pytest.approx(0.001 / math.sqrt(n), rel=0.05)


def test_wall_sd_is_stated_at_its_far_end(rng):
    # a 6 m wall y = 3 seen from x = 0.5 with 1 deg of yaw drift: the far end (5.5 m
    # from the pose) can be off by 5.5 m x 1 deg = 96 mm, the near one by 9 mm
    b = MapBuilder(BuildConfig(min_observations=3))
    drift = np.diag([0.0, 0.0, math.radians(1.0) ** 2])
    for k in range(12):
        x0 = 0.5 * k
        b.add(line_lm(3.0, math.pi / 2), np.array([x0 + 0.25, 2.0]),
              pose=np.array([0.5, 2.0, 0.0]), drift_cov=drift,
              feet=np.array([[x0, 3.0], [x0 + 0.5, 3.0]]))
    (w,) = b.features()
    far = 5.5 * math.radians(1.0)
    assert w.sd_m == pytest.approx(far, rel=0.05)
    assert w.sd_alpha_deg == pytest.approx(1.0, rel=0.05)


def test_feature_errors_against_the_true_map():
    """`maps.compare.feature_errors`: a point's distance to the nearest true point, a
    wall's worse end from the line of a true wall of its direction; beyond the gate (a
    ghost) or at another direction: left out."""
    from sonarloc.maps.build import BuiltFeature

    world = load_map(ROOM)
    pole = BuiltFeature("pole", np.array([2.53, 2.04]), 0.5, 0.01, 5)       # pole-a, 5 cm
    wall = BuiltFeature("wall", np.array([[1.0, 0.01], [6.0, -0.02]]), 0.1, 0.01, 5)
    ghost = BuiltFeature("pole", np.array([6.0, 2.5]), 0.5, 0.01, 5)
    slanted = BuiltFeature("wall", np.array([[1.0, 0.5], [1.6, 1.3]]), 0.1, 0.01, 5)
    got = feature_errors([pole, wall, ghost, slanted], world, gate_m=0.3)
    assert [f for f, _ in got] == [pole, wall]
    assert got[0][1] == pytest.approx(0.05) and got[1][1] == pytest.approx(0.02)


def test_frame_relative_drift_goes_into_sd_rel_m(rng):
    """``drift_rel_cov`` (the drift less the map frame's own error) is kept whole in
    ``sd_rel_m`` next to ``sd_m`` (which keeps the whole drift), for points and for
    walls at their far end; the GeoJSON carries it, and a build without it has none."""
    b = MapBuilder(BuildConfig(min_observations=3))
    whole = np.diag([0.05**2, 0.05**2, 0.0])
    rel = np.diag([0.004**2, 0.004**2, 0.0])
    q = np.array([2.0, 1.0])
    for k in range(20):
        view = q + np.array([-1.0, 0.2 * (k % 5 - 2)])
        b.add(point_lm(q + rng.normal(0, 0.0005, 2), sd=0.0005, kappa=0.15), view,
              pose=np.array([*view, 0.0]), drift_cov=whole, drift_rel_cov=rel)
    yaw = np.diag([0.0, 0.0, math.radians(1.0) ** 2])
    for k in range(12):
        x0 = 0.5 * k
        b.add(line_lm(3.0, math.pi / 2), np.array([x0 + 0.25, 2.0]),
              pose=np.array([0.5, 2.0, 0.0]), drift_cov=4 * yaw, drift_rel_cov=yaw,
              feet=np.array([[x0, 3.0], [x0 + 0.5, 3.0]]))
    feats = b.features()
    (p,) = [f for f in feats if f.kind != "wall"]
    (w,) = [f for f in feats if f.kind == "wall"]
    assert p.sd_m == pytest.approx(0.05, rel=0.05)
    assert p.sd_rel_m == pytest.approx(0.004, rel=0.05)
    far = 5.5 * math.radians(1.0)
    assert w.sd_m == pytest.approx(2 * far, rel=0.05)
    assert w.sd_rel_m == pytest.approx(far, rel=0.05)
    props = [f["properties"] for f in b.geojson()["features"]]
    assert sorted(pr["sd_rel_m"] for pr in props) == pytest.approx(
        sorted([p.sd_rel_m, w.sd_rel_m]), abs=1e-5)
    assert [f.properties["sd_rel_m"] for f in b.to_map().features] == \
        [pr["sd_rel_m"] for pr in props]
    # without it (a pose track, or a builder fed the whole drift alone): no sd_rel_m
    b2 = MapBuilder(BuildConfig(min_observations=3))
    for k in range(20):
        view = q + np.array([-1.0, 0.2 * (k % 5 - 2)])
        b2.add(point_lm(q, sd=0.0005, kappa=0.15), view, pose=np.array([*view, 0.0]),
               drift_cov=whole)
    (f2,) = b2.features()
    assert math.isnan(f2.sd_rel_m) and "sd_rel_m" not in b2.geojson()["features"][0][
        "properties"]

