"""Pose CSV reader (FORMATS.md section 5): what it refuses, naming the file and line."""

import io
import math

import numpy as np
import pytest

from sonarloc.errors import LogFormatError
from sonarloc.io.posescsv import COLUMNS, PoseTrack, read_poses_csv, write_poses_csv

HEADER = ",".join(COLUMNS)
ROW = "0.5,1.0,2.0,90.0,0.01,0.0,0.0,0.01,0.0,0.001"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        # a scan CSV (section 1) has the same pose columns, but of the transducer
        ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n0.0,1.2,1.0,0.0,8800.0,0\n",
         r"line 1: this is a scan CSV \(column `tof_us`"),
        ("", "line 1: empty file"),
        (HEADER + "\n", "line 2: no pose rows"),
        (HEADER + "\n\n \n", "line 2: no pose rows"),
        ("t_s,x_m,yaw_deg\n0,1,0\n", "line 1: missing column `y_m`"),
        (HEADER + "\n" + ROW + "\n0.6,nan,2,90\n", "line 3: column `x_m` must be finite"),
        (HEADER + "\n" + ROW + "\n0.6,1,inf,90\n", "line 3: column `y_m` must be finite"),
        (HEADER + "\n" + ROW + "\n0.6,1,two,90\n", "line 3: column `y_m` must be a number"),
        (HEADER + "\n" + ROW + "\n0.6,1,2\n", "line 3: column `yaw_deg` must be a number, got ''"),
    ],
)
def test_bad_pose_csv_names_the_line(text, match):
    with pytest.raises(LogFormatError, match=match):
        read_poses_csv(io.StringIO(text))


def test_errors_name_the_file(tmp_path):
    path = tmp_path / "scan.csv"
    path.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,100\n", encoding="utf-8")
    with pytest.raises(LogFormatError, match=r"^pose CSV .*scan\.csv: line 1: this is a scan"):
        read_poses_csv(path)
    path.write_bytes(b"t_s,x_m,y_m,yaw_deg\n0,\xff,0,0\n")
    with pytest.raises(LogFormatError, match=r"scan\.csv is not UTF-8 text"):
        read_poses_csv(path)


def test_byte_order_mark_and_rows_as_written(tmp_path):
    # a spreadsheet's byte-order mark is no part of the first column's name; rows whose
    # time repeats or goes back (where the log's odometry did) come as written
    path = tmp_path / "p.csv"
    path.write_text("\ufeff" + HEADER + "\n" + ROW + "\n0.5,1.1,2,90,1,0,0,1,0,1\n"
                    "0.4,1.2,2,90,1,0,0,1,0,1\n", encoding="utf-8")
    track = read_poses_csv(path)
    assert track.t_s.tolist() == [0.5, 0.5, 0.4] and track.x_m.tolist() == [1.0, 1.1, 1.2]
    assert track.yaw_rad[0] == pytest.approx(math.pi / 2) and track.cov[0, 2, 2] == 0.001


def test_round_trip_and_missing_covariance():
    t = np.array([0.0, 0.05, 0.1])
    track = PoseTrack(t, t + 1, t - 1, t * 2, np.tile(np.eye(3) * 0.01, (3, 1, 1)))
    buf = io.StringIO()
    write_poses_csv(buf, track)
    back = read_poses_csv(io.StringIO(buf.getvalue()))
    for name in ("t_s", "x_m", "y_m", "yaw_rad", "cov"):
        assert np.allclose(getattr(back, name), getattr(track, name), rtol=1e-15, atol=0)
    bare = read_poses_csv(io.StringIO("yaw_deg,t_s,y_m,x_m,status\n90,0.5,2,1,tracking\n"))
    assert bare.x_m.tolist() == [1.0] and np.isnan(bare.cov).all()
