"""`sonarloc rosbag import` of a damaged bag: one line naming the bag and the trouble."""

from __future__ import annotations

import pytest

pytest.importorskip("rosbags")


def test_damaged_ros2_metadata_is_one_line(run_cli, tmp_path) -> None:
    # A bag directory whose metadata.yaml was cut short (the recorder killed): the
    # error quoted rosbags' five-line YAML parser report.
    poses, bag = tmp_path / "p.csv", tmp_path / "bag2"
    poses.write_text("t_s,x_m,y_m,yaw_deg,cov_xx,cov_xy,cov_xt,cov_yy,cov_yt,cov_tt\n"
                     "0.0,1,2,30,0.01,0,0,0.01,0,0.001\n")
    run_cli("rosbag", "export", str(poses), "--out", str(bag), check=True)
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text()[:40] + "\n  bad: [\n")
    proc = run_cli("rosbag", "import", str(bag), "--out", str(tmp_path / "log.jsonl"))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"sonarloc rosbag: error: bag {bag}: ")
