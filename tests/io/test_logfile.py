import io
import json

import pytest

from sonarloc.errors import LogFormatError
from sonarloc.io.logfile import (
    InitRecord,
    LogStats,
    LogWriter,
    OdomRecord,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
    iter_log,
)

RECORDS = [
    RigRecord((SensorMount(0, 0.2, 0.0, 0.0), SensorMount(1, 0.0, 0.2, 90.0)), 343.5),
    InitRecord(0.0, 1.0, 2.0, 30.0, 0.1, 5.0),
    OdomRecord(0.0, 0.0, 0.0, 0.0),
    TofRecord(0.01, 0, 8746.0),
    TofRecord(0.02, 1, None, pan_deg=-12.3),
    TruthRecord(0.02, 1.0, 2.0, 30.0),
]


def test_round_trip():
    buf = io.StringIO()
    LogWriter(buf).write_all(RECORDS)
    stats = LogStats()
    back = list(iter_log(io.StringIO(buf.getvalue()), stats))
    assert back == RECORDS
    assert stats.records == len(RECORDS) and stats.malformed_count == 0


def test_no_echo_is_null_and_pan_optional():
    buf = io.StringIO()
    LogWriter(buf).write_all([TofRecord(1.0, 3, None), TofRecord(1.0, 3, 900.0, 5.0)])
    lines = [json.loads(s) for s in buf.getvalue().splitlines()]
    assert lines[0] == {"type": "tof", "t_s": 1.0, "sensor": 3, "tof_us": None}
    assert lines[1]["pan_deg"] == 5.0


def test_bad_lines_are_named_counted_and_skipped():
    text = "\n".join([
        '{"type":"odom","t_s":0,"x_m":0,"y_m":0,"yaw_deg":0}',
        "{not json",
        '{"type":"odom","t_s":1,"x_m":"a","y_m":0,"yaw_deg":0}',
        '{"type":"imu","t_s":1.5}',
        '{"type":"tof","t_s":2,"sensor":0,"tof_us":1000}',
        '{"type":"tof","t_s":1.9,"sensor":0,"tof_us":NaN}',
        '{"type":"tof","t_s":1.8,"sensor":0,"tof_us":1200}',
        "[1, 2]",
        "[" * 100_000 + "]" * 100_000,  # deeper than json's recursion: it stopped the run
        '{"type":"odom","t_s":3,"x_m":0,"y_m":0,"yaw_deg":0}',
    ])
    stats = LogStats()
    recs = list(iter_log(io.StringIO(text), stats))
    assert [r.t_s for r in recs] == [0.0, 2.0, 1.8, 3.0]
    assert [ln for ln, _ in stats.malformed] == [2, 3, 6, 8, 9]
    assert "x_m" in stats.malformed[1][1]
    assert stats.unknown == {"imu": 1}
    assert stats.time_backwards == [(7, 2.0, 1.8)]
    assert "line 2" in stats.summary()


def test_strict_raises_with_line_number():
    with pytest.raises(LogFormatError, match="line 2"):
        list(iter_log(io.StringIO('{"type":"odom","t_s":0,"x_m":0,"y_m":0,"yaw_deg":0}\n{x\n'),
                      strict=True))


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(LogFormatError, match="cannot open log"):
        list(iter_log(tmp_path / "nope.jsonl"))


def test_a_rig_whose_speed_of_sound_is_not_air_is_malformed():
    # a rig record of 3 m/s (a typo, or another unit) was taken: every reading of the
    # log then matched nothing in the map, the run ended `lost` with no word of why
    rig = ('{"type":"rig","t_s":0,"sensors":[{"id":0,"x_m":0.2,"y_m":0,"yaw_deg":0}],'
           '"speed_of_sound_mps":%s}')
    for c in ("3", "3430", "0"):
        stats = LogStats()
        assert list(iter_log(io.StringIO(rig % c), stats)) == []
        ((line, msg),) = stats.malformed
        assert line == 1 and msg.startswith("`speed_of_sound_mps` must be within [250, 450]")
    (rec,) = iter_log(io.StringIO(rig % "331.3"))
    assert isinstance(rec, RigRecord) and rec.speed_of_sound_mps == 331.3


def test_an_init_record_with_a_bad_sd_is_malformed_and_named(run_cli, tmp_path):
    """An init record whose SD was negative or 1e300 (its square overflows) stopped
    `localize` with "`sd_yaw_rad` must be positive and finite" and no line number, and
    crashed `map build` (OverflowError). It is a malformed line now, named and skipped;
    `localize` says a prior is missing and which line was refused."""
    init = '{"type":"init","t_s":0,"x_m":1,"y_m":2,"yaw_deg":30,"sd_xy_m":%s,"sd_yaw_deg":%s}'
    for xy, yaw in (("0.1", "-5"), ("0.1", "1e300"), ("-0.1", "5"), ("1e200", "5")):
        stats = LogStats()
        assert list(iter_log(io.StringIO(init % (xy, yaw)), stats)) == []
        ((line, msg),) = stats.malformed
        assert line == 1 and msg.startswith("init record: field `sd_")
    for xy, yaw in ((0.1, 180.0), (0.0, 0.0)):   # 0: an exact prior (a simulation's)
        (rec,) = iter_log(io.StringIO(init % (xy, yaw)))
        assert rec == InitRecord(0.0, 1.0, 2.0, 30.0, xy, yaw)
    log = tmp_path / "bad_init.jsonl"
    with LogWriter(log) as w:
        w.write_all([RECORDS[0], RECORDS[2], RECORDS[3]])
    lines = log.read_text().splitlines()
    log.write_text("\n".join([lines[0], init % ("0.1", "-1e300"), *lines[1:]]) + "\n")
    proc = run_cli("localize", str(log), "--map", "maps/room.geojson")
    assert proc.returncode == 2
    assert "no `init` record" in proc.stderr and "line 2: init record: field `sd_yaw_deg`" \
        in proc.stderr
    built = run_cli("map", "build", str(log), "--out", str(tmp_path / "m.geojson"))
    assert "Traceback" not in built.stderr and "line 2" in built.stderr


def test_odom_reset_round_trip_and_old_lines():
    """``"reset": true`` (FORMATS.md §4 extension) survives a round trip; it is written
    only when true, so a log without resets is byte for byte as before."""
    recs = [OdomRecord(0.0, 1.0, 2.0, 30.0), OdomRecord(0.1, 0.0, 0.0, 0.0, reset=True)]
    buf = io.StringIO()
    LogWriter(buf).write_all(recs)
    lines = buf.getvalue().splitlines()
    assert lines[0] == '{"type":"odom","t_s":0.0,"x_m":1.0,"y_m":2.0,"yaw_deg":30.0}'
    assert json.loads(lines[1]) == {"type": "odom", "t_s": 0.1, "x_m": 0.0, "y_m": 0.0,
                                    "yaw_deg": 0.0, "reset": True}
    assert list(iter_log(io.StringIO(buf.getvalue()), strict=True)) == recs
    # "reset": false is read (as absent); anything but a boolean is named
    text = ('{"type":"odom","t_s":0.2,"x_m":0,"y_m":0,"yaw_deg":0,"reset":false}\n'
            '{"type":"odom","t_s":0.3,"x_m":0,"y_m":0,"yaw_deg":0,"reset":1}\n')
    stats = LogStats()
    back = list(iter_log(io.StringIO(text), stats))
    assert back == [OdomRecord(0.2, 0.0, 0.0, 0.0)]
    assert stats.malformed == [(2, "field `reset` must be true or false, got 1")]
