"""`sonarloc drive`: end to end through the device protocol; short drives, real checks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import numpy as np
import pytest

from sonarloc.report.pipeline import SHARED_MAPS, DriveConfig, find_map, map_dirs, run_drive

REQUIRED = ("pose_rmse_m", "yaw_rmse_deg", "landmarks_fitted", "wall_time_s", "plot")


def test_drive_json_over_can_beats_odometry(tmp_path: Path, run_cli):
    png = tmp_path / "drive.png"
    proc = run_cli("drive", "--duration", "15", "--seed", "3", "--json", "--plot", str(png))
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1, "--json prints exactly one JSON object"
    rep = json.loads(lines[0])
    for key in REQUIRED:
        assert key in rep and rep[key] is not None, key
    assert rep["plot"] == str(png) and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 50_000
    assert rep["device"] == "can" and rep["duration_s"] == 15.0
    # readings and odometry came through the CAN decoder, nothing lost or corrupted
    assert rep["readings"] > 1000 and rep["odom_records"] == 301
    assert rep["device_stats"]["crc_errors"] == 0 and rep["device_stats"]["dropped"] == 0
    # the module sends the drive faster than the Localizer reads it and is then silent:
    # that is its end, not a restart (6 wake-up Starts were sent and reported)
    assert "wakeups" not in rep["device_stats"]  # (reported only when not 0)
    assert rep["landmarks_fitted"] >= 10 and rep["landmarks_matched"] >= 3
    assert isinstance(rep["landmarks_skipped"], int) and rep["landmarks_skipped"] >= 0
    # the point of it all: fitted landmarks beat dead reckoning from the same prior
    assert rep["pose_rmse_m"] < 0.7 * rep["odom_pose_rmse_m"]
    assert rep["pose_rmse_m"] < 0.08
    assert rep["yaw_rmse_deg"] < 3.0
    # once the prior's error is worked off the estimate is millimetre-level (issue: <= 2 cm)
    assert rep["steady_pose_rmse_m"] < min(rep["pose_rmse_m"], 0.02)
    assert rep["steady_yaw_rmse_deg"] < 1.0
    assert rep["compute_per_reading_us"] > 0 and rep["realtime_factor"] > 0
    # the worst call's CPU time is at least its share of all the compute, and the 99th
    # percentile lies below it (the CPU time of a call is never more than its wall time)
    total_ms = rep["compute_per_reading_us"] * rep["readings"] / 1e3
    n_calls = rep["readings"] + rep["odom_records"] + 2  # + the init record and finish()
    assert 0 < rep["call_p99_ms"] <= rep["call_max_ms"] <= total_ms
    assert rep["call_max_ms"] >= 0.5 * total_ms / n_calls
    assert rep["status"].startswith("tracking")


def test_drive_serial_same_numbers_as_can():
    """A pseudo-terminal carries the same stream: same seed, same estimate."""
    can = run_drive(DriveConfig(duration_s=6.0, seed=5, device="can"))
    ser = run_drive(DriveConfig(duration_s=6.0, seed=5, device="serial"))
    assert ser.report.readings == can.report.readings > 0
    assert ser.report.device_stats["crc_errors"] == 0
    assert ser.report.pose_rmse_m == pytest.approx(can.report.pose_rmse_m, rel=1e-9)
    assert len(ser.estimate) == len(ser.truth) == 121
    # truth never crossed the wire; the odometry-only track starts at the prior
    assert ser.odometry.shape == ser.truth.shape
    # the figure's material: landmarks in map with their match flag, segments with readings
    assert any(fused for _, fused in ser.landmarks)
    assert ser.segments and all(np.isfinite(v.tof_us).sum() >= 3 for v in ser.segments)


def test_drive_text_report(tmp_path: Path, run_cli):
    proc = run_cli("drive", "--duration", "4", "--no-plot", "--rig", "pan")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    for needle in ("pose RMSE", "odometry only", "landmarks", "us per reading", "x real time",
                   "rig pan", "ms CPU at the 99th percentile"):
        assert needle in out, needle
    assert proc.stderr == ""  # no progress bar when stderr is not a terminal


def test_drive_bad_input(run_cli, tmp_path: Path):
    proc = run_cli("drive", "--map", str(tmp_path / "nope.geojson"), "--no-plot")
    assert proc.returncode == 2 and "not found" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    proc = run_cli("drive", "--duration", "-3")
    assert proc.returncode == 2 and "--duration" in proc.stderr
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature", '
                   '"properties": {"kind": "pole"}, "geometry": {"type": "Point", '
                   '"coordinates": [1]}}]}')
    proc = run_cli("drive", "--map", str(bad), "--no-plot")
    assert proc.returncode == 2 and "feature 0" in proc.stderr


def test_find_map():
    assert find_map("room").name == "room.geojson"
    assert find_map("paper_fig5.geojson").exists()
    with pytest.raises(Exception, match="not found"):
        find_map("no-such-map")


ROOT = Path(__file__).resolve().parents[2]


def test_every_map_is_shipped_where_find_map_looks():
    # pyproject's data-files put maps/ under <data prefix>/SHARED_MAPS for an install that
    # is not a checkout (a wheel has no maps/ next to the package): both sides must agree,
    # and the glob must take every map of maps/
    files = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "data-files"]
    assert list(files) == [SHARED_MAPS.as_posix()]
    shipped = {p.name for pattern in files[SHARED_MAPS.as_posix()]
               for p in ROOT.glob(pattern)}
    assert shipped == {p.name for p in (ROOT / "maps").iterdir() if p.is_file()}
    assert Path(sysconfig.get_path("data")) / SHARED_MAPS in map_dirs()


@pytest.mark.slow
def test_a_regular_install_finds_its_maps_outside_a_checkout(tmp_path: Path):
    # a real `pip install .` (not editable) into a fresh venv, which sees this
    # environment's packages for the dependencies; `sonarloc drive` from a folder with no
    # maps/ above it
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          check=True, capture_output=True, text=True).stdout.strip()
    Path(site, "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(ROOT)], check=True)
    work = tmp_path / "empty"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    found = subprocess.run(
        [str(py), "-c", "from sonarloc.report.pipeline import find_map; print(find_map('room'))"],
        cwd=work, env=env, check=True, capture_output=True, text=True).stdout.strip()
    # the installed copy (a maps/ folder above the working directory would do too, and
    # /tmp may have one)
    assert Path(found).parent == venv / SHARED_MAPS
    proc = subprocess.run([str(py), "-m", "sonarloc", "drive", "--duration", "2", "--no-plot"],
                          cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def test_drive_rate_paces_the_simulated_module(run_cli):
    """`--rate R` paces the module at R times real time (as `serve-sim --rate`): the
    drive cannot run faster than that; a bad value names the flag."""
    proc = run_cli("drive", "--duration", "3", "--rate", "10", "--json", "--no-plot")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(proc.stdout)
    assert rep["readings"] > 0 and rep["realtime_factor"] <= 10.5
    for bad in ("0", "-2", "fast"):
        proc = run_cli("drive", "--rate", bad, "--no-plot")
        assert proc.returncode == 2 and "--rate" in proc.stderr
