"""`sonarloc plot` and the drawing helpers, on logs and scans made here with eq. 3."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import (
    InitRecord,
    LogWriter,
    OdomRecord,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
)
from sonarloc.io.posescsv import PoseTrack, write_poses_csv
from sonarloc.physics.tof import eq3_tof_us
from sonarloc.report import plots
from sonarloc.report.fitjson import read_fit_json
from sonarloc.report.logdata import load_log, odometry_in_map, transducer_poses

pytest.importorskip("matplotlib")

C = 343.0
# the paper's Fig. 5 scene: (range m, bearing deg, kappa us)
FIG5 = [(1.46, -17.0, 0.67), (1.50, 4.0, 0.15), (1.47, 22.0, 2.68)]


def _fig5_scan(path: Path, rng: np.random.Generator) -> None:
    yaw = np.arange(-40.0, 40.0 + 1e-9, 0.3)
    tofs = []
    for a in yaw:
        cands = []
        for r, b, k in FIG5:
            tm = float(eq3_tof_us(2 * r / C * 1e6, math.radians(a - b), k))
            if tm - 2 * r / C * 1e6 < 12.0:
                cands.append(tm + rng.normal(0, 5.0))
        tofs.append(min(cands) if cands else math.nan)
    with open(path, "w") as f:
        f.write("t_s,x_m,y_m,yaw_deg,tof_us\n")
        for i, (a, t) in enumerate(zip(yaw, tofs, strict=True)):
            f.write(f"{0.1 * i},0,0,{a},{'' if math.isnan(t) else round(t, 1)}\n")


def _fits_json(path: Path) -> None:
    lms = []
    for r, b, k in FIG5:
        x, y = r * math.cos(math.radians(b)), r * math.sin(math.radians(b))
        lms.append({"kind": "point", "x_m": x, "y_m": y, "range_m": r, "bearing_deg": b,
                    "kappa_us": k, "n_readings": 50, "cov": np.diag([1e-6, 1e-6, 0.01]).tolist()})
    path.write_text(json.dumps({"landmarks": lms}))


def _drive_log(path: Path) -> PoseTrack:
    """A robot on a circle with two sensors, truth, odometry with heading drift, init."""
    rig = RigRecord((SensorMount(0, 0.2, 0.0, 0.0), SensorMount(1, 0.0, 0.2, 90.0)))
    t = np.arange(0, 20, 0.1)
    truth = np.stack([t, 2 * np.cos(t / 5), 2 * np.sin(t / 5), t / 5 + np.pi / 2], -1)
    with LogWriter(path) as w:
        w.write(rig)
        w.write(InitRecord(0.0, 2.0, 0.0, 90.0, 0.05, 2.0))
        for k, (ti, x, y, yaw) in enumerate(truth):
            w.write(TruthRecord(ti, x, y, math.degrees(yaw)))
            drift = 0.01 * ti
            # odometry in its own frame: starts at 0, heading drifts
            w.write(OdomRecord(ti, 2 * math.sin(ti / 5 + drift), 2 - 2 * math.cos(ti / 5),
                               math.degrees(ti / 5 + drift)))
            w.write(TofRecord(ti, k % 2, 9000.0 if k % 3 else None))
    cov = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (len(t), 1, 1))
    return PoseTrack(t, truth[:, 1] + 0.01, truth[:, 2], truth[:, 3], cov)


def test_model_curve_of_a_point_matches_eq3():
    lm = Landmark("point", np.array([1.0, 0.0, 0.67]), np.eye(3), 1.0, 0.0, 10, 0.0,
                  (0.0, 0.0, 0.0))
    yaw = np.radians([-10.0, 0.0, 10.0])
    tof, theta = plots.landmark_model_us(lm, 0.0, 0.0, yaw)
    assert theta == pytest.approx(-yaw)
    assert tof == pytest.approx(eq3_tof_us(2 / C * 1e6, yaw, 0.67))
    wall = Landmark("line", np.array([2.0, math.pi / 2, 0.15]), np.eye(3), 2.0, math.pi / 2, 10,
                    0.0, (0.0, 0.0, 0.0))
    tof, theta = plots.landmark_model_us(wall, [0.0, 0.0], [0.5, 3.0], [math.pi / 2] * 2)
    # from y=0.5 the wall y=2 is 1.5 m ahead; from y=3 it is 1 m behind (theta = 180 deg)
    assert tof[0] == pytest.approx(2 * 1.5 / C * 1e6 + 0.15)
    assert abs(theta[1]) == pytest.approx(math.pi)


def test_covariance_ellipse_axes():
    e = plots.covariance_ellipse((1.0, 2.0), np.diag([4.0, 1.0]), n_sigma=2.0, n=5)
    assert np.ptp(e[:, 0]) == pytest.approx(8.0) and np.ptp(e[:, 1]) == pytest.approx(4.0,
                                                                                         rel=0.01)
    assert np.isnan(plots.covariance_ellipse((0, 0), [[1, 0], [0, -1]])).all()


def test_log_arrays_and_transducer_poses(tmp_path: Path):
    log = tmp_path / "drive.jsonl"
    _drive_log(log)
    data = load_log(log)
    assert data.has_truth and len(data.odom) == len(data.truth) == 200
    sp = transducer_poses(data, data.truth)
    # sensor 0 sits 0.2 m ahead of base_link, along the heading
    t0 = data.truth[0]
    assert sp[0] == pytest.approx([t0[1] + 0.2 * math.cos(t0[3]), t0[2] + 0.2 * math.sin(t0[3]),
                                   t0[3]])
    aligned = odometry_in_map(data)
    assert aligned[0, 1:] == pytest.approx(data.truth[0, 1:], abs=1e-9)
    # the heading drift makes odometry leave the truth
    assert np.hypot(*(aligned[-1, 1:3] - data.truth[-1, 1:3])) > 0.1


def test_cli_plot_scan_map_trajectory(tmp_path: Path, run_cli, rng):
    scan, fits = tmp_path / "fig5.csv", tmp_path / "fits.json"
    _fig5_scan(scan, rng)
    _fits_json(fits)
    assert [round(math.degrees(lm.bearing_rad)) for lm in read_fit_json(fits)] == [-17, 4, 22]
    out = tmp_path / "scan.png"
    proc = run_cli("plot", "scan", str(scan), "--fits", str(fits), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out2 = tmp_path / "scan_fit_here.png"  # without --fits: fitted here
    proc = run_cli("plot", "scan", str(scan), "--out", str(out2))
    assert proc.returncode == 0, proc.stderr
    assert out2.stat().st_size > 20_000
    log, poses = tmp_path / "drive.jsonl", tmp_path / "poses.csv"
    write_poses_csv(poses, _drive_log(log))
    for kind, extra in (("map", []), ("trajectory", ["--poses", str(poses)])):
        out = tmp_path / f"{kind}.png"
        proc = run_cli("plot", kind, str(log), "--out", str(out), *extra)
        assert proc.returncode == 0, proc.stderr
        assert out.stat().st_size > 10_000


def test_cli_plot_errors(tmp_path: Path, run_cli):
    bad = tmp_path / "bad.json"
    bad.write_text('{"landmarks": [{"kind": "blob"}]}')
    scan = tmp_path / "s.csv"
    scan.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,8000\n")
    proc = run_cli("plot", "scan", str(scan), "--fits", str(bad), "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "landmarks[0]" in proc.stderr and "blob" in proc.stderr
    log = tmp_path / "empty.jsonl"
    log.write_text('{"type":"odom","t_s":0,"x_m":0,"y_m":0,"yaw_deg":0}\n')
    proc = run_cli("plot", "map", str(log), "--out", str(tmp_path / "y.png"))
    assert proc.returncode == 2 and "no `rig` record" in proc.stderr
