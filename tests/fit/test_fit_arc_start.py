"""The closed-form arc start of ``FitConfig(start="arc")`` (``FitConfig.fast()``)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarloc.fit import model as M
from sonarloc.fit.lsq import FitConfig, _arc_start, _grid_start, fit_batch, pack_segments
from sonarloc.fit.synth import Reflector, pan_scan


def _pans(rng, n, bearing=(-10.0, 10.0), lo=-40.0, hi=40.0, steps=(0.3, 1.0)):
    """Pans of poles and rods at 1-3 m (the benchmark's kind); (batch, truth (n, 3))."""
    segs, truth = [], []
    for _ in range(n):
        r, b = rng.uniform(1.0, 3.0), rng.uniform(*bearing)
        k, step = rng.choice([0.67, 2.68]), rng.choice(steps)
        sc = pan_scan([Reflector.polar(r, b, k)], rng, lo, hi, step)
        segs.append((sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, sc.tof_us))
        truth.append((r, np.deg2rad(b), k))
    return segs, np.array(truth)


def _starts(batch, cfg=None):
    cfg = cfg or FitConfig.fast()
    y = np.where(batch.valid, batch.tof_us - 0.5 * cfg.module.count_period_us, 0.0)
    return (_arc_start("point", "gauss", batch, y, batch.valid, cfg),
            _grid_start("point", "gauss", batch, y, batch.valid, cfg))


def test_arc_start_is_near_the_truth_on_whole_arcs(rng):
    segs, truth = _pans(rng, 200)
    (start, _, second, arc, whole), grid = _starts(pack_segments(segs))
    assert whole.all() and not second.any()
    err = start - truth
    err_b = np.rad2deg(M.wrap_angle(err[:, 1]))
    # the edges' midpoint: within about half a pan step plus the edges' randomness
    assert np.sqrt(np.mean(err_b ** 2)) < 0.6 and np.abs(err_b).max() < 2.5
    assert np.abs(err[:, 0]).max() < 1.5e-3
    # kappa from the arc's half-width (detection limit over the beam factor at the edge)
    log_k = np.log(start[:, 2] / truth[:, 2])
    assert np.sqrt(np.mean(log_k ** 2)) < 0.3 and np.abs(log_k).max() < 1.0
    # about 3x closer in bearing than fast()'s 12 deg grid bracket
    grid_b = np.rad2deg(M.wrap_angle(grid[0][:, 1] - truth[:, 1]))
    assert np.sqrt(np.mean(err_b ** 2)) < 0.5 * np.sqrt(np.mean(grid_b ** 2))
    # the arc reported is the echoes' (as the grid's)
    np.testing.assert_allclose(arc, grid[3])


def test_arc_start_falls_back_to_the_grid(rng):
    whole_segs, _ = _pans(rng, 3)
    partial, _ = _pans(rng, 3, bearing=(36.0, 44.0))             # cut by the scan's edge
    coarse, _ = _pans(rng, 2, steps=(6.0,))                       # edges 6 deg apart
    sc = pan_scan([Reflector.polar(1.5, 0.0, 0.67)], rng, -40.0, 40.0, 0.5)
    tof = sc.tof_us.copy()
    tof[~np.isfinite(tof)] = np.where(np.arange((~np.isfinite(tof)).sum()) % 2, np.nan,
                                      9000.0)                     # echoes all over the pan
    noisy = [(sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, tof)]
    segs = whole_segs + partial + coarse + noisy
    batch = pack_segments(segs)
    (start, start2, second, arc, whole), grid = _starts(batch)
    assert whole.tolist() == [True] * 3 + [False] * 6
    # the others: the grid bracket's starts, exactly as fitted alone
    idx = np.flatnonzero(~whole)
    _, alone = _starts(pack_segments([segs[i] for i in idx]))
    for got, ref in zip((start, start2, second, arc), alone, strict=True):
        np.testing.assert_array_equal(got[idx], ref)
    # moving segments: the grid for all
    moved = [(t, x + 0.01 * np.arange(t.size), y, yaw, tof)
             for t, x, y, yaw, tof in whole_segs]
    (start, _, _, _, whole), grid = _starts(pack_segments(moved))
    assert not whole.any()
    np.testing.assert_array_equal(start, grid[0])


def test_fast_from_the_arc_reaches_the_default(rng):
    # one guarded step from the arc start: the converged grid-started fit's answers to
    # a fraction of an SD, closer than the old grid-started fast() (two steps)
    segs, truth = _pans(rng, 150)
    batch = pack_segments(segs)
    ref = fit_batch(batch, "point", "gauss", FitConfig(start="grid", float32=False))
    sd = np.sqrt(np.einsum("bkk->bk", ref.cov))
    f = fit_batch(batch, "point", "gauss", FitConfig.fast())
    old = fit_batch(batch, "point", "gauss", FitConfig.fast(start="grid", arc_iterations=None))
    z = np.abs(f.local - ref.local) / sd
    z_old = np.abs(old.local - ref.local) / sd
    rms, rms_old = np.sqrt(np.mean(z ** 2, 0)), np.sqrt(np.mean(z_old ** 2, 0))
    assert np.all(rms < 0.3) and np.all(rms < 0.5 * rms_old), (rms, rms_old)
    assert z.max() < 1.5
    # start="arc" with the grid's step count: a second step closes in further
    f2 = fit_batch(batch, "point", "gauss", FitConfig.fast(arc_iterations=None))
    rms2 = np.sqrt(np.mean(((f2.local - ref.local) / sd) ** 2, 0))
    assert np.all(rms2 < rms), (rms2, rms)
    # the default (since session 5) starts from the arc and takes all its steps: the
    # grid-started fit's answers to a few hundredths of an SD
    assert FitConfig().start == "arc" and FitConfig().arc_iterations is None
    d = fit_batch(batch, "point", "gauss")
    z_d = np.abs(d.local - ref.local) / sd
    assert np.all(np.sqrt(np.mean(z_d ** 2, 0)) < 0.05) and z_d.max() < 0.5, z_d.max(0)


def test_start_settings_are_checked():
    with pytest.raises(ValueError, match="start"):
        FitConfig(start="edges")
    with pytest.raises(ValueError, match="arc_iterations"):
        FitConfig(arc_iterations=0)
