"""Report pieces: trajectory errors, landmarks moved into map, the drive report and figure."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.report.drive import (
    DriveReport,
    SegmentView,
    drive_figure,
    map_from_odom,
)
from sonarloc.report.metrics import track_error
from sonarloc.report.plots import landmark_model_us
from sonarloc.report.progress import Progress


def test_track_error_known_offsets():
    t = np.arange(0, 10, 0.5)
    truth = np.stack([t, t, np.zeros_like(t), np.full_like(t, math.pi - 0.01)], -1)
    est = truth.copy()
    est[:, 2] += 0.03  # 3 cm off everywhere
    est[:, 3] = -math.pi + 0.01  # 0.02 rad across the wrap
    e = track_error(est, truth)
    assert e.rmse_m == pytest.approx(0.03) and e.max_m == pytest.approx(0.03)
    assert e.yaw_rmse_deg == pytest.approx(math.degrees(0.02))
    assert e.n == len(t)
    # times outside the truth span are not compared
    late = est.copy()
    late[:, 0] += 100
    assert track_error(late, truth).n == 0 and math.isnan(track_error(late, truth).rmse_m)


def _lm(kind, params, cov=None, ref=(0.0, 0.0, 0.0)):
    return Landmark(kind, np.array(params, float), np.eye(3) * 1e-4 if cov is None else cov,
                    1.0, 0.3, 20, 1.0, ref)


pose = st.tuples(st.floats(-10, 10), st.floats(-10, 10), st.floats(-math.pi, math.pi))


@settings(max_examples=60, deadline=None)
@given(T=pose, s=pose, p=st.tuples(st.floats(-5, 5), st.floats(-5, 5)),
       wall=st.tuples(st.floats(0.1, 5), st.floats(-math.pi, math.pi)))
def test_transformed_landmark_keeps_what_a_sensor_sees(T, s, p, wall):
    """A sensor pose moved along with the landmark sees the same TOF and angle."""
    # A sensor sitting on the point or the wall has no defined bearing to it.
    assume(math.hypot(p[0] - s[0], p[1] - s[1]) > 1e-3)
    assume(abs(s[0] * math.cos(wall[1]) + s[1] * math.sin(wall[1]) - wall[0]) > 1e-3)
    c, si = math.cos(T[2]), math.sin(T[2])
    s_map = (c * s[0] - si * s[1] + T[0], si * s[0] + c * s[1] + T[1], s[2] + T[2])
    for lm in (_lm("point", [p[0], p[1], 0.67]), _lm("line", [wall[0], wall[1], 0.15])):
        moved = lm.transformed(T)
        a = landmark_model_us(lm, s[0], s[1], s[2])
        b = landmark_model_us(moved, *s_map)
        assert float(b[0]) == pytest.approx(float(a[0]), rel=1e-9, abs=1e-6)
        assert math.remainder(float(b[1]) - float(a[1]), 2 * math.pi) == pytest.approx(0, abs=1e-7)
        if lm.kind == "line":
            assert moved.params[0] >= 0


def test_point_covariance_rotates():
    lm = _lm("point", [1.0, 0.0, 1.0], np.diag([4e-4, 1e-4, 0.01]))
    moved = lm.transformed((0.0, 0.0, math.pi / 2))
    assert np.diag(moved.cov) == pytest.approx([1e-4, 4e-4, 0.01])


def test_map_from_odom_inverts_composition():
    est = np.array([[1.0, 2.0, 0.5]])
    odo = np.array([[-3.0, 0.5, -1.0]])
    T = map_from_odom(est, odo)[0]
    c, s = math.cos(T[2]), math.sin(T[2])
    assert (c * odo[0, 0] - s * odo[0, 1] + T[0], s * odo[0, 0] + c * odo[0, 1] + T[1]) == \
        pytest.approx((1.0, 2.0))


def test_report_json_and_text():
    r = DriveReport(map="room", rig="ring16", device="can", seed=1, duration_s=60.0,
                    pose_rmse_m=0.012, yaw_rmse_deg=0.3, odom_pose_rmse_m=0.24,
                    landmarks_fitted=40, wall_time_s=12.0, plot="out.png")
    obj = r.to_json()
    json.dumps(obj)  # JSON-ready: NaN became None
    for key in ("pose_rmse_m", "yaw_rmse_deg", "landmarks_fitted", "wall_time_s", "plot"):
        assert key in obj
    assert obj["improvement_over_odometry"] == pytest.approx(20.0)
    assert obj["odom_yaw_rmse_deg"] is None
    text = r.text()
    assert "1.2 cm" in text and "24.0 cm" in text and "20.0x better" in text


def test_progress_only_on_a_tty():
    quiet = io.StringIO()
    with Progress(10, "x", stream=quiet) as p:
        p.update(5)
    assert quiet.getvalue() == ""
    loud = io.StringIO()
    with Progress(10, "drive", stream=loud, enabled=True) as p:
        p.update(10)
    assert "drive [" in loud.getvalue() and "10/10" in loud.getvalue()


def test_drive_figure_writes_png(tmp_path: Path):
    pytest.importorskip("matplotlib")
    t = np.linspace(0, 10, 50)
    truth = np.stack([t, t / 2, np.sin(t / 3), np.zeros_like(t)], -1)
    lm = _lm("point", [2.0, 1.0, 0.67])
    yaw = np.radians(np.linspace(-15, 15, 40)) + math.atan2(1.0, 2.0)
    tof, _ = landmark_model_us(lm, np.zeros(40), np.zeros(40), yaw)
    seg = SegmentView(lm, np.zeros(40), np.zeros(40), yaw, tof + 0.5, "pole")
    wall = _lm("line", [3.0, math.pi / 2, 0.15])
    bad = Landmark("point", np.array([1.0, 1.0, 1.0]), np.eye(3), 1, 0, 3, 0, (0, 0, 0),
                   status=FitStatus.TOO_FEW_POINTS)
    mp = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"kind": "wall"},
         "geometry": {"type": "LineString", "coordinates": [[0, 3], [6, 3]]}},
        {"type": "Feature", "properties": {"kind": "pole", "radius_m": 0.04},
         "geometry": {"type": "Point", "coordinates": [2, 1]}}]}
    rep = DriveReport(map="test", rig="ring16", device="can", seed=0, duration_s=10.0)
    out = drive_figure(tmp_path / "d.png", map_source=mp, tracks={"truth": truth},
                       landmarks=[(lm, True), (wall, False), (bad, False)],
                       segments=[seg], report=rep)
    assert out.read_bytes()[:4] == b"\x89PNG" and out.stat().st_size > 20_000
