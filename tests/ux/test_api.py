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
