"""Map building with SLAM: the odometry corrected by the landmarks seen again.

The fixture drives 1.6 laps of a 6.8 m loop around pole-a of ``maps/room.geojson``
(ring16, 36 s) with an ``init`` record of 1 mm / 0.05 deg SD, so that the map frame is
the true one and every error left is the build's. Measured on it (seed 1): SLAM puts
the 4 walls within 11 mm, pole-a within 5 mm and every point within 54 mm (the far
ones seen from 2-3 m) of the truth, each within 1.1 of its ``sd_m``; the odometry
build of the same log (``method="odometry"``) leaves walls 17-76 mm and points up to
194 mm off, rod-a built twice.
"""

from __future__ import annotations

import io
import json
import math
import re

import numpy as np
import pytest
from shapely.geometry import LineString

from sonarloc import se2
from sonarloc.io.logfile import LogWriter, OdomRecord, TofRecord, TruthRecord, iter_log
from sonarloc.maps import compare
from sonarloc.maps.build import BuildConfig, build_from_log
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.maps.slam import SlamConfig, _Graph, _whitening
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"
LOOP = LineString([[1.5, 1.2], [3.3, 1.2], [3.3, 2.8], [1.5, 2.8], [1.5, 1.2]])
DURATION_S = 36.0


def _text(records) -> str:
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(records)
    return buf.getvalue()


@pytest.fixture(scope="module")
def loop_records():
    return list(simulate_records(load_map(ROOM), ring16(), duration_s=DURATION_S, seed=1,
                                 route=LOOP, init_sd_xy_m=0.001, init_sd_yaw_deg=0.05))


@pytest.fixture(scope="module")
def loop_log(loop_records, tmp_path_factory):
    path = tmp_path_factory.mktemp("slam") / "loop.jsonl"
    path.write_text(_text(loop_records), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def slam_build(loop_log):
    return build_from_log(loop_log)


def _errors(result, gate_m=0.5):
    return compare.feature_errors(result.builder.features(), load_map(ROOM), gate_m)


def _check_room_features(result):
    """Every built feature near a true one, no feature built twice, the pole and the
    walls the loop passes within a few cm, and each error within 3.5 of its sd_m."""
    feats = result.builder.features()
    pairs = _errors(result)
    assert len(pairs) == len(feats) >= 9          # nothing built far from the truth
    walls = [(f, e) for f, e in pairs if f.kind == "wall"]
    points = [(f, e) for f, e in pairs if f.kind != "wall"]
    assert len(walls) >= 4 and len(points) >= 5
    for f, e in walls:
        assert e < 0.02, (f, e)
    pole_a = [e for f, e in points if np.hypot(*(f.coords - [2.5, 2.0])) < 0.1]
    assert len(pole_a) == 1 and pole_a[0] < 0.01
    for f, e in points:
        assert e < 0.08, (f, e)
    # no duplicates: no two walls on one line overlapping, no two points within 0.2 m
    xy = np.array([f.coords for f, _ in points])
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy))
    assert d.min() > 0.2
    for i, (a, _) in enumerate(walls):
        for b, _ in walls[i + 1:]:
            da, db = a.coords[1] - a.coords[0], b.coords[1] - b.coords[0]
            if abs(da[0] * db[1] - da[1] * db[0]) > 0.1 * np.hypot(*da) * np.hypot(*db):
                continue  # not parallel
            u = da / np.hypot(*da)
            off = abs(float((b.coords[0] - a.coords[0]) @ [-u[1], u[0]]))
            t = sorted(float((p - a.coords[0]) @ u) for p in b.coords)
            assert off > 0.3 or t[1] < 0 or t[0] > np.hypot(*da), (a, b)
    # honest sd_m: normalized errors (points 2-D, walls 1-D)
    z = np.array([e / f.sd_m for f, e in pairs])
    assert z.max() < 3.5 and np.mean(z**2) < 3.0


def test_slam_build_recovers_the_room_without_poses(slam_build):
    res = slam_build
    assert res.method == "slam" and res.slam is not None and res.slam.ok
    _check_room_features(res)
    s = res.slam
    assert s.rounds >= 2 and s.revisited >= 3
    assert s.moved_m > 0.1                 # the dead reckoning was decimetres off
    assert s.last_move_m < 0.005          # converged
    assert s.associated >= 0.95 * s.observations
    assert 0.0 < s.chi2_odom < 2.0 and 0.0 < s.chi2_obs < 2.0
    assert np.all(np.isfinite(s.node_cov)) and np.all(np.linalg.eigvalsh(s.node_cov) > 0)
    summary = res.summary()
    assert summary.startswith("method: slam;")
    assert re.search(r"slam: \d+ rounds, \d+ poses, \d+ landmarks \(\d+ seen again\)", summary)
    assert "poses moved up to" in summary and "chi2/dof odometry" in summary
    assert "its drift is in the map" not in summary


def test_slam_poses_follow_the_truth(slam_build, loop_records):
    """The optimized poses against the simulator's truth: mm, and within their SDs."""
    truth = [r for r in loop_records if isinstance(r, TruthRecord)]
    t = np.array([r.t_s for r in truth])
    s = slam_build.slam
    o = slam_build.builder.origin
    tx = np.interp(s.node_t, t, [r.x_m for r in truth]) - o[0]
    ty = np.interp(s.node_t, t, [r.y_m for r in truth]) - o[1]
    err = np.hypot(s.node_pose[:, 0] - tx, s.node_pose[:, 1] - ty)
    dr = np.hypot(s.node_dr[:, 0] - tx, s.node_dr[:, 1] - ty)
    assert np.median(err) < 0.01 and dr.max() > 0.1
    sd = np.sqrt(s.node_cov[:, 0, 0] + s.node_cov[:, 1, 1])
    assert np.mean((err / sd) ** 2) < 3.0


@pytest.mark.slow   # (a second build of the fixture's log: 6 s)
def test_odometry_method_keeps_the_dead_reckoning(loop_log, slam_build):
    """``method="odometry"``: the build of before (its drift in the map)."""
    res = build_from_log(loop_log, method="odometry")
    assert res.method == "odometry" and res.slam is None
    assert "its drift is in the map" in res.summary()
    worst = max(e for _, e in _errors(res, 1.0))
    assert worst > 0.1 > max(e for _, e in _errors(slam_build))


def test_slam_across_an_odometry_reset(loop_records):
    """The odometry restarts at zero mid-drive (flagged ``reset``): no odometry across
    it, only a weak factor; the landmarks tie the two halves together."""
    out, ref = [], None
    for r in loop_records:
        if isinstance(r, OdomRecord) and r.t_s >= 15.0:
            p = np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])
            first = ref is None
            if first:
                ref = p
            q = se2.between(ref, p)
            r = OdomRecord(r.t_s, float(q[0]), float(q[1]), math.degrees(q[2]), reset=first)
        out.append(r)
    res = build_from_log(io.StringIO(_text(out)))
    assert res.odom_resets == 1 and res.method == "slam" and res.slam.ok
    _check_room_features(res)


def test_a_log_without_landmarks_falls_back_with_a_reason(loop_records):
    recs = [TofRecord(r.t_s, r.sensor, None, r.pan_deg) if isinstance(r, TofRecord) else r
            for r in loop_records if r.t_s < 5.0]
    res = build_from_log(io.StringIO(_text(recs)))
    assert res.method == "odometry" and res.slam is not None and not res.slam.ok
    assert "SLAM fell back to the odometry: no landmark fits" in res.summary()
    assert res.geojson()["features"] == []


def test_a_log_without_a_loop_closure_falls_back(loop_records):
    res = build_from_log(io.StringIO(_text([r for r in loop_records if r.t_s < 8.0])))
    assert res.method == "odometry" and not res.slam.ok
    assert "no landmark seen again" in res.slam.reason
    assert "SLAM fell back to the odometry" in res.summary()
    obj = res.geojson()
    map_from_geojson(obj)
    assert not any("sd_rel_m" in f["properties"] for f in obj["features"])
    assert "NaN" not in json.dumps(obj)


def test_method_is_checked():
    with pytest.raises(ValueError, match="`method` must be one of slam, odometry, got 'x'"):
        BuildConfig(method="x")
    with pytest.raises(ValueError, match="`method`"):
        build_from_log(io.StringIO(""), method="fancy")
    with pytest.raises(ValueError, match="`slam_huber` must be positive"):
        SlamConfig(huber=0.0)


def test_cli_builds_with_slam_and_the_map_localizes(run_cli, loop_log, slam_build, tmp_path):
    out = tmp_path / "m.geojson"
    proc = run_cli("map", "build", str(loop_log), "--out", str(out), check=True)
    assert "method: slam" in proc.stderr and "slam: " in proc.stderr
    built = load_map(out)
    assert json.loads(out.read_text())["features"] == \
        json.loads(json.dumps(slam_build.geojson()))["features"]
    proc = run_cli("map", "build", str(loop_log), "--method", "slam", "--poses",
                   str(tmp_path / "p.csv"), "--out", str(tmp_path / "n.geojson"))
    assert proc.returncode == 2 and "--method slam is for a build without --poses" in proc.stderr
    # a second drive (another seed), localized against the built map
    drive = tmp_path / "drive.jsonl"
    recs = list(simulate_records(load_map(ROOM), ring16(), duration_s=10.0, seed=5,
                                 route=LOOP, init_sd_xy_m=0.001, init_sd_yaw_deg=0.05))
    drive.write_text(_text(recs), encoding="utf-8")
    poses = tmp_path / "poses.csv"
    run_cli("localize", str(drive), "--map", str(out), "--out", str(poses), check=True)
    truth = {r.t_s: r for r in iter_log(drive) if isinstance(r, TruthRecord)}
    rows = np.genfromtxt(poses, delimiter=",", names=True)
    err = [math.hypot(r["x_m"] - truth[r["t_s"]].x_m, r["y_m"] - truth[r["t_s"]].y_m)
           for r in rows if r["t_s"] in truth]
    assert len(err) > 100 and np.sqrt(np.mean(np.square(err))) < 0.03
    assert built.features


def _random_graph(rng):
    """A small graph with every factor kind (a point landmark of radius 5 cm)."""
    n = 4
    x_nodes = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n),
                               rng.uniform(-3, 3, n)])
    odo_z = se2.between(x_nodes[:-1], x_nodes[1:]) + rng.normal(0, 0.05, (n - 1, 3))
    cov = np.stack([np.diag(rng.uniform(0.01, 0.1, 3)) for _ in range(n - 1)])
    g = _Graph(np.arange(n, dtype=float), x_nodes.copy(), odo_z, _whitening(cov),
               np.zeros(3), _whitening(np.eye(3) * 0.1), 0.03, 1e9)
    g.n_nodes = n
    g.lm_kind = ["point", "line"]
    g.lm_offset = np.array([3 * n, 3 * n + 3])
    g.p_node, g.p_lm = np.array([0, 2]), np.array([0, 0])
    g.p_z, g.p_view = rng.normal(0, 1, (2, 2)), rng.normal(0, 1, (2, 2))
    g.p_a = _whitening(np.stack([np.eye(2) * 0.01] * 2))
    g.w_node, g.w_lm = np.array([1, 3]), np.array([1, 1])
    g.w_z = np.column_stack([rng.uniform(0.5, 2, 2), rng.uniform(-3, 3, 2)])
    g.w_a = _whitening(np.stack([np.diag([0.01, 0.02])] * 2))
    x = np.concatenate([x_nodes.reshape(-1), [0.3, -0.2, 0.05], [1.5, 0.7]])
    return g, x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_factor_jacobians_match_finite_differences(seed):
    g, x = _random_graph(np.random.default_rng(seed))
    r, jac, _, _ = g.linearize(x)
    num = np.zeros(jac.shape)
    h = 1e-6
    for k in range(len(x)):
        dx = np.zeros(len(x))
        dx[k] = h
        rp, _, _, _ = g.linearize(x + dx, jacobian=False)
        rm, _, _, _ = g.linearize(x - dx, jacobian=False)
        num[:, k] = (rp - rm) / (2 * h)
    np.testing.assert_allclose(jac.toarray(), num, atol=1e-5)


def test_rigid_alignment_undoes_a_map_frame_error():
    """`maps.compare.rigid_alignment`: a map moved as a whole (the init prior's error)
    is put back, a ghost point among its features left out of the fit; its shape error
    is then what is left."""
    from sonarloc.localize.features import FeatureMap
    from sonarloc.maps.build import BuiltFeature

    true = FeatureMap.from_map(load_map(ROOM))
    shift = np.array([0.04, -0.03, math.radians(1.5)])
    feats = [BuiltFeature("pole", se2.transform_points(shift, p), 0.5, 0.01, 5)
             for p in true.point_xy]
    feats.append(BuiltFeature("wall", se2.transform_points(shift, np.array([[1.0, 0.0],
                                                                           [6.0, 0.0]])),
                              0.1, 0.01, 5))
    assert max(e for _, e in compare.feature_errors(feats, load_map(ROOM), 0.5)) > 0.05
    ghost = BuiltFeature("corner", np.array([7.99, 0.886]), 0.15, 0.2, 5)  # 0.9 m off
    motion = compare.rigid_alignment([*feats, ghost], load_map(ROOM), 1.5)
    np.testing.assert_allclose(se2.compose(motion, shift), np.zeros(3), atol=1e-9)
    back = compare.moved(feats, motion)
    assert max(e for _, e in compare.feature_errors(back, load_map(ROOM), 0.5)) < 1e-9
    assert np.array_equal(compare.rigid_alignment(feats[:1], load_map(ROOM), 0.5), np.zeros(3))


def test_pose_marginals_sparse_path_agrees_with_the_dense_inverse(monkeypatch):
    """Large graphs take their pose marginals from sparse LU solves (a subset of nodes,
    interpolated between): the same numbers as the dense inverse where both solve."""
    from sonarloc.maps import slam

    g, x = _random_graph(np.random.default_rng(4))
    _, jac, _, _ = g.linearize(x)
    args = (slam._rigid_generators(x, g), slam._alignment_rows(g))
    dense, dense_rel = slam._pose_marginals(jac, g.n_nodes, 400, g.node_t, *args)
    monkeypatch.setattr(slam, "_DENSE_MARGINALS", 0)
    sparse, sparse_rel = slam._pose_marginals(jac, g.n_nodes, 400, g.node_t, *args)
    np.testing.assert_allclose(sparse, dense, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(sparse_rel, dense_rel, rtol=1e-8, atol=1e-12)
    # nodes 0 and 3, interpolated
    few, few_rel = slam._pose_marginals(jac, g.n_nodes, 2, g.node_t, *args)
    np.testing.assert_allclose(few[[0, 3]], dense[[0, 3]], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(few[1], (2 * dense[0] + dense[3]) / 3, rtol=1e-8, atol=1e-12)
    # the frame-relative ones solved at those nodes too, and interpolated (not taken
    # from the interpolated marginals: their error would swamp them)
    np.testing.assert_allclose(few_rel[[0, 3]], dense_rel[[0, 3]], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(few_rel[2], (dense_rel[0] + 2 * dense_rel[3]) / 3, rtol=1e-8,
                               atol=1e-12)


@pytest.mark.parametrize("kind", ["point", "line"])
def test_transform_with_cov_carries_the_covariance(kind, rng):
    """`slam.transform_with_cov`: the mean as `se2.transform_points` / `transform_line`
    (rho >= 0, the normal flipped where rho would turn negative), the covariance through
    the Jacobian of exactly that (checked by finite differences, both sides of a flip)."""
    from sonarloc.maps.slam import transform_with_cov

    for _ in range(20):
        pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi)])
        z = np.array([rng.uniform(0.2, 3.0), rng.uniform(-np.pi, np.pi)])
        a = rng.normal(size=(2, 2))
        cov = a @ a.T + 0.1 * np.eye(2)
        out, out_cov = transform_with_cov(kind, pose, z, cov)
        f = (lambda v, p=pose: se2.transform_points(p, v)) if kind == "point" else \
            (lambda v, p=pose: se2.transform_line(p, v))
        np.testing.assert_allclose(out, f(z))
        jac = np.zeros((2, 2))
        for k in range(2):
            dz = np.zeros(2)
            dz[k] = 1e-6
            d = f(z + dz) - f(z - dz)
            d[1] = se2.wrap_angle(d[1]) if kind == "line" else d[1]
            jac[:, k] = d / 2e-6
        np.testing.assert_allclose(out_cov, jac @ cov @ jac.T, rtol=1e-5, atol=1e-7)


def test_frame_relative_marginals_take_out_the_map_frame_s_error():
    """`_pose_marginals`' second result: the nodes' covariances less the rigid motion a
    weighted fit of the landmarks finds (P H⁻¹ Pᵀ, written out densely here), the same
    whatever the prior on node 0 says (the map frame's error); without landmarks to fit,
    conditioned on node 0 (its own covariance zero)."""
    from sonarloc.maps import slam

    for seed in range(3):
        g, x = _random_graph(np.random.default_rng(seed))
        _, jac, _, _ = g.linearize(x)
        gen, pairs = slam._rigid_generators(x, g), slam._alignment_rows(g)
        assert pairs.tolist() == [[12, 13], [15, 16]]   # the point's centre, the wall's line
        cov, rel = slam._pose_marginals(jac, g.n_nodes, 400, g.node_t, gen, pairs)
        sigma = np.linalg.inv((jac.T @ jac).toarray())
        p0 = np.eye(len(x)) - gen @ np.linalg.solve(gen[:3], np.eye(len(x))[:3])
        rel0 = p0 @ sigma @ p0.T
        w = np.zeros_like(sigma)
        for p in pairs:
            w[np.ix_(p, p)] = np.linalg.inv(rel0[np.ix_(p, p)])
        proj = np.eye(len(x)) - gen @ np.linalg.solve(gen.T @ w @ gen, gen.T @ w)
        want = proj @ sigma @ proj.T
        for i in range(g.n_nodes):
            np.testing.assert_allclose(rel[i], want[3 * i:3 * i + 3, 3 * i:3 * i + 3],
                                       atol=1e-12)
            np.testing.assert_allclose(cov[i], sigma[3 * i:3 * i + 3, 3 * i:3 * i + 3],
                                       atol=1e-12)
        # a prior 50 times wider: the marginals grow, the frame-relative ones stay
        g.prior_a = _whitening(np.eye(3) * 5.0)
        _, jac_w, _, _ = g.linearize(x)
        cov_w, rel_w = slam._pose_marginals(jac_w, g.n_nodes, 400, g.node_t, gen, pairs)
        assert np.all(np.trace(cov_w, axis1=1, axis2=2) > 10 * np.trace(cov, axis1=1, axis2=2))
        np.testing.assert_allclose(rel_w, rel, atol=1e-12)
        # nothing to fit: conditioned on node 0
        _, rel_0 = slam._pose_marginals(jac, g.n_nodes, 400, g.node_t, gen,
                                        np.zeros((0, 2), np.int64))
        np.testing.assert_allclose(rel_0[0], np.zeros((3, 3)), atol=1e-12)
        np.testing.assert_allclose(rel_0[1:], np.stack(
            [rel0[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(1, g.n_nodes)]), atol=1e-12)


def test_slam_build_writes_the_frame_relative_sd(slam_build):
    """Every feature of a SLAM build carries ``sd_rel_m`` (GeoJSON too): finite,
    positive, and covering the feature's error after the map's best rigid alignment
    onto the true one (the loop's init is exact here: little frame error to take out)."""
    s = slam_build.slam
    assert s.node_cov_rel.shape == s.node_cov.shape
    assert np.all(np.linalg.eigvalsh(s.node_cov_rel)[:, 1:] > 0)
    feats = slam_build.builder.features()
    assert all(math.isfinite(f.sd_rel_m) and f.sd_rel_m > 0 for f in feats)
    props = [f["properties"] for f in slam_build.geojson()["features"]]
    assert all("sd_rel_m" in p and "sd_m" in p for p in props)
    world = load_map(ROOM)
    moved = compare.moved(feats, compare.rigid_alignment(feats, world, 0.5))
    z = np.array([e / f.sd_rel_m for f, e in compare.feature_errors(moved, world, 0.5)])
    assert len(z) >= 9 and z.max() < 3.5 and np.mean(z**2) < 3.0
