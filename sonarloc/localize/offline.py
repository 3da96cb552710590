"""Offline replay of a log through a :class:`Localizer`, in batches, fused on time.

A recorded log can be localized faster than record by record: every reading's
transducer pose is interpolated from the odometry in one numpy call, the segmenter
runs in a lean loop, the closed segments are fitted together in large batches (the
fitter's cost per segment falls steeply with the batch size), and the odometry between
landmark updates is predicted in closed form (:func:`~sonarloc.localize.ekf.predict_chain`).

The filter result is that of *on-time* fusion: a landmark is fused at its reference
reading, before any later odometry, whatever batch it was fitted in. A pose row for an
odom record is handed out once every landmark that can refer to a time at or before
it is known (no segment still open or waiting for the fitter began earlier), and it
holds every landmark whose reference reading is at or before that record: what a live
Localizer reports for the same moment once the fits have caught up, without their
latency. A live :class:`Localizer` fed record by record fuses the same landmarks, but
associates each one when its fit completes, after the landmarks fitted before it.

Memory stays bounded: odometry waits for the fitter at most ``max_wait_s`` of log time
or ``batch_segments`` segments, and the Localizer's history is trimmed as usual.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import OdomRecord, TofRecord
from sonarloc.localize.localizer import Localizer, PoseEstimate, SegmentFitSource

EstimateCallback = Callable[[OdomRecord, PoseEstimate], None]


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
    """

    def __init__(self, localizer: Localizer, on_estimate: EstimateCallback | None = None,
                 batch_segments: int = 1024, max_wait_s: float = 120.0,
                 round_odom: int = 50) -> None:
        if localizer.config.method not in ("kuc", "odometry"):
            raise ValueError(f"the offline pipeline runs methods 'kuc' and 'odometry', got "
                             f"{localizer.config.method!r}")
        if not (isinstance(batch_segments, int) and batch_segments >= 1):
            raise ValueError(f"`batch_segments` must be a positive integer, got "
                             f"{batch_segments!r}")
        if not (math.isfinite(max_wait_s) and max_wait_s >= 0):
            raise ValueError(f"`max_wait_s` must be non-negative, got {max_wait_s!r}")
        self.loc = localizer
        self.on_estimate = on_estimate
        self.batch_segments = batch_segments
        self.max_wait_s = max_wait_s
        self.round_odom = max(int(round_odom), 1)
        self.rows = 0
        self.last: PoseEstimate | None = None
        self._odom: list[tuple[float, OdomRecord]] = []  # received, not yet in the history
        self._last_t = -math.inf
        self._new = 0                            # odom records since the last round
        self._rows: list[tuple[float, OdomRecord]] = []  # in the history, not yet handed out
        self._tof: list[TofRecord] = []          # waiting for odometry at or after them
        self._waiting: list[Any] = []            # closed segments waiting for the fitter
        self._landmarks: list[Landmark] = []     # fitted, waiting to be fused
        self._track_t: list[float] = []          # odometry track for the readings' poses
        self._track: list[tuple[float, float, float]] = []
        self._source: SegmentFitSource | None = None

    # -- records --------------------------------------------------------------------

    def odom(self, rec: OdomRecord) -> None:
        """An odom record (after the prior)."""
        t = max(rec.t_s, self._last_t)  # time going backwards: keep the track sorted
        self._last_t = t
        self._odom.append((t, rec))
        self._track_t.append(t)
        self._track.append((rec.x_m, rec.y_m, math.radians(rec.yaw_deg)))
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
            self._tof.append(rec)

    def finish(self) -> None:
        """End of the records (or a rig/init record follows): fit and fuse everything."""
        self._round(final=True)
        self._source = None

    # -- internals ------------------------------------------------------------------

    def _round(self, final: bool) -> None:
        self._new = 0
        t_odom = self._track_t[-1] if self._track_t else -math.inf
        self._segment(t_odom, final)
        horizon = math.inf if final else t_odom
        if self._source is not None:
            seg = self._source.segmenter
            horizon = min(horizon, seg.open_since_s)
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
        t_min = min((r.t_s for r in self._tof), default=self._track_t[-1])
        k = int(np.searchsorted(self._track_t, t_min, side="right")) - 1
        k = min(max(k, 0), len(self._track_t) - 1)
        if k > 0:
            del self._track_t[:k]
            del self._track[:k]

    def _segment(self, t_odom: float, final: bool) -> None:
        """Push the readings up to the latest odometry through the segmenter."""
        self._push_ready(t_odom, final)
        if final and self._source is not None:
            self._waiting += self._source.segmenter.flush()

    def _push_ready(self, t_odom: float, final: bool) -> None:
        if not self._tof:
            return
        loc = self.loc
        ready = [r for r in self._tof if r.t_s <= t_odom]
        self._tof = [r for r in self._tof if r.t_s > t_odom] if not final else []
        if final and self._tof:
            loc.stats.skipped["tof_after_last_odom"] += len(self._tof)
        if not ready:
            return
        first_t = loc._times[0] if loc._times else self._odom[0][0] if self._odom \
            else math.inf
        old = [r for r in ready if r.t_s < first_t]
        if old:
            loc.stats.skipped["tof_older_than_history"] += len(old)
            ready = [r for r in ready if r.t_s >= first_t]
            if not ready:
                return
        if self._source is None:
            n = loc.segment_max_readings(ready[0].pan_deg is not None)
            self._source = SegmentFitSource(
                loc._c_mps, max_readings=n, min_echoes=loc.segment_min_echoes,
                sweep_away_deg=loc.segment_sweep_away_deg(ready[0].pan_deg is not None))
        t = np.array([r.t_s for r in ready])
        # odometry pose at each reading: linear between records, yaw the short way round
        tt, tr = np.array(self._track_t), np.array(self._track)
        i = np.searchsorted(tt, t, side="right")
        a = np.clip(i - 1, 0, len(tt) - 1)
        b = np.minimum(a + 1, len(tt) - 1)
        span = tt[b] - tt[a]
        f = np.where((b > a) & (span > 0) & (t > tt[a]),
                     (t - tt[a]) / np.where(span > 0, span, 1.0), 0.0)
        dth = (tr[b, 2] - tr[a, 2] + math.pi) % (2.0 * math.pi) - math.pi
        bx = tr[a, 0] + f * (tr[b, 0] - tr[a, 0])
        by = tr[a, 1] + f * (tr[b, 1] - tr[a, 1])
        bth = (tr[a, 2] + f * dth + math.pi) % (2.0 * math.pi) - math.pi
        mounts = loc._mounts
        m = np.array([mounts[r.sensor] for r in ready])
        pan = np.array([0.0 if r.pan_deg is None else math.radians(r.pan_deg) for r in ready])
        c, s = np.cos(bth), np.sin(bth)
        px = bx + c * m[:, 0] - s * m[:, 1]
        py = by + s * m[:, 0] + c * m[:, 1]
        pth = bth + m[:, 2] + pan
        tof = [math.nan if r.tof_us is None else float(r.tof_us) for r in ready]
        sensors = [r.sensor for r in ready]
        push = self._source.segmenter.push
        closed = self._waiting
        for args in zip(t.tolist(), px.tolist(), py.tolist(), pth.tolist(), tof, sensors,
                        strict=True):
            out = push(*args)
            if out:
                closed += out

    def _fuse(self, horizon: float) -> None:
        """Fuse the landmarks referring to times before ``horizon`` at their reference
        times, the odometry entered as needed; hand out the rows before ``horizon``."""
        loc = self.loc
        odom, self._odom = self._odom, []
        pending_t = np.array([t for t, _ in odom])
        pos = 0  # next pending odom record to enter into the history

        def enter(upto: int) -> None:
            nonlocal pos
            if upto <= pos:
                return
            part = odom[pos:upto]
            loc.extend_odometry(pending_t[pos:upto],
                                [(r.x_m, r.y_m, math.radians(r.yaw_deg)) for _, r in part])
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
            t, rec = rows[k]
            est = self.loc.estimate_at(t)
            if est is not None:
                self.rows += 1
                self.last = est
                if self.on_estimate is not None:
                    self.on_estimate(rec, est)
            k += 1
        if k:
            del rows[:k]
