"""The status says `tracking` only while the features confirmed lately pin x, y and yaw:
the rule (two points 0.1 m apart, a point and a wall, two walls 5 deg apart), its time
window, and simulated drives with one pole (never `tracking`, though 14 cm off) and two
(tracking at millimetres), online and in the batch replay alike."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from sonarloc.io.logfile import LogWriter, TruthRecord, iter_log
from sonarloc.localize.confirmed import (
    MIN_POINT_SEPARATION_M,
    MIN_WALL_ANGLE_DEG,
    POSE,
    ConfirmedFeatures,
    missing_dof,
)
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import Localizer
from sonarloc.localize.replay import replay_log
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records
from tests.conftest import MAPS


def _map(points=(), walls=()) -> FeatureMap:
    return FeatureMap.build(np.asarray(points, float).reshape(-1, 2),
                            np.asarray(walls, float).reshape(-1, 2, 2))


def _wall(deg: float, offset: float = 0.0) -> list[list[float]]:
    """A 2 m wall in direction ``deg``, shifted ``offset`` along its normal."""
    d = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
    n = np.array([-d[1], d[0]])
    p0 = np.array([1.0, 1.0]) + offset * n
    return [p0.tolist(), (p0 + 2.0 * d).tolist()]


def test_two_points_must_be_apart():
    fm = _map([[1.0, 1.0], [1.06, 1.0], [1.0, 1.0 + MIN_POINT_SEPARATION_M + 1e-6]])
    assert missing_dof(fm, [("point", 0)], 5.0) == \
        "only one point landmark (p0) confirmed in the last 5 s: yaw unconstrained"
    close = missing_dof(fm, [("point", 0), ("point", 1)], 5.0)
    assert close == ("only point landmarks less than 0.1 m apart (p0, p1) confirmed in the "
                     "last 5 s: yaw unconstrained")
    assert missing_dof(fm, [("point", 0), ("point", 2)], 5.0) == ""
    assert missing_dof(fm, [("point", 1), ("point", 0), ("point", 2)], 5.0) == ""


def test_parallel_walls_leave_the_position_along_them():
    fm = _map(walls=[_wall(0.0), _wall(180.0, 3.0), _wall(MIN_WALL_ANGLE_DEG - 0.5, 1.0),
                     _wall(MIN_WALL_ANGLE_DEG + 0.5, 2.0), _wall(90.0)])
    assert missing_dof(fm, [("wall", 0)], 5.0) == \
        "only one wall (w0) confirmed in the last 5 s: position along it unconstrained"
    # the two faces of a corridor, opposite normals: the same direction
    par = missing_dof(fm, [("wall", 0), ("wall", 1), ("wall", 2)], 5.0)
    assert par == ("only walls within 5 deg of parallel (w0, w1, w2) confirmed in the last "
                   "5 s: position along them unconstrained")
    assert missing_dof(fm, [("wall", 0), ("wall", 3)], 5.0) == ""
    assert missing_dof(fm, [("wall", 1), ("wall", 4)], 5.0) == ""


def test_a_point_and_a_wall_pin_the_pose():
    fm = _map([[1.0, 1.0]], [_wall(30.0)])
    assert missing_dof(fm, [("point", 0), ("wall", 0)], 5.0) == ""
    assert missing_dof(fm, [(POSE, -1)], 5.0) == ""  # a relocalization fix
    assert missing_dof(fm, [], 5.0) == "no landmark confirmed in the last 5 s"


def test_the_record_keeps_one_entry_per_feature_in_the_window():
    rec = ConfirmedFeatures()
    for k in range(1000):
        rec.add(0.01 * k, "point", k % 3)
        rec.add(0.01 * k, "wall", 7)
    assert len(rec) == 4 and rec.newest_s == pytest.approx(9.99)
    rec.add(12.0, "wall", 2)
    assert rec.recent(9.985) == [("point", 0), ("wall", 2), ("wall", 7)]
    assert len(rec) == 3   # older ones dropped
    rec.add(5.0, "wall", 2)  # an older confirmation does not move the latest back
    assert rec.recent(11.0) == [("wall", 2)]


def test_localizer_status_follows_the_window():
    """A point confirmed at 1 s and a wall at 2 s: tracking until the point is older than
    ``dead_reckoning_after_s`` (5 s), then dead reckoning along the wall."""
    fm = _map([[3.0, 1.0]], [_wall(0.0), _wall(0.0, 2.0)])
    loc = Localizer(fm)
    loc.set_prior(0.0, 1.0, 1.5, 0.0, 0.01, 0.01)

    def at(t):
        est = loc.on_odom(t, 0.1 * t, 0.0, 0.0)
        assert est is not None
        return est.status, est.reason

    assert at(0.0) == ("dead_reckoning", "no landmark fused yet (0.0 s since the prior)")
    loc.confirm(1.0, "point", 0)
    assert at(1.5) == ("dead_reckoning", "only one point landmark (p0) confirmed in the last "
                                         "5 s: yaw unconstrained")
    loc.confirm(2.0, "wall", 0)
    assert at(2.5) == ("tracking", "ok")
    assert at(6.0) == ("tracking", "ok")
    assert at(6.1)[0] == "dead_reckoning" and "only one wall (w0)" in at(6.1)[1]
    loc.confirm(6.2, "wall", 1)   # the other, parallel, wall
    assert "only walls within 5 deg of parallel (w0, w1)" in at(6.3)[1]
    assert at(12.0) == ("dead_reckoning", "no landmark fused for 5.8 s")


def _one_lap(ids: set[str], tmp_path: Path, seed: int = 4, duration_s: float = 32.0
             ) -> tuple[FeatureMap, str]:
    """A map (and world) of the room's features ``ids`` and its route; a drive along it."""
    doc = json.loads((MAPS / "room.geojson").read_text())
    doc["features"] = [f for f in doc["features"] if f["properties"]["id"] in ids | {"loop"}]
    path = tmp_path / "map.geojson"
    path.write_text(json.dumps(doc))
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(path), ring16(), duration_s=duration_s,
                                     seed=seed))
    return FeatureMap.from_map(load_map(path)), buf.getvalue()


def _rows(fmap: FeatureMap, text: str, mode: str) -> list[tuple[float, float, str, str]]:
    truth = {r.t_s: (r.x_m, r.y_m) for r in iter_log(io.StringIO(text))
             if isinstance(r, TruthRecord)}
    rows: list[tuple[float, float, str, str]] = []

    def keep(rec, est) -> None:
        x, y = truth[rec.t_s]
        rows.append((rec.t_s, math.hypot(est.x_m - x, est.y_m - y), est.status, est.reason))

    replay_log(io.StringIO(text), fmap, mode=mode, on_estimate=keep)
    return rows


def test_one_pole_drive_is_never_tracking(tmp_path):
    """One pole (pole-c), the room's route, seed 4: its readings are fused all along, yet
    the estimate drifts 10-14 cm off from 21 s on (yaw and the position around the pole
    are unobservable: the prior's yaw error stays; seed 4 draws a 3-sigma one, and over
    30 seeds the covariance covers the error, NEES ~3). The status said `tracking`
    throughout (69 % of the rows of a 120 s drive > 10 cm off); now `dead_reckoning`."""
    fmap, text = _one_lap({"pole-c"}, tmp_path)
    for mode in ("online", "batch"):
        rows = _rows(fmap, text, mode)
        off = [r for r in rows if r[1] > 0.1 and r[0] > 5.0]
        assert len(off) > 0.2 * len(rows), mode   # the case this is about
        assert not [r for r in rows if r[2] == "tracking"], mode
        assert rows[-1][3] == ("only one point landmark (pole-c) confirmed in the last 5 s: "
                               "yaw unconstrained"), mode


def test_two_pole_drive_tracks(tmp_path):
    """Two poles 3.1 m apart on the same drive: tracking at millimetres once both are
    seen, online and batch (the same statuses)."""
    fmap, text = _one_lap({"pole-a", "pole-b"}, tmp_path)
    on, ba = _rows(fmap, text, "online"), _rows(fmap, text, "batch")
    for rows in (on, ba):
        late = [r for r in rows if r[0] > 5.0]
        assert all(r[2] == "tracking" for r in late)
        assert max(r[1] for r in late) < 0.02
    same = np.mean([a[2] == b[2] for a, b in zip(on, ba, strict=True)])
    assert same > 0.98
