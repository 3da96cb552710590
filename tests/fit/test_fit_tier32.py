"""Float32 passes of the piston and waveform tiers, and giving up hopeless tier fits."""

from __future__ import annotations

import numpy as np
import pytest

from sonarloc.fit import model as M
from sonarloc.fit import select as S
from sonarloc.fit.lsq import FitConfig, _evaluate32, _evaluate_core, _take, fit_batch, pack_segments
from sonarloc.fit.synth import Reflector, pan_scan
from sonarloc.physics import ModuleParams


def _pans(rng, n, tier):
    """Pans of the simulator's ``tier`` over one reflector: planes, poles and rods at
    1-3 m, 0.3 or 1 deg steps; (batch, truth (n, 3))."""
    segs, truth = [], []
    for _ in range(n):
        r, b = rng.uniform(1.0, 3.0), rng.uniform(-10.0, 10.0)
        k, step = rng.choice([0.15, 0.67, 2.68]), rng.choice([0.3, 1.0])
        sc = pan_scan([Reflector.polar(r, b, k)], rng, -40.0, 40.0, step, tier=tier)
        segs.append((sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, sc.tof_us))
        truth.append((r, np.deg2rad(b), k))
    return pack_segments(segs), np.array(truth)


def test_piston_table_in_float32_matches_float64():
    mod = ModuleParams()
    table = M._piston_table(mod.diameter_m, mod.carrier_hz, mod.c_mps)
    th = np.linspace(-np.pi, np.pi, 20001)          # beyond the table at |th| > pi/2
    g, dlng, lng = table.lookup_log(th, True, True)
    lng32, dlng32, beyond = table.lookup_log32(th.astype(np.float32), True, 2.0)
    assert lng32.dtype == np.float32 and beyond
    # ln g to float32 rounding of the position in the interval; the slope (per unit
    # of ``ddiv``) likewise (steep next to the nulls: relative there)
    np.testing.assert_allclose(lng32, lng, rtol=0, atol=2e-4 * max(1.0, np.abs(lng).max()))
    np.testing.assert_allclose(2.0 * dlng32, dlng, rtol=5e-3, atol=1e-3)
    main = np.abs(th) < np.deg2rad(30.0)           # main lobe and first side lobes
    np.testing.assert_allclose(lng32[main], lng[main], rtol=0, atol=5e-4)
    np.testing.assert_allclose(2.0 * dlng32[main], dlng[main], rtol=1e-3, atol=1e-3)
    # float64 angles: placed in float64, ln g within float32 rounding everywhere
    lng32, dlng32, _ = table.lookup_log32(th, True)
    np.testing.assert_allclose(lng32, lng, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(dlng32, dlng, rtol=1e-5, atol=1e-3)
    assert np.all(lng32[np.abs(th) > 0.5 * np.pi + 1e-3] == np.float32(np.log(M._G_MAX)))


def test_delay_table_in_float32_matches_float64():
    mod = ModuleParams()
    tab = M.waveform_delay_table(mod)
    u = np.geomspace(1e-4, 200.0, 5001)            # below, on and above the table
    m, dm_du, var = tab.lookup(u)
    x32 = np.log(u).astype(np.float32)
    m32, dm_dx32, var32 = tab.lookup_log32(x32)
    np.testing.assert_allclose(m32, m, rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(var32, var, rtol=2e-5, atol=1e-6 * var.max())
    # d mean / d ln u = u d mean / d u
    np.testing.assert_allclose(dm_dx32, dm_du * u, rtol=1e-4, atol=1e-5 * np.abs(dm_du * u).max())


@pytest.mark.parametrize("tier", ["piston", "waveform"])
def test_float32_tier_passes_equal_float64_ones(rng, tier):
    batch, truth = _pans(rng, 90, "auto" if tier == "waveform" else tier)
    cfg64 = FitConfig(float32=False)
    cfg32 = FitConfig()
    y = np.where(batch.valid, batch.tof_us - 0.5 * cfg64.module.count_period_us, 0.0)
    # one model pass at the same parameters: near the optimum everything; off it the
    # objective (where the model puts echoes deep beyond the detection limit, z ~ 50
    # next to a piston null, the tail's curvature m0 (m0 - z) cancels in float32, as
    # in the gauss tier's float32 pass; steps from there are damped anyway)
    off = truth + np.array([2e-3, np.deg2rad(3.0), 0.3])
    for p in (truth, off):
        ref = _evaluate_core("point", tier, p, batch, y, batch.valid, None, cfg64)
        got = _evaluate_core("point", tier, p, batch, y, batch.valid, None, cfg32)
        also = _evaluate32("point", p, batch, y, batch.valid, None, cfg32, True, None, tier)
        np.testing.assert_array_equal(got[1], also[1])       # the float32 path it is
        assert got[4].dtype == np.float32
        F_o, F, grad, H, e, s2 = ref
        np.testing.assert_allclose(got[1], F, rtol=3e-3, atol=2e-3)
        np.testing.assert_allclose(got[0], F_o, rtol=3e-3, atol=2e-3)
        if p is off:
            continue
        np.testing.assert_allclose(got[1], F, rtol=2e-5, atol=2e-3)
        scale = np.sqrt(np.einsum("bkk->bk", H))               # gradient in SD units
        np.testing.assert_allclose(got[2] / scale, grad / scale, rtol=1e-3, atol=1e-4)
        norm = scale[:, :, None] * scale[:, None, :]           # correlation units
        np.testing.assert_allclose(got[3] / norm, H / norm, rtol=0, atol=5e-4)
        np.testing.assert_allclose(got[4], e, rtol=0, atol=1e-4)         # in SDs
        np.testing.assert_allclose(got[5], s2, rtol=2e-5)
    # converged fits: the same answers to a small fraction of an SD
    a = fit_batch(batch, "point", tier, cfg64)
    b = fit_batch(batch, "point", tier, cfg32)
    sd = np.sqrt(np.einsum("bkk->bk", a.cov))
    d = np.abs(b.local - a.local) / sd
    assert np.median(d) < 0.002 and np.all(d < 0.05)
    np.testing.assert_allclose(b.cost, a.cost, atol=2e-2)
    # and refined from the Gaussian fit (how model selection uses them)
    g = fit_batch(batch, "point", "gauss", cfg32)
    a = fit_batch(batch, "point", tier, cfg64, start=g)
    b = fit_batch(batch, "point", tier, cfg32, start=g)
    d = np.abs(b.local - a.local) / np.sqrt(np.einsum("bkk->bk", a.cov))
    assert np.median(d) < 0.002 and np.all(d < 0.05)


def test_given_up_refinements_are_frozen_not_converged(rng):
    batch, _ = _pans(rng, 40, "auto")
    cfg = FitConfig()
    g = fit_batch(batch, "point", "gauss", cfg)
    full = fit_batch(batch, "point", "waveform", cfg, start=g)
    # bars the fits cannot reach for half of the segments (far below their optimum)
    stop = np.where(np.arange(batch.size) % 2 == 0, full.robust_cost - 50.0, np.inf)
    part = fit_batch(batch, "point", "waveform", cfg, start=g, stop_above=stop)
    hopeless = np.isfinite(stop)
    assert not part.converged[hopeless].any()
    # given up where they stood: no lower than the converged fit
    assert np.all(part.robust_cost[hopeless] >= full.robust_cost[hopeless] - 1e-6)
    assert np.any(part.robust_cost[hopeless] > full.robust_cost[hopeless] + 1e-3)
    # the others ran to the end: the fits without the stop (to the tolerance)
    sd = np.sqrt(np.einsum("bkk->bk", full.cov))
    assert np.all(np.abs(part.local - full.local)[~hopeless] < 0.05 * sd[~hopeless])
    np.testing.assert_array_equal(part.converged[~hopeless], full.converged[~hopeless])
    # a bar of +inf stops nothing
    same = fit_batch(batch, "point", "waveform", cfg, start=g,
                     stop_above=np.full(batch.size, np.inf))
    np.testing.assert_array_equal(same.local, full.local)


def test_giving_up_hopeless_tiers_keeps_every_choice(monkeypatch):
    # pans of every tier's data: the tiers, kinds, statuses and chosen fits are those
    # of running every alternative to the end; only hopeless alternatives' reported
    # gains may differ (and by less than HOPELESS_DCOST takes off them)
    from sonarloc.fit.landmarks import fit_segments

    rng = np.random.default_rng(31)
    segs = []
    for tier in ("auto", "gauss", "piston"):
        for k in (0.15, 0.67, 2.68):
            for r in (1.5, 3.0):
                for _ in range(4):
                    sc = pan_scan([Reflector.polar(r, rng.uniform(-5, 5), k)], rng, -40.0,
                                  40.0, 0.3, tier=tier)
                    segs.append((sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, sc.tof_us))
    now = fit_segments(segs)
    hopeless = S.HOPELESS_DCOST
    monkeypatch.setattr(S, "HOPELESS_DCOST", np.inf)
    before = fit_segments(segs)
    n_tiers = set()
    moved = 0
    for a, b in zip(now, before, strict=True):
        assert (a.kind, a.tier, a.status) == (b.kind, b.tier, b.status)
        sd = np.sqrt(np.diag(b.cov))
        if np.any(np.abs(a.params - b.params) > 0.05 * sd):
            # the same fit, stopped elsewhere in a flat valley (the order of the solves
            # of a batch's steps depends on which segments are still active)
            moved += 1
            assert np.all(np.abs(a.params - b.params) < sd)
            assert abs(float(a.extra["cost"]) - float(b.extra["cost"])) < 1.0
        n_tiers.add(a.tier)
        for t in ("waveform", "piston"):
            da, db = a.extra.get(f"dcost_{t}"), b.extra.get(f"dcost_{t}")
            assert (da is None) == (db is None)
            if da is not None and abs(float(da) - float(db)) > 1.0:
                assert float(db) < -hopeless + 250.0     # a hopeless alternative
    assert n_tiers >= {"gauss", "waveform"} and moved <= 0.05 * len(now)


def test_tier_model_equals_the_tests_own_passes(rng):
    # the predictions, Jacobian and event probabilities of the one shared pass are the
    # numbers the score and misfit tests compute on their own
    batch, _ = _pans(rng, 30, "auto")
    cfg = FitConfig()
    sel = S.Selection.from_fit(fit_batch(batch, "point", "gauss", cfg))
    idx = np.arange(1, batch.size, 2)
    pred, gm = S._tier_model(batch, sel, idx, "point", ("gauss", "waveform", "piston"), cfg,
                             jacobian=True)
    assert gm is not None
    for tier in ("gauss", "waveform", "piston"):
        d, p = S._tier_predictions(batch, sel, idx, "point", (tier,), cfg)[tier]
        np.testing.assert_array_equal(pred[tier][0], d)
        np.testing.assert_array_equal(pred[tier][1], p)
    r = np.arange(idx.size)
    for tier_b in ("waveform", "piston"):
        z_own = S.score_z(batch, sel, idx, "point", "gauss", tier_b, cfg)
        z_shared = S.score_z(batch, sel, idx, "point", "gauss", tier_b, cfg,
                             pred[tier_b][0], gm.rows(r))
        np.testing.assert_allclose(z_shared, z_own, rtol=1e-9, atol=1e-9)
    own = S.misfit(batch, sel, idx, "point", cfg, surprise=4.0)
    shared = S.misfit(batch, sel, idx, "point", cfg, surprise=4.0, model=(gm.log_p, gm.zn))
    np.testing.assert_array_equal(shared, own)
    assert own.any() and not own.all()          # the surprise bar splits these


def test_landmark_from_fields_is_the_dataclass_construction():
    from dataclasses import fields

    from sonarloc.fit.result import FitStatus, Landmark

    kw = dict(kind="line", params=np.array([1.0, 0.2, 0.15]), cov=np.eye(3), range_m=1.0,
              bearing_rad=0.2, n_readings=7, ref_t_s=3.0, ref_pose=(0.0, 1.0, 0.5),
              status=FitStatus.FLAT, reason="why", tier="waveform", rms_us=1.1,
              sensors=(2, 3), extra={"a": 1})
    assert [f.name for f in fields(Landmark)] == list(kw)
    a, b = Landmark(**kw), Landmark._from_fields(dict(kw))
    for f in fields(Landmark):
        assert getattr(a, f.name) is getattr(b, f.name)
    with pytest.raises(AttributeError):
        b.reason = "frozen"                     # type: ignore[misc]
    assert b.ok is False and b.kappa_us == 0.15


def _assert_pass_near(got, ref, f_rtol, sd_atol, e_atol):
    """A float32 pass's (F_other, F, grad, H, e, s2) near the float64 one's: objectives
    to ``f_rtol``, gradient and Fisher matrix to ``sd_atol`` in SD and correlation units
    (of the float64 H), standardised residuals to ``e_atol``, variances to 2e-5."""
    names = ("F_other", "F", "grad", "H", "e", "s2")
    g, r = dict(zip(names, got, strict=True)), dict(zip(names, ref, strict=True))
    for name in ("F_other", "F"):
        np.testing.assert_allclose(g[name], r[name], rtol=f_rtol, atol=2e-3, err_msg=name)
    sd = np.sqrt(np.einsum("bkk->bk", r["H"]))
    np.testing.assert_allclose(g["grad"] / sd, r["grad"] / sd, rtol=1e-3, atol=sd_atol)
    corr = sd[:, :, None] * sd[:, None, :]
    np.testing.assert_allclose(g["H"] / corr, r["H"] / corr, rtol=0, atol=sd_atol)
    np.testing.assert_allclose(g["e"], r["e"], rtol=1e-5, atol=e_atol)
    np.testing.assert_allclose(g["s2"], r["s2"], rtol=2e-5)


def _drive_bys(rng, n, kind, tier):
    """Segments of a sensor driving past one reflector (a pole or a wall, 0.8-2.5 m off
    the path, 0.6-1.5 m driven, the axis sweeping as a ring's transducers do); (batch,
    its float64 fits)."""
    from sonarloc.fit.synth import simulate_readings

    segs = []
    for _ in range(n):
        d, k = rng.uniform(0.8, 2.5), rng.choice([0.15, 0.67, 2.68])
        length, m = rng.uniform(0.6, 1.5), int(rng.integers(30, 90))
        x = np.linspace(-length, 0.0, m)
        yaw = np.deg2rad(np.linspace(rng.uniform(40, 70), rng.uniform(110, 140), m))
        refl = (Reflector.point(rng.uniform(-0.6, 0.2), d, k) if kind == "point"
                else Reflector.line(d, np.pi / 2, 0.15))
        sc = simulate_readings(np.arange(m) * 0.05, x, 0.0, yaw, [refl], rng,
                               tier="auto" if tier == "waveform" else tier)
        segs.append((sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, sc.tof_us))
    batch = pack_segments(segs)
    g = fit_batch(batch, kind, tier, FitConfig(float32=False))
    return batch, g


@pytest.mark.parametrize("kind", ["point", "line"])
@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform"])
def test_float32_moving_passes_equal_float64_ones(rng, kind, tier):
    # a moving batch's float32 pass (ranges formed in float64, the rest in float32)
    # against the float64 pass: at the fits and off them, and far off them (a grid
    # start's first steps: kappa and range off by orders of magnitude, echoes put far
    # beyond the detection limit, where the Mills ratio's excess must hold)
    batch, g = _drive_bys(rng, 60, kind, tier)
    keep = np.flatnonzero(g.n_used >= 8)[:40]           # (weak ones go undetected)
    assert batch.moving and keep.size == 40
    batch, g = _take(batch, keep), g.take(keep)
    cfg64, cfg32 = FitConfig(float32=False), FitConfig()
    y = np.where(batch.valid, batch.tof_us - 0.5 * cfg64.module.count_period_us, 0.0)
    use = g.used
    off = g.local + np.array([0.02, np.deg2rad(4.0), 0.0]) * rng.choice([-1, 1], (40, 3))
    far = g.local * np.array([0.5, 1.0, 0.0]) + np.array([0.0, 0.3, 0.002])
    for p in (g.local, off, far):
        ref = _evaluate_core(kind, tier, p, batch, y, use, None, cfg64)
        got = _evaluate_core(kind, tier, p, batch, y, use, None, cfg32)
        assert got[4].dtype == np.float32
        _assert_pass_near(got, ref, f_rtol=2e-5, sd_atol=2e-3, e_atol=1e-4)
    # the fits, converged tightly (the default's tolerance leaves each within ~0.03 SD
    # of its optimum, where flat valleys let two runs end apart by more): the same
    # answers to a small fraction of an SD
    tight = {"tolerance": 1e-7, "iterations": 60}
    a = fit_batch(batch, kind, tier, FitConfig(float32=False, **tight))
    b = fit_batch(batch, kind, tier, FitConfig(**tight))
    sd = np.sqrt(np.einsum("bkk->bk", a.cov))
    d = np.abs(b.local - a.local) / sd
    both = a.converged & b.converged
    assert both.sum() >= 30
    assert np.median(d[both]) < 0.002 and np.all(d[both] < 0.02)
