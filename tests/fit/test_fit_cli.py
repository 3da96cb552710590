"""`sonarloc fit SCAN.csv [--json]` against FORMATS.md sections 1-2."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sonarloc.fit.synth import Reflector, pan_scan
from sonarloc.io.scancsv import write_scan_csv


def _fig5_csv(tmp_path, rng):
    scan = pan_scan([Reflector.polar(1.46, -17, 0.67), Reflector.polar(1.50, 4, 0.15),
                     Reflector.polar(1.47, 22, 2.68)], rng, -40, 40, 0.3)
    path = tmp_path / "scan.csv"
    write_scan_csv(path, scan)
    return path


def test_fit_json_follows_formats(tmp_path, rng, run_cli):
    path = _fig5_csv(tmp_path, rng)
    proc = run_cli("fit", str(path), "--json", check=True)
    out = json.loads(proc.stdout)
    lms = out["landmarks"]
    assert len(lms) == 3
    for lm in lms:
        assert lm["kind"] in ("point", "line")
        keys = ("x_m", "y_m") if lm["kind"] == "point" else ("rho_m", "alpha_deg")
        for k in (*keys, "range_m", "bearing_deg", "kappa_us", "n_readings", "cov", "status"):
            assert k in lm
        cov = np.array(lm["cov"], dtype=float)
        assert cov.shape == (3, 3)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=1e-15)
        assert -180.0 < lm["bearing_deg"] <= 180.0
        if lm["kind"] == "point":
            # the point is range_m along bearing_deg from the reference transducer position
            ref = lm["ref_pose"]
            b = math.radians(lm["bearing_deg"])
            assert lm["x_m"] == pytest.approx(ref["x_m"] + lm["range_m"] * math.cos(b), abs=1e-9)
            assert lm["y_m"] == pytest.approx(ref["y_m"] + lm["range_m"] * math.sin(b), abs=1e-9)
        else:
            assert lm["rho_m"] >= 0
    pole, plane, rod = lms
    assert pole["status"] == "ok" and abs(pole["bearing_deg"] + 17) < 1.0
    assert rod["status"] == "ok" and abs(rod["bearing_deg"] - 22) < 1.5
    assert plane["kind"] == "line"
    assert pole["kappa_us"] < rod["kappa_us"]
    assert out["readings"]["total"] == 267


def test_fit_table_and_speed_of_sound(tmp_path, rng, run_cli):
    path = _fig5_csv(tmp_path, rng)
    proc = run_cli("fit", str(path), check=True)
    assert "3 landmark(s)" in proc.stdout and "ok" in proc.stdout
    a = json.loads(run_cli("fit", str(path), "--json", check=True).stdout)["landmarks"][0]
    b = json.loads(run_cli("fit", str(path), "--json", "--temperature", "30",
                           check=True).stdout)["landmarks"][0]
    assert b["range_m"] / a["range_m"] == pytest.approx((331.3 + 0.606 * 30) / 343.0, rel=1e-4)


def test_fit_bad_input_one_line_error(tmp_path, run_cli):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,8000\n0.1,0,zero,0,8000\n")
    proc = run_cli("fit", str(bad), "--json")
    assert proc.returncode == 2
    assert "line 3" in proc.stderr and proc.stderr.count("\n") == 1
    missing = run_cli("fit", str(tmp_path / "nope.csv"))
    assert missing.returncode == 2 and "nope.csv" in missing.stderr


def test_fit_all_no_echo_gives_empty_list(tmp_path, run_cli):
    p = tmp_path / "quiet.csv"
    p.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n" + "".join(f"{i*0.1},0,0,{i},\n" for i in range(20)))
    out = json.loads(run_cli("fit", str(p), "--json", check=True).stdout)
    assert out["landmarks"] == []


def test_fit_odometry_sd_widens_moving_walls_only(tmp_path, rng, run_cli):
    # a side-looking transducer driving 1.2 m past a wall: its covariance carries the
    # odometry term at the given SD (none at 0), a bad SD is a one-line error
    from sonarloc.fit.synth import simulate_readings

    n = 200
    t = np.arange(n) * 0.02
    yaw = np.full(n, np.pi / 2) + np.deg2rad(12.0) * np.sin(2 * np.pi * t / 1.3)
    scan = simulate_readings(t, np.linspace(-0.6, 0.6, n), 0.0, yaw,
                             [Reflector.line(1.5, np.deg2rad(93.0), 0.15)], rng)
    path = tmp_path / "drive.csv"
    write_scan_csv(path, scan)

    def wall(*extra):
        lms = json.loads(run_cli("fit", str(path), "--json", *extra, check=True).stdout)
        return max(lms["landmarks"], key=lambda lm: lm["n_readings"])

    exact, default, double = wall("--odometry-sd", "0"), wall(), wall("--odometry-sd", "2")
    assert exact["kind"] == default["kind"] == double["kind"] == "line"
    var = [np.array(w["cov"])[1, 1] for w in (exact, default, double)]
    assert var[0] < var[1] < var[2]
    # variances add: the term at 2 deg/m is four times that at the default 1 deg/m
    assert var[2] - var[0] == pytest.approx(4.0 * (var[1] - var[0]), rel=1e-6)
    bad = run_cli("fit", str(path), "--odometry-sd", "-1")
    assert bad.returncode == 2 and "--odometry-sd" in bad.stderr
    assert bad.stderr.count("\n") == 1


def test_fit_max_travel_cuts_a_long_pass(tmp_path, rng, run_cli):
    # a side-looking transducer driving 3 m along a wall: by default (1 m) the pass is
    # cut into segments that each stay within the cap; --max-travel 0 keeps it whole
    from sonarloc.fit.synth import simulate_readings

    n = 300
    t = np.arange(n) * 0.05
    x = np.linspace(-1.5, 1.5, n)
    yaw = np.full(n, np.pi / 2) + np.deg2rad(12.0) * np.sin(2 * np.pi * t / 1.3)
    scan = simulate_readings(t, x, 0.0, yaw, [Reflector.line(1.5, np.pi / 2, 0.15)], rng)
    path = tmp_path / "pass.csv"
    write_scan_csv(path, scan)

    def fit(*extra):
        return json.loads(run_cli("fit", str(path), "--json", *extra, check=True).stdout)

    whole, default, half = fit("--max-travel", "0"), fit(), fit("--max-travel", "0.5")
    n_seg = [out["readings"]["segments"] for out in (whole, default, half)]
    assert n_seg[0] == 1 and 3 <= n_seg[1] < n_seg[2]
    echoes = int(np.isfinite(scan.tof_us).sum())
    for out in (whole, default, half):      # every echo in some landmark or dropped
        lms = out["landmarks"]
        assert sum(lm["n_readings"] + lm.get("n_spikes", 0) for lm in lms) == echoes
        for lm in lms:                       # every piece is the wall
            assert lm["kind"] == "line"
    bad = run_cli("fit", str(path), "--max-travel", "-1")
    assert bad.returncode == 2 and "--max-travel" in bad.stderr
    assert bad.stderr.count("\n") == 1


_BLAS_PROBE = """
import contextlib, io, os, sys
import sonarloc.cli as cli
before = "numpy" in sys.modules
with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
    cli.main([sys.argv[1], "--help"])    # imports the command's module
print(before, os.environ.get("OPENBLAS_NUM_THREADS"), os.environ.get("OMP_NUM_THREADS"))
"""


@pytest.mark.parametrize(("command", "preset", "want"),
                         [("fit", None, "1"), ("fit", "3", "3"), ("drive", None, "1")])
def test_commands_set_one_blas_thread_before_numpy_loads(command, preset, want):
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2])
    if preset is not None:        # the user's choice is kept
        env["OPENBLAS_NUM_THREADS"] = preset
    out = subprocess.run([sys.executable, "-c", _BLAS_PROBE, command], env=env,
                         capture_output=True, text=True, check=True).stdout.split()
    # set before numpy (which reads it when it loads BLAS) comes with the command
    assert out == ["False", want, "1"]


def test_fit_reads_a_large_csv_in_blocks(tmp_path, rng, run_cli):
    # `sonarloc fit` reads and fits a scan a block of lines at a time (bounded memory):
    # blocks of 700 lines give the landmarks of one block for the whole file
    from sonarloc.fit.synth import rotation_scan

    path = tmp_path / "rotation.csv"
    write_scan_csv(path, rotation_scan(4000, rng))

    def fit(*extra):
        return json.loads(run_cli("fit", str(path), "--json", *extra, check=True).stdout)

    whole, blocks = fit(), fit("--block-rows", "700")
    assert whole["readings"] == blocks["readings"] and whole["readings"]["total"] == 4000
    # a file of one block: fit_scan's landmarks exactly (the end's segments in its batch)
    from sonarloc.commands.fit import landmark_to_json
    from sonarloc.fit.landmarks import fit_scan
    from sonarloc.io.scancsv import read_scan_csv

    same = [landmark_to_json(lm) for lm in fit_scan(read_scan_csv(path)).landmarks]
    assert json.loads(json.dumps(same)) == whole["landmarks"]
    # JSON Lines: the same objects, a line each, then the counts
    lines = [json.loads(line) for line in run_cli("fit", str(path), "--jsonl", "--block-rows",
                                                  "700", check=True).stdout.splitlines()]
    assert lines[:-1] == blocks["landmarks"] and lines[-1] == {"readings": blocks["readings"]}
    assert len(whole["landmarks"]) == len(blocks["landmarks"]) > 50
    for a, b in zip(whole["landmarks"], blocks["landmarks"], strict=True):
        assert (a["kind"], a["status"], a["n_readings"]) == (b["kind"], b["status"],
                                                             b["n_readings"])
        assert b["range_m"] == pytest.approx(a["range_m"], abs=1e-6)
        assert b["bearing_deg"] == pytest.approx(a["bearing_deg"], abs=1e-4)
    bad = run_cli("fit", str(path), "--block-rows", "0")
    assert bad.returncode == 2 and "--block-rows" in bad.stderr


def test_fit_bad_line_after_the_first_block_keeps_what_was_fitted(tmp_path, rng, run_cli):
    # a bad line found after landmarks went out: the JSON object is closed with the
    # error (naming the line) and the landmarks of the lines before its block, exit 2
    from sonarloc.fit.synth import rotation_scan

    path = tmp_path / "rotation.csv"
    write_scan_csv(path, rotation_scan(3000, rng))
    lines = path.read_text().splitlines(keepends=True)
    lines[2501] = lines[2501].replace(",", ",oops", 1)       # line 2502 of the file
    path.write_text("".join(lines))
    good = tmp_path / "first.csv"
    good.write_text("".join(lines[:2001]))                   # the blocks before it
    proc = run_cli("fit", str(path), "--json", "--block-rows", "1000")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "line 2502" in proc.stderr
    out = json.loads(proc.stdout)
    assert "line 2502" in out["error"] and out["readings"]["total"] == 2000
    want = json.loads(run_cli("fit", str(good), "--json", check=True).stdout)
    assert [lm["n_readings"] for lm in out["landmarks"]] == [
        lm["n_readings"] for lm in want["landmarks"]]
    # within the first block: nothing printed, the one-line error as for a small file
    early = run_cli("fit", str(path), "--json", "--block-rows", "5000")
    assert early.returncode == 2 and early.stdout == "" and "line 2502" in early.stderr
    table = run_cli("fit", str(path), "--block-rows", "1000")
    assert table.returncode == 2 and "stopped at a bad line" in table.stdout
    jsonl = run_cli("fit", str(path), "--jsonl", "--block-rows", "1000")
    last = json.loads(jsonl.stdout.splitlines()[-1])
    assert jsonl.returncode == 2 and "line 2502" in last["error"]
    assert len(jsonl.stdout.splitlines()) == len(out["landmarks"]) + 1


def test_fit_spreadsheet_csv_and_overlong_field(tmp_path, rng, run_cli):
    # found by the session-15 sweep (tests/fit/test_fit_fuzz.py): a byte-order mark read
    # as a header without `t_s`; a field over csv's size limit (a line of junk) and a
    # sensor id beyond 64 bits crashed with a traceback (exit 1)
    path = _fig5_csv(tmp_path, rng)
    text = path.read_text()
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    want = run_cli("fit", str(path), "--json", check=True).stdout
    assert run_cli("fit", str(bom), "--json", check=True).stdout == want
    lines = text.splitlines(keepends=True)
    for name, junk, match in [("field", "9" * 140_000, "line 4: field larger than field limit"),
                              ("sensor", "0,0,0,0,8000," + "9" * 30, "line 4: column `sensor`")]:
        bad = tmp_path / f"{name}.csv"
        bad.write_text("".join(lines[:3] + [junk + "\n"] + lines[3:]))
        proc = run_cli("fit", str(bad), "--json")
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
        assert match in proc.stderr


def test_fit_refuses_a_speed_of_sound_that_is_not_air(tmp_path, capsys):
    # 3 m/s put a pole 12.8 mm away marked ok, 1e308 m/s printed overflow warnings:
    # typos and unit errors are refused (as --temperature is outside [-50, 60] degC)
    from sonarloc.cli import main

    scan = tmp_path / "scan.csv"
    scan.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,8000\n", encoding="utf-8")
    for value in ("3", "3.43", "3430", "1e308", "nan", "inf", "-343"):
        assert main(["fit", str(scan), "--speed-of-sound", value]) == 2, value
        out = capsys.readouterr()
        assert out.out == "" and out.err.strip() == (
            "sonarloc fit: error: --speed-of-sound: the speed of sound must be within "
            "[250, 450] m/s (sound in air: 301 m/s at -50 degC to 368 m/s at 60 degC), "
            f"got {float(value)!r}"), value
    for value in ("250", "343", "450"):
        assert main(["fit", str(scan), "--speed-of-sound", value, "--json"]) == 0, value
        assert json.loads(capsys.readouterr().out)["readings"]["total"] == 1


def test_fit_max_tof_takes_a_module_s_timeouts_as_no_echo(tmp_path, rng, run_cli):
    """A module that reports its timeout as a reading (62,000 us, 10.6 m) instead of as
    no echo: fitted as echoes, those readings gave `flat` "walls" at 10.6 m and lost
    their no-echo information. `fit` says so on stderr (once, whatever the block size)
    and names the fix; `--max-tof 62000` gives the landmarks of the clean scan, and counts
    the timeouts. A clean scan gets no note."""
    import csv

    clean = _fig5_csv(tmp_path, rng)
    rows = list(csv.DictReader(clean.open()))
    assert sum(not r["tof_us"] for r in rows) >= 20
    for r in rows:
        r["tof_us"] = r["tof_us"] or "62000"
    sat = tmp_path / "timeouts.csv"
    with sat.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    n_timeouts = sum(r["tof_us"] == "62000" for r in rows)

    want = json.loads(run_cli("fit", str(clean), "--json", check=True).stdout)
    for block in ("100000", "50"):
        proc = run_cli("fit", str(sat), "--json", "--block-rows", block, check=True)
        assert proc.stderr.count("note:") == 1
        assert f"{n_timeouts} of " in proc.stderr and "--max-tof 62000" in proc.stderr
        got = json.loads(proc.stdout)
        assert any(lm["range_m"] > 10 for lm in got["landmarks"])
    fixed = run_cli("fit", str(sat), "--json", "--max-tof", "62000", check=True)
    assert "note:" not in fixed.stderr
    out = json.loads(fixed.stdout)
    assert out["landmarks"] == want["landmarks"]
    assert out["readings"] == {**want["readings"], "timeouts": n_timeouts}
    assert "note:" not in run_cli("fit", str(clean), "--json", check=True).stderr
    table = run_cli("fit", str(sat), "--max-tof", "61000", check=True).stdout
    assert f", {n_timeouts} timeouts)" in table
    bad = run_cli("fit", str(sat), "--max-tof", "-1")
    assert bad.returncode == 2 and "--max-tof" in bad.stderr
