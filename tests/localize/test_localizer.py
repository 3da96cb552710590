import math

import numpy as np
import pytest
from hypothesis import given, settings
from loc_synth import feed, log_records, make_drive, room_map

from sonarloc import se2
from sonarloc.io.logfile import TruthRecord
from sonarloc.localize import ekf
from sonarloc.localize.localizer import Localizer, LocalizerConfig


def no_source(c):
    raise AssertionError("the kuc source must not be needed in these tests")


def loc(**cfg):
    # the synthetic landmarks' covariance is exact: no floor
    cfg = {"fit_sd_floor_m": 0.0, "fit_sd_floor_deg": 0.0, **cfg}
    return Localizer(room_map(), LocalizerConfig(**cfg), landmark_source=no_source)


def errors(ests, drive):
    mean = np.array([e.state.mean for e in ests])
    d = mean - drive.truth
    d[:, 2] = se2.wrap_angle(d[:, 2])
    return d


@pytest.mark.parametrize("every_landmark", [True, False])
def test_delayed_landmarks_equal_on_time_fusion(every_landmark):
    """Rewind-and-replay gives exactly what on-time fusion gives: with every landmark
    fused (no update_min_d / update_min_a), and with the default limits (a landmark
    every 1.5 cm of driving: a feature fused again only 2 cm on, the rest skipped alike)."""
    drive = make_drive(delay_steps=6, every=1)
    cfg = {"update_min_d": 0.0, "update_min_a": 0.0} if every_landmark else {}
    la, lb = loc(**cfg), loc(**cfg)
    feed(la, drive)
    feed(lb, drive, deliver=lambda idx, lm: idx - 6)
    fused = 0.95 if every_landmark else 0.25
    assert la.stats.accepted == lb.stats.accepted > fused * len(drive.landmarks)
    assert la.stats.outcomes == lb.stats.outcomes
    assert la.stats.skipped == lb.stats.skipped
    assert (la.stats.skipped["no_motion_since_fused"] > 0) != every_landmark
    assert la.stats.replayed_steps > lb.stats.replayed_steps
    a, b = la.estimate.state, lb.estimate.state
    assert np.allclose(a.mean, b.mean, atol=1e-12, rtol=0)
    assert np.allclose(a.cov, b.cov, atol=1e-15, rtol=1e-10)


def test_tracks_better_than_odometry():
    drive = make_drive(seed=3, n=600)
    ests = feed(loc(), drive)
    d = errors(ests, drive)
    rmse = math.sqrt(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2))
    # odometry alone, anchored at the same prior
    odo_only = feed(loc(), make_drive(seed=3, n=600), deliver=lambda i, lm: 10**9)
    d0 = errors(odo_only, drive)
    rmse0 = math.sqrt(np.mean(d0[:, 0] ** 2 + d0[:, 1] ** 2))
    assert rmse < 0.01
    assert rmse0 > 3 * rmse
    assert all(e.status == "tracking" for e in ests[20:])
    nees = np.array([ekf.nees(e.state, t) for e, t in zip(ests, drive.truth, strict=True)])
    assert 1.0 < nees[50:].mean() < 6.0


def test_map_to_odom_composes_to_pose():
    drive = make_drive(n=100)
    ests = feed(loc(), drive)
    for e in ests[::10]:
        assert np.allclose(se2.compose(e.map_to_odom, e.odom_pose), e.state.mean, atol=1e-12)


def test_truth_records_are_never_read():
    drive = make_drive(n=120)
    ests = feed(loc(), drive)
    garbled = make_drive(n=120)
    garbled.records = [TruthRecord(r.t_s, 1e6, -1e6, 123.0) if isinstance(r, TruthRecord)
                       else r for r in garbled.records]
    ests2 = feed(loc(), garbled)
    assert np.array_equal(ests[-1].state.mean, ests2[-1].state.mean)


def test_lost_when_updates_keep_being_rejected():
    drive = make_drive(n=300)
    # the prior is confidently 1 m off: every landmark fails the gate
    drive.records[1] = type(drive.records[1])(0.0, drive.records[1].x_m + 1.0,
                                              drive.records[1].y_m - 0.6,
                                              drive.records[1].yaw_deg, 0.01, 0.2)
    ests = feed(loc(lost_after_rejections=10), drive)
    assert ests[-1].status == "lost"
    assert "rejected" in ests[-1].reason


def test_dead_reckoning_without_landmarks():
    drive = make_drive(n=200)
    ests = feed(loc(dead_reckoning_after_s=2.0), drive, deliver=lambda i, lm: 10**9)
    # a prior is no confirmation of the pose: dead reckoning from the start
    assert (ests[10].status, ests[10].reason) == \
        ("dead_reckoning", "no landmark fused yet (0.5 s since the prior)")
    assert (ests[-1].status, ests[-1].reason) == \
        ("dead_reckoning", "no landmark fused for 10.0 s")
    # covariance grows without updates
    assert np.trace(ests[-1].state.cov) > np.trace(ests[10].state.cov)


def test_too_old_landmark_is_counted():
    drive = make_drive(n=400)
    lc = loc(history_s=2.0)
    feed(lc, drive, deliver=lambda idx, lm: idx + 80 if idx < 50 else idx)
    assert lc.stats.outcomes["too_old"] > 0
    assert lc.stats.accepted > 50


def test_history_is_bounded():
    drive = make_drive(n=1200)
    lc = loc(history_s=2.0)
    feed(lc, drive)
    assert lc.history_len < (2.0 / 0.05) * 2 + 200


def test_odom_before_init_gives_no_estimate():
    lc = loc()
    assert lc.on_odom(0.0, 0, 0, 0) is None
    assert lc.stats.skipped["odom_before_init"] == 1


def test_config_validation():
    with pytest.raises(ValueError, match="method"):
        LocalizerConfig(method="magic")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="history_s"):
        LocalizerConfig(history_s=0.0)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="odom_gap_s"):
            LocalizerConfig(odom_gap_s=bad)
    assert LocalizerConfig(odom_gap_s=math.inf).odom_gap_s == math.inf   # no gaps


def test_segment_length_chosen_for_the_rig():
    from sonarloc.localize.localizer import SegmentFitSource

    made = []

    def factory(c):
        made.append(SegmentFitSource(c))
        return made[-1]

    # reading-level fusion takes a pan's pass in chunks of 8 too; fusing fits needs
    # whole passes (a partial U fits poorly)
    for pan, expect, away, config in ((None, 8, None, LocalizerConfig()),
                                      (10.0, 8, 50.0, LocalizerConfig()),
                                      (10.0, 400, 50.0, LocalizerConfig(kuc_fusion="fit")),
                                      (None, 8, None, LocalizerConfig(kuc_fusion="fit")),
                                      (10.0, 8, 30.0,
                                       LocalizerConfig(segment_sweep_away_deg=30.0)),
                                      (10.0, 8, None,
                                       LocalizerConfig(segment_sweep_away_deg=math.inf))):
        lc = Localizer(room_map(), config, landmark_source=factory)
        lc.handle(make_drive(n=3).records[0])
        lc.set_prior(0.0, 2.0, 1.0, 0.0, 0.05, 0.05)
        lc.on_odom(0.0, 0.0, 0.0, 0.0)
        lc.on_tof(0.01, 0, 5000.0, None if pan is None else math.radians(pan))
        lc.on_odom(0.05, 0.01, 0.0, 0.0)
        assert made[-1].max_readings == expect
        assert made[-1].segmenter.config.max_readings == expect
        # a panning transducer's pass closes once the beam has swept past it
        assert made[-1].segmenter.config.sweep_away_deg == away
        assert lc.segment_sweep_away_deg(pan is not None) == away
        assert lc.segment_max_readings(pan is not None) == expect


def test_offline_pipeline_segments_a_pan_like_the_live_localizer():
    """The batch replay's segmenter gets the same pan settings as the live one."""
    from sonarloc.io.logfile import OdomRecord, TofRecord
    from sonarloc.localize.offline import OfflinePipeline

    lc = Localizer(room_map(), LocalizerConfig())
    lc.handle(make_drive(n=3).records[0])
    lc.set_prior(0.0, 2.0, 1.0, 0.0, 0.05, 0.05)
    pipe = OfflinePipeline(lc)
    pipe.odom(OdomRecord(0.0, 0.0, 0.0, 0.0))
    pipe.tof(TofRecord(0.01, 0, 5000.0, 10.0))
    pipe.odom(OdomRecord(0.05, 0.01, 0.0, 0.0))
    pipe._round(final=False)
    assert pipe._source is not None
    cfg = pipe._source.segmenter.config
    assert (cfg.max_readings, cfg.sweep_away_deg) == (8, 50.0)


@pytest.mark.parametrize("method", ["specular", "kuc"])
@settings(max_examples=40, deadline=None)
@given(records=log_records)
def test_any_record_sequence_is_survived(method, records):
    """Time going backwards, unknown sensors, jumps, re-inits: no exception, sane output."""
    lc = Localizer(room_map(), LocalizerConfig(method=method))
    for rec in records:
        est = lc.handle(rec)
        if est is not None:
            assert np.all(np.isfinite(est.state.mean))
            assert bool(est.state.is_spd())
            assert est.status in ("tracking", "dead_reckoning", "lost")
    lc.finish()


def test_segment_fit_source_reports_every_fit_with_its_segment():
    """``on_fit`` sees each fitted segment with its landmark, in the order returned."""
    from sonarloc.fit.synth import Reflector, pan_scan
    from sonarloc.localize.localizer import SegmentFitSource

    scan = pan_scan([Reflector.point(1.5, -0.3, 0.67), Reflector.point(1.4, 0.5, 2.68)],
                    np.random.default_rng(3), step_deg=0.5)
    seen: list = []
    src = SegmentFitSource(343.0, max_readings=400, on_fit=lambda s, lm: seen.append((s, lm)))
    out = []
    for i in range(scan.t_s.size):
        out += src.push(scan.t_s[i], scan.x_m[i], scan.y_m[i], scan.yaw_rad[i],
                        scan.tof_us[i], 0)
    out += src.flush()
    assert len(out) >= 2
    assert [lm for _, lm in seen] == out
    for seg, lm in seen:
        echo = np.isfinite(seg.readings.tof_us)
        assert lm.extra["view_xy"] == pytest.approx(
            (np.mean(seg.readings.x_m[echo]), np.mean(seg.readings.y_m[echo])))


def test_pose_estimate_of_equals_the_constructor():
    from sonarloc.localize.localizer import PoseEstimate
    g = ekf.Gaussian.of_lists([1.0, 2.0, 0.5], [[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.01]])
    args = (3.5, g, np.array([0.1, 0.2, 0.3]), np.array([1.0, 1.5, 0.2]), "tracking", "ok")
    a, b = PoseEstimate._of(*args), PoseEstimate(*args)
    assert vars(a).keys() == vars(b).keys()
    assert all(x is y for x, y in zip(vars(a).values(), vars(b).values(), strict=True))
    assert a.x_m == b.x_m == 1.0
    with pytest.raises(AttributeError):
        a.t_s = 1.0   # type: ignore[misc]


def test_set_rig_refuses_a_speed_of_sound_that_is_not_air():
    from sonarloc.io.logfile import SensorMount

    loc = Localizer(room_map(), LocalizerConfig())
    for c in (3.0, 3430.0, math.nan, -343.0):
        with pytest.raises(ValueError, match=r"`speed_of_sound_mps` must be within \[250, 450\]"):
            loc.set_rig([SensorMount(0, 0.2, 0.0, 0.0)], c)
    loc.set_rig([SensorMount(0, 0.2, 0.0, 0.0)], 343.0)
