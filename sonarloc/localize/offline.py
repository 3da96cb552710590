"""Offline replay of a log through a :class:`Localizer`, in batches, fused on time.

A recorded log can be localized faster than record by record: every reading's
transducer pose is interpolated from the odometry in one numpy call, the segmenter
takes them in batches (:meth:`~sonarloc.fit.segment.Segmenter.push_many`), and the
odometry between landmark updates is predicted in closed form
(:func:`~sonarloc.localize.ekf.predict_chain`). With reading-level fusion (the
default, ``fast``) the closed segments are not fitted: they are associated by their
readings and reduced to small updates many at a time
(:mod:`~sonarloc.localize.batchfuse`), applied in time order with no history replay.
Otherwise they are fitted together in large batches (the fitter's cost per segment
falls steeply with the batch size) and fused one by one through
:meth:`Localizer.add_landmark`.

The filter result is that of *on-time* fusion: a landmark is fused at its reference
reading, before any later odometry, whatever batch it was fitted in. A pose row for an
odom record is handed out once every landmark that can refer to a time at or before
it is known (no segment still open or waiting for the fitter began earlier), and it
holds every landmark whose reference reading is at or before that record: what a live
Localizer reports for the same moment once the fits have caught up, without their
latency. A live :class:`Localizer` fed record by record fuses the same landmarks, but
associates each one when its fit completes, after the landmarks fitted before it.

Memory stays bounded: odometry waits for the fitter at most ``max_wait_s`` of log time
or ``batch_segments`` segments (fast: for the open segments only), and the Localizer's
history is trimmed as usual.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import OdomRecord, TofRecord, TofRun
from sonarloc.localize import echoes, ekf
from sonarloc.localize.batchfuse import (
    FAST_DXY_M,
    FAST_DYAW_RAD,
    FAST_STEP_M,
    FAST_STEP_RAD,
    BatchFuser,
    Linearized,
    Prepared,
    SegmentEchoes,
    interpolate_track,
    reduced_update_lists,
)
from sonarloc.localize.echoes import EchoObservation
from sonarloc.localize.localizer import (
    ECHO_MIN_FRACTION,
    Localizer,
    PoseEstimate,
    SegmentFitSource,
    _Entry,
    odom_moved,
)
from sonarloc.localize.odomframe import Frame, Pose

Array = NDArray[np.float64]
EstimateCallback = Callable[[OdomRecord, PoseEstimate], None]
#: A pending odom record: (time, record, joined pose, raw frame in the joined one,
#: whether the odometry restarted there) (:mod:`~sonarloc.localize.odomframe`).
_Odom = tuple[float, OdomRecord, Pose, Frame | None, bool]
#: How :meth:`OfflinePipeline._fuse_prepared` fused a segment.
FuseHow = Literal["reduced", "segment", "stale"]

#: The (empty) readings of an observation fused through its reduced form alone.
_NO_READINGS = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
for _a in _NO_READINGS:
    _a.flags.writeable = False


class OfflinePipeline:
    """Feeds a log's odom and tof records to a :class:`Localizer` in batches.

    Parameters
    ----------
    localizer : a Localizer with method ``kuc`` or ``odometry``, its rig and prior set
        (by :meth:`Localizer.handle` of the log's ``rig`` / ``init`` records, routed
        by the caller after :meth:`finish`-ing the records before them).
    on_estimate : called with each odom record and the estimate for it, in order.
    batch_segments : closed segments fitted together.
    max_wait_s : log time a closed segment waits at most for the batch to fill.
    round_odom : odom records gathered before the readings up to them are segmented.
    fast : fuse the segments' readings without fitting them (association by the
        readings, linearised many segments at a time at the beliefs predicted by the
        odometry: :mod:`sonarloc.localize.batchfuse`). None (default): for the ``kuc``
        method with ``kuc_fusion="echoes"`` (whose fits only serve association). False:
        every segment fitted and given to :meth:`Localizer.add_landmark` on time (the
        rows then equal a live Localizer's given the same landmarks on time).
    linearize_segments : (fast) segments linearised together at most (transducer
        chains, candidates, forward model: at the beliefs the odometry predicts from the
        latest one).
    chunk_segments, chunk_s : (fast) segments screened, gated and associated together
        at most, and the longest span of their reference times [s] (the beliefs they are
        decided at are predicted that far ahead without the updates in between; the
        updates themselves are applied one by one at the true beliefs, and a segment
        whose belief moved too far is linearised and decided anew, with the rest). 2 s:
        the replay's steady error as with 0.5 s (within 0.005 mm / 0.005 deg over the
        benchmark's drives), a third fewer numpy calls per segment.
    """

    def __init__(self, localizer: Localizer, on_estimate: EstimateCallback | None = None,
                 batch_segments: int = 1024, max_wait_s: float = 120.0,
                 round_odom: int = 50, fast: bool | None = None,
                 linearize_segments: int = 128, chunk_segments: int = 128,
                 chunk_s: float = 2.0) -> None:
        if localizer.config.method not in ("kuc", "odometry"):
            raise ValueError(f"the offline pipeline runs methods 'kuc' and 'odometry', got "
                             f"{localizer.config.method!r}")
        if not (isinstance(batch_segments, int) and batch_segments >= 1):
            raise ValueError(f"`batch_segments` must be a positive integer, got "
                             f"{batch_segments!r}")
        if not (math.isfinite(max_wait_s) and max_wait_s >= 0):
            raise ValueError(f"`max_wait_s` must be non-negative, got {max_wait_s!r}")
        cfg = localizer.config
        echo_level = cfg.method == "kuc" and cfg.kuc_fusion == "echoes"
        if fast and not echo_level:
            raise ValueError(f"`fast` needs method 'kuc' with kuc_fusion 'echoes', got "
                             f"{cfg.method!r} / {cfg.kuc_fusion!r}")
        if not (isinstance(chunk_segments, int) and chunk_segments >= 1):
            raise ValueError(f"`chunk_segments` must be a positive integer, got "
                             f"{chunk_segments!r}")
        self.fast = echo_level if fast is None else bool(fast)
        if not (math.isfinite(chunk_s) and chunk_s > 0):
            raise ValueError(f"`chunk_s` must be positive, got {chunk_s!r}")
        if not (isinstance(linearize_segments, int) and linearize_segments >= 1):
            raise ValueError(f"`linearize_segments` must be a positive integer, got "
                             f"{linearize_segments!r}")
        self.linearize_segments = linearize_segments
        self.chunk_segments = chunk_segments
        self.chunk_s = chunk_s
        self._chunk = chunk_segments
        self._segs: list[SegmentEchoes] = []     # (fast) closed, waiting to be fused
        self._fuser: BatchFuser | None = None
        self.loc = localizer
        self.on_estimate = on_estimate
        self.batch_segments = batch_segments
        self.max_wait_s = max_wait_s
        self.round_odom = max(int(round_odom), 1)
        self.rows = 0
        self.last: PoseEstimate | None = None
        self._odom: list[_Odom] = []  # received, not yet in the history
        self._last_t = -math.inf
        self._last_rec: OdomRecord | None = None  # the last odom record taken
        self._last_pushed_t = -math.inf           # the segmenter's latest reading
        self._new = 0                            # odom records since the last round
        self._rows: list[_Odom] = []  # in the history, not yet handed out
        # odometry restarts (resets, jumps): (time of the record before, of the restart)
        # spans whose readings have no pose, and restarts whose open segments the
        # segmenter has yet to close; any at all (entries then carry frames)
        self._restart_spans: list[tuple[float, float]] = []
        self._flush_t: list[float] = []
        self._restarted = False
        # readings waiting for odometry at or after them, as columns (tof NaN: no echo)
        self._tof_t: list[float] = []
        self._tof_sensor: list[int] = []
        self._tof_us: list[float] = []
        self._tof_pan: list[float | None] = []
        self._waiting: list[Any] = []            # closed segments waiting for the fitter
        self._landmarks: list[Landmark] = []     # fitted, waiting to be fused
        self._track_t: list[float] = []          # odometry track for the readings' poses
        self._track: list[tuple[float, float, float]] = []
        self._source: SegmentFitSource | None = None

    # -- records --------------------------------------------------------------------

    def odom(self, rec: OdomRecord) -> None:
        """An odom record (after the prior).

        A record older than the last one is skipped as :meth:`Localizer.on_odom` skips
        it (``skipped["odom_time_backwards"]``), yet keeps its row: the belief as it is,
        the last pose held (no motion) at the last time.
        """
        t = rec.t_s
        last = self._last_rec
        joiner = self.loc.odom_joiner
        if t < self._last_t and last is not None:
            self.loc.stats.skipped["odom_time_backwards"] += 1
            self._odom.append((self._last_t, OdomRecord(rec.t_s, last.x_m, last.y_m,
                                                        last.yaw_deg),
                               self._track[-1], joiner.frame, False))
            return  # the track and the rounds as without it
        if t - self._last_t > self.loc.config.odom_gap_s and last is not None:
            self.loc.stats.odom_gaps += 1          # as Localizer.on_odom
        if last is None:
            joiner.forget()                        # as the Localizer's first entry
        raw = (rec.x_m, rec.y_m, math.radians(rec.yaw_deg))
        restart = joiner.restart(t, raw, rec.reset)
        if restart is not None:                    # as Localizer.on_odom
            if restart == "reset":
                self.loc.stats.odom_resets += 1
            else:
                self.loc.stats.odom_jumps += 1
            self._restart_spans.append((self._last_t, t))
            self._flush_t.append(t)
            self._restarted = True
        joined = joiner.join(t, raw, restart)
        self._last_t = t
        self._last_rec = rec
        self._odom.append((t, rec, joined, joiner.frame, restart is not None))
        self._track_t.append(t)
        self._track.append(joined)
        self._new += 1
        if self._new >= self.round_odom:
            self._round(final=False)

    def tof(self, rec: TofRecord) -> None:
        """A tof record; counted and checked as :meth:`Localizer.on_tof` does."""
        loc = self.loc
        loc.stats.tof += 1
        if rec.sensor not in loc._mounts:
            loc.stats.skipped["unknown_sensor" if loc._mounts else "tof_before_rig"] += 1
            return
        if loc.config.method == "kuc":
            tof_us = loc._timeout_as_no_echo(rec.tof_us)
            self._tof_t.append(rec.t_s)
            self._tof_sensor.append(rec.sensor)
            self._tof_us.append(math.nan if tof_us is None else float(tof_us))
            self._tof_pan.append(rec.pan_deg)

    def tofs(self, run: TofRun) -> None:
        """A run of tof records (:func:`~sonarloc.io.logfile.iter_log_runs`): :meth:`tof`
        of each."""
        loc = self.loc
        mounts = loc._mounts
        if not mounts.keys() >= set(run.sensor):
            for rec in run.records():
                self.tof(rec)
            return
        loc.stats.tof += len(run)
        if loc.config.method == "kuc":
            self._tof_t += run.t_s
            self._tof_sensor += run.sensor
            limit = loc.config.max_tof_us
            if limit is None:
                self._tof_us += run.tof_us
            else:  # as Localizer._timeout_as_no_echo (NaN compares False: stays no echo)
                tofs = [math.nan if v >= limit else v for v in run.tof_us]
                loc.stats.timeouts += sum(v >= limit for v in run.tof_us)
                self._tof_us += tofs
            self._tof_pan += run.pan_deg

    def finish(self, restart: bool = False) -> None:
        """End of the records (or a rig/init record follows): fit and fuse everything.
        ``restart``: a new prior follows (``init``), and with it the odometry may start
        again from an earlier time, as after :meth:`Localizer.set_prior`."""
        self._round(final=True)
        self._source = None
        self._last_pushed_t = -math.inf
        if restart:
            self._last_t = -math.inf
            self._last_rec = None
            self._track_t, self._track = [], []
            self._restart_spans, self._flush_t = [], []

    # -- internals ------------------------------------------------------------------

    def _round(self, final: bool) -> None:
        self._new = 0
        t_odom = self._track_t[-1] if self._track_t else -math.inf
        self._segment(t_odom, final)
        horizon = math.inf if final else t_odom
        if self._source is not None:
            seg = self._source.segmenter
            horizon = min(horizon, seg.open_since_s)
            if self.fast:
                self._fuse_fast(horizon)
                self.loc.trim_history()
                self._trim_track()
                return
            if self._waiting and (final or len(self._waiting) >= self.batch_segments
                                  or t_odom - float(self._waiting[0].readings.t_s[0])
                                  >= self.max_wait_s):
                self._landmarks += self._source.fit(self._waiting)
                self._waiting = []
            for s in self._waiting:
                horizon = min(horizon, float(s.readings.t_s[0]))
        self._fuse(horizon)
        self.loc.trim_history()
        self._trim_track()

    def _trim_track(self) -> None:
        # keep the odometry the readings still waiting may need (and one record before)
        if len(self._track_t) < 2:
            return
        t_min = min(self._tof_t, default=self._track_t[-1])
        if self.fast:  # the readings of segments still to come, inside the history
            t_min = min(t_min, self.loc._times[0] if self.loc._times else -math.inf)
        k = int(np.searchsorted(self._track_t, t_min, side="right")) - 1
        k = min(max(k, 0), len(self._track_t) - 1)
        if k > 0:
            del self._track_t[:k]
            del self._track[:k]
            t0 = self._track_t[0]
            self._restart_spans = [s for s in self._restart_spans if s[1] > t0]

    def _segment(self, t_odom: float, final: bool) -> None:
        """Push the readings up to the latest odometry through the segmenter."""
        self._push_ready(t_odom, final)
        if final and self._source is not None:
            self._waiting += self._source.segmenter.flush()
        if self.fast and self._waiting:
            self.loc.stats.segments += len(self._waiting)
            self._segs += SegmentEchoes.from_segments(self._waiting)
            self._waiting = []

    def _push_ready(self, t_odom: float, final: bool) -> None:
        if not self._tof_t:
            return
        loc = self.loc
        t_all = np.array(self._tof_t)
        sel = t_all <= t_odom
        cols = (self._tof_sensor, self._tof_us, self._tof_pan)
        if final or sel.all():
            ready = np.flatnonzero(sel)
            if ready.size < t_all.size:     # final: no odometry reaches these readings
                loc.stats.skipped[loc._no_odom_after()] += int(t_all.size - ready.size)
            self._tof_t, self._tof_sensor, self._tof_us, self._tof_pan = [], [], [], []
        else:
            ready, later = np.flatnonzero(sel), np.flatnonzero(~sel).tolist()
            self._tof_t = [self._tof_t[i] for i in later]
            self._tof_sensor = [self._tof_sensor[i] for i in later]
            self._tof_us = [self._tof_us[i] for i in later]
            self._tof_pan = [self._tof_pan[i] for i in later]
        if not ready.size:
            return
        sensor_all, tof_all, pan_all = cols
        tof = np.array(tof_all)[ready]
        bad = (tof <= 0.0) | np.isinf(tof)   # as Localizer.on_tof (the segmenter drops them)
        if bad.any():
            loc.stats.skipped["bad_tof"] += int(np.count_nonzero(bad))
            ready, tof = ready[~bad], tof[~bad]
            if not ready.size:
                return
        first_t = loc._times[0] if loc._times else self._odom[0][0] if self._odom \
            else math.inf
        t = t_all[ready]
        old = t < first_t
        if old.any():
            start = loc._odom_start_t if loc._times else first_t
            before = int(np.count_nonzero(old & ~(t >= start)))
            for name, n in (("tof_before_odom", before),
                            ("tof_older_than_history", int(np.count_nonzero(old)) - before)):
                if n:
                    loc.stats.skipped[name] += n
            ready, t, tof = ready[~old], t[~old], tof[~old]
            if not ready.size:
                return
        # in time order, as Localizer._drain_pending; older than the segmenter's last: out
        order = np.argsort(t, kind="stable")
        ready, t, tof = ready[order], t[order], tof[order]
        late = t < self._last_pushed_t
        if late.any():
            loc.stats.skipped["tof_out_of_order"] += int(np.count_nonzero(late))
            ready, t, tof = ready[~late], t[~late], tof[~late]
            if not ready.size:
                return
        if self._restart_spans:   # no pose between a restart and the record before it
            across = np.zeros(len(t), dtype=bool)
            for ta, tb in self._restart_spans:
                across |= (t > ta) & (t < tb)
            if across.any():
                loc.stats.skipped["tof_across_odom_reset"] += int(np.count_nonzero(across))
                ready, t, tof = ready[~across], t[~across], tof[~across]
                if not ready.size:
                    return
        track_t = np.array(self._track_t)
        track = np.array(self._track)
        gap = self._in_odom_gap(track_t, track, t)
        if gap is not None:
            loc.stats.skipped["tof_in_odom_gap"] += int(np.count_nonzero(gap))
            ready, t, tof = ready[~gap], t[~gap], tof[~gap]
            if not ready.size:
                return
        self._last_pushed_t = float(t[-1])
        if self._source is None:
            panning = pan_all[int(ready[0])] is not None
            n = loc.segment_max_readings(panning)
            self._source = SegmentFitSource(
                loc._c_mps, max_readings=n, min_echoes=loc.segment_min_echoes,
                sweep_away_deg=loc.segment_sweep_away_deg(panning))
        sensors = np.array(sensor_all, dtype=np.int64)[ready]
        pans = [pan_all[i] for i in ready.tolist()]
        pan = np.zeros(len(ready)) if all(p is None for p in pans) else \
            np.array([0.0 if p is None else math.radians(p) for p in pans])
        # odometry pose at each reading: linear between records, yaw the short way round
        base = interpolate_track(track_t, track, t)
        bx, by, bth = base[:, 0], base[:, 1], base[:, 2]
        mounts = loc._mounts
        ids, inv = np.unique(sensors, return_inverse=True)
        m = np.array([mounts[i] for i in ids.tolist()])[inv]
        c, s = np.cos(bth), np.sin(bth)
        px = bx + c * m[:, 0] - s * m[:, 1]
        py = by + s * m[:, 0] + c * m[:, 1]
        pth = bth + m[:, 2] + pan
        seg = self._source.segmenter
        lo = 0
        while self._flush_t and self._flush_t[0] <= t[-1]:
            # an odometry restart: the segments open before it are closed there (as
            # Localizer.on_odom closes them), those after it begin afresh
            hi = int(np.searchsorted(t, self._flush_t.pop(0), side="left"))
            if hi > lo:
                closed = seg.push_many(t[lo:hi], px[lo:hi], py[lo:hi], pth[lo:hi],
                                       tof[lo:hi], sensors[lo:hi])
                self._waiting += [s for _, s in closed]
            self._waiting += seg.flush()
            lo = hi
        closed = seg.push_many(t[lo:], px[lo:], py[lo:], pth[lo:], tof[lo:], sensors[lo:])
        self._waiting += [s for _, s in closed]

    def _in_odom_gap(self, track_t: Array, track: Array, t: Array
                     ) -> NDArray[np.bool_] | None:
        """Which readings (times ``t``, sorted) lie strictly inside an odometry gap the
        robot moved across, as :meth:`Localizer._in_odom_gap` says; None: none."""
        gap_s = self.loc.config.odom_gap_s
        if len(track_t) < 2 or not np.any(np.diff(track_t) > gap_s):
            return None
        b = np.clip(np.searchsorted(track_t, t, side="right"), 1, len(track_t) - 1)
        a = b - 1
        inside = (track_t[b] - track_t[a] > gap_s) & (t > track_t[a]) & (t < track_t[b])
        gap = inside & odom_moved(track[a], track[b])
        return gap if gap.any() else None

    def _fuse(self, horizon: float) -> None:
        """Fuse the landmarks referring to times before ``horizon`` at their reference
        times, the odometry entered as needed; hand out the rows before ``horizon``."""
        loc = self.loc
        odom, self._odom = self._odom, []
        pending_t = np.array([o[0] for o in odom])
        pos = 0  # next pending odom record to enter into the history

        def enter(upto: int) -> None:
            nonlocal pos
            if upto <= pos:
                return
            part = odom[pos:upto]
            self._extend(part, pending_t[pos:upto])
            self._rows += part
            pos = upto

        now = [lm for lm in self._landmarks if lm.ref_t_s < horizon]
        self._landmarks = [lm for lm in self._landmarks if not lm.ref_t_s < horizon]
        now.sort(key=lambda lm: lm.ref_t_s)
        for lm in now:
            if loc.fuses(lm):
                # the odometry up to the first record at or after the reference reading
                j = int(np.searchsorted(pending_t, lm.ref_t_s, side="left"))
                enter(min(j + 1, len(odom)))
                self._hand_out(lm.ref_t_s)
            loc.add_landmark(lm)
        enter(len(odom) if not math.isfinite(horizon)
              else int(np.searchsorted(pending_t, horizon, side="left")))
        self._odom = odom[pos:]
        self._hand_out(horizon)

    def _hand_out(self, before: float) -> None:
        """Rows of odom records earlier than ``before`` (all landmarks up to them fused)."""
        k = 0
        rows = self._rows
        while k < len(rows) and rows[k][0] < before:
            t, rec = rows[k][0], rows[k][1]
            est = self.loc.estimate_at(t)
            if est is not None:
                self.rows += 1
                self.last = est
                if self.on_estimate is not None:
                    self.on_estimate(rec, est)
            k += 1
        if k:
            del rows[:k]

    # -- fast path (no fits: segments fused by their readings) ---------------------

    def _extend(self, part: list[_Odom], t: Any = None) -> None:
        """Enter odom records into the Localizer's history (joined poses; with resets
        and frames once the odometry has restarted); ``t``: their times, if at hand."""
        ts = [o[0] for o in part] if t is None else t
        poses = [o[2] for o in part]
        if self._restarted:
            self.loc.extend_odometry(ts, poses, resets=[o[4] for o in part],
                                     frames=[o[3] for o in part])
        else:
            self.loc.extend_odometry(ts, poses)

    def _enter_upto(self, odom: list[_Odom], pos: int, t: float) -> int:
        """Enter the pending odom records at or before ``t`` (from ``pos``); rows of those
        before ``t`` handed out. Returns the new position."""
        end = pos
        while end < len(odom) and odom[end][0] <= t:
            end += 1
        if end > pos:
            part = odom[pos:end]
            self._extend(part)
            self._rows += part
        if self._rows and self._rows[0][0] < t:
            self._hand_out(t)
        return end

    def _fuse_fast(self, horizon: float) -> None:
        """Fuse the waiting segments whose reference is before ``horizon`` in time order,
        linearised ``chunk_segments`` at a time; hand out the rows before ``horizon``."""
        loc = self.loc
        odom, self._odom = self._odom, []
        now = [s for s in self._segs if s.t_ref < horizon]
        self._segs = [s for s in self._segs if not s.t_ref < horizon]
        now.sort(key=lambda s: s.t_ref)
        pos = 0
        k = 0
        if self._fuser is None and now:
            c = loc.config
            a = c.association
            self._fuser = BatchFuser(loc.fmap, c.odom_noise, loc._c_mps,
                                     c.echo_screen_probability, c.echo_gate_probability,
                                     a.max_range_m, a.wall_margin_m, a.min_match_probability,
                                     ECHO_MIN_FRACTION, loc.map_var_all())
        noise = loc.config.odom_noise
        lin: Linearized | None = None
        base = 0                              # index in ``now`` of lin's first segment
        while k < len(now):
            if lin is None or k - base >= len(lin.t_ref):
                pos = self._enter_upto(odom, pos, now[k].t_ref)
                if not loc._entries:
                    loc.stats.observations += len(now) - k
                    loc.stats.skipped["landmark_before_init"] += len(now) - k
                    break
                assert self._fuser is not None
                last = loc._entries[-1]
                base = k
                lin = self._fuser.linearize(now[k:k + self.linearize_segments],
                                            np.array(self._track_t), np.array(self._track),
                                            loc._times[0], last.odom, last.state)
                assert lin is not None
            # decide a few segments at a time at the beliefs the latest one predicts
            t_end = now[k].t_ref + self.chunk_s
            j = k + 1
            stop = base + len(lin.t_ref)
            while j < stop and j - k < self._chunk and now[j].t_ref < t_end:
                j += 1
            pos = self._enter_upto(odom, pos, now[k].t_ref)
            last = loc._entries[-1]
            pred = ekf.predict(
                ekf.Gaussian(np.broadcast_to(last.state.mean, (j - k, 3)).copy(),
                             np.broadcast_to(last.state.cov, (j - k, 3, 3)).copy()),
                se2.between(last.odom, lin.odom_ref[k - base:j - base]), noise)
            assert self._fuser is not None
            prepared = self._fuser.decide(lin, k - base, j - base, pred.mean, pred.cov,
                                          loc.map_var_grown_m2(now[k].t_ref))
            slow = stale = False
            for i, p in enumerate(prepared):
                pos = self._enter_upto(odom, pos, p.t_ref)
                how = self._fuse_prepared(p, redecide=i > 0)
                if how == "stale":
                    stale = True
                    break
                k += 1
                slow |= how == "segment"
            if slow or stale:
                # updates the reduced forms could not take (or the belief moved away from
                # where the rest were decided): re-linearise the rest at the belief now,
                # and decide fewer at a time for now
                lin = None
                self._chunk = max(1, self._chunk // 4)
            else:
                self._chunk = min(self.chunk_segments, 2 * self._chunk)
        end = len(odom) if not math.isfinite(horizon) else \
            next((j for j in range(pos, len(odom)) if not odom[j][0] < horizon), len(odom))
        if end > pos:
            part = odom[pos:end]
            self._extend(part)
            self._rows += part
            pos = end
        self._odom = odom[pos:]
        self._hand_out(horizon)

    def _fuse_prepared(self, p: Prepared, redecide: bool = False) -> FuseHow:
        """Fuse one prepared segment into the history (appended: it is the latest).

        Returns how: ``"reduced"`` (by its reduced update, or rejected as decided),
        ``"segment"`` (the Localizer's per-segment path: the update too large for the
        reduced form, or, unless ``redecide``, the belief too far from the one it was
        decided at) or ``"stale"`` (``redecide`` and the belief too far: nothing done,
        the caller decides it again at the belief now)."""
        loc = self.loc
        st = loc.stats
        if p.outcome == "none":
            st.observations += 1
            st.outcomes["echo_none"] += 1
            return "reduced"
        last = loc._entries[-1]
        # the belief at the reference time: the last one moved by the odometry since
        # (in floats: a Gaussian is made only for what goes into the history)
        u = se2.between_floats(last.odom.tolist(), p.odom_ref.tolist())
        mean_ref, cov_ref = ekf.predict_lists(last.state.mean.tolist(), last.state.cov.tolist(),
                                              u, loc.config.odom_noise)
        x0 = p.x0.tolist()
        m0, m1, m2 = mean_ref
        dyaw = abs((m2 - x0[2] + math.pi) % (2.0 * math.pi) - math.pi)
        near = abs(m0 - x0[0]) + abs(m1 - x0[1]) <= FAST_DXY_M and dyaw <= FAST_DYAW_RAD
        if redecide and not near:
            return "stale"
        st.observations += 1
        if near and p.outcome == "unmatched":
            loc._rejected(p.t_ref)
            st.outcomes["echo_unmatched"] += 1
            return "reduced"
        fuser = self._fuser
        assert fuser is not None
        if near and p.reduced is not None and p.feature is not None and \
                p.screen_holds_lists(mean_ref, cov_ref, fuser.screen_gate):
            res = reduced_update_lists(mean_ref, cov_ref, p.reduced)
            big = True
            if res is not None:
                new_mean, new_cov, d2 = res
                n0, n1, n2 = new_mean
                big = abs(n0 - m0) + abs(n1 - m1) > FAST_STEP_M or \
                    abs((n2 - m2 + math.pi) % (2.0 * math.pi) - math.pi) > FAST_STEP_RAD
            if not big:
                st.outcomes["echo_matched"] += 1
                d2 += p.reduced.resid2
                if not d2 <= fuser.gate(p.n_kept):
                    st.outcomes["echo_gated"] += 1
                    loc._rejected(p.t_ref)
                    return "reduced"
                where = _sensor_odom(p)
                if not loc.may_fuse_again(p.kind, p.index, where, p.t_ref):
                    return "reduced"
                obs = EchoObservation(*_NO_READINGS, math.nan, p.feature, p.t_ref,
                                      loc._c_mps, p.kind, compressed=p.reduced)
                self._append_fused(p, ekf.Gaussian.of_lists(new_mean, new_cov),
                                   obs, p.n_kept, p.kind, p.index, where)
                return "reduced"
        state_ref = ekf.Gaussian.of_lists(mean_ref, cov_ref)
        # the per-segment path: associate and update (iterated) at the true belief
        assert p.chain is not None
        found = loc._associate_echoes(p.chain, math.nan, state_ref)
        if found is None:
            loc._rejected(p.t_ref)
            st.outcomes["echo_unmatched"] += 1
            return "segment"
        eo, assoc = found
        st.outcomes["echo_matched"] += 1
        gate = ekf.chi2_gate(len(eo), loc.config.echo_gate_probability)
        new, innov = echoes.update(state_ref, eo, gate)
        if not bool(np.all(innov.accepted)):
            st.outcomes["echo_gated"] += 1
            loc._rejected(p.t_ref)
            return "segment"
        where = _sensor_odom(p)
        if not loc.may_fuse_again(assoc.kind, assoc.index, where, p.t_ref):
            return "segment"
        self._append_fused(p, new, eo, len(eo), assoc.kind, assoc.index, where)
        return "segment"

    def _append_fused(self, p: Prepared, state: ekf.Gaussian, obs: EchoObservation,
                      n: int, kind: str | None, index: int, sensor_odom: list[float]) -> None:
        loc = self.loc
        last = loc._entries[-1]
        loc.note_fused(kind, index, sensor_odom, p.t_ref)
        loc._append(_Entry(max(p.t_ref, last.t), p.odom_ref, state, obs, obs.feature,
                           frame=last.frame))
        st = loc.stats
        st.echoes_fused += n
        st.accepted += 1
        loc._consecutive_rejected = 0
        loc.confirm(p.t_ref, str(kind), index)


def _sensor_odom(p: Prepared) -> list[float]:
    """The transducer pose (in ``odom``) of a prepared segment's latest reading (as
    :meth:`Localizer._add_echoes` takes it for ``update_min_d`` / ``update_min_a``)."""
    if p.batch is None:
        return [float(v) for v in p.odom_ref]
    rel = p.batch[2]
    return se2.compose_floats(p.odom_ref.tolist(), rel[p.row, -1].tolist())
