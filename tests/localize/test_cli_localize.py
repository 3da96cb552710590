import io
import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sonarloc.commands._args import parse_pose
from sonarloc.io.logfile import LogWriter, OdomRecord, TruthRecord, iter_log
from sonarloc.io.posescsv import COLUMNS, read_poses_csv
from sonarloc.localize.ekf import Gaussian
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import PoseEstimate
from sonarloc.localize.replay import PoseCsvWriter
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"


@pytest.fixture(scope="module")
def room_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("loc") / "drive.jsonl"
    with LogWriter(path) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=12.0, seed=3))
    return path


def _truth(path):
    return {r.t_s: (r.x_m, r.y_m, math.radians(r.yaw_deg))
            for r in iter_log(path) if isinstance(r, TruthRecord)}


def test_feature_map_from_room():
    fm = FeatureMap.from_map(load_map(ROOM))
    assert fm.n_walls == 8  # 6 room segments + 2 partition segments
    assert {"pole", "rod", "corner", "edge"} <= set(fm.point_kind)
    assert np.all(fm.wall_line[:, 0] >= 0)


def test_localize_conventional_writes_one_row_per_odom(run_cli, room_log, tmp_path):
    out = tmp_path / "poses.csv"
    proc = run_cli("localize", str(room_log), "--map", ROOM, "--out", str(out),
                   "--method", "conventional", check=True)
    header = out.read_text().splitlines()[0]
    assert header == ",".join(COLUMNS)
    track = read_poses_csv(out)
    n_odom = sum(isinstance(r, OdomRecord) for r in iter_log(room_log))
    assert len(track) == n_odom
    truth = _truth(room_log)
    err = [math.hypot(x - truth[t][0], y - truth[t][1])
           for t, x, y in zip(track.t_s, track.x_m, track.y_m, strict=True)]
    assert np.sqrt(np.mean(np.square(err))) < 0.05
    assert np.all(np.linalg.eigvalsh(track.cov) > 0)
    assert "fused" in proc.stderr


def test_localize_odometry_only_to_stdout_with_status(run_cli, room_log):
    proc = run_cli("localize", str(room_log), "--map", ROOM, "--method", "odometry",
                   "--status", check=True)
    lines = proc.stdout.splitlines()
    assert lines[0] == ",".join(COLUMNS) + ",status"
    # odometry alone confirms nothing: dead reckoning from the first row (the prior is
    # no confirmation of the pose) to the last
    assert lines[1].endswith(",dead_reckoning") and lines[-1].endswith(",dead_reckoning")


def test_bad_log_is_reported_not_fatal(run_cli, room_log, tmp_path):
    lines = room_log.read_text().splitlines()
    bad = lines[:40] + ["{not json", '{"type": "odom", "t_s": "x"}',
                        '{"type": "weather", "t_s": 1.0}'] + lines[40:60] + \
        [json.dumps({"type": "odom", "t_s": 0.0, "x_m": 0, "y_m": 0, "yaw_deg": 0})] + \
        lines[60:200]
    log = tmp_path / "bad.jsonl"
    log.write_text("\n".join(bad) + "\n")
    out = tmp_path / "p.csv"
    proc = run_cli("localize", str(log), "--map", ROOM, "--out", str(out), "--method",
                   "conventional")
    assert proc.returncode == 0, proc.stderr
    assert "line 41" in proc.stderr and "line 42" in proc.stderr
    assert "weather" in proc.stderr
    assert "backwards" in proc.stderr
    n_odom = sum('"odom"' in ln and '"x"' not in ln for ln in bad)
    assert len(read_poses_csv(out)) == n_odom


@pytest.mark.parametrize("text", ["", '{"type":"rig","sensors":[]}\nnotjson\n'])
def test_a_log_without_one_usable_record_fails(run_cli, tmp_path, text):
    # every line malformed (or none at all): exit 2 with a line saying so, after the
    # malformed lines are listed; before session 15 it exited 0 with a bare header
    log = tmp_path / "bad.jsonl"
    log.write_text(text)
    proc = run_cli("localize", str(log), "--map", ROOM, "--method", "odometry")
    assert proc.returncode == 2
    assert "no usable record" in proc.stderr.strip().splitlines()[-1]
    assert proc.stdout.strip().splitlines() == [",".join(COLUMNS)]


def test_no_init_needs_init_flag(run_cli, room_log, tmp_path):
    lines = [ln for ln in room_log.read_text().splitlines()[:300] if '"init"' not in ln]
    log = tmp_path / "noinit.jsonl"
    log.write_text("\n".join(lines) + "\n")
    proc = run_cli("localize", str(log), "--map", ROOM, "--method", "odometry")
    assert proc.returncode == 2 and "--init" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    out = tmp_path / "p.csv"
    ok = run_cli("localize", str(log), "--map", ROOM, "--method", "odometry", "--init",
                 "-1.0,1.0,-90", "--out", str(out), check=True)
    assert ok.returncode == 0
    track = read_poses_csv(out)
    assert track.x_m[0] == pytest.approx(-1.0) and math.degrees(track.yaw_rad[0]) == \
        pytest.approx(-90.0)


@pytest.mark.parametrize("bad", ["1,2", "a,b,c", "1,2,nan"])
def test_bad_init_value(run_cli, room_log, bad):
    proc = run_cli("localize", str(room_log), "--map", ROOM, "--init", bad)
    assert proc.returncode == 2 and "--init" in proc.stderr


def test_bad_map_and_missing_log(run_cli, room_log, tmp_path):
    bad_map = tmp_path / "m.geojson"
    bad_map.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature"}]}')
    proc = run_cli("localize", str(room_log), "--map", str(bad_map))
    assert proc.returncode == 2 and "feature 0" in proc.stderr
    proc = run_cli("localize", str(tmp_path / "nope.jsonl"), "--map", ROOM)
    assert proc.returncode == 2 and "nope.jsonl" in proc.stderr


def test_localize_kuc_default_method(run_cli, room_log, tmp_path):
    out = tmp_path / "kuc.csv"
    proc = run_cli("localize", str(room_log), "--map", ROOM, "--out", str(out), "--status",
                   check=True)
    assert " segments; " in proc.stderr and " fused; " in proc.stderr  # batch: not fitted
    track = read_poses_csv(out)
    truth = _truth(room_log)
    err = np.array([math.hypot(x - truth[t][0], y - truth[t][1])
                    for t, x, y in zip(track.t_s, track.x_m, track.y_m, strict=True)])
    steady = track.t_s > 5.0
    assert np.sqrt(np.mean(err[steady] ** 2)) < 0.02
    status = out.read_text().splitlines()[-1].rsplit(",", 1)[1]
    assert status == "tracking"


def test_specular_and_conventional_both_run(run_cli, room_log, tmp_path):
    for method in ("specular", "conventional"):
        out = tmp_path / f"{method}.csv"
        run_cli("localize", str(room_log), "--map", ROOM, "--out", str(out), "--method",
                method, check=True)
        assert len(read_poses_csv(out)) > 200


finite = st.floats(-1e6, 1e6, allow_nan=False)


@given(finite, finite, finite)
def test_parse_init_round_trip(x, y, yaw):
    assert parse_pose(f"{x!r},{y!r},{yaw!r}", "--init") == (x, y, yaw)


@given(st.text(max_size=30))
def test_parse_init_garbage_names_the_flag(text):
    try:
        parse_pose(text, "--init")
    except ValueError as err:
        assert "--init" in str(err)


def test_pose_writer_round_trips_through_the_reader(rng):
    buf = io.StringIO()
    w = PoseCsvWriter(buf, with_status=True)
    states = []
    for k in range(20):
        a = rng.normal(size=(3, 3))
        g = Gaussian(rng.normal(size=3) * [5, 5, 1], a @ a.T + np.eye(3) * 1e-3)
        states.append(g)
        w.write(OdomRecord(0.05 * k, 0, 0, 0),
                PoseEstimate(0.05 * k, g, np.zeros(3), np.zeros(3), "tracking", "ok"))
    track = read_poses_csv(io.StringIO(buf.getvalue()))
    assert np.allclose(track.cov, np.array([g.cov for g in states]), rtol=1e-12, atol=0)
    assert np.allclose(track.yaw_rad, [g.mean[2] for g in states], atol=1e-12)


def test_localize_online_flag_gives_the_same_rows_count(run_cli, room_log, tmp_path):
    """--online feeds the Localizer record by record; the default replays in batches."""
    a, b = tmp_path / "batch.csv", tmp_path / "online.csv"
    run_cli("localize", str(room_log), "--map", ROOM, "--out", str(a), check=True)
    proc = run_cli("localize", str(room_log), "--map", ROOM, "--out", str(b), "--online",
                   check=True)
    ta, tb = read_poses_csv(a), read_poses_csv(b)
    assert np.array_equal(ta.t_s, tb.t_s)
    assert "landmarks fitted" in proc.stderr
    # the same landmarks, fused on time (batch) or when fitted (online): after the
    # warm-up (the prior is off by ~5 cm) the estimates agree closely
    steady = ta.t_s > 5.0
    assert np.max(np.hypot(ta.x_m - tb.x_m, ta.y_m - tb.y_m)[steady]) < 0.02


def test_odom_gap_flag(run_cli, room_log, tmp_path):
    """Odometry thinned to 2 Hz (a slow base, or a throttled bag): at the default gap
    (1 s) its readings are all placed; `--odom-gap 0.3` calls every interval a gap and
    skips the readings taken while moving, counted; a bad value names the flag."""
    lines = room_log.read_text().splitlines(keepends=True)
    kept, n_odom = [], 0
    for line in lines:
        if '"type":"odom"' in line.replace(" ", ""):
            n_odom += 1
            if n_odom % 10 != 1:  # 20 Hz -> 2 Hz
                continue
        kept.append(line)
    slow = tmp_path / "slow.jsonl"
    slow.write_text("".join(kept))
    proc = run_cli("localize", str(slow), "--map", ROOM, "--method", "conventional",
                   check=True)
    assert "odometry gaps" not in proc.stderr and "tof_in_odom_gap" not in proc.stderr
    proc = run_cli("localize", str(slow), "--map", ROOM, "--method", "conventional",
                   "--odom-gap", "0.3", check=True)
    assert "odometry gaps" in proc.stderr and "tof_in_odom_gap" in proc.stderr
    proc = run_cli("localize", str(slow), "--map", ROOM, "--odom-gap", "0")
    assert proc.returncode == 2 and "--odom-gap" in proc.stderr


def test_a_still_robot_s_skipped_readings_are_counted_in_the_summary(run_cli, tmp_path):
    """`sonarloc localize` on a robot standing still: the observations not fused
    because their map feature was fused from there already are named in the summary
    (the library tests cover every method, online and in batch)."""
    path = tmp_path / "still.jsonl"
    with LogWriter(path) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=2.0,
                                     at=(3.0, 1.5, 20.0), seed=3))
    proc = run_cli("localize", str(path), "--map", ROOM, "--status", check=True)
    assert "no_motion_since_fused" in proc.stderr
    assert proc.stdout.splitlines()[-1].endswith(",tracking")


def test_max_tof_takes_a_module_s_timeouts_as_no_echo(run_cli, room_log, tmp_path):
    """A module that logs its timeout as a reading (62,000 us) instead of no echo:
    `localize --max-tof 62000` gives the clean log's poses, batch and online, and counts
    the timeouts; without it the readings are taken as echoes 10.6 m away."""
    text = room_log.read_text()
    n_none = text.count('"tof_us":null')
    assert n_none > 100
    sat = tmp_path / "timeouts.jsonl"
    sat.write_text(text.replace('"tof_us":null', '"tof_us":62000.0'))

    def poses(log, *flags):
        out = tmp_path / "poses.csv"
        proc = run_cli("localize", str(log), "--map", ROOM, "--out", str(out), *flags,
                       check=True)
        return out.read_text(), proc.stderr

    for mode in ((), ("--online",)):
        want, clean_err = poses(room_log, *mode)
        assert "timeouts" not in clean_err and "timeout" not in clean_err
        # without the flag: the summary names it (the echoes pile up at 62,000 us)
        assert "--max-tof 62000 takes them as no echo" in poses(sat, *mode)[1]
        got, err = poses(sat, "--max-tof", "62000", *mode)
        assert got == want
        assert f"{n_none} timeouts taken as no echo" in err
    assert poses(sat)[0] != poses(room_log)[0]
    bad = run_cli("localize", str(sat), "--map", ROOM, "--max-tof", "0")
    assert bad.returncode == 2 and "--max-tof" in bad.stderr and "max_tof_us" in bad.stderr


@pytest.mark.parametrize(("flag", "value"), [("--odom-max-speed", "0"),
                                             ("--odom-max-yaw-rate", "-5")])
def test_odom_limit_flags_name_themselves(run_cli, room_log, flag, value):
    proc = run_cli("localize", str(room_log), "--map", ROOM, flag, value)
    assert proc.returncode == 2 and flag in proc.stderr


def test_odom_max_speed_flag_reaches_the_jump_detector(run_cli, room_log, tmp_path):
    """The simulated robot drives at ~0.3 m/s: a 0.05 m/s limit takes every odometry
    increment as a jump (counted), inf or the default none."""
    out = tmp_path / "poses.csv"
    slow = run_cli("localize", str(room_log), "--map", ROOM, "--out", str(out),
                   "--odom-max-speed", "0.05", check=True)
    assert "odometry jumps" in slow.stderr
    for value in ("inf", None):
        flags = () if value is None else ("--odom-max-speed", value)
        proc = run_cli("localize", str(room_log), "--map", ROOM, "--out", str(out), *flags,
                       check=True)
        assert "odometry jumps" not in proc.stderr


def test_an_exact_init_record_is_a_prior(run_cli, tmp_path):
    """An init record with SDs of 0 (exact, as a simulation writes its truth): `map build`
    took it, `localize` stopped with "`sd_xy_m` must be positive and finite". It is
    the prior at EXACT_PRIOR_SD_M / _RAD now, in the API too."""
    from sonarloc.api import LocalizerNode
    from sonarloc.io.logfile import EXACT_PRIOR_SD_M, InitRecord

    log = tmp_path / "exact.jsonl"
    with LogWriter(log) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=6.0, seed=3,
                                     init_sd_xy_m=0.0, init_sd_yaw_deg=0.0))
    (init,) = [r for r in iter_log(log) if isinstance(r, InitRecord)]
    assert init.sd_xy_m == 0.0 and init.sd_yaw_deg == 0.0
    out = tmp_path / "poses.csv"
    run_cli("localize", str(log), "--map", ROOM, "--out", str(out), check=True)
    track, truth = read_poses_csv(out), _truth(log)
    err = [math.hypot(x - truth[t][0], y - truth[t][1])
           for t, x, y in zip(track.t_s, track.x_m, track.y_m, strict=True)]
    assert max(err) < 0.01
    node = LocalizerNode(FeatureMap.from_map(load_map(ROOM)))
    node.feed(init)
    node.odometry(init.t_s, 0.0, 0.0, 0.0)
    assert node.covariance[0, 0] == pytest.approx(EXACT_PRIOR_SD_M**2)
