"""Background fit workers (``LocalizerConfig.fit_workers``): same landmarks, same fusion.

The workers only move *where* a batch of closed segments is fitted; the landmarks are
fused in the order their segments closed, each at its own reference time (rewind and
replay). So once every fit is fused (after ``finish()``) the belief is the synchronous
one, bit for bit; the estimates reported on the way lack the fits still in flight.
"""

from __future__ import annotations

import json
import threading
from concurrent.futures import Future
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from sonarloc.api import LocalizerNode
from sonarloc.errors import FitWorkerError, SonarlocError
from sonarloc.fit.result import Landmark
from sonarloc.localize import fitpool
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.fitpool import FitPool, fit_job
from sonarloc.localize.localizer import Localizer, LocalizerConfig, SegmentFitSource
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import rig_by_name
from sonarloc.world.simulate import simulate_records

ROOM = Path(__file__).resolve().parents[2] / "maps" / "room.geojson"


@pytest.fixture(scope="module")
def drive() -> tuple[FeatureMap, list[Any]]:
    """A 6 s drive of the room with the ring of 16 (some 40 batches of segments)."""
    world = load_map(ROOM)
    recs = list(simulate_records(world, rig_by_name("ring16"), duration_s=6.0, seed=1))
    return FeatureMap.from_map(world), recs


def _run(loc: Localizer, recs: list[Any]) -> tuple[np.ndarray, Any]:
    """Every estimate (t, mean, cov) and the final one, after finish()."""
    rows = []
    for rec in recs:
        est = loc.handle(rec)
        if est is not None:
            rows.append(np.concatenate([[est.t_s], est.state.mean, est.state.cov.ravel()]))
    loc.finish()
    return np.array(rows), loc.estimate


def _counts(loc: Localizer) -> tuple[Any, ...]:
    s = loc.stats
    return (s.landmarks, s.observations, s.accepted, s.echoes_fused, dict(s.outcomes),
            dict(s.skipped))


class _PlainSource:
    """The built-in fitter behind the plain ``LandmarkSource`` protocol (push, flush):
    the Localizer takes its landmarks in the call, as before background fits existed."""

    def __init__(self, c_mps: float) -> None:
        self.inner = SegmentFitSource(c_mps, max_readings=8, min_echoes=1)

    def push(self, *args: Any) -> list[Landmark]:
        return self.inner.push(*args)

    def flush(self) -> list[Landmark]:
        return self.inner.flush()


def test_no_workers_is_the_synchronous_localizer_bit_for_bit(drive):
    fmap, recs = drive
    plain = Localizer(fmap, landmark_source=_PlainSource)
    rows0, end0 = _run(plain, recs)
    loc = Localizer(fmap, LocalizerConfig(fit_workers=0))
    rows, end = _run(loc, recs)
    assert loc.stats.accepted > 20
    assert rows.shape == rows0.shape and np.array_equal(rows, rows0)
    assert np.array_equal(end.state.mean, end0.state.mean)
    assert np.array_equal(end.state.cov, end0.state.cov)
    assert _counts(loc) == _counts(plain)
    assert loc.stats.fit_jobs == 0 and loc.stats.fit_waits == 0


@pytest.mark.parametrize("executor", ["thread", "process"])
def test_one_worker_fuses_the_same_landmarks(drive, executor):
    """Thread and process workers: the same fits (same code, same segments), fused in
    the same order at the same reference times, so the final belief equals the
    synchronous one exactly. The estimates on the way differ: they lack the fits in
    flight, and fed as fast as possible here the worker lags by up to fit_max_lag_s (2 s)
    of log time, so they keep more of the prior's error (several cm) for longer: up to
    8 cm apart in the first seconds on this drive (bounded by how far off the prior is,
    whatever the timing). Fed in real time the lag is a fit's
    duration: 0.91 against 0.97 mm after warm-up (benchmarks/results/latency.md)."""
    fmap, recs = drive
    rows0, end0 = _run(Localizer(fmap), recs)
    with Localizer(fmap, LocalizerConfig(fit_workers=1, fit_executor=executor)) as loc:
        rows, end = _run(loc, recs)
        assert loc.pending_fits == 0
    ref = Localizer(fmap)
    _run(ref, recs)
    assert loc.stats.fit_jobs > 10
    assert np.array_equal(end.state.mean, end0.state.mean)
    assert np.array_equal(end.state.cov, end0.state.cov)
    assert _counts(loc) == _counts(ref)
    assert rows.shape == rows0.shape and np.array_equal(rows[:, 0], rows0[:, 0])
    assert np.max(np.hypot(*(rows[:, 1:3] - rows0[:, 1:3]).T)) < 0.15


class _Deferred(Future):  # type: ignore[type-arg]
    """A job that runs when its result is asked for: never done before a wait."""

    def __init__(self, segs: list[Any], config: Any) -> None:
        super().__init__()
        self.job = (segs, config)

    def result(self, timeout: float | None = None) -> Any:
        if not self.done():
            try:
                self.set_result(fit_job(*self.job))
            except Exception as err:
                self.set_exception(err)
        return super().result(timeout)


def test_back_pressure_waits_are_counted(drive, monkeypatch):
    """Fits that never finish on their own are waited for once fit_max_lag_s old (in
    log time), and the result is still the synchronous one."""
    fmap, recs = drive
    monkeypatch.setattr(FitPool, "submit", lambda self, segs, cfg: _Deferred(list(segs), cfg))
    _, end0 = _run(ref := Localizer(fmap), recs)
    with Localizer(fmap, LocalizerConfig(fit_workers=1, fit_max_lag_s=0.5)) as loc:
        _, end = _run(loc, recs)
    st = loc.stats
    # every batch but those of the last 0.5 s (waited for by finish(), not counted)
    assert 0.7 * st.fit_jobs < st.fit_waits < st.fit_jobs
    assert np.array_equal(end.state.mean, end0.state.mean)
    assert _counts(loc) == _counts(ref)
    assert f"{st.fit_jobs} fit batches in workers ({st.fit_waits} waited for)" in st.summary()


@pytest.mark.parametrize("executor", ["thread", "process"])
def test_a_worker_error_surfaces_with_its_cause(drive, executor):
    fmap, recs = drive

    def broken(c_mps: float) -> SegmentFitSource:
        src = SegmentFitSource(c_mps)
        # settings the worker's fit_job fails on (picklable, for a process worker)
        src.fit_config = SimpleNamespace(module=src.fit_config.module, min_echoes="five")
        return src

    loc = Localizer(fmap, LocalizerConfig(fit_workers=1, fit_executor=executor),
                    landmark_source=broken)
    with loc, pytest.raises(FitWorkerError, match="background fit") as info:
        _run(loc, recs)
    assert isinstance(info.value, SonarlocError)
    assert isinstance(info.value.__cause__, TypeError)
    assert loc.stats.skipped["fit_worker_error"] > 0


def test_close_and_context_manager(drive):
    fmap, recs = drive
    loc = Localizer(fmap, LocalizerConfig(fit_workers=1))
    pool = loc._pool
    assert pool is not None
    with loc as entered:
        assert entered is loc
        for rec in recs[:len(recs) // 2]:
            loc.handle(rec)
        pending = loc.pending_fits
    assert pool.closed and loc._pool is None
    assert loc.stats.skipped["fit_dropped_at_close"] == pending
    loc.close()   # again: nothing to do
    # later calls fit in the call, as without workers
    jobs = loc.stats.fit_jobs
    for rec in recs[len(recs) // 2:]:
        loc.handle(rec)
    loc.finish()
    assert loc.stats.fit_jobs == jobs and loc.pending_fits == 0

    names = {t.name for t in threading.enumerate()}
    with LocalizerNode(fmap, config=LocalizerConfig(fit_workers=2)) as node:
        node_pool = node.localizer._pool
        for rec in recs:
            node.feed(rec)
        node.finish()
        assert node.localizer.stats.fit_jobs > 0 and node.localizer.pending_fits == 0
    assert node_pool is not None and node_pool.closed
    # the workers' threads are gone
    assert {t.name for t in threading.enumerate()} <= names


def test_settings_are_checked():
    for name, bad in (("fit_workers", {"fit_workers": -1}), ("fit_workers", {"fit_workers": True}),
                      ("fit_executor", {"fit_executor": "fork"}),
                      ("fuse_per_call", {"fuse_per_call": 0}),
                      ("fit_max_lag_s", {"fit_max_lag_s": 0.0}),
                      ("fit_max_lag_s", {"fit_workers": 1, "fit_max_lag_s": 10.0})):
        with pytest.raises(ValueError, match=f"`{name}`"):
            LocalizerConfig(**bad)
    with pytest.raises(ValueError, match="`workers`"):
        FitPool(0)
    # other methods have nothing to fit: no pool
    assert Localizer(FeatureMap.build(np.zeros((0, 2)), np.zeros((0, 2, 2))),
                     LocalizerConfig(method="conventional", fit_workers=1))._pool is None


def test_warm_up_and_fit_job_are_plain_functions():
    assert fitpool.warm_up() == 5
    assert fit_job([], None) == []
    assert fitpool.process_context().get_start_method() in ("forkserver", "spawn")


def test_drive_cli_fit_workers(run_cli):
    proc = run_cli("drive", "--duration", "4", "--seed", "2", "--json", "--no-plot",
                   "--fit-workers", "1", "--fit-executor", "thread")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(proc.stdout)
    assert rep["fit_workers"] == 1 and rep["fit_executor"] == "thread"
    assert rep["landmarks_matched"] > 0 and rep["fit_waits"] >= 0
    bad = run_cli("drive", "--fit-workers", "-1", "--no-plot")
    assert bad.returncode == 2 and "--fit-workers" in bad.stderr


def test_warm_up_fills_the_fitter_s_tables_and_changes_no_estimate(drive):
    """`LocalizerNode.warm_up` / `Localizer.warm_up` build the tables the first fit would
    (the waveform tier's delay table, the piston beam's) and the fusion's delay table for
    the map's features, for the rig's speed of sound; a warmed-up node's estimates are
    the cold one's, bit for bit."""
    from sonarloc.fit import model
    from sonarloc.localize import echoes

    fmap, recs = drive
    echoes.delay_table.cache_clear()
    cold_rows, _ = _run(Localizer(fmap), recs)
    model.waveform_delay_table.cache_clear()
    model._piston_table.cache_clear()
    echoes.delay_table.cache_clear()
    node = LocalizerNode(fmap)
    node.warm_up()
    assert model.waveform_delay_table.cache_info().currsize >= 1
    assert model._piston_table.cache_info().currsize >= 1
    # the fusion's delay table: the rows of the map's strengths
    assert echoes.delay_table(343.0)._row_built.sum() > 10
    warm_rows, _ = _run(node.localizer, recs)
    assert np.array_equal(warm_rows, cold_rows)
    # nothing to fit, nothing built
    model.waveform_delay_table.cache_clear()
    Localizer(fmap, LocalizerConfig(method="conventional")).warm_up()
    assert model.waveform_delay_table.cache_info().currsize == 0


def test_a_killed_process_worker_is_replaced_and_fits_go_on(drive):
    """A process worker killed mid-drive (as the out-of-memory killer would): at most one
    FitWorkerError for the segments lost with it, a new pool in its place
    (`stats.fit_pool_restarts`), and the fits and fusions go on after it."""
    fmap, recs = drive
    loc = Localizer(fmap, LocalizerConfig(fit_workers=1, fit_executor="process"))
    half = len(recs) // 2
    errors = []
    with loc:
        for rec in recs[:half]:
            loc.handle(rec)
        assert loc._pool is not None
        for proc in list(loc._pool._executor._processes.values()):  # type: ignore[attr-defined]
            proc.kill()
            proc.join()
        fused_before = loc.stats.accepted
        for rec in recs[half:]:
            try:
                loc.handle(rec)
            except FitWorkerError as err:
                errors.append(err)
        loc.finish()
    assert len(errors) <= 1
    assert all("pool broke" in str(e) for e in errors)
    assert loc.stats.fit_pool_restarts == 1
    assert "1 fit worker pools restarted" in loc.stats.summary()
    assert loc.stats.accepted > fused_before + 5    # fitted by the new pool and fused
