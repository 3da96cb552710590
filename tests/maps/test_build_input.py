"""Map building on odd input: every reading gets a true pose or is counted, never a
made-up one; what the builder writes always loads."""

import io
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import (
    InitRecord,
    LogWriter,
    OdomRecord,
    RigRecord,
    TofRecord,
    TruthRecord,
)
from sonarloc.io.posescsv import PoseTrack
from sonarloc.maps.build import BuildConfig, MapBuilder, build_from_log
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records
from tests.conftest import MAPS

ROOM = MAPS / "room.geojson"


@pytest.fixture(scope="module")
def records():
    """20 s of the room's route, ring16."""
    return list(simulate_records(load_map(ROOM), ring16(), duration_s=20.0, seed=3))


def log_text(recs):
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(recs)
    return buf.getvalue()


def truth_track(recs, t_min=-np.inf, t_max=np.inf):
    tr = [r for r in recs if isinstance(r, TruthRecord) and t_min <= r.t_s <= t_max]
    return PoseTrack(np.array([r.t_s for r in tr]), np.array([r.x_m for r in tr]),
                     np.array([r.y_m for r in tr]), np.radians([r.yaw_deg for r in tr]),
                     np.zeros((len(tr), 3, 3)))


def build(recs, poses=None, **cfg):
    return build_from_log(io.StringIO(log_text(recs)), poses, BuildConfig(**cfg))


def test_readings_outside_the_poses_are_counted_not_extrapolated(records):
    # poses for 5..12 s of a 20 s log: the readings before and after have no pose; they
    # were given the first / last pose (the robot parked there for 13 s)
    result = build(records, truth_track(records, 5.0, 12.0), min_observations=2)
    tofs = [r.t_s for r in records if isinstance(r, TofRecord)]
    inside = sum(5.0 <= t <= 12.0 for t in tofs)
    assert result.readings == inside > 0
    assert result.skipped["tof_outside_poses"] == len(tofs) - inside
    assert "tof_outside_poses" in result.summary()
    alone = build([r for r in records if isinstance(r, RigRecord) or 5.0 <= r.t_s <= 12.0],
                  truth_track(records, 5.0, 12.0), min_observations=2)
    assert result.geojson() == alone.geojson() and result.builder.features()


def test_pose_rows_going_back_in_time_are_dropped(records):
    # `sonarloc localize` writes a row for an odom record whose time went backwards:
    # the older time with the estimate of the later one
    track = truth_track(records)
    k = 150
    back = PoseTrack(*(np.insert(a, k, v, axis=0) for a, v in (
        (track.t_s, 0.3), (track.x_m, track.x_m[k - 1]), (track.y_m, track.y_m[k - 1]),
        (track.yaw_rad, track.yaw_rad[k - 1]), (track.cov, track.cov[k - 1]))))
    result = build(records, back)
    assert result.skipped["poses_time_backwards"] == 1
    assert result.geojson() == build(records, track).geojson()


def test_readings_after_the_last_odometry_are_counted(records):
    cut = [r for r in records if not (isinstance(r, OdomRecord) and r.t_s > 15.0)]
    last = max(r.t_s for r in cut if isinstance(r, OdomRecord))
    result = build(cut)
    tofs = [r.t_s for r in cut if isinstance(r, TofRecord)]
    # those at the last odometry's time (written after it) are placed
    assert result.readings == sum(t <= last for t in tofs)
    assert result.skipped["tof_after_last_odom"] == sum(t > last for t in tofs) > 0
    assert "no init record" not in result.summary()


def test_an_init_after_readings_leaves_one_map_frame(records):
    # without init the map frame is the first odometry pose (said in the summary); an
    # init arriving after readings were placed there would move the rest of the map
    no_init = [r for r in records if not isinstance(r, InitRecord)]
    (init,) = [r for r in records if isinstance(r, InitRecord)]
    k = next(i for i, r in enumerate(no_init) if isinstance(r, OdomRecord) and r.t_s >= 2.0)
    late = no_init[:k] + [InitRecord(no_init[k].t_s, init.x_m, init.y_m, init.yaw_deg,
                                     init.sd_xy_m, init.sd_yaw_deg)] + no_init[k:]
    result, plain = build(late), build(no_init)
    assert result.skipped["init_after_readings"] == 1
    assert "no init record: the map frame is the first odometry pose" in plain.summary()
    assert result.geojson() == plain.geojson()


def _run_build(run_cli, tmp_path, recs, *args):
    log = tmp_path / "log.jsonl"
    log.write_text(log_text(recs), encoding="utf-8")
    out = tmp_path / "map.geojson"
    out.unlink(missing_ok=True)
    return run_cli("map", "build", str(log), "--out", str(out), *args), out


def test_cli_refuses_a_scan_csv_as_poses(run_cli, records, tmp_path):
    # a scan CSV (FORMATS.md section 1) has t_s,x_m,y_m,yaw_deg too, of the transducer;
    # the map was silently built from those poses
    scan = tmp_path / "scan.csv"
    scan.write_text("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n0.0,1.2,1.0,0.0,,0\n"
                    "0.0,1.0,1.2,90.0,17494.0,4\n", encoding="utf-8")
    proc, out = _run_build(run_cli, tmp_path, records, "--poses", str(scan))
    assert proc.returncode == 2 and not out.exists()
    (line,) = proc.stderr.strip().splitlines()
    assert "scan.csv: line 1: this is a scan CSV (column `tof_us`" in line


def test_cli_will_not_overwrite_its_input(run_cli, records, tmp_path):
    # `--out` naming the log replaced the recording with the map
    log = tmp_path / "log.jsonl"
    text = log_text([r for r in records if r.t_s <= 3.0])
    log.write_text(text, encoding="utf-8")
    proc = run_cli("map", "build", str(log), "--out", str(tmp_path / "." / "log.jsonl"))
    assert proc.returncode == 2 and "is the input LOG" in proc.stderr
    assert log.read_text(encoding="utf-8") == text


@pytest.mark.parametrize("keep", ["truth", "rig", "nothing", "no rig"])
def test_cli_fails_without_a_reading_to_build_from(run_cli, records, tmp_path, keep):
    recs = {"truth": [r for r in records if isinstance(r, TruthRecord)],
            "rig": records[:1], "nothing": [],
            "no rig": [r for r in records if not isinstance(r, RigRecord)]}[keep]
    proc, out = _run_build(run_cli, tmp_path, recs)
    assert proc.returncode == 2 and not out.exists()
    (line,) = proc.stderr.strip().splitlines()
    assert "no sonar reading with a pose" in line
    assert ("tof_before_rig" in line) == (keep == "no rig")


@pytest.mark.parametrize("case", ["no echoes", "one pass", "no init", "min-observations 1",
                                  "min-observations huge"])
def test_cli_output_always_loads(run_cli, records, tmp_path, case):
    recs, args = records, ()
    if case == "no echoes":
        recs = [TofRecord(r.t_s, r.sensor, None) if isinstance(r, TofRecord) else r
                for r in records]
    elif case == "one pass":
        recs = [r for r in records if r.t_s <= 6.0]
    elif case == "no init":
        recs = [r for r in records if not isinstance(r, InitRecord)]
    else:
        args = ("--min-observations", "1" if case.endswith("1") else str(10**30))
    proc, out = _run_build(run_cli, tmp_path, recs, *args)
    assert proc.returncode == 0, proc.stderr
    back = load_map(out)
    kinds = [f.kind for f in back.features]
    assert ("map: empty" in proc.stderr) == (not kinds)
    if case in ("no echoes", "min-observations huge"):
        assert not kinds
    if case in ("no init", "min-observations 1"):
        assert "wall" in kinds and len(kinds) >= 3
    if case == "no init":
        assert "no init record" in proc.stderr


def _landmark(kind, p, sd):
    cov = np.diag([sd**2, sd**2 if kind == "point" else (sd / 2) ** 2, 0.01])
    return Landmark(kind, np.array(p), cov, 1.0, 0.0, 10, 0.0, (0.0, 0.0, 0.0))


coord = st.floats(-5, 5, allow_nan=False, allow_infinity=False)
points = st.builds(lambda x, y, k, sd, vx, vy: ("point", [x, y, k], sd, [vx, vy], None),
                   coord, coord, st.sampled_from([0.15, 0.67, 2.68]), st.floats(1e-4, 0.05),
                   coord, coord)
walls = st.builds(lambda rho, a, sd, t0, dt: ("line", [rho, a, 0.15], sd, None, (t0, dt)),
                  st.floats(0.1, 5), st.sampled_from([0.0, 0.5 * np.pi, np.pi, 2.0, -1.0]),
                  st.floats(1e-4, 0.02), coord, st.floats(0.0, 3.0))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.one_of(points, walls), max_size=40), st.integers(1, 3))
def test_whatever_the_builder_merges_loads_as_a_map(items, min_obs):
    b = MapBuilder(BuildConfig(min_observations=min_obs))
    for kind, p, sd, view, extent in items:
        if kind == "point":
            b.add(_landmark(kind, p, sd), np.array(view))
            continue
        n = np.array([np.cos(p[1]), np.sin(p[1])])
        d = np.array([-n[1], n[0]])
        feet = p[0] * n + np.outer(np.linspace(extent[0], extent[0] + extent[1], 3), d)
        b.add(_landmark(kind, p, sd), p[0] * 0.5 * n, feet=feet)
    obj = b.geojson()
    m = map_from_geojson(json.loads(json.dumps(obj)))  # what `map build` writes
    assert len(m.features) == len(obj["features"])


def test_readings_inside_a_gap_of_the_poses_are_counted_not_interpolated(records):
    """Odometry (or pose rows) missing for 5 s while the robot drives: the readings in
    between would be placed on a pose interpolated across seconds of unknown motion;
    they are skipped and counted (`tof_in_odom_gap`), as the Localizer does, and the
    rest still builds the map. `odom_gap_s=inf` places them as before."""
    t0, t1 = 8.0, 13.0
    cut = [r for r in records if not (isinstance(r, OdomRecord) and t0 < r.t_s < t1)]
    inside = sum(isinstance(r, TofRecord) and t0 < r.t_s < t1 for r in records)
    assert inside > 500
    for poses in (None, truth_track([r for r in records
                                     if not (isinstance(r, TruthRecord) and t0 < r.t_s < t1)])):
        result = build(cut, poses, min_observations=2)
        assert result.skipped["tof_in_odom_gap"] == inside
        # built from odometry alone over metres, the summary says its drift is in the map
        drift = [n for n in result.notes if "poses from odometry alone over" in n]
        assert len(drift) == (poses is None), result.notes
        assert result.odom_travel_m > 5.0 and result.odom_turn_deg > 30.0
        assert result.readings == sum(isinstance(r, TofRecord) for r in records) - inside
        assert result.geojson()["features"]
    again = build(cut, None, min_observations=2, odom_gap_s=float("inf"))
    assert "tof_in_odom_gap" not in again.skipped
    with pytest.raises(ValueError, match="odom_gap_s"):
        BuildConfig(odom_gap_s=0.0)


def test_a_gap_of_a_robot_standing_still_keeps_its_readings():
    recs = list(simulate_records(load_map(ROOM), ring16(), duration_s=6.0,
                                 at=(2.0, 2.0, 30.0), seed=5))
    cut = [r for r in recs if not (isinstance(r, OdomRecord) and 1.0 < r.t_s < 4.0)]
    result = build(cut, min_observations=1)
    assert "tof_in_odom_gap" not in result.skipped
    assert result.odom_travel_m < 1e-9 and not any("drift" in n for n in result.notes)
    assert result.readings == sum(isinstance(r, TofRecord) for r in recs)


def test_cli_odom_gap_flag(records, tmp_path, run_cli):
    cut = [r for r in records if not (isinstance(r, OdomRecord) and 8.0 < r.t_s < 13.0)]
    proc, _ = _run_build(run_cli, tmp_path, cut, "--min-observations", "2")
    assert proc.returncode == 0 and "tof_in_odom_gap" in proc.stderr
    proc, _ = _run_build(run_cli, tmp_path, cut, "--odom-gap", "inf")
    assert proc.returncode == 0 and "tof_in_odom_gap" not in proc.stderr
    proc, _ = _run_build(run_cli, tmp_path, cut, "--odom-gap", "0")
    assert proc.returncode == 2 and "--odom-gap" in proc.stderr


def test_max_tof_takes_a_module_s_timeouts_as_no_echo(records, tmp_path, run_cli):
    """A module that logs its timeout as a reading (62,000 us): without `--max-tof` the
    build says the readings look like timeouts and names the flag; with `--max-tof 62000`
    the map is the clean log's, byte for byte, and the timeouts are counted. The odometry
    limits reach the jump detector and a bad value names its flag (as `localize`)."""
    text = log_text(records)
    n_none = text.count('"tof_us":null')
    assert n_none > 100
    sat = [TofRecord(r.t_s, r.sensor, 62000.0 if r.tof_us is None else r.tof_us, r.pan_deg)
           if isinstance(r, TofRecord) else r for r in records]
    clean, out = _run_build(run_cli, tmp_path, records)
    clean_map = out.read_text()
    assert clean.returncode == 0 and "timeout" not in clean.stderr
    raw, _ = _run_build(run_cli, tmp_path, sat)
    assert raw.returncode == 0 and "--max-tof 62000 takes them as no echo" in raw.stderr
    fixed, out = _run_build(run_cli, tmp_path, sat, "--max-tof", "62000")
    assert fixed.returncode == 0 and out.read_text() == clean_map
    assert f"{n_none} timeouts taken as no echo" in fixed.stderr
    jumps, _ = _run_build(run_cli, tmp_path, records, "--odom-max-speed", "0.05")
    assert jumps.returncode == 0 and "odometry jumps" in jumps.stderr
    for flag, value in (("--max-tof", "0"), ("--odom-max-speed", "-1"),
                        ("--odom-max-yaw-rate", "0")):
        bad, _ = _run_build(run_cli, tmp_path, records, flag, value)
        assert bad.returncode == 2 and flag in bad.stderr
