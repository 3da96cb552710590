"""Landmark fits off the caller's thread: one pure job, and a small pool to run it.

:func:`fit_job` fits the closed segments of one batch (what
:class:`~sonarloc.localize.localizer.SegmentFitSource` does when a batch is due); the
synchronous path calls it in the caller's thread, :class:`FitPool` in a worker thread
or process (``LocalizerConfig.fit_workers``, ``fit_executor``). It keeps no state and
does no I/O: its arguments and its result are plain data (segments of readings, the
fitter's settings, landmarks), so a process worker receives and returns them pickled.

The first fit in a process builds tables (beam patterns, waveform templates, delay
tables; cached per module parameters): :func:`warm_up` builds them from a small
synthetic scan, and a pool runs it as each worker starts, so the first real batch does
not pay for it.

Process workers start with the ``forkserver`` method where the platform has it, else
``spawn``; never ``fork``, which copies a threaded program's locks in whatever state
they were in.
"""

from __future__ import annotations

import math
import multiprocessing
from collections.abc import Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from sonarloc.fit.result import FitStatus, Landmark

FitExecutor = Literal["thread", "process"]
#: Reflector strengths [us] of the warm-up scan: a strong corner to a weak rod (the
#: fitter picks its tier by strength, each tier has its tables) and a wall.
WARM_UP_KAPPA_US = (0.05, 0.15, 0.67, 2.68)


def fit_job(segments: Sequence[Any], fit_config: Any) -> list[Landmark]:
    """Fit closed segments (one vectorised batch): one landmark per segment, in order.

    Parameters
    ----------
    segments : :class:`~sonarloc.fit.segment.Segment` s (readings with their
        transducer poses in ``odom``).
    fit_config : the fitter's settings (:class:`~sonarloc.fit.lsq.FitConfig`).

    Returns
    -------
    The landmarks, each with ``extra["view_xy"]`` (mean transducer position of its
    echoes) and ``extra["echoes"]`` (its echoes as arrays ``(t_s, x_m, y_m, yaw_rad,
    tof_us)``) when it has echoes. A segment with fewer echoes than the fitter needs
    gets the ``too_few_points`` result without a fit.
    """
    from sonarloc.fit.landmarks import fit_segments

    if not segments:
        return []
    # too few echoes for the fitter: it would say so; skip the work
    need = fit_config.min_echoes
    long = [s for s in segments if getattr(s, "n_echo", need) >= need]
    fitted = iter(fit_segments(long, fit_config)) if long else iter(())
    out = []
    for s in segments:
        lm = next(fitted) if getattr(s, "n_echo", need) >= need else too_few(s, need)
        r = s.readings
        echo = np.isfinite(r.tof_us)
        if echo.any():
            view = (float(np.mean(r.x_m[echo])), float(np.mean(r.y_m[echo])))
            readings = tuple(np.asarray(a, dtype=float)[echo] for a in
                             (r.t_s, r.x_m, r.y_m, r.yaw_rad, r.tof_us))
            lm = replace(lm, extra={**lm.extra, "view_xy": view, "echoes": readings})
        out.append(lm)
    return out


def too_few(seg: Any, need: int) -> Landmark:
    """The ``too_few_points`` result of a segment with fewer echoes than the fitter needs
    (what :func:`~sonarloc.fit.landmarks.fit_segments` would return, without fitting)."""
    r = seg.readings
    echo = np.flatnonzero(np.isfinite(r.tof_us))
    k = int(echo[-1]) if echo.size else len(r.t_s) - 1
    nan3 = np.full(3, np.nan)
    return Landmark("point", nan3, np.full((3, 3), np.nan), math.nan, math.nan,
                    int(echo.size), float(r.t_s[k]),
                    (float(r.x_m[k]), float(r.y_m[k]), float(r.yaw_rad[k])),
                    FitStatus.TOO_FEW_POINTS, f"{echo.size} echoes; {need} are needed",
                    sensors=tuple(sorted({int(v) for v in np.asarray(r.sensor)[echo]})))


def warm_up(speed_of_sound_mps: float = 343.0) -> int:
    """Build the fitter's tables for this speed of sound in this process: fit a small
    synthetic pan scan of point reflectors of :data:`WARM_UP_KAPPA_US` and a wall with
    the default :class:`~sonarloc.fit.lsq.FitConfig`. Returns the number of landmarks
    fitted (pure apart from filling the module-level caches)."""
    from sonarloc.fit.lsq import FitConfig
    from sonarloc.fit.segment import Segment
    from sonarloc.fit.synth import Reflector, pan_scan
    from sonarloc.physics.tof import ModuleParams

    params = ModuleParams(c_mps=speed_of_sound_mps)
    config = FitConfig(module=params)
    rng = np.random.default_rng(0)
    scans = [pan_scan([Reflector.polar(1.5, 0.0, k)], rng, -40.0, 40.0, 2.0, params=params,
                      tier="auto") for k in WARM_UP_KAPPA_US]
    scans.append(pan_scan([Reflector("line", 1.2, 0.0, 0.67)], rng, -40.0, 40.0, 2.0,
                          params=params, tier="auto"))
    return len(fit_job([Segment(s, k, "flush") for k, s in enumerate(scans)], config))


def _ready() -> None:
    """A no-op job: makes a pool start its workers."""


def process_context() -> multiprocessing.context.BaseContext:
    """The start method of process workers: ``forkserver`` where available, else
    ``spawn`` (never ``fork`` in a threaded program)."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")


class FitPool:
    """A few workers running :func:`fit_job` (a thin wrapper of
    :mod:`concurrent.futures`).

    Parameters
    ----------
    workers : number of worker threads or processes (>= 1).
    executor : ``"thread"`` (the fits' NumPy work and Python work share the
        interpreter with the caller; the caller's own CPU per call drops, its wall time
        less so) or ``"process"`` (separate interpreters: segments and landmarks are
        pickled across).
    speed_of_sound_mps : the workers are warmed up (:func:`warm_up`) for this speed of
        sound as they start.

    Jobs finish in any order; the caller keeps their futures in the order it submitted
    them (the :class:`~sonarloc.localize.localizer.Localizer` fuses their landmarks in
    that order).
    """

    def __init__(self, workers: int, executor: FitExecutor = "thread",
                 speed_of_sound_mps: float = 343.0) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"`workers` must be a positive integer, got {workers!r}")
        if executor not in ("thread", "process"):
            raise ValueError(f"`executor` must be 'thread' or 'process', got {executor!r}")
        self.workers = workers
        self.kind: FitExecutor = executor
        self.closed = False
        self._warm: list[Future[Any]] = []
        self._warmed_c: set[float] = set()
        self._executor: Executor
        if executor == "process":
            self._executor = ProcessPoolExecutor(
                workers, mp_context=process_context(), initializer=warm_up,
                initargs=(float(speed_of_sound_mps),))
            self._warmed_c.add(float(speed_of_sound_mps))
            # start the workers now (each warms up as it starts), not at the first fit
            self._warm += [self._executor.submit(_ready) for _ in range(workers)]
        else:
            self._executor = ThreadPoolExecutor(workers, thread_name_prefix="sonarloc-fit")
            self.warm(speed_of_sound_mps)

    def warm(self, speed_of_sound_mps: float) -> None:
        """Warm the workers up for another speed of sound (once per value): a thread
        pool's workers share the caller's caches, one job does; a process pool gets one
        job per worker (not pinned to a worker: most likely one each, as idle workers
        take them)."""
        c = float(speed_of_sound_mps)
        if c in self._warmed_c:
            return
        self._warmed_c.add(c)
        n = 1 if self.kind == "thread" else self.workers
        self._warm += [self._executor.submit(warm_up, c) for _ in range(n)]

    def submit(self, segments: Sequence[Any], fit_config: Any) -> Future[list[Landmark]]:
        """Fit ``segments`` in a worker (:func:`fit_job`)."""
        return self._executor.submit(fit_job, list(segments), fit_config)

    def warm_up_errors(self) -> list[BaseException]:
        """Exceptions of the finished warm-up jobs (forgotten once returned)."""
        if not self._warm:
            return []
        done = [f for f in self._warm if f.done()]
        self._warm = [f for f in self._warm if not f.done()]
        return [e for f in done if not f.cancelled() and (e := f.exception()) is not None]

    def close(self, wait: bool = True) -> None:
        """Shut the workers down; jobs not started are cancelled."""
        self.closed = True
        self._executor.shutdown(wait=wait, cancel_futures=True)
