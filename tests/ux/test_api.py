"""sonarloc.api.LocalizerNode: the embedding API, with explicit calls as a node makes them."""

from __future__ import annotations

import doctest
import math
import os
from pathlib import Path

import numpy as np
import pytest

import sonarloc.api
from sonarloc.api import LocalizerNode
from sonarloc.io.logfile import InitRecord, OdomRecord, RigRecord, TofRecord, TruthRecord
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

REPO = Path(__file__).resolve().parents[2]
ROOM = REPO / "maps" / "room.geojson"


def test_module_doctest():
    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        res = doctest.testmod(sonarloc.api)
    finally:
        os.chdir(cwd)
    assert res.attempted >= 5 and res.failed == 0


def test_node_tracks_a_simulated_drive():
    rig = ring16()
    node = LocalizerNode.from_map_file(ROOM, [(s.id, s.x_m, s.y_m, s.yaw_deg)
                                              for s in rig.sensors])
    assert node.status == "initializing"
    with pytest.raises(RuntimeError, match="no estimate yet"):
        _ = node.pose
    errs = []
    for rec in simulate_records(load_map(ROOM), rig, duration_s=12.0, seed=4):
        if isinstance(rec, RigRecord):
            node.set_rig(rec.sensors, rec.speed_of_sound_mps)
        elif isinstance(rec, InitRecord):
            node.set_pose(rec.x_m, rec.y_m, math.radians(rec.yaw_deg), sd_xy_m=rec.sd_xy_m,
                          sd_yaw_rad=math.radians(rec.sd_yaw_deg))
        elif isinstance(rec, TofRecord):
            node.reading(rec.t_s, rec.sensor, rec.tof_us)
        elif isinstance(rec, OdomRecord):
            est = node.odometry(rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg))
            assert est is not None and est.t_s == rec.t_s
        elif isinstance(rec, TruthRecord):
            x, y, _ = node.pose
            errs.append(math.hypot(x - rec.x_m, y - rec.y_m))
    node.finish()
    assert np.mean(errs[-60:]) < 0.05  # last 3 s within 5 cm on average
    cov = node.covariance
    assert cov.shape == (3, 3) and np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # map->odom composes the odometry pose into the map pose
    mx, my, myaw = node.map_to_odom
    est = node.estimate
    assert est is not None
    ox, oy, oyaw = est.odom_pose
    x = mx + math.cos(myaw) * ox - math.sin(myaw) * oy
    y = my + math.sin(myaw) * ox + math.cos(myaw) * oy
    assert (x, y) == pytest.approx(node.pose[:2], abs=1e-9)
    reports = node.landmarks()
    assert any(r.fused for r in reports) and node.stats.accepted == sum(r.fused for r in reports)
    fused = [r for r in reports if r.fused]
    assert all(r.in_map is not None and r.outcome == "fused" for r in fused)
    late = node.landmarks(since_t_s=6.0)
    assert late and all(r.landmark.ref_t_s >= 6.0 for r in late)
    assert node.status in ("tracking", "dead_reckoning")


def test_node_bad_arguments():
    from sonarloc.localize.features import FeatureMap

    fmap = FeatureMap.from_map(load_map(ROOM))
    with pytest.raises(ValueError, match="sensor must be"):
        LocalizerNode(fmap, [(0, 0.1, 0.0)])
    with pytest.raises(ValueError, match="sensor id"):
        LocalizerNode(fmap, [(0.5, 0.1, 0.0, 0.0)])
    node = LocalizerNode(fmap, [(0, 0.1, 0.0, 0.0)])
    with pytest.raises(ValueError, match="sd_xy_m"):
        node.set_pose(0, 0, 0, sd_xy_m=-1)
    assert node.odometry(0.0, 0, 0, 0) is None  # no prior yet: no estimate
    assert node.reason.startswith("no prior")


def test_no_estimate_says_why_and_what_brings_one():
    # A node configured to relocalize needs no set_pose(): before its first fix, reading
    # the pose says it is relocalizing and why it has no fix, not "call set_pose()".
    from sonarloc.localize.localizer import LocalizerConfig

    rig = ring16()
    node = LocalizerNode.from_map_file(ROOM, [(s.id, s.x_m, s.y_m, s.yaw_deg)
                                              for s in rig.sensors],
                                       config=LocalizerConfig(relocalize=True))
    for rec in simulate_records(load_map(ROOM), rig, duration_s=1.5, seed=4):
        if not isinstance(rec, InitRecord):  # no prior: relocalization must find the pose
            node.feed(rec)
    assert node.estimate is None and node.reason.startswith("relocalizing: ")
    with pytest.raises(RuntimeError) as err:
        _ = node.pose
    assert node.reason in str(err.value) and "relocalization" in str(err.value)
    assert "set_pose() and odometry() first" not in str(err.value)
    plain = LocalizerNode.from_map_file(ROOM, [(0, 0.2, 0.0, 0.0)])  # without: a prior is due
    with pytest.raises(RuntimeError, match=r"no estimate yet \(no prior.*set_pose\(\) and"):
        _ = plain.covariance


# -- what a real robot feeds it: stale, garbage and wrongly typed messages -------------


def _drive(duration_s: float = 6.0, seed: int = 4) -> tuple[list, list]:
    """The mounts and the records of a simulated drive with the 16-ring."""
    rig = ring16()
    mounts = [(s.id, s.x_m, s.y_m, s.yaw_deg) for s in rig.sensors]
    return mounts, list(simulate_records(load_map(ROOM), rig, duration_s=duration_s,
                                         seed=seed))


def _run(mounts, records, extra=lambda node, rec: None, method: str = "kuc"):
    """Feed ``records`` to a fresh node, calling ``extra(node, rec)`` after each (the
    faults a robot adds); the estimate after every good odom record and the node."""
    from sonarloc.localize.localizer import LocalizerConfig

    node = LocalizerNode.from_map_file(ROOM, mounts, config=LocalizerConfig(method=method))
    out = []
    for rec in records:
        est = node.feed(rec)
        if isinstance(rec, OdomRecord):
            assert est is not None
            out.append((est.t_s, est.state.mean.tolist(), est.state.cov.tolist()))
        extra(node, rec)
    node.finish()
    return out, node


def test_stale_odometry_is_skipped_counted_and_changes_nothing():
    """An odometry message older than the last (delivered late) is skipped: the node
    returns its current estimate, counts it, and every later estimate is exactly that of
    the stream without it. (Taken as the newest pose it moved the belief back and forth,
    grew the covariance and mislocated the readings in between.)"""
    mounts, records = _drive()
    clean, _ = _run(mounts, records)
    odoms = [r for r in records if isinstance(r, OdomRecord)]
    stale = 0

    def late(node, rec):
        nonlocal stale
        if isinstance(rec, OdomRecord) and odoms.index(rec) % 10 == 9:
            old = odoms[odoms.index(rec) - 4]
            before = node.estimate
            assert node.odometry(old.t_s, old.x_m, old.y_m, math.radians(old.yaw_deg)) \
                is before
            stale += 1

    faulty, node = _run(mounts, records, late)
    assert stale > 5 and node.stats.skipped["odom_time_backwards"] == stale
    assert faulty == clean
    assert "odom_time_backwards" in node.stats.summary()


@pytest.mark.parametrize("method", ["kuc", "conventional"])
def test_a_corrupted_odometry_pose_is_skipped_and_never_reported_good(method):
    """An odometry message with an absurd pose (1e200 m: a corrupted frame) between two
    good ones is skipped and counted (``bad_odom``): every later estimate is exactly that
    of the stream without it. (It was taken: the covariance stayed NaN/inf for the rest
    of the drive, the pose at times -1e184 m, and the status said ``tracking``.)"""
    mounts, records = _drive(3.0)
    clean, _ = _run(mounts, records, method=method)
    odoms = [r for r in records if isinstance(r, OdomRecord)]
    bad = 0

    def corrupt(node, rec):
        nonlocal bad
        k = odoms.index(rec) if isinstance(rec, OdomRecord) else -1
        if 0 <= k < len(odoms) - 1 and k % 20 == 10:
            t = 0.5 * (rec.t_s + odoms[k + 1].t_s)
            for pose in ((rec.x_m, 1e200, 0.3), (1e200, -1e200, 0.0)):
                est = node.odometry(t, *pose)
                assert est is node.estimate and est.status != "lost"
                assert np.all(np.isfinite(est.state.cov))
                bad += 1

    faulty, node = _run(mounts, records, corrupt, method=method)
    assert bad >= 4 and node.stats.skipped["bad_odom"] == bad
    assert faulty == clean


def test_a_non_finite_belief_is_reported_lost():
    """Whatever makes the belief non-finite, the status says ``lost`` (it said
    ``tracking`` when the x variance was NaN: ``max(nan, ...)`` is NaN, and NaN > the
    limit is False)."""
    from sonarloc.localize.ekf import Gaussian

    node = LocalizerNode.from_map_file(ROOM, [(0, 0.2, 0.0, 0.0)])
    node.set_pose(1.0, 1.0, 0.0)
    loc = node.localizer
    est = node.odometry(0.0, 0.0, 0.0, 0.0)
    assert est is not None and est.status == "dead_reckoning"   # nothing fused yet
    for bad in ((0, 0), (1, 1), (2, 2), (0, 2)):
        cov = est.state.cov.copy()
        cov[bad] = math.nan
        assert loc._status(0.0, Gaussian(est.state.mean, cov)) == \
            ("lost", "the estimate is not finite"), bad
    assert loc._status(0.0, Gaussian(np.array([math.inf, 1.0, 0.0]), est.state.cov))[0] \
        == "lost"


def test_a_prior_of_1e150_m_keeps_every_estimate_finite():
    """A prior SD of 1e150 m (finite, accepted) with readings fused: updates whose
    covariance would overflow are reported singular and leave the belief as it was, so
    every estimate is finite (and lost); four were inf/NaN. 1e200 m, whose variance
    overflows, is refused naming the argument (was OverflowError)."""
    node = LocalizerNode.from_map_file(ROOM, [(k, 0.2 * math.cos(k), 0.2 * math.sin(k),
                                                math.degrees(k)) for k in range(4)])
    with pytest.raises(ValueError, match="`sd_xy_m`"):
        node.set_pose(1.0, 1.0, 0.0, sd_xy_m=1e200)
    node.set_pose(1.0, 1.0, 0.0, sd_xy_m=1e150)
    for i in range(40):
        est = node.odometry(0.05 * i, 0.01 * i, 0.0, 0.0)
        assert np.isfinite(est.state.cov).all() and np.isfinite(est.state.mean).all(), i
        assert est.status == "lost"
        for k in range(4):
            node.reading(0.05 * i + 0.01, k, 5000.0 + 100 * k)
    assert node.stats.accepted > 0


@pytest.mark.parametrize("method", ["kuc", "conventional"])
def test_garbage_readings_are_skipped_counted_and_change_nothing(method):
    """Negative, zero and infinite TOFs, NaN or infinite times and pan angles, unknown
    sensors: each skipped and counted in ``stats.skipped``, every good reading still
    used (the estimates are exactly those of the clean stream)."""
    mounts, records = _drive()
    clean, ref = _run(mounts, records, method=method)
    bad = [(0, -4000.0, None), (0, 0.0, None), (0, math.inf, None), (0, -math.inf, None),
           (0, 9000.0, math.nan), (0, 9000.0, math.inf)]

    def garbage(node, rec):
        if isinstance(rec, TofRecord) and rec.sensor == 3:
            for sensor, tof, pan in bad:
                node.reading(rec.t_s, sensor, tof, pan_rad=pan)
            node.reading(math.nan, 0, 9000.0)
            node.reading(math.inf, 0, 9000.0)
            node.reading(rec.t_s, 99, 9000.0)      # a sensor not in the rig

    faulty, node = _run(mounts, records, garbage, method=method)
    n = sum(isinstance(r, TofRecord) and r.sensor == 3 for r in records)
    assert n > 10
    assert node.stats.skipped["bad_tof"] == 8 * n
    assert node.stats.skipped["unknown_sensor"] == n
    assert node.stats.tof == ref.stats.tof + 9 * n      # counted as received
    assert faulty == clean
    assert node.stats.accepted == ref.stats.accepted > 0


def test_readings_out_of_order_still_arrive():
    """Readings that come just after a later one (two drivers, two queues) are used in
    time order while they wait for odometry: the estimates are exactly those of the
    ordered stream. One that comes after odometry and later readings were processed is
    skipped and counted (``tof_out_of_order``: the segmenter takes readings in time
    order)."""
    mounts, records = _drive()
    clean, _ = _run(mounts, records)
    swapped = list(records)
    n = 0
    for i in range(len(swapped) - 1):
        a, b = swapped[i], swapped[i + 1]
        if isinstance(a, TofRecord) and isinstance(b, TofRecord) and a.t_s < b.t_s \
                and i % 3 == 0:
            swapped[i], swapped[i + 1] = b, a
            n += 1
    assert n > 10
    out, node = _run(mounts, swapped)
    assert out == clean and not node.stats.skipped.get("tof_out_of_order")
    late = [rec for rec in records if isinstance(rec, TofRecord)][40]

    def very_late(node, rec):
        if isinstance(rec, OdomRecord) and late.t_s + 1.0 <= rec.t_s < late.t_s + 1.05:
            node.reading(late.t_s, late.sensor, late.tof_us)

    _, node = _run(mounts, records, very_late)
    assert node.stats.skipped["tof_out_of_order"] == 1


def test_no_echo_is_not_garbage():
    """``tof_us`` None or NaN is a reading without an echo, not a fault."""
    node = LocalizerNode.from_map_file(ROOM, [(0, 0.2, 0.0, 0.0)])
    node.set_pose(1.0, 1.0, 0.0)
    node.odometry(0.0, 0.0, 0.0, 0.0)
    node.reading(0.01, 0, None)
    node.reading(0.02, 0, math.nan)
    node.odometry(0.05, 0.0, 0.0, 0.0)
    assert not node.stats.skipped and node.stats.tof == 2


@pytest.mark.parametrize("call, name", [
    (lambda n: n.odometry(None, 0.0, 0.0, 0.0), "t_s"),
    (lambda n: n.odometry(1.0, "0.2", 0.0, 0.0), "x_m"),
    (lambda n: n.odometry(1.0, 0.0, np.array([0.1, 0.2]), 0.0), "y_m"),
    (lambda n: n.odometry(1.0, 0.0, 0.0, None), "yaw_rad"),
    (lambda n: n.reading("1.0", 0, 9000.0), "t_s"),
    (lambda n: n.reading(1.0, True, 9000.0), "sensor"),     # would be sensor 1
    (lambda n: n.reading(1.0, 0.0, 9000.0), "sensor"),
    (lambda n: n.reading(1.0, "0", 9000.0), "sensor"),
    (lambda n: n.reading(1.0, 0, "9000"), "tof_us"),
    (lambda n: n.reading(1.0, 0, [9000.0]), "tof_us"),
    (lambda n: n.reading(1.0, 0, 9000.0, pan_rad="0.1"), "pan_rad"),
    (lambda n: n.set_pose(math.nan, 1.0, 0.0), "x_m"),
    (lambda n: n.set_pose(1.0, math.inf, 0.0), "y_m"),
    (lambda n: n.set_pose(1.0, 1.0, None), "yaw_rad"),
    (lambda n: n.set_pose(1.0, 1.0, 0.0, t_s=math.inf), "t_s"),
    (lambda n: n.feed({"type": "odom", "t_s": 1.0}), "feed"),
    (lambda n: n.feed(None), "feed"),
])
def test_wrong_types_are_a_clear_value_error(call, name):
    """A programming error (wrong type or shape, a non-finite prior) raises ValueError
    naming the argument, before anything reaches the filter."""
    node = LocalizerNode.from_map_file(ROOM, [(0, 0.2, 0.0, 0.0), (1, 0.0, 0.2, 90.0)])
    node.set_pose(1.0, 1.0, 0.0)
    node.odometry(0.0, 0.0, 0.0, 0.0)
    before = node.estimate
    with pytest.raises(ValueError, match=f"`{name}`"):
        call(node)
    assert node.estimate is before and node.pose == (1.0, 1.0, 0.0)
    assert not node.stats.skipped
    # numpy scalars are numbers
    est = node.odometry(np.float64(0.05), np.float32(0.01), np.int64(0), 0.0)
    assert est is not None and est.t_s == 0.05
    node.reading(np.float64(0.04), np.int64(1), np.float64(9000.0))
    assert node.stats.tof == 1 and not node.stats.skipped


def test_set_pose_restarts_the_clock():
    """After set_pose the odometry may start again from an earlier time (a restarted
    clock or bag): the node then tracks exactly as a fresh one, nothing is skipped."""
    mounts, records = _drive(4.0)
    fresh, _ = _run(mounts, records)
    _, node = _run(mounts, records)
    again = []
    for rec in records:               # the same drive again, its clock from 0, same rig
        if isinstance(rec, RigRecord):
            continue
        est = node.feed(rec)
        if isinstance(rec, OdomRecord):
            assert est is not None
            again.append((est.t_s, est.state.mean.tolist(), est.state.cov.tolist()))
    assert not node.stats.skipped
    assert again == fresh


def test_readings_without_odometry_keep_memory_bounded():
    """No odometry arriving: at most 10,000 readings wait; the oldest are dropped and
    counted, the 10,000 newest all processed once odometry comes."""
    from sonarloc.localize.localizer import LocalizerConfig

    node = LocalizerNode.from_map_file(ROOM, [(0, 0.2, 0.0, 0.0)],
                                       config=LocalizerConfig(method="conventional"))
    node.set_pose(1.0, 1.0, 0.0)
    node.odometry(0.0, 0.0, 0.0, 0.0)
    for k in range(10_005):   # the 5 oldest: 7 m (beyond max_range_m); then 1.5 m ahead
        node.reading(1.0 + 1e-4 * k, 0, 40_000.0 if k < 5 else 9000.0)
    assert node.stats.skipped["tof_without_odom"] == 5
    assert node.stats.observations == 0
    node.odometry(3.0, 0.0, 0.0, 0.0)
    assert node.stats.observations == 10_000     # the newest 10,000, every one
    assert node.stats.skipped["tof_without_odom"] == 5
