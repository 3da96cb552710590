"""The offline (batch) replay: same landmarks, fused on time, rows for every odom record."""

import io
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from loc_synth import log_records

from sonarloc.io.logfile import (
    InitRecord,
    LogWriter,
    OdomRecord,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
    iter_log,
)
from sonarloc.localize import ekf
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import Localizer, LocalizerConfig
from sonarloc.localize.offline import OfflinePipeline
from sonarloc.localize.replay import replay_log
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import PanRig, ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"


def _log(rig, seed, duration_s):
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), rig, duration_s=duration_s, seed=seed))
    return buf.getvalue()


@pytest.fixture(scope="module")
def ring_log():
    return _log(ring16(), 3, 12.0)


@pytest.fixture(scope="module")
def fmap():
    return FeatureMap.from_map(load_map(ROOM))


class Recording(Localizer):
    """A Localizer that keeps the landmarks it is given."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.given = []

    def add_landmark(self, lm):
        self.given.append(lm)
        return super().add_landmark(lm)


def _rows(text, fmap, **kw):
    rows = []
    res = replay_log(io.StringIO(text), fmap,
                     on_estimate=lambda r, e: rows.append((r.t_s, e)), **kw)
    return res, rows


def test_predict_chain_equals_repeated_predict():
    rng = np.random.default_rng(4)
    g = ekf.Gaussian(np.array([1.0, -2.0, 3.1]),
                     np.array([[1e-3, 2e-4, 1e-4], [2e-4, 2e-3, 3e-4], [1e-4, 3e-4, 1e-3]]))
    u = rng.normal(0, [0.03, 0.005, 0.2], (300, 3))
    noise = ekf.OdomNoise()
    chain = ekf.predict_chain(g, u, noise)
    s = g
    for k in range(len(u)):
        s = ekf.predict(s, u[k], noise)
        d = chain.mean[k] - s.mean
        d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi
        assert np.max(np.abs(d)) < 1e-12
        assert np.allclose(chain.cov[k], s.cov, rtol=1e-10, atol=1e-16)
    assert chain.is_spd().all()
    assert ekf.predict_chain(g, np.zeros((0, 3))).mean.shape == (0, 3)
    with pytest.raises(ValueError, match="one filter"):
        ekf.predict_chain(ekf.Gaussian(np.zeros((2, 3)), np.zeros((2, 3, 3))), u)


def test_batch_is_on_time_fusion(ring_log, fmap):
    """Batch rows (``fast=False``: fitted, one landmark at a time) = a live Localizer
    given each landmark at the next odom record (the rewind makes that on-time fusion)."""
    loc = Recording(fmap)
    res, rows = _rows(ring_log, fmap, localizer=loc, mode="batch", fast=False)
    n_odom = sum(isinstance(r, OdomRecord) for r in iter_log(io.StringIO(ring_log)))
    assert res.rows == len(rows) == n_odom
    assert loc.stats.accepted > 10
    live = Localizer(fmap, landmark_source=lambda c: None)  # type: ignore[arg-type,return-value]
    todo = sorted(loc.given, key=lambda lm: lm.ref_t_s)
    records = list(iter_log(io.StringIO(ring_log)))
    for r in records:
        if isinstance(r, (RigRecord, InitRecord)):  # the log's rig and prior come first
            live.handle(r)
    k = 0
    odoms = [r for r in records if isinstance(r, OdomRecord)]
    for (t, est), rec in zip(rows, odoms, strict=True):
        assert t == rec.t_s
        live.handle(rec)
        while k < len(todo) and todo[k].ref_t_s <= rec.t_s:
            live.add_landmark(todo[k])
            k += 1
        ref = live.estimate
        assert ref is not None
        assert np.allclose(est.state.mean, ref.state.mean, atol=1e-9, rtol=0)
        assert np.allclose(est.state.cov, ref.state.cov, atol=1e-14, rtol=1e-8)
        assert est.status == ref.status
        assert np.allclose(est.map_to_odom, ref.map_to_odom, atol=1e-9)
    assert live.stats.accepted == loc.stats.accepted
    assert live.stats.outcomes == loc.stats.outcomes


def test_batch_fuses_the_same_segments_as_online(ring_log, fmap):
    on, rows_on = _rows(ring_log, fmap, mode="online")
    ba, rows_ba = _rows(ring_log, fmap, mode="batch")
    # the fast batch path does not fit: one observation per segment, as online
    assert ba.localizer.stats.landmarks == 0
    assert on.localizer.stats.landmarks == ba.localizer.stats.segments > 20
    assert on.localizer.stats.observations == ba.localizer.stats.observations
    assert on.localizer.stats.tof == ba.localizer.stats.tof
    assert [t for t, _ in rows_on] == [t for t, _ in rows_ba]
    truth = {r.t_s: r for r in iter_log(io.StringIO(ring_log)) if isinstance(r, TruthRecord)}

    def steady_rmse(rows):
        e = [math.hypot(est.x_m - truth[t].x_m, est.y_m - truth[t].y_m)
             for t, est in rows if t > 5.0]
        return math.sqrt(np.mean(np.square(e)))

    assert steady_rmse(rows_ba) < 0.02
    assert steady_rmse(rows_ba) < steady_rmse(rows_on) + 0.003


def test_fit_batch_size_barely_matters(ring_log, fmap):
    _, a = _rows(ring_log, fmap, mode="batch", batch_segments=1, fast=False)
    _, b = _rows(ring_log, fmap, mode="batch", fast=False)
    diff = max(float(np.max(np.abs(x.state.mean - y.state.mean)))
               for (_, x), (_, y) in zip(a, b, strict=True))
    assert diff < 1e-3  # the batch fitter's rounding, not the fusion


def test_panning_rig_and_odometry_method(fmap):
    text = _log(PanRig(SensorMount(0, 0.1, 0.0, 0.0), (-90.0, 90.0, 1.5), 1, 0.03), 5, 10.0)
    on, rows_on = _rows(text, fmap, mode="online")
    ba, rows_ba = _rows(text, fmap, mode="batch")
    assert len(rows_on) == len(rows_ba)
    assert on.localizer.stats.landmarks == ba.localizer.stats.segments > 0
    _, odo_on = _rows(text, fmap, mode="online", config=LocalizerConfig(method="odometry"))
    _, odo_ba = _rows(text, fmap, mode="batch", config=LocalizerConfig(method="odometry"))
    for (_, x), (_, y) in zip(odo_on, odo_ba, strict=True):
        assert np.allclose(x.state.mean, y.state.mean, atol=1e-12)
        assert np.allclose(x.state.cov, y.state.cov, rtol=1e-9, atol=1e-18)


def test_mode_checks(ring_log, fmap):
    with pytest.raises(ValueError, match="mode"):
        replay_log(io.StringIO(ring_log), fmap, mode="fast")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="conventional"):
        replay_log(io.StringIO(ring_log), fmap, mode="batch",
                   config=LocalizerConfig(method="conventional"))
    with pytest.raises(ValueError, match="batch_segments"):
        OfflinePipeline(Localizer(fmap), batch_segments=0)
    with pytest.raises(ValueError, match="method"):
        OfflinePipeline(Localizer(fmap, LocalizerConfig(method="specular")))


def test_buffers_stay_bounded(ring_log, fmap):
    """Small batches: odometry waiting for the fitter and the history stay short."""
    loc = Localizer(fmap)
    pipe = OfflinePipeline(loc, batch_segments=4, max_wait_s=1.0, round_odom=10)
    worst = 0
    for rec in iter_log(io.StringIO(ring_log)):
        if isinstance(rec, OdomRecord):
            pipe.odom(rec)
            worst = max(worst, len(pipe._odom) + len(pipe._rows))
        elif isinstance(rec, TofRecord):
            pipe.tof(rec)
        elif isinstance(rec, (RigRecord, InitRecord)):
            loc.handle(rec)
    pipe.finish()
    assert pipe.rows == loc.stats.odom
    assert worst < 120  # ~ a few seconds of odometry at 20 Hz
    # history_s = 10 s: 200 odom entries plus the fused segments (reading-level fusion
    # fuses some 25 a second, lone echoes included), plus the trim's slack of 64
    assert loc.history_len < 800




@settings(max_examples=40, deadline=None)
@given(records=log_records)
def test_any_record_sequence_is_survived(fmap, records):
    """Time going backwards, unknown sensors, jumps, re-inits: a row per odom record."""
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(records)
    rows = []
    res = replay_log(io.StringIO(buf.getvalue()), fmap, init=(2.0, 1.0, 0.0), mode="batch",
                     on_estimate=lambda r, e: rows.append(e))
    assert res.rows == len(rows) == sum(isinstance(r, OdomRecord) for r in records)
    for est in rows:
        assert np.all(np.isfinite(est.state.mean))
        assert bool(est.state.is_spd())
        assert est.status in ("tracking", "dead_reckoning", "lost")


def test_tof_runs_equal_tof_records(ring_log, fmap):
    """replay_log hands the pipeline runs of tof records as columns
    (iter_log_runs, OfflinePipeline.tofs): the same rows and counters as handing it each
    tof record (OfflinePipeline.tof), unknown sensors and time going backwards
    included."""
    lines = ring_log.splitlines(keepends=True)
    odd = []
    for i, line in enumerate(lines):
        odd.append(line)
        if i % 97 == 50 and '"type":"tof"' in line:   # an unknown sensor, a late reading
            odd.append(line.replace('"sensor":', '"sensor":4', 1))
            t = float(line.split('"t_s":')[1].split(",")[0])
            odd.append(line.replace(f'"t_s":{t!r}', f'"t_s":{t - 0.3!r}', 1))
    text = "".join(odd)

    def by_records():
        loc = Localizer(fmap)
        rows = []
        pipe = OfflinePipeline(loc, lambda r, e: rows.append((r.t_s, e.state.mean.tolist(),
                                                              e.state.cov.tolist())))
        for rec in iter_log(io.StringIO(text)):
            if isinstance(rec, OdomRecord):
                pipe.odom(rec)
            elif isinstance(rec, TofRecord):
                pipe.tof(rec)
            elif isinstance(rec, (RigRecord, InitRecord)):
                pipe.finish()
                loc.handle(rec)
        pipe.finish()
        return rows, loc.stats

    rows_rec, stats_rec = by_records()
    rows = []
    res = replay_log(io.StringIO(text), fmap, on_estimate=lambda r, e: rows.append(
        (r.t_s, e.state.mean.tolist(), e.state.cov.tolist())))
    assert stats_rec.skipped["unknown_sensor"] > 0 and res.log.time_backwards_count > 0
    assert rows == rows_rec
    assert repr(res.localizer.stats) == repr(stats_rec)


def test_readings_after_the_last_odometry_are_counted_online_and_in_batch(ring_log, fmap):
    # a log that stops between an odom record and the readings after it: those readings
    # can never be placed; both replays say how many they left out
    recs = list(iter_log(io.StringIO(ring_log)))
    t_end = max(r.t_s for r in recs)
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all([TofRecord(t_end + 0.01 * (k + 1), 0, 5000.0, None) for k in range(3)])
    text = ring_log + buf.getvalue()
    t_odom = max(r.t_s for r in recs if isinstance(r, OdomRecord))
    late = sum(isinstance(r, TofRecord) and r.t_s > t_odom for r in recs) + 3
    for mode in ("online", "batch"):
        res, _ = _rows(text, fmap, mode=mode)
        assert res.localizer.stats.skipped["tof_after_last_odom"] == late, mode


@pytest.mark.parametrize("mode", ["batch", "online"])
def test_stale_odometry_and_garbage_readings_in_a_log(ring_log, fmap, mode):
    """A log with stale odom records (older than the last: delivered late), readings
    with a zero or negative TOF and pairs of readings swapped, as the embedding API gets
    them: each fault skipped and counted (``odom_time_backwards``, ``bad_tof``; the
    swapped readings used in time order), a row per odom record, and the rows of the
    good odom records exactly those of the log without the faults; a stale record's row
    is the belief as it was. (A stale record was taken as the newest pose at the last
    time: the belief moved back and forth.)"""
    lines = ring_log.splitlines(keepends=True)
    odom = [ln for ln in lines if '"type":"odom"' in ln]
    def t_of(line):
        return float(line.split('"t_s":')[1].split(",")[0])

    def swap(i):   # line i is the first of two readings at different times
        return '"type":"tof"' in lines[i] and '"type":"tof"' in lines[i + 1] and \
            t_of(lines[i]) < t_of(lines[i + 1])

    faulty, n_stale, n_bad, n_swap = [], 0, 0, 0
    for i, line in enumerate(lines):
        if i % 5 == 0 and swap(i):
            line = lines[i + 1]                              # two readings swapped
            n_swap += 1
        elif i % 5 == 1 and swap(i - 1):
            line = lines[i - 1]
        faulty.append(line)
        if line in odom and odom.index(line) % 10 == 9:
            faulty.append(odom[odom.index(line) - 3])        # a stale copy, late
            n_stale += 1
        if '"type":"tof"' in line and '"sensor":3,' in line:
            faulty.append(line.replace('"tof_us":', '"tof_us":-', 1).replace(":-null", ":0"))
            n_bad += 1

    def rows_of(text):
        rows = []
        res = replay_log(io.StringIO(text), fmap, mode=mode,
                         on_estimate=lambda r, e: rows.append(
                             (r.t_s, e.state.mean.tolist(), e.state.cov.tolist())))
        return rows, res

    clean, _ = rows_of("".join(lines))
    rows, res = rows_of("".join(faulty))
    assert n_stale > 5 and n_bad > 10 and n_swap > 10
    assert res.localizer.stats.skipped["odom_time_backwards"] == n_stale
    assert res.localizer.stats.skipped["bad_tof"] == n_bad
    assert "tof_out_of_order" not in res.localizer.stats.skipped
    assert len(rows) == len(clean) + n_stale
    good, k = [], 0
    for row in rows:
        if k < len(clean) and row[0] == clean[k][0]:
            good.append(row)
            k += 1
        else:                                  # a stale record: the belief as it was
            assert row[1:] == good[-1][1:]
    if mode == "online":
        assert good == clean
    else:  # batch: the stale record held as a step without motion (the last bit may move)
        assert [r[0] for r in good] == [r[0] for r in clean]
        for name in (1, 2):
            assert np.array([r[name] for r in good]) == pytest.approx(
                np.array([r[name] for r in clean]), rel=1e-9, abs=1e-15)


def test_readings_waiting_at_an_init_are_counted_online_and_in_batch(ring_log, fmap):
    """Readings still waiting for odometry when an ``init`` record (set_pose) restarts
    the filter are dropped and counted as ``tof_after_last_odom``, as at the end of a
    log: the odometry after the init may run on a restarted clock (here the same drive
    again from 0 s), which would place them at the wrong pose. (The online replay
    dropped them uncounted.)"""
    recs = list(iter_log(io.StringIO(ring_log)))
    t_odom = max(r.t_s for r in recs if isinstance(r, OdomRecord))
    late = sum(isinstance(r, TofRecord) and r.t_s > t_odom for r in recs)
    buf = io.StringIO()
    with LogWriter(buf) as w:   # three more readings after the last odometry
        w.write_all([TofRecord(t_odom + 0.01 * (k + 1), 0, 5000.0, None) for k in range(3)])
    again = "".join(ln for ln in ring_log.splitlines(keepends=True)
                    if '"type":"rig"' not in ln)
    text = ring_log + buf.getvalue() + again
    for mode in ("online", "batch"):
        res, rows = _rows(text, fmap, mode=mode)
        skipped = res.localizer.stats.skipped
        # before the init, and again at the end of the log
        assert skipped["tof_after_last_odom"] == 2 * late + 3, mode
        assert res.localizer.stats.tof == 2 * sum(isinstance(r, TofRecord) for r in recs) + 3


def test_readings_before_the_first_odometry_have_one_name_online_and_in_batch(ring_log, fmap):
    """A log without an ``init`` record whose first second has readings and no odometry,
    replayed with an ``init`` pose (`localize --init`): those readings have no pose, and
    both modes say so with one name (online said ``tof_after_last_odom``, batch
    ``tof_older_than_history``)."""
    lines = [ln for ln in ring_log.splitlines(keepends=True) if '"type":"init"' not in ln]
    text = "".join(ln for ln in lines
                   if not ('"type":"odom"' in ln and json.loads(ln)["t_s"] < 1.0))
    before = sum(isinstance(r, TofRecord) and r.t_s < 1.0 for r in iter_log(io.StringIO(text)))
    assert before > 50
    for mode in ("online", "batch"):
        res, _ = _rows(text, fmap, mode=mode, init=(1.07, 0.96, 1.6))
        skipped = res.localizer.stats.skipped
        assert skipped["tof_before_odom"] == before, (mode, skipped)
        assert "tof_older_than_history" not in skipped and \
            "tof_after_last_odom" not in skipped, (mode, skipped)


def _odom_gap(text, t0, t1):
    """The log without its odom records strictly between ``t0`` and ``t1`` (a link drop:
    the readings still arrive), and how many readings lie strictly inside."""
    keep, inside = [], 0
    for line in text.splitlines(keepends=True):
        rec = next(iter(iter_log(io.StringIO(line))), None)
        if isinstance(rec, OdomRecord) and t0 < rec.t_s < t1:
            continue
        inside += isinstance(rec, TofRecord) and t0 < rec.t_s < t1
        keep.append(line)
    return "".join(keep), inside


@pytest.fixture(scope="module")
def turn_log():
    """The room drive up to and around its first corner (a turn of 90 deg at 19-22 s)."""
    return _log(ring16(), 3, 24.0)


def _truth(text):
    return {r.t_s: r for r in iter_log(io.StringIO(text)) if isinstance(r, TruthRecord)}


@pytest.mark.parametrize("mode,method", [("batch", "kuc"), ("online", "kuc"),
                                         ("online", "conventional")])
def test_readings_inside_an_odometry_gap_are_skipped_and_counted(turn_log, fmap, mode,
                                                                 method):
    """Odometry missing for 5 s while the robot turns a corner: the readings taken in
    the gap cannot be placed (a pose interpolated across the turn is a guess), so they
    are skipped and counted (``tof_in_odom_gap``), the gap counted in
    ``stats.odom_gaps``; the odometry increment across the gap is used with its noise,
    and the estimate after the gap stays near the truth and consistent with its
    covariance. (Interpolated readings put the conventional EKF 0.44 m off while its
    covariance said millimetres, and the kuc method's squared Mahalanobis distance up
    to 35.)"""
    text, inside = _odom_gap(turn_log, 18.5, 23.5)
    truth = _truth(text)
    rows = []
    res = replay_log(io.StringIO(text), fmap, mode=mode,
                     config=LocalizerConfig(method=method),
                     on_estimate=lambda r, e: rows.append((r.t_s, e.state)))
    stats = res.localizer.stats
    assert inside > 500 and stats.skipped["tof_in_odom_gap"] == inside
    assert stats.odom_gaps == 1
    for t, state in rows:
        if t >= 23.5:
            tr = truth[t]
            d = np.array([tr.x_m, tr.y_m, math.radians(tr.yaw_deg)]) - state.mean
            d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi
            assert math.hypot(d[0], d[1]) < 0.05, t
            if method == "kuc":  # (the conventional model is overconfident anyway)
                assert d @ np.linalg.solve(state.cov, d) < 30.0, t


def test_an_odometry_gap_standing_still_keeps_its_readings(fmap):
    """A robot standing still whose odometry stops for 3 s (a driver that publishes only
    on change): the pose inside is known, no reading is skipped; the gap is counted."""
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=6.0,
                                     at=(2.0, 2.0, 30.0), seed=5))
    text, inside = _odom_gap(buf.getvalue(), 1.0, 4.0)
    for mode in ("batch", "online"):
        res, _ = _rows(text, fmap, mode=mode)
        stats = res.localizer.stats
        assert inside > 100 and "tof_in_odom_gap" not in stats.skipped, mode
        assert stats.odom_gaps == 1
