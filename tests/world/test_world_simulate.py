import json
import math
import re

import numpy as np
import pytest

from sonarloc.cli import main as cli_main
from sonarloc.io.logfile import (
    InitRecord,
    LogStats,
    OdomRecord,
    RigRecord,
    TofRecord,
    TruthRecord,
    iter_log,
)
from sonarloc.io.scancsv import read_scan_csv
from sonarloc.maps import load_map
from sonarloc.world.rig import PanRig, pan_angles_deg, ring16
from sonarloc.world.simulate import simulate_records, simulate_scan
from tests.conftest import MAPS


@pytest.fixture(scope="module")
def room():
    return load_map(MAPS / "room.geojson")


def test_drive_log_structure(room):
    recs = list(simulate_records(room, ring16(), duration_s=3.0, seed=7))
    assert isinstance(recs[0], RigRecord) and len(recs[0].sensors) == 16
    assert isinstance(recs[1], InitRecord)
    t = [r.t_s for r in recs]
    assert all(b >= a for a, b in zip(t, t[1:], strict=False))
    odom = [r for r in recs if isinstance(r, OdomRecord)]
    truth = [r for r in recs if isinstance(r, TruthRecord)]
    tof = [r for r in recs if isinstance(r, TofRecord)]
    assert len(odom) == len(truth) == 61  # 20 Hz, 0..3 s inclusive
    assert (odom[0].x_m, odom[0].y_m, odom[0].yaw_deg) == (0.0, 0.0, 0.0)  # REP-105
    assert len(tof) == 100 * 4  # 30 ms slots, 4 sensors per slot
    assert {r.sensor for r in tof} == set(range(16))
    assert all(r.pan_deg is None for r in tof)
    assert sum(r.tof_us is not None for r in tof) > 100
    # the robot drives: about 0.3 m/s along the route
    assert math.hypot(truth[-1].x_m - truth[0].x_m, truth[-1].y_m - truth[0].y_m) == \
        pytest.approx(0.9, abs=0.1)
    # init is a prior near the true start
    assert math.hypot(recs[1].x_m - truth[0].x_m, recs[1].y_m - truth[0].y_m) < 0.3


def test_seeded_and_streaming(room):
    a = list(simulate_records(room, ring16(), duration_s=1.0, seed=1))
    b = list(simulate_records(room, ring16(), duration_s=1.0, seed=1))
    c = list(simulate_records(room, ring16(), duration_s=1.0, seed=2))
    assert a == b and a != c
    # a generator: the first records come before the whole run is computed
    gen = simulate_records(room, ring16(), duration_s=1e6, seed=1)
    first = [next(gen) for _ in range(50)]
    assert first[:20] == a[:20]


def test_readings_match_truth_geometry(room):
    pings = []
    recs = list(simulate_records(room, ring16(), duration_s=2.0, seed=3, on_ping=pings.append))
    tof = [r for r in recs if isinstance(r, TofRecord)]
    assert len(pings) == len(tof)
    for p, r in zip(pings, tof, strict=True):
        assert p.t_s == r.t_s and p.sensor == r.sensor
        assert (r.tof_us is None) == math.isnan(p.tof_us)
        assert (p.reflector >= 0) == (r.tof_us is not None)
    # each echo's range is at least the distance to the reflector's geometry
    from shapely.geometry import Point
    for p in pings:
        if p.reflector >= 0:
            refl = room.reflectors[p.reflector]
            d = refl.geometry.distance(Point(p.x_m, p.y_m)) - refl.radius_m
            assert p.tof_us * 343e-6 / 2 == pytest.approx(d, abs=0.05)


def test_pan_scan_in_map_frame():
    fig5 = load_map(MAPS / "paper_fig5.geojson")
    scan = simulate_scan(fig5, PanRig(), at=(0.0, 0.0, 0.0), seed=11)
    r = scan.readings
    assert len(r) == 267 and np.all(r.x_m == 0) and np.all(r.y_m == 0)
    angles = pan_angles_deg(-40, 40, 0.3)  # -40 .. 39.8
    np.testing.assert_allclose(np.rad2deg(r.yaw_rad), angles, atol=1e-9)
    assert set(scan.reflector[np.isfinite(r.tof_us)].tolist()) == {0, 1, 2}
    # the rig's pose and the robot's yaw both turn the scan
    turned = simulate_scan(fig5, PanRig(), at=(1.0, -2.0, 30.0), seed=11)
    np.testing.assert_allclose(np.rad2deg(turned.readings.yaw_rad),
                               angles + 30, atol=1e-9)


def test_simulate_bad_arguments(room):
    fig5 = load_map(MAPS / "paper_fig5.geojson")
    with pytest.raises(ValueError, match="no default route"):
        next(simulate_records(fig5, ring16()))
    with pytest.raises(ValueError, match="`at` must be"):
        next(simulate_records(room, ring16(), at=(0.0, float("nan"), 0.0)))
    with pytest.raises(ValueError, match="`duration_s`.*-1"):
        next(simulate_records(room, ring16(), duration_s=-1.0))
    with pytest.raises(ValueError, match="`tier`.*'fast'"):
        next(simulate_records(room, ring16(), tier="fast"))
    with pytest.raises(ValueError, match="`seed`"):
        next(simulate_records(room, ring16(), seed=-3))


def test_cli_simulate_writes_log_and_scan(run_cli, tmp_path):
    log, csv = tmp_path / "sim.jsonl", tmp_path / "scan.csv"
    proc = run_cli("simulate", "--map", str(MAPS / "paper_fig5.geojson"), "--out", str(log),
                   "--rig", "pan", "--at", "0,0,0", "--pan", "-40:40:0.3", "--repeat", "2",
                   "--seed", "5", "--tier", "gauss", "--scan-csv", str(csv), check=True)
    assert "534 pings" in proc.stderr
    stats = LogStats()
    recs = list(iter_log(log, stats))
    assert stats.malformed_count == 0 and not stats.unknown and stats.time_backwards_count == 0
    tof = [r for r in recs if isinstance(r, TofRecord)]
    assert len(tof) == 534 and tof[0].pan_deg == -40.0 and tof[1].pan_deg == -40.0
    scan = read_scan_csv(csv)
    assert len(scan) == 534
    got = np.array([np.nan if r.tof_us is None else r.tof_us for r in tof])
    np.testing.assert_array_equal(np.isnan(scan.tof_us), np.isnan(got))
    np.testing.assert_allclose(scan.tof_us[~np.isnan(got)], got[~np.isnan(got)])
    first = json.loads(log.read_text().splitlines()[0])
    assert first["type"] == "rig"


def test_cli_drive_with_rig_file(run_cli, tmp_path):
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"kind": "ring", "sensors": [
        {"id": 0, "x_m": 0.2, "y_m": 0, "yaw_deg": 0}, {"id": 1, "x_m": -0.2, "y_m": 0,
                                                         "yaw_deg": 180}],
        "groups": [[0, 1]], "slot_s": 0.05}))
    log = tmp_path / "d.jsonl"
    run_cli("simulate", "--map", str(MAPS / "room.geojson"), "--out", str(log), "--rig",
            str(rig), "--duration", "2", check=True)
    recs = list(iter_log(log, strict=True))
    assert sum(isinstance(r, TofRecord) for r in recs) == 80


@pytest.mark.parametrize(("at", "why"), [("50,50,0", "--at 50,50 is outside the map, "
                                                      "which spans x 0..8 m, y 0..5 m"),
                                         ("4,2.5,0", None)])
def test_cli_a_still_robot_that_sees_nothing_is_warned(capsys, tmp_path, at, why):
    # Before: "wrote 180 records ...: 136 pings, 0 echoes" and nothing else, exit 0.
    code = cli_main(["simulate", "--map", str(MAPS / "room.geojson"), "--at", at,
                     "--duration", "1", "--out", str(tmp_path / "x.jsonl")])
    assert code == 0
    err = capsys.readouterr().err
    warned = "warning: no ping had an echo: nothing of the map was in range" in err
    assert warned == (why is not None), err
    assert why is None or f"({why})" in err


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--at", "1,2"], "--at must be X,Y,YAW_DEG.*'1,2'"),
        (["--at", "-1,2"], "--at must be X,Y,YAW_DEG.*'-1,2'"),
        (["--duration", "soon"], "--duration.*'soon'"),
        (["--duration", "-4"], "--duration.*'-4'"),
        (["--rig", "pan", "--pan", "-40:40"], "pan schedule.*'-40:40'"),
        (["--rig", "pan", "--repeat", "0"], "--repeat must be at least 1, got '0'"),
        (["--tier", "fast"], "--tier.*'fast'"),
        (["--seed", "x"], "--seed must be an integer, got 'x'"),
        (["--rig", "hexapod"], "--rig.*'hexapod'"),
        (["--repeat", "3"], "need a pan rig"),
    ],
)
def test_cli_bad_arguments_name_the_value(capsys, tmp_path, args, match):
    # in-process (same dispatch as the `sonarloc` command; one subprocess case below)
    code = cli_main(["simulate", "--map", str(MAPS / "room.geojson"), "--out",
                     str(tmp_path / "x.jsonl"), *args])
    assert code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert re.search(match, lines[0]), lines[0]
    assert not (tmp_path / "x.jsonl").exists()


def test_cli_bad_map_names_the_feature(run_cli, tmp_path):
    bad = tmp_path / "bad.geojson"
    bad.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"kind": "pole"},
         "geometry": {"type": "Point", "coordinates": [0, 0]}},
        {"type": "Feature", "properties": {"kind": "pole", "radius_m": -1},
         "geometry": {"type": "Point", "coordinates": [1, 0]}}]}))
    proc = run_cli("simulate", "--map", str(bad), "--out", str(tmp_path / "x.jsonl"),
                   "--at", "0,0,0")
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "feature 1" in proc.stderr and "radius_m" in proc.stderr
