"""A robot standing still: each map feature fused once until the robot moves
(``LocalizerConfig.update_min_d`` / ``update_min_a``), the map's error shared by the
readings of one update (``map_sd_m``, the map's ``sd_m``). Fused again and again from
the same pose, readings that share the map's error average it down: the covariance
collapses to micrometres and a map a few millimetres off is then rejected."""

import io
import json
import math

import numpy as np
import pytest

from sonarloc.io.logfile import LogWriter, TruthRecord, iter_log
from sonarloc.localize import ekf
from sonarloc.localize.echoes import EchoObservation, relative_sensor_chain
from sonarloc.localize.ekf import Feature, OdomNoise
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import LocalizerConfig, moved_enough
from sonarloc.localize.replay import replay_log
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"
NEES_999 = 16.27  # chi-square(3) 0.999 quantile
#: each feature of the room moved by 5 mm, in different directions (a built map's error)
SHIFTS = {"room": (0.005, 0.0), "partition": (0.0, -0.005), "pole-a": (0.0035, 0.0035),
          "pole-b": (-0.005, 0.0), "pole-c": (0.0, 0.005), "rod-a": (-0.0035, 0.0035),
          "rod-b": (0.0, -0.005)}


def _still_log(duration_s):
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=duration_s,
                                     at=(3.0, 1.5, 20.0), seed=3))
    return buf.getvalue()


@pytest.fixture(scope="module")
def still_log():
    return _still_log(10.0)


def _shifted_geojson(sd_m=None, sd_rel_m=None):
    with open(ROOM, encoding="utf-8") as f:
        d = json.load(f)

    def move(c, s):
        return [c[0] + s[0], c[1] + s[1]] if isinstance(c[0], (int, float)) else \
            [move(x, s) for x in c]

    for feat in d["features"]:
        s = SHIFTS.get(feat["properties"].get("id"))
        if s is not None:
            feat["geometry"]["coordinates"] = move(feat["geometry"]["coordinates"], s)
            if sd_m is not None:
                feat["properties"]["sd_m"] = sd_m
            if sd_rel_m is not None:
                feat["properties"]["sd_rel_m"] = sd_rel_m
    return d


def _shifted_map(sd_m=None, sd_rel_m=None):
    return FeatureMap.from_map(map_from_geojson(_shifted_geojson(sd_m, sd_rel_m)))


def _replay(text, fmap, mode, **cfg):
    truth = {r.t_s: np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])
             for r in iter_log(io.StringIO(text)) if isinstance(r, TruthRecord)}
    rows = []
    res = replay_log(io.StringIO(text), fmap, config=LocalizerConfig(**cfg), mode=mode,
                     on_estimate=lambda r, e: rows.append((r.t_s, e)))
    t, est = rows[-1]
    return res.localizer.stats, est, float(ekf.nees(est.state, truth[t]))


def _sd_m(est):
    return math.sqrt(max(est.state.cov[0, 0], est.state.cov[1, 1]))


def test_a_still_robot_fuses_each_feature_once(still_log):
    """10 s standing still in the room (ring16, 1300 readings): a dozen updates, the
    rest skipped and counted; the position SD stays at the readings' worth (0.22 mm, not
    the 0.05 mm of 160 updates of the same features), consistent with the truth, and
    the status says tracking although nothing was fused for 9 s (the skipped readings
    agree with the map)."""
    stats, est, nees = _replay(still_log, FeatureMap.from_map(load_map(ROOM)), "batch")
    assert stats.accepted <= 20
    assert stats.skipped["no_motion_since_fused"] > 100
    assert stats.observations == stats.accepted + stats.skipped["no_motion_since_fused"] \
        + stats.outcomes["echo_unmatched"]
    assert _sd_m(est) > 1e-4
    assert nees < NEES_999
    assert est.status == "tracking"


def test_a_still_robot_on_a_map_5_mm_off(still_log):
    """The room's features moved by 5 mm each, their ``sd_m`` saying so: the filter
    stays consistent (NEES 3.7; 9600 fusing every segment) and keeps associating the
    readings (2 of 163 segments unmatched; 48 when fused every time, the belief sure to
    0.06 mm)."""
    stats, est, nees = _replay(still_log, _shifted_map(0.005), "batch")
    assert nees < NEES_999
    assert stats.outcomes["echo_unmatched"] <= 0.05 * stats.observations
    assert _sd_m(est) > 1e-3
    assert est.status == "tracking"


def test_map_sd_m_is_the_floor_of_the_map_s_own():
    """``map_sd_m`` stands in for a map without ``sd_m`` and is a floor under one."""
    from sonarloc.localize.localizer import Localizer

    plain, with_sd = FeatureMap.from_map(load_map(ROOM)), _shifted_map(0.004)
    assert np.all(np.isnan(plain.wall_sd_m)) and np.all(np.isnan(plain.point_sd_m))
    assert np.all(with_sd.wall_sd_m == 0.004) and np.all(with_sd.point_sd_m == 0.004)
    assert Localizer(plain).map_var_m2("wall", 0) == 0.0
    assert Localizer(plain, LocalizerConfig(map_sd_m=0.003)).map_var_m2("point", 1) == \
        pytest.approx(0.003**2)
    assert Localizer(with_sd, LocalizerConfig(map_sd_m=0.003)).map_var_m2("wall", 2) == \
        pytest.approx(0.004**2)
    assert Localizer(with_sd, LocalizerConfig(map_sd_m=0.006)).map_var_all() == \
        pytest.approx(np.full(with_sd.n_points + with_sd.n_walls, 0.006**2))


def test_the_frame_relative_sd_is_the_map_error_where_given():
    """A map's ``sd_rel_m`` (its features' SD relative to the map frame, which ``map
    build`` writes next to ``sd_m``) is the map error of their readings where given,
    ``sd_m`` elsewhere: a map stating 0.2 m of frame error in ``sd_m`` and 5 mm in
    ``sd_rel_m`` localizes exactly as the map stating 5 mm in ``sd_m`` alone, and a map
    without ``sd_rel_m`` as before."""
    both = _shifted_map(0.2, 0.005)
    assert np.all(both.point_sd_m == 0.005) and np.all(both.wall_sd_m == 0.005)
    d = _shifted_geojson(0.2)
    for feat in d["features"]:
        if feat["properties"].get("id") == "pole-a":
            feat["properties"]["sd_rel_m"] = 0.005
    mixed = FeatureMap.from_map(map_from_geojson(d))
    i = mixed.point_id.index("pole-a")
    assert mixed.point_sd_m[i] == 0.005
    assert np.all(np.delete(mixed.point_sd_m, i) == 0.2) and np.all(mixed.wall_sd_m == 0.2)
    text = _still_log(3.0)
    _, e_rel, _ = _replay(text, both, "batch")
    _, e_sd, _ = _replay(text, _shifted_map(0.005), "batch")
    _, e_whole, _ = _replay(text, _shifted_map(0.2), "batch")
    np.testing.assert_array_equal(e_rel.state.mean, e_sd.state.mean)
    np.testing.assert_array_equal(e_rel.state.cov, e_sd.state.cov)
    assert not np.array_equal(e_whole.state.cov, e_sd.state.cov)
    assert _sd_m(e_whole) > 2 * _sd_m(e_sd)


@pytest.mark.parametrize("memory_s", [0.0, 10.0])
def test_online_and_batch_agree_standing_still(memory_s):
    """The live Localizer and the batch replay skip alike and end at the same belief
    (also with the map variance grown by each feature's fusions)."""
    text = _still_log(3.0)
    fmap = _shifted_map(0.005)
    a, ea, _ = _replay(text, fmap, "batch", map_error_memory_s=memory_s)
    b, eb, _ = _replay(text, fmap, "online", map_error_memory_s=memory_s)
    assert a.accepted == b.accepted
    assert a.skipped["no_motion_since_fused"] == b.skipped["no_motion_since_fused"] > 20
    assert np.allclose(ea.state.mean[:2], eb.state.mean[:2], atol=2e-4)
    assert _sd_m(ea) == pytest.approx(_sd_m(eb), rel=0.05)


@pytest.mark.parametrize("method", ["conventional", "specular"])
def test_the_conventional_filter_standing_still(method):
    """Every reading a range update, 700 of them in 5 s from one pose: fused once per
    wall, pole or rod, the belief stays honest (NEES 80 and 27 at 10 s when each is
    fused)."""
    stats, est, nees = _replay(_still_log(5.0), FeatureMap.from_map(load_map(ROOM)),
                               "online", method=method)
    assert stats.skipped["no_motion_since_fused"] > 300
    assert nees < NEES_999
    assert _sd_m(est) > 1e-3
    assert est.status == "tracking"


def test_a_feature_s_map_error_is_not_averaged_down(still_log):
    """Standing still with the limits off (every segment fused, 160 updates of the same
    features) on the map 5 mm off, its ``sd_m`` saying so: a feature's map error is one
    constant, its variance grown by the feature's recent fusions
    (``map_error_memory_s``), and the belief stays consistent with the truth (NEES 4;
    21 with the map error taken anew by each update, the position SD 0.6 mm)."""
    off = {"update_min_d": 0.0, "update_min_a": 0.0}
    stats, est, nees = _replay(still_log, _shifted_map(0.005), "batch",
                               map_error_memory_s=10.0, **off)
    assert stats.accepted > 150
    assert nees < NEES_999
    assert _sd_m(est) > 1e-3
    _, est0, nees0 = _replay(still_log, _shifted_map(0.005), "batch", **off)
    assert nees0 > NEES_999
    assert _sd_m(est0) < 0.7 * _sd_m(est)


def test_map_uses_count_a_feature_s_recent_fusions():
    """Each fusion counts exp(-age / ``map_error_memory_s``); the variance an update
    takes is the map's times one plus that; none without a map error."""
    from sonarloc.localize.localizer import Localizer

    loc = Localizer(_shifted_map(0.004), LocalizerConfig(map_error_memory_s=10.0))
    for t in (1.0, 2.0, 3.0):
        loc.note_fused("wall", 1, (0.0, 0.0, 0.0), t)
    want = math.exp(-0.2) + math.exp(-0.1) + 1.0
    assert loc.map_uses("wall", 1, 3.0) == pytest.approx(want)
    assert loc.map_uses("wall", 1, 13.0) == pytest.approx(want * math.exp(-1.0))
    assert loc.map_uses("wall", 0, 3.0) == 0.0 and loc.map_uses("point", 1, 3.0) == 0.0
    assert loc.map_var_m2("wall", 1, 13.0) == pytest.approx(0.004**2 * (1 + want / math.e))
    assert loc.map_var_m2("wall", 1) == pytest.approx(0.004**2)
    k = loc.fmap.n_points + 1
    assert loc.map_var_all(3.0)[k] == pytest.approx(0.004**2 * (1 + want))
    plain = Localizer(FeatureMap.from_map(load_map(ROOM)),
                      LocalizerConfig(map_error_memory_s=10.0))
    plain.note_fused("wall", 1, (0.0, 0.0, 0.0), 1.0)
    assert plain.map_uses("wall", 1, 1.0) == 0.0 and plain.map_var_m2("wall", 1, 1.0) == 0.0
    off = Localizer(_shifted_map(0.004), LocalizerConfig(map_error_memory_s=0.0))
    off.note_fused("wall", 1, (0.0, 0.0, 0.0), 1.0)
    assert off.map_var_m2("wall", 1, 1.0) == pytest.approx(0.004**2)


def test_a_map_without_sd_localizes_as_before():
    """No map error (no ``sd_m``, ``map_sd_m`` 0): ``map_error_memory_s`` changes
    nothing, to the bit (a moving drive, batch)."""
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=20.0, seed=4))
    fmap = FeatureMap.from_map(load_map(ROOM))
    _, ea, _ = _replay(buf.getvalue(), fmap, "batch")
    _, eb, _ = _replay(buf.getvalue(), fmap, "batch", map_error_memory_s=10.0)
    np.testing.assert_array_equal(ea.state.mean, eb.state.mean)
    np.testing.assert_array_equal(ea.state.cov, eb.state.cov)


def test_limits_off_fuse_every_segment(still_log):
    """``update_min_d = update_min_a = 0``: every segment fused (the old behaviour)."""
    stats, est, _ = _replay(still_log, FeatureMap.from_map(load_map(ROOM)), "batch",
                            update_min_d=0.0, update_min_a=0.0)
    assert "no_motion_since_fused" not in stats.skipped
    assert stats.accepted > 150
    assert _sd_m(est) < 1e-4


def test_moved_enough():
    d, a = 0.05, math.radians(5.0)
    assert not moved_enough((1.0, 2.0, 0.3), (1.03, 2.03, 0.3), d, a)
    assert moved_enough((1.0, 2.0, 0.3), (1.04, 2.031, 0.3), d, a)
    assert moved_enough((1.0, 2.0, 0.3), (1.0, 2.0, 0.3 + math.radians(5.01)), d, a)
    # the short way round at ±180 deg
    assert not moved_enough((0.0, 0.0, math.pi - 0.01), (0.0, 0.0, -math.pi + 0.01), d, a)
    assert moved_enough((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 0.0)


@pytest.mark.parametrize("name", ["update_min_d", "update_min_a", "map_sd_m",
                                  "map_error_memory_s"])
@pytest.mark.parametrize("value", [-0.01, math.nan, math.inf])
def test_config_checks(name, value):
    with pytest.raises(ValueError, match=f"`{name}` must be non-negative"):
        LocalizerConfig(**{name: value})
    LocalizerConfig(**{name: 0.0})


def test_feature_map_checks_sd_m():
    with pytest.raises(ValueError, match="sd_m"):
        FeatureMap.build([[1.0, 1.0]], wall_sd_m=[], point_sd_m=[-0.001])
    fm = FeatureMap.build([[1.0, 1.0]], [[[0, 0], [1, 0]]], point_sd_m=[0.002])
    assert fm.sd_m("point", 0) == 0.002 and math.isnan(fm.sd_m("wall", 0))


def test_map_error_is_shared_by_the_readings():
    """``map_var_m2`` adds the same variance to every element of R (a common offset)."""
    rng = np.random.default_rng(0)
    n = 6
    base = np.zeros(3)
    sens = np.column_stack([np.full(n, 0.2), np.zeros(n), np.linspace(-0.05, 0.05, n)])
    rel, p_fac, v_fac = relative_sensor_chain(base, np.zeros((n, 3)), sens,
                                              OdomNoise())
    wall = Feature("wall", np.array([2.0, 0.0]))
    z = 1.8 + rng.normal(0, 1e-3, n)
    pose = np.array([0.0, 0.0, 0.0])
    a = EchoObservation(z, rel, p_fac, v_fac, 0.15, wall, 0.0)
    b = EchoObservation(z, rel, p_fac, v_fac, 0.15, wall, 0.0, map_var_m2=0.004**2)
    ha, hxa, ra = a.measure(pose)
    hb, hxb, rb = b.measure(pose)
    assert np.array_equal(ha, hb) and np.array_equal(hxa, hxb)
    assert np.allclose(rb - ra, 0.004**2, rtol=1e-9, atol=0)
    assert len(b.subset(np.arange(n) < 3).measure(pose)[2]) == 3
    assert b.subset(np.arange(n) < 3).map_var_m2 == b.map_var_m2


def test_the_kept_poses_apply_moved_enough_to_each():
    """The vectorised test of the poses a feature was fused from is
    :func:`moved_enough` applied to each (ring buffer: the last ones kept)."""
    from sonarloc.localize.localizer import FUSED_POSES_KEPT, _FusedPoses

    rng = np.random.default_rng(5)
    kept = _FusedPoses()
    poses = []
    for _ in range(FUSED_POSES_KEPT + 40):
        p = [float(v) for v in rng.uniform([-0.1, -0.1, -math.pi], [0.1, 0.1, math.pi])]
        kept.add(p)
        poses.append(p)
        q = [float(v) for v in rng.uniform([-0.1, -0.1, -math.pi], [0.1, 0.1, math.pi])]
        for d, a in ((0.05, 0.5), (0.02, math.radians(1.0)), (0.0, 0.0), (1.0, 7.0)):
            want = not all(moved_enough(p0, q, d, a) for p0 in poses[-FUSED_POSES_KEPT:])
            assert kept.near(q, d, a) == want


def test_the_node_reports_skipped_landmarks_as_matched_not_fused():
    """`LocalizerNode.landmarks()` says why a still robot's segment was not fused (the
    drive figure draws those as matched to the map, not as unmatched)."""
    from sonarloc.api import LocalizerNode
    from sonarloc.localize.localizer import NO_MOTION_REASON

    node = LocalizerNode(FeatureMap.from_map(load_map(ROOM)))
    for rec in iter_log(io.StringIO(_still_log(2.0))):
        node.feed(rec)
    node.finish()
    reports = node.landmarks()
    skipped = [r for r in reports if r.outcome == NO_MOTION_REASON]
    assert skipped and not any(r.fused for r in skipped)
    assert len(skipped) == node.stats.skipped["no_motion_since_fused"]
    assert any(r.fused for r in reports)


def test_localize_map_sd_flag(run_cli, still_log, tmp_path):
    """`sonarloc localize --map-sd M`: a map measured to 5 mm, its file without ``sd_m``
    (a hand-made map): taken as exact, the still robot's belief is sure of itself to a
    fraction of a millimetre and inconsistent with the truth; with ``--map-sd 0.005`` it
    is consistent. A bad value names the flag."""
    from sonarloc.io.posescsv import read_poses_csv

    log, map_path = tmp_path / "still.jsonl", tmp_path / "off.geojson"
    log.write_text(still_log)
    map_path.write_text(json.dumps(_shifted_geojson()))
    truth = [r for r in iter_log(io.StringIO(still_log)) if isinstance(r, TruthRecord)][-1]
    truth_pose = np.array([truth.x_m, truth.y_m, math.radians(truth.yaw_deg)])

    def final_nees(*flags):
        out = tmp_path / f"poses{len(flags)}.csv"
        run_cli("localize", str(log), "--map", str(map_path), "--out", str(out), *flags,
                check=True)
        track = read_poses_csv(out)
        last = ekf.Gaussian(np.array([track.x_m[-1], track.y_m[-1], track.yaw_rad[-1]]),
                            track.cov[-1])
        return float(ekf.nees(last, truth_pose))

    assert final_nees() > 3 * NEES_999
    with_sd = final_nees("--map-sd", "0.005")
    assert with_sd < NEES_999
    # the map error as one constant per feature: the option reaches the Localizer
    with_memory = final_nees("--map-sd", "0.005", "--map-error-memory", "10")
    assert with_memory < NEES_999 and with_memory != with_sd
    proc = run_cli("localize", str(log), "--map", str(map_path), "--map-sd", "-1")
    assert proc.returncode == 2 and "--map-sd" in proc.stderr and "map_sd_m" in proc.stderr
    proc = run_cli("localize", str(log), "--map", str(map_path), "--map-error-memory", "nan")
    assert proc.returncode == 2 and "--map-error-memory" in proc.stderr
