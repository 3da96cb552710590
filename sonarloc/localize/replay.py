"""Replay a log through a :class:`Localizer`: the library side of ``sonarloc localize``.

Streams the log (memory stays flat however long it is), hands every record to the
Localizer and every estimate (one per ``odom`` record) to a callback, e.g. a pose CSV
writer (FORMATS.md section 5). Problems in the log are counted and named by
:func:`sonarloc.io.logfile.iter_log`; a log without a prior needs ``init``.

Two ways through the Localizer: ``online`` hands it one record at a time, as a live
robot would (fits fused when they complete, rewinding the history); ``batch`` (the
default for the ``kuc`` and ``odometry`` methods) runs the
:class:`~sonarloc.localize.offline.OfflinePipeline`: readings segmented and fitted in
large batches, each landmark fused at its reference reading as if fitting took no time,
an order of magnitude faster; with reading-level fusion (the default) the segments are
not fitted at all but fused by their readings, many linearised at a time
(:mod:`~sonarloc.localize.batchfuse`).
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

import numpy as np

from sonarloc.errors import LogFormatError
from sonarloc.io.logfile import (
    InitRecord,
    LogStats,
    OdomRecord,
    Record,
    RigRecord,
    TofRecord,
    TofRun,
    TruthRecord,
    iter_log,
    iter_log_runs,
)
from sonarloc.io.posescsv import COLUMNS
from sonarloc.io.scancsv import TimeoutWatch
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import Localizer, LocalizerConfig, PoseEstimate
from sonarloc.localize.offline import OfflinePipeline

Mode = Literal["auto", "batch", "online"]

#: Prior SDs used with ``init`` when the log has no ``init`` record to take them from.
DEFAULT_INIT_SD_XY_M = 0.1
DEFAULT_INIT_SD_YAW_DEG = 5.0


@dataclass
class ReplayResult:
    """What a replay did: log problems, localizer counters, rows, last estimate, time."""

    log: LogStats
    localizer: Localizer
    rows: int
    last: PoseEstimate | None
    wall_time_s: float
    log_duration_s: float
    #: CPU time of this process during the replay [s] (wall time less what other
    #: processes took: the speed measure on a shared machine)
    cpu_time_s: float = math.nan
    #: what the replay noticed (e.g. readings that look like a module's timeouts)
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        speed = self.log_duration_s / self.wall_time_s if self.wall_time_s > 0 else math.inf
        parts = [f"log: {self.log.summary()}", f"localizer: {self.localizer.stats.summary()}",
                 f"{self.rows} poses"]
        if self.last is not None:
            parts.append(f"final status {self.last.status} ({self.last.reason})")
        parts.append(f"{self.log_duration_s:.1f} s of log in {self.wall_time_s:.2f} s "
                     f"({speed:.0f}x real time)")
        return "; ".join(parts + self.notes)


def replay_log(source: str | Path | IO[str], fmap: FeatureMap, *,
               config: LocalizerConfig | None = None,
               init: tuple[float, float, float] | None = None,
               on_estimate: Callable[[OdomRecord, PoseEstimate], None] | None = None,
               localizer: Localizer | None = None, mode: Mode = "auto",
               batch_segments: int = 1024, fast: bool | None = None) -> ReplayResult:
    """Localize a whole log.

    Parameters
    ----------
    source : log path or text stream (FORMATS.md section 4).
    fmap : the map's features.
    config : Localizer settings (ignored when ``localizer`` is given).
    init : (x_m, y_m, yaw_deg) overriding the log's ``init`` record (its SDs are kept;
        without one, :data:`DEFAULT_INIT_SD_XY_M` / :data:`DEFAULT_INIT_SD_YAW_DEG`).
    on_estimate : called with each odom record and the estimate after it.
    localizer : use this Localizer (e.g. with a custom landmark source).
    mode : ``"online"`` (record by record, as live), ``"batch"`` (the offline pipeline;
        methods ``kuc`` and ``odometry`` with the default landmark source) or
        ``"auto"`` (batch where it applies).
    batch_segments : segments fitted together in batch mode (``fast=False``).
    fast : batch mode only: the :class:`~sonarloc.localize.offline.OfflinePipeline`'s
        ``fast`` (None: segments fused by their readings without fits, linearised many
        at a time, for ``kuc_fusion="echoes"``; False: every segment fitted and fused
        on time through :meth:`Localizer.add_landmark`).

    Raises
    ------
    LogFormatError
        if an ``odom`` record comes before any prior (no ``init`` record, no ``init``),
        unless the Localizer relocalizes (``LocalizerConfig.relocalize``): then rows begin
        at its first fix.
    """
    if mode not in ("auto", "batch", "online"):
        raise ValueError(f"`mode` must be 'auto', 'batch' or 'online', got {mode!r}")
    stats = LogStats()
    loc = localizer if localizer is not None else Localizer(fmap, config)
    # relocalization (LocalizerConfig.relocalize) runs record by record
    batchable = loc.config.method in ("kuc", "odometry") and loc._source_factory is None \
        and not loc.config.relocalize
    if mode == "batch" and not batchable:
        raise ValueError(f"`mode` 'batch' runs methods 'kuc' and 'odometry' with the default "
                         f"landmark source and without relocalization, not "
                         f"{loc.config.method!r}" + (" with relocalize" if
                                                      loc.config.relocalize else ""))
    pipe = OfflinePipeline(loc, on_estimate, batch_segments=batch_segments, fast=fast) \
        if mode != "online" and batchable else None
    rows = 0
    t0, c0 = time.perf_counter(), time.process_time()
    first_t, last_t = math.nan, -math.inf
    have_prior = False
    # batch: runs of tof records as columns (no record objects)
    items: Iterator[Record | TofRun] = iter_log_runs(source, stats) if pipe is not None \
        else iter_log(source, stats)
    # a module's timeouts logged as echoes? (only asked where they are not taken as such)
    watch = TimeoutWatch() if loc.config.max_tof_us is None else None
    for rec in items:
        kind = type(rec)
        if watch is not None and isinstance(rec, TofRecord):
            watch.push_one(math.nan if rec.tof_us is None else float(rec.tof_us))
        if isinstance(rec, TofRun):
            assert pipe is not None
            if watch is not None:
                watch.push(np.asarray(rec.tof_us, float))
            t_run = max(rec.t_s)
            if t_run > last_t:
                last_t = t_run
            if math.isnan(first_t):
                first_t = rec.t_s[0]
            pipe.tofs(rec)
            continue
        t_s = rec.t_s
        if t_s > last_t:
            last_t = t_s
        if pipe is not None and not math.isnan(first_t):
            # the frequent records first (batch)
            if kind is OdomRecord and have_prior:
                pipe.odom(rec)  # type: ignore[arg-type]
                continue
            if kind is TruthRecord:
                continue
            if kind is TofRecord:
                pipe.tof(rec)  # type: ignore[arg-type]
                continue
        if math.isnan(first_t):
            first_t = t_s
        if isinstance(rec, InitRecord):
            if init is not None:
                rec = InitRecord(rec.t_s, init[0], init[1], init[2], rec.sd_xy_m, rec.sd_yaw_deg)
            have_prior = True
        elif isinstance(rec, OdomRecord) and not have_prior and \
                not (init is None and loc.config.relocalize):  # relocalizes from scratch
            if init is None:
                bad = [f"line {n}: {m}" for n, m in stats.malformed
                       if m.startswith("init record")][:1]   # a refused init record
                raise LogFormatError(
                    f"the log has no `init` record before its first `odom` record (t_s="
                    f"{rec.t_s}); give --init X,Y,YAW_DEG" +
                    "".join(f" (malformed, skipped: {b})" for b in bad))
            loc.set_prior(rec.t_s, init[0], init[1], math.radians(init[2]),
                          DEFAULT_INIT_SD_XY_M, math.radians(DEFAULT_INIT_SD_YAW_DEG))
            have_prior = True
        if pipe is not None:
            if isinstance(rec, OdomRecord):
                pipe.odom(rec)
            elif isinstance(rec, TofRecord):
                pipe.tof(rec)
            elif isinstance(rec, (RigRecord, InitRecord)):
                # what came before is localized with the old rig / prior
                pipe.finish(restart=isinstance(rec, InitRecord))
                loc.handle(rec)
            continue
        est = loc.handle(rec)
        if est is not None and isinstance(rec, OdomRecord):
            rows += 1
            if on_estimate is not None:
                on_estimate(rec, est)
    if pipe is not None:
        pipe.finish()
        rows, last = pipe.rows, pipe.last
    else:
        loc.finish()
        last = loc.estimate
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    duration = 0.0 if math.isnan(first_t) else last_t - first_t
    advice = None if watch is None else watch.advice()
    return ReplayResult(stats, loc, rows, last, wall, duration, cpu,
                        [] if advice is None else [advice])


class PoseCsvWriter:
    """Streams pose rows (FORMATS.md section 5), optionally with a ``status`` column."""

    def __init__(self, handle: IO[str], with_status: bool = False) -> None:
        self._w = csv.writer(handle, lineterminator="\n")
        self._status = with_status
        self._w.writerow(COLUMNS + (("status",) if with_status else ()))

    def write(self, rec: OdomRecord, est: PoseEstimate) -> None:
        m, c = est.state.mean, est.state.cov
        row = [repr(float(v)) for v in (rec.t_s, m[0], m[1], math.degrees(m[2]), c[0, 0],
                                        c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2])]
        if self._status:
            row.append(est.status)
        self._w.writerow(row)
