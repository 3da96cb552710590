"""Cutting ``UNRESOLVED`` segments in two (:func:`sonarloc.fit.landmarks.split_unresolved`):
the staged search (short parts first, the other part only where that one fits alone)
picks what fitting every cut picks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.fit.landmarks import (
    _fit_p,
    _fits_alone,
    _select_segments,
    _split_groups,
    fit_scan,
    fit_segments,
)
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.pair import resolve_pair_groups
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import Segment, Segmenter, SegmenterConfig
from sonarloc.fit.select import KAPPA_WALL_US
from tests.conftest import MAPS


def _ring_drive(duration_s=30.0, seed=2):
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.simulate import simulate_scan

    return simulate_scan(load_map(MAPS / "room.geojson"), rig_by_name("ring16"),
                         frame="odom", duration_s=duration_s, seed=seed).readings


def test_staged_cuts_split_as_fitting_every_cut_does():
    # a moving ring's drive on odometry poses: a cut whose shorter part does not fit
    # alone has its other part never fitted, and the cuts whose parts pass get the
    # odometry term added to those fits
    # (whole passes, no travel cap: long UNRESOLVED segments to cut)
    scan = _ring_drive()
    cfg = FitConfig()
    segs = list(Segmenter(SegmenterConfig(max_travel_m=0.0)).feed(scan))
    groups = resolve_pair_groups(segs, fit_segments(segs, cfg), cfg)
    todo = [k for k, g in enumerate(groups)
            if len(g) == 1 and g[0].status is FitStatus.UNRESOLVED]
    got = _split_groups([segs[k] for k in todo], [groups[k][0] for k in todo], cfg)
    n_split = 0
    for k, parts in zip(todo, got, strict=True):
        want = _plain_split(segs[k], groups[k][0], cfg)
        if want is None:
            assert parts == [groups[k][0]]
            continue
        n_split += 1
        assert len(parts) == 2
        for lm, ref in zip(parts, want, strict=True):
            assert (lm.kind, lm.status, lm.n_readings, lm.ref_t_s, lm.tier) == (
                ref.kind, ref.status, ref.n_readings, ref.ref_t_s, ref.tier)
            # the same fit, in another batch (its chunks converge a little differently:
            # up to 0.03 SD here)
            sd = np.sqrt(np.diag(ref.cov))
            assert np.all(np.abs(lm.params - ref.params) < 0.1 * sd)
            # (and the odometry term, the derivative at that fit)
            assert lm.extra.get("odom_bearing_sd_deg", 0.0) == pytest.approx(
                ref.extra.get("odom_bearing_sd_deg", 0.0), rel=0.1)
    # (6 before the odometry's random walk entered the status test, which leaves fewer
    # segments UNRESOLVED to cut)
    assert n_split >= 3


def _plain_split(seg: Segment, whole: Landmark, cfg: FitConfig
                 ) -> tuple[Landmark, Landmark] | None:
    """The split that fitting both parts of every cut (with the odometry term) gives,
    None if none: the plain search the staged one must agree with."""
    r = seg.readings
    echo = np.flatnonzero(np.isfinite(r.tof_us))
    n = echo.size
    if n < 2 * cfg.min_echoes:
        return None
    even = np.linspace(cfg.min_echoes, n - cfg.min_echoes, 8).astype(int)
    order = np.argsort(-np.abs(np.diff(r.tof_us[echo]))) + 1
    jumps = order[(order >= cfg.min_echoes) & (order <= n - cfg.min_echoes)][:4]
    parts = []
    for c in np.unique(np.concatenate([even, jumps])).tolist():
        pos = int(echo[c])
        parts += [Segment(r.select(slice(0, pos)), seg.seg_id, seg.closed_by,
                          (seg.occluded[0], False)),
                  Segment(r.select(slice(pos, None)), seg.seg_id, seg.closed_by,
                          (False, seg.occluded[1]))]
    fits = fit_segments(parts, cfg)
    weak = whole.kind == "line" and whole.kappa_us > 3.0 * KAPPA_WALL_US
    best: tuple[float, Landmark, Landmark] | None = None
    for a, b in zip(fits[0::2], fits[1::2], strict=True):
        if _fits_alone(a, weak) and _fits_alone(b, weak):
            total = float(a.extra["cost"]) + float(b.extra["cost"])
            if best is None or total < best[0]:
                best = (total, a, b)
    if best is None or float(whole.extra["cost"]) - best[0] <= 3.0 * math.log(
            best[1].n_readings + best[2].n_readings):
        return None
    return best[1], best[2]


def _part(kind: str, kappa: float, chi2: float = 10.0, n: int = 12,
          status: FitStatus = FitStatus.OK) -> Landmark:
    return Landmark(kind, np.array([1.0, 0.5, kappa]), np.eye(3) * 1e-4, 1.2, 0.4, n,
                    3.0, (0.0, 0.0, 0.0), status, extra={"chi2": chi2})


def test_a_part_must_fit_alone_and_a_weak_walls_points_be_strong():
    assert _fit_p(_part("point", 0.67, chi2=30.0)) < 0.01 < _fit_p(_part("point", 0.67))
    assert _fits_alone(_part("point", 0.67), weak_wall=False)
    assert not _fits_alone(_part("point", 0.67, chi2=30.0), weak_wall=False)
    assert not _fits_alone(_part("point", 0.67, status=FitStatus.FLAT), weak_wall=False)
    # a segment fitted as a wall too weak for one: a weak point part is that wall seen
    # from part of the path; a strong one (a corner, a pole) is what the test suspects
    weak = 3.5 * KAPPA_WALL_US
    assert _fits_alone(_part("point", weak), weak_wall=False)
    assert not _fits_alone(_part("point", weak), weak_wall=True)
    assert _fits_alone(_part("point", 0.15), weak_wall=True)
    assert _fits_alone(_part("line", 0.15), weak_wall=True)


def test_cut_parts_take_the_callers_odometry_sd():
    # fit_scan's odometry SD reaches the parts of cut segments, as it does the whole ones
    scan = _ring_drive(20.0, seed=4)

    def parts(sd):
        lms = fit_scan(scan, odometry_sd_deg_per_m=sd).landmarks
        return {(lm.ref_t_s, lm.n_readings): lm for lm in lms if "split_of" in lm.extra}

    none, default, double = parts(0.0), parts(None), parts(2.0)
    assert default and all("odom_bearing_sd_deg" not in lm.extra for lm in none.values())
    both = default.keys() & double.keys()
    assert len(both) >= len(default) // 2
    # (the SD also moves which whole segments pass the status test, so the cut stage's
    # batches differ and the parts' fits converge a little differently: ~1e-5)
    for k in both:
        assert float(double[k].extra["odom_bearing_sd_deg"]) == pytest.approx(
            2.0 * float(default[k].extra["odom_bearing_sd_deg"]), rel=1e-3)


def test_landmarks_of_some_fits_are_those_of_all():
    # the cut stage adds the odometry term to the parts it ranks, out of the batch that
    # fitted them: the landmarks of a subset, with or without the term and asked for in
    # any order and again, are those of the whole batch (and the whole batch's, asked
    # for last, are fit_segments')
    cfg = FitConfig()
    segs = list(Segmenter().feed(_ring_drive(20.0, seed=4)))
    fitted = _select_segments(segs, cfg)
    some = list(range(len(segs) - 1, -1, -3))
    plain = fitted.landmarks(cfg, 0.0, some)
    term = fitted.landmarks(cfg, None, some)
    again = fitted.landmarks(cfg, 0.0, some)
    whole = fitted.landmarks(cfg, None)
    ref, ref0 = fit_segments(segs, cfg), fit_segments(segs, cfg, 0.0)
    assert [lm.status for lm in whole] == [lm.status for lm in ref]
    assert any("odom_bearing_sd_deg" in lm.extra for lm in term)
    for k, a, b, c in zip(some, plain, term, again, strict=True):
        for got, want in ((a, ref0[k]), (c, ref0[k]), (b, ref[k]), (whole[k], ref[k])):
            assert (got.kind, got.status, got.reason, got.n_readings) == (
                want.kind, want.status, want.reason, want.n_readings)
            np.testing.assert_array_equal(got.params, want.params)
            # (the term's derivative is a float32 difference: batched with other
            # segments its last bits move, ~1e-8 relative)
            np.testing.assert_allclose(got.cov, want.cov, rtol=1e-6, atol=0.0)
            assert got.extra.get("odom_bearing_sd_deg", 0.0) == pytest.approx(
                want.extra.get("odom_bearing_sd_deg", 0.0), rel=1e-6)
