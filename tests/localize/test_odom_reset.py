"""Odometry that restarts mid-drive (the base controller rebooted: its odometry begins
again at (0, 0, 0)): flagged ``reset`` in the log, or detected as a jump, it is not taken
as motion, online, in the batch replay and in map building; without the handling the
same log puts the estimate metres off."""

import io
import math

import numpy as np
import pytest

from sonarloc import se2
from sonarloc.api import LocalizerNode
from sonarloc.io.logfile import LogWriter, OdomRecord, TofRecord, TruthRecord, iter_log
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import LocalizerConfig
from sonarloc.localize.replay import replay_log
from sonarloc.maps.build import BuildConfig, build_from_log
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"
T_RESTART = 8.0
#: no jump detection and no flag: the behaviour before resets were handled
NO_HANDLING = dict(odom_max_speed_mps=math.inf, odom_max_yaw_rate_rad_s=math.inf)


@pytest.fixture(scope="module")
def drive():
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=16.0, seed=3))
    return list(iter_log(io.StringIO(buf.getvalue())))


@pytest.fixture(scope="module")
def fmap():
    return FeatureMap.from_map(load_map(ROOM))


def restarted(records, flag):
    """The drive with its odometry restarted at zero at ``T_RESTART`` (the first record
    of the new odometry flagged ``reset`` if ``flag``), as a log text."""
    out, ref = [], None
    for r in records:
        if isinstance(r, OdomRecord) and r.t_s >= T_RESTART:
            p = np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])
            first = ref is None
            if first:
                ref = p
            q = se2.between(ref, p)
            r = OdomRecord(r.t_s, float(q[0]), float(q[1]), math.degrees(q[2]),
                           reset=flag and first)
        out.append(r)
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(out)
    return buf.getvalue()


def _across(records):
    """Readings strictly between the last odom record before the restart and it."""
    odom_t = [r.t_s for r in records if isinstance(r, OdomRecord)]
    k = next(i for i, t in enumerate(odom_t) if t >= T_RESTART)
    return sum(isinstance(r, TofRecord) and odom_t[k - 1] < r.t_s < odom_t[k]
               for r in records)


def _run(text, fmap, mode, **config):
    rows = []
    res = replay_log(io.StringIO(text), fmap, mode=mode, config=LocalizerConfig(**config),
                     on_estimate=lambda r, e: rows.append((r, e)))
    return res, rows


def _errors(records, rows):
    truth = {r.t_s: r for r in records if isinstance(r, TruthRecord)}
    return [(r.t_s, math.hypot(e.x_m - truth[r.t_s].x_m, e.y_m - truth[r.t_s].y_m))
            for r, e in rows]


@pytest.mark.parametrize("flag", [True, False], ids=["flagged", "jump"])
@pytest.mark.parametrize("mode", ["online", "batch"])
def test_a_restarted_odometry_is_not_taken_as_motion(drive, fmap, mode, flag):
    """Before: 2.42 m off and lost (online), 2.41 m off (batch); now 0.34 mm, tracking."""
    text = restarted(drive, flag)
    res, rows = _run(text, fmap, mode)
    st = res.localizer.stats
    assert (st.odom_resets, st.odom_jumps) == ((1, 0) if flag else (0, 1))
    assert st.skipped["tof_across_odom_reset"] == _across(drive) > 0
    assert ("1 odometry resets" if flag else "1 odometry jumps") in st.summary()
    errs = _errors(drive, rows)
    # the reset's 10 cm SD is pulled in by the next landmarks: 15 mm at worst, then mm
    assert max(e for t, e in errs if t >= T_RESTART) < 0.03
    assert max(e for t, e in errs if t >= T_RESTART + 1.0) < 0.005
    assert errs[-1][1] < 0.002 and rows[-1][1].status == "tracking"
    for rec, est in rows[-5:]:  # map -> odom follows the new odometry frame
        assert np.allclose(est.odom_pose[:2], [rec.x_m, rec.y_m], atol=1e-9)
        assert np.allclose(se2.compose(est.map_to_odom, est.odom_pose), est.state.mean,
                           atol=1e-9)


@pytest.mark.parametrize("mode", ["online", "batch"])
def test_without_the_handling_a_restart_is_metres_off(drive, fmap, mode):
    """The contrast (the tests above can fail): no flag, no jump detection."""
    res, rows = _run(restarted(drive, False), fmap, mode, **NO_HANDLING)
    assert res.localizer.stats.odom_resets == res.localizer.stats.odom_jumps == 0
    assert _errors(drive, rows)[-1][1] > 1.0
    if mode == "online":
        assert rows[-1][1].status == "lost"


def test_online_and_batch_agree_across_a_reset(drive, fmap):
    text = restarted(drive, True)
    on, rows_on = _run(text, fmap, "online")
    ba, rows_ba = _run(text, fmap, "batch")
    assert on.localizer.stats.landmarks == ba.localizer.stats.segments > 100
    assert on.localizer.stats.observations == ba.localizer.stats.observations
    assert [r.t_s for r, _ in rows_on] == [r.t_s for r, _ in rows_ba]
    for (_, a), (_, b) in zip(rows_on, rows_ba, strict=True):
        # (right after the start and the reset, online reports its fits' latency)
        if 2.0 < a.t_s < T_RESTART or a.t_s > T_RESTART + 1.0:
            assert math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) < 0.003, a.t_s


def test_fitted_batch_replay_across_a_reset(drive, fmap):
    """The batch replay that fits and fuses through the history (``fast=False``:
    rewinds and replays across the reset entry)."""
    rows = []
    res = replay_log(io.StringIO(restarted(drive, True)), fmap, mode="batch", fast=False,
                     on_estimate=lambda r, e: rows.append((r, e)))
    assert res.localizer.stats.odom_resets == 1
    assert _errors(drive, rows)[-1][1] < 0.005


def test_the_reset_grows_the_covariance_and_keeps_the_pose(fmap):
    node = LocalizerNode(fmap, config=LocalizerConfig(method="odometry"))
    node.set_pose(1.0, 2.0, 0.5, sd_xy_m=0.01, sd_yaw_rad=math.radians(1.0), t_s=0.0)
    node.odometry(0.0, 3.0, 4.0, 0.2)
    before = node.odometry(0.1, 3.0, 4.0, 0.2)
    after = node.odometry(0.2, 0.0, 0.0, 0.0, reset=True)
    assert np.allclose(after.state.mean, before.state.mean)
    grown = np.diag(after.state.cov) - np.diag(before.state.cov)
    assert np.allclose(grown, [0.1**2, 0.1**2, math.radians(5.0) ** 2])
    assert np.allclose(after.odom_pose, 0.0) and np.allclose(after.map_to_odom,
                                                            before.state.mean)
    moved = node.odometry(0.3, 0.05, 0.0, 0.0)  # 5 cm forward in the new frame
    assert np.allclose(moved.state.mean[:2], before.state.mean[:2] + 0.05 * np.array(
        [math.cos(0.5), math.sin(0.5)]))
    assert node.stats.odom_resets == 1 and node.stats.odom_jumps == 0
    node.odometry(0.31, 0.3, 0.0, 0.0)  # 25 cm in 10 ms: under the 0.02 s floor, 12.5 m/s
    assert node.stats.odom_jumps == 1
    with pytest.raises(ValueError, match="reset"):
        node.odometry(0.4, 0.3, 0.0, 0.0, reset="yes")  # type: ignore[arg-type]


@pytest.mark.parametrize("name,value", [
    ("odom_max_speed_mps", 0.0), ("odom_max_speed_mps", -1.0),
    ("odom_max_speed_mps", math.nan), ("odom_max_yaw_rate_rad_s", 0.0),
    ("odom_reset_sd_m", -0.1), ("odom_reset_sd_m", math.inf),
    ("odom_reset_sd_deg", math.nan), ("odom_reset_sd_deg", -5.0)])
def test_bad_reset_settings_are_named(name, value):
    with pytest.raises(ValueError, match=f"`{name}`.*{value!r}"):
        LocalizerConfig(**{name: value})
    with pytest.raises(ValueError, match=f"`{name}`"):
        BuildConfig(**{name: value})
    LocalizerConfig(odom_max_speed_mps=math.inf, odom_max_yaw_rate_rad_s=math.inf,
                    odom_reset_sd_m=0.0, odom_reset_sd_deg=0.0)


def test_map_built_from_a_restarted_odometry(drive):
    """Map building from odometry: the restart is not a jump of the map frame. With it
    handled, the same features as from the clean log; without, the second half of the
    drive lands elsewhere and the points are lost (0 of 3)."""
    true = FeatureMap.from_map(load_map(ROOM))

    def points(text, cfg=None):
        res = build_from_log(io.StringIO(text), None, cfg)
        return res, FeatureMap.from_map(map_from_geojson(res.geojson())).point_xy

    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(drive)
    _, clean = points(buf.getvalue())
    res, pts = points(restarted(drive, True))
    assert res.odom_resets == 1 and "1 odometry resets" in res.summary()
    assert res.skipped["tof_across_odom_reset"] == _across(drive)
    assert len(pts) == len(clean) >= 3
    for p in pts:  # within the dead reckoning's drift of a true reflector (clean: 0.13 m)
        assert np.hypot(*(true.point_xy - p).T).min() < 0.25
    res, pts = points(restarted(drive, False))
    assert res.odom_jumps == 1 and len(pts) == len(clean)
    _, pts = points(restarted(drive, False), BuildConfig(**NO_HANDLING))
    assert len(pts) < len(clean)


def test_map_build_widens_the_dead_reckoning_across_a_restart(drive):
    """From odometry alone, a feature's ``sd_m`` carries the dead reckoning's drift; the
    motion across a restart is unknown, so the drift's covariance grows there by
    ``BuildConfig.odom_reset_sd_m`` / ``odom_reset_sd_deg`` (as the Localizer's belief
    does): the features seen after it say so (``sd_m`` 0.09-0.21 -> 0.10-0.28 m here)."""
    text = restarted(drive, True)

    def sds(**cfg):
        res = build_from_log(io.StringIO(text), None, BuildConfig(**cfg))
        return sorted(float(f["properties"]["sd_m"]) for f in res.geojson()["features"]
                      if "sd_m" in f["properties"])

    none, default = sds(odom_reset_sd_m=0.0, odom_reset_sd_deg=0.0), sds()
    assert len(none) == len(default) >= 3
    assert max(default) > max(none) + 0.05   # 0.1 m and 5 deg, at 1-3 m
    assert all(d >= n - 1e-9 for d, n in zip(default, none, strict=True))
