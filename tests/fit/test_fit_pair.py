"""Two overlapping reflectors: the min-of-two-U's model (sonarloc.fit.pair)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.fit import pair as P
from sonarloc.fit.landmarks import fit_scan
from sonarloc.fit.lsq import FitConfig, fit_batch, pack_segments
from sonarloc.fit.synth import Reflector, pan_scan, simulate_readings
from sonarloc.io.scancsv import ScanReadings


def _batch(scan: ScanReadings):
    return pack_segments([(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us)])


def _x(local: np.ndarray) -> np.ndarray:
    return np.array([local[0] / P._SCALE[0], local[1] / P._SCALE[1], math.log(local[2])])


def test_one_component_is_the_fitters_likelihood(rng):
    # with one component the pair model's cost is the single fit's -2 log-likelihood
    # (up to the spike floor, negligible for readings the model explains); the floor
    # only ever lowers it (here: edge echoes the piston beam calls improbable)
    scan = pan_scan([Reflector.polar(1.5, 5.0, 0.67)], rng, -25, 35, 0.3)
    batch = _batch(scan)
    for tier in ("gauss", "piston", "waveform"):
        fit = fit_batch(batch, "point", tier)
        seg = P._Segment(batch, 0, FitConfig(), tier)
        c = float(np.asarray(seg.cost(P._unscale(_x(fit.local[0])[None, :])))[0])
        if tier == "gauss":
            assert c == pytest.approx(float(fit.cost[0]), abs=0.1)
        else:
            assert c <= float(fit.cost[0]) + 1e-6


def test_pair_cost_is_symmetric_and_reduces_to_one_when_the_other_is_silent(rng):
    refl = [Reflector.polar(1.5, -8.0, 0.67), Reflector.polar(1.5005, 8.0, 0.67)]
    batch = _batch(pan_scan(refl, rng, -40, 40, 0.3))
    seg = P._Segment(batch, 0, FitConfig(), "gauss")
    a = np.array([1500.0, -8.0, math.log(0.67)])
    b = np.array([1500.5, 8.0, math.log(0.67)])
    ab = np.asarray(seg.cost(P._unscale(np.concatenate([a, b])[None, :])))[0]
    ba = np.asarray(seg.cost(P._unscale(np.concatenate([b, a])[None, :])))[0]
    assert ab == pytest.approx(ba, rel=1e-12)
    silent = b.copy()
    silent[2] = math.log(1e4)      # never detected: the pair is the single model
    c2 = np.asarray(seg.cost(P._unscale(np.concatenate([a, silent])[None, :])))[0]
    c1 = np.asarray(seg.cost(P._unscale(a[None, :])))[0]
    pen = P._kappa_penalty(np.array([1e4]), FitConfig())[0][0]
    assert c2 - pen == pytest.approx(c1, abs=1e-6)


def test_two_poles_20_deg_apart_equal_range_are_resolved(rng):
    truth = ((1.5, -10.0), (1.5005, 10.0))
    resolved = 0
    for _ in range(3):
        lms = fit_scan(pan_scan([Reflector.polar(r, b, 0.67) for r, b in truth], rng,
                                -40, 40, 0.3)).landmarks
        assert lms
        for lm in lms:
            if lm.ok:   # every trusted landmark sits on a reflector (4 SDs)
                sd = float(lm.extra["bearing_sd_deg"])
                assert any(abs(math.degrees(lm.bearing_rad) - b) < 4 * sd + 0.1
                           and abs(lm.range_m - r) < 2e-3 for r, b in truth), lm
            else:
                assert lm.reason
        if len(lms) == 2 and all("pair_of" in lm.extra for lm in lms):
            resolved += 1
            assert lms[0].bearing_rad < lms[1].bearing_rad
            assert float(lms[0].extra["pair_gain"]) > P.MIN_GAIN
    assert resolved >= 2


@pytest.mark.parametrize("kappa,tier", [(0.67, "gauss"), (0.15, "auto"), (2.68, "auto")])
def test_single_reflectors_are_not_split(rng, kappa, tier):
    for _ in range(3):
        b = rng.uniform(-10, 10)
        lms = fit_scan(pan_scan([Reflector.polar(1.5, b, kappa)], rng, -40, 40, 0.3,
                                tier=tier)).landmarks
        assert not any("pair_of" in lm.extra for lm in lms)


def test_spikes_do_not_buy_a_second_reflector(rng):
    for _ in range(3):
        scan = pan_scan([Reflector.polar(1.5, rng.uniform(-5, 5), 0.67)], rng, -40, 40, 0.3)
        tof = scan.tof_us.copy()
        inside = np.flatnonzero(np.isfinite(tof))[::17]
        tof[inside] -= rng.uniform(20, 35, inside.size)
        lms = fit_scan(ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof,
                                    scan.sensor)).landmarks
        assert not any("pair_of" in lm.extra for lm in lms)


def test_a_rejected_pair_says_why(rng):
    # 12 deg apart at equal range: one segment; whatever the decision, it is recorded
    refl = [Reflector.polar(1.5, -6.0, 0.67), Reflector.polar(1.5, 6.0, 0.67)]
    lms = fit_scan(pan_scan(refl, rng, -40, 40, 0.3)).landmarks
    assert any("pair_basis" in lm.extra for lm in lms)
    for lm in lms:
        if not lm.ok:
            assert lm.reason


def test_lockstep_bfgs_matches_scipy_per_start_and_holds_fixed_variables(rng):
    # the batched optimiser from several starts reaches (about) the optima scipy's BFGS
    # finds from each start alone; a held variable keeps its start value
    from scipy.optimize import minimize
    refl = [Reflector.polar(1.5, -8.0, 0.67), Reflector.polar(1.5005, 8.0, 0.67)]
    batch = _batch(pan_scan(refl, rng, -40, 40, 0.3))
    seg = P._Segment(batch, 0, FitConfig(), "gauss")
    starts = np.array([[1500.0, -6.0, math.log(0.5), 1500.0, 6.0, math.log(0.9)],
                       [1499.0, -10.0, math.log(0.9), 1501.0, 9.0, math.log(0.5)],
                       [1500.2, -1.0, math.log(0.3), 1500.2, 1.0, math.log(0.3)]])
    xs, cs = P._minimise_batch(seg, starts)
    def cost(v: np.ndarray) -> float:
        return float(np.asarray(seg.cost(P._unscale(v[None, :])))[0])

    for x0, x, c in zip(starts, xs, cs, strict=True):
        ref = minimize(cost, x0, method="BFGS", options={"gtol": 1e-3, "maxiter": 400})
        assert c <= ref.fun + 0.5
        assert c == pytest.approx(cost(x))   # the returned cost is that of the optimum
    assert cs.min() < float(np.asarray(seg.cost(P._unscale(starts))).min()) - 10.0
    xf, _ = P._minimise_batch(seg, starts[:2], fixed=[2, None])
    assert xf[0, 2] == starts[0, 2] and xf[1, 2] != starts[1, 2]


def test_padded_segments_cost_each_row_on_its_own_segment(rng):
    # rows of a _Segments evaluate their own segment (only its readings), and
    # cost_grad's cost is cost()'s exactly
    cfg = FitConfig()
    scans = [pan_scan([Reflector.polar(r, b, k)], rng, -30, 30, step)
             for r, b, k, step in ((1.2, 3.0, 0.67, 0.3), (2.5, -4.0, 2.68, 1.0),
                                   (1.8, 0.0, 0.15, 2.0))]
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    singles = [P._Segment(batch, b, cfg, "gauss") for b in range(3)]
    assert len({s.y.size for s in singles}) == 3 and len({s.npx.size for s in singles}) > 1
    group = P._Segments(singles)
    owner = np.array([0, 1, 2, 2, 0, 1])
    x = np.array([[1200.0 + d, 3.0 + d, math.log(0.67), 1200.0, 8.0 - d, math.log(1.0)]
                  for d in (-0.5, 0.0, 0.5)] * 2)
    x[owner == 1, 0::3] += 1300.0
    x[owner == 2, 0::3] += 600.0
    for comps in (P._unscale(x), P._unscale(x[:, :3])):
        got = group.cost(comps, owner)
        want = [float(singles[o].cost([c[j:j + 1] for c in comps])[0])
                for j, o in enumerate(owner.tolist())]
        np.testing.assert_allclose(got, want, rtol=1e-12)
    for ev, own in ((singles[1], None), (group, owner)):
        for xx in (x, x[:, :3]):
            c, _ = ev.cost_grad(xx, own)
            np.testing.assert_array_equal(c, ev.cost(P._unscale(xx), own))


def test_segments_of_several_tiers_evaluate_each_row_in_its_own_tier(rng):
    # a _Segments of several tiers (one search for all of them) gives each row the cost,
    # gradient and detail of its segment's own tier, whatever the rows' order: the same
    # per-reading terms as a _Segments of that tier alone (up to echo_terms' rounding)
    cfg = FitConfig()
    scans = [pan_scan([Reflector.polar(r, b, k)], rng, -30, 30, step)
             for r, b, k, step in ((1.2, 3.0, 0.67, 0.3), (2.5, -4.0, 2.68, 1.0),
                                   (1.8, 0.0, 0.15, 2.0), (1.5, 2.0, 0.67, 0.5))]
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    tiers = ["waveform", "gauss", "piston", "gauss"]
    segs = [P._Segment(batch, b, cfg, t) for b, t in enumerate(tiers)]
    mixed = P._Segments(segs)
    owner = np.array([0, 1, 2, 3, 2, 0, 1, 3, 3, 0])
    base = np.array([[1200.0, 3.0], [2500.0, -4.0], [1800.0, 0.0], [1500.0, 2.0]])
    x = np.array([[base[o, 0] + d, base[o, 1] + d, math.log(0.67), base[o, 0] - d,
                   base[o, 1] + 6.0, math.log(1.0)]
                  for o, d in zip(owner.tolist(), np.linspace(-0.8, 0.8, owner.size),
                                  strict=True)])
    for xx in (x, x[:, :3]):
        c, g = mixed.cost_grad(xx, owner)
        _, resp, resid = mixed.detail(P._unscale(xx), owner)
        for o, seg in enumerate(segs):
            j = np.flatnonzero(owner == o)
            c1, g1 = seg.cost_grad(xx[j])
            _, resp1, resid1 = seg.detail(P._unscale(xx[j]))
            np.testing.assert_allclose(c[j], c1, rtol=1e-12)
            np.testing.assert_allclose(g[j], g1, rtol=1e-9, atol=1e-9 * np.abs(g1).max())
            n = seg.y.size
            np.testing.assert_allclose(resp[j][:, :, :n], resp1, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(resid[j][:, :n], resid1, rtol=1e-9, atol=1e-12)
            assert not resp[j][:, :, n:].any()
        np.testing.assert_array_equal(c, mixed.cost(P._unscale(xx), owner))


def _fd_grad(ev: P._Segment, x: np.ndarray, own: np.ndarray | None, h: float = 1e-5
             ) -> np.ndarray:
    out = np.zeros_like(x)
    for i in range(x.shape[1]):
        e = np.zeros(x.shape[1])
        e[i] = h
        out[:, i] = (ev.cost(P._unscale(x + e), own) - ev.cost(P._unscale(x - e), own)) / (2 * h)
    return out


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform"])
def test_pair_cost_gradient_matches_central_differences(rng, tier):
    # the analytic gradient of the one- and two-component cost (pan, a moving
    # transducer, padded rows of several segments) against central differences
    cfg = FitConfig()
    pan = pan_scan([Reflector.polar(1.5, -8.0, 0.67), Reflector.polar(1.5005, 8.0, 0.67)],
                   rng, -40, 40, 0.3)
    n = 120
    yaw = np.full(n, math.pi / 2)                      # side-looking, driving by
    drive = simulate_readings(np.arange(n) * 0.05, np.linspace(-0.6, 0.6, n), np.zeros(n),
                              yaw, [Reflector.polar(1.2, 90.0, 0.67)], rng, tier="gauss")
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us)
                           for s in (pan, drive)])
    segs = [P._Segment(batch, b, cfg, tier) for b in range(2)]
    assert not segs[0].moving and segs[1].moving
    x_pan = np.array([[1500.0, -6.0, math.log(0.5), 1500.0, 6.0, math.log(0.9)],
                      [1499.0, -10.0, math.log(0.9), 1501.0, 9.0, math.log(0.5)],
                      [1500.2, -1.0, math.log(0.3), 1500.2, 1.0, math.log(0.3)],
                      [1500.5, -8.0, math.log(0.67), 1500.5, 8.0, math.log(0.05)]])
    rx, ry = batch.ref_xy[1]
    r0, b0 = 1e3 * math.hypot(rx, 1.2 - ry), math.degrees(math.atan2(1.2 - ry, -rx))
    x_drive = np.array([[r0, b0, math.log(0.67), r0 + 20.0, b0 - 10.0, math.log(2.0)],
                        [r0 - 30.0, b0 + 5.0, math.log(0.3), r0, b0 + 1.0, 0.0]])
    both = P._Segments([segs[0], P._Segment(batch, 0, cfg, tier)])
    for ev, x, own in ((segs[0], x_pan, None), (segs[1], x_drive, None),
                       (both, x_pan, np.array([0, 1, 1, 0]))):
        for xx in (x, x[:, :3]):
            c, g = ev.cost_grad(xx, own)
            assert np.all(c < 1e12)
            fd = _fd_grad(ev, xx, own)
            np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-4 * (1.0 + np.abs(fd).max()))


def test_candidates_searched_together_decide_as_one_at_a_time(rng):
    # resolve_pair_groups on many candidates at once (padded, in lockstep) gives each
    # the result of its search alone (up to rounding of the padded sums)
    from sonarloc.fit.landmarks import fit_segments
    from sonarloc.fit.segment import Segmenter
    segs = []
    for sep, dr in ((14.0, 0.0005), (9.0, 0.001), (20.0, 0.0), (6.0, 0.0)):
        refl = [Reflector.polar(1.5, -sep / 2, 0.67), Reflector.polar(1.5 + dr, sep / 2, 0.67)]
        segs += list(Segmenter().feed(pan_scan(refl, rng, -40, 40, 0.3)))
    cfg = FitConfig()
    together = P.resolve_pair_groups(segs, fit_segments(segs, cfg), cfg)
    lms = fit_segments(segs, cfg)
    assert sum(P.is_candidate(lm, cfg) for lm in lms) >= 3
    alone = [P.resolve_pair_groups([s], [lm], cfg)[0] for s, lm in zip(segs, lms, strict=True)]
    assert any(len(g) == 2 for g in together)
    for a, b in zip(together, alone, strict=True):
        assert [lm.status for lm in a] == [lm.status for lm in b]
        for la, lb in zip(a, b, strict=True):
            np.testing.assert_allclose(la.params, lb.params, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(la.cov, lb.cov, rtol=1e-6, atol=1e-15)
            assert la.extra.get("pair_basis", "")[:20] == lb.extra.get("pair_basis", "")[:20]


def test_screen_runs_two_starts_and_passed_candidates_search_from_all(rng, monkeypatch):
    # the screen runs each candidate's best grid start and its split single fit; the
    # other grid starts only of the candidates it passes, whose result is then that of
    # the search without a screen (all starts, every candidate run to the end)
    from sonarloc.fit.landmarks import fit_segments
    from sonarloc.fit.segment import Segmenter
    segs = []
    for sep in (20.0, 16.0, 12.0, 10.0, 10.0):
        refl = [Reflector.polar(1.5, -sep / 2, 0.67), Reflector.polar(1.5005, sep / 2, 0.67)]
        segs += list(Segmenter().feed(pan_scan(refl, rng, -40, 40, 0.3)))
    cfg = FitConfig()
    lms = fit_segments(segs, cfg)
    n_cand = sum(P.is_candidate(lm, cfg) for lm in lms)
    assert n_cand >= 3
    calls: list[int] = []
    minimise = P._minimise_batch

    def recording(seg, x0, fixed=None, maxiter=60, *args, **kwargs):
        if x0.shape[1] == 6 and fixed is None and maxiter == P.SCREEN_ITER:
            calls.append(x0.shape[0])
        return minimise(seg, x0, fixed, maxiter, *args, **kwargs)

    monkeypatch.setattr(P, "_minimise_batch", recording)
    screened = P.resolve_pair_groups(segs, lms, cfg)
    n_screen_rows = sum(calls)
    n_screened = sum("screened" in str(g[0].extra.get("pair_basis", "")) for g in screened)
    calls.clear()
    monkeypatch.setattr(P, "SCREEN_MARGIN", math.inf)       # nothing screened
    full = P.resolve_pair_groups(segs, fit_segments(segs, cfg), cfg)
    # every candidate here has four starts (three grid starts and the split single fit):
    # a screened one ran two of them to the screen, the others all four
    assert n_screened >= 1 and sum(calls) == 4 * n_cand
    assert n_screen_rows == 4 * n_cand - 2 * n_screened
    passed = 0
    for a, b in zip(screened, full, strict=True):
        if "screened" in str(a[0].extra.get("pair_basis", "screened")):
            continue
        passed += 1
        assert [lm.status for lm in a] == [lm.status for lm in b]
        for la, lb in zip(a, b, strict=True):
            np.testing.assert_allclose(la.params, lb.params, rtol=1e-9, atol=1e-12)
            assert la.extra["pair_gain"] == pytest.approx(lb.extra["pair_gain"], abs=1e-6)
    assert passed >= 1 and any(len(g) == 2 for g in screened)


def _grid_reference(seg: P._Segment, single: np.ndarray):
    """The start grid written out per segment and per bearing pair (masked sums over each
    pair's echoes, no cumulative sums, no padding): what _start_grids must reproduce."""
    mod = seg.cfg.module
    tau = P.M.us_per_m(mod)
    r0 = float(single[0])
    rel = P.M.wrap_angle(seg.yaw - single[1])
    nodes = single[1] + np.arange(float(rel.min()) - math.radians(3.0),
                                  float(rel.max()) + math.radians(3.0) + 1e-9,
                                  math.radians(P.GRID_STEP_DEG))
    geo = P.M.geometry("point", np.full((nodes.size, 1), r0), nodes[:, None], seg.px, seg.py,
                       seg.yaw)
    g = P.M.beam_delay_factor(geo.theta, seg.tier, mod, derivative=False)[0]
    g = np.minimum(g, 1e6) * math.exp(0.5 * P.M.sigma_a(mod) ** 2)
    yy = seg.y[None, :] - tau * (geo.R - r0)
    best = []
    for a in range(nodes.size):
        for b in range(a + 2, nodes.size):
            mine = g[a] <= g[b]
            total, sol = 0.0, []
            for j, m in ((a, mine), (b, ~mine)):
                G, Y = g[j][m], yy[j][m]
                A = np.stack([np.ones(G.size), G], axis=1)
                N = A.T @ A
                if G.size < 3 or np.linalg.det(N) <= 1e-12 * N[0, 0] * N[1, 1]:
                    total = math.inf
                    break
                to, kap = np.linalg.lstsq(A, Y, rcond=None)[0]
                if kap <= 0:
                    total = math.inf
                    break
                total += float(((Y - to - kap * G) ** 2).sum())
                sol += [to / tau * 1e3, math.degrees(nodes[j]),
                        math.log(max(kap, seg.cfg.kappa_min_us))]
            if math.isfinite(total):
                best.append((total, a, b, sol))
    best.sort(key=lambda t: t[0])
    return best[:P.N_CANDIDATES]


@pytest.mark.parametrize("tier,moving", [("gauss", False), ("waveform", False),
                                         ("gauss", True)])
def test_start_grids_of_many_segments_match_the_per_pair_solves(rng, tier, moving):
    # the batched grid (padded segments, cumulative sums where the assignment is a
    # split, the direct sums where it is not) gives each segment the best bearing pairs
    # and the (To, kappa) solves a per-pair least-squares fit gives
    scans = []
    for sep, step in ((8.0, 0.3), (14.0, 1.0), (0.0, 0.5), (20.0, 2.0)):
        refl = [Reflector.polar(1.5, -sep / 2, 0.67), Reflector.polar(1.5005, sep / 2, 0.67)]
        if moving:     # a slow drive-by: positions change along the pan
            yaw = np.deg2rad(np.arange(-35.0, 35.0, step))
            t = np.arange(yaw.size) * 0.05
            scans.append(simulate_readings(t, -0.3 + 0.01 * t, 0.02 * t, yaw, refl, rng))
        else:
            scans.append(pan_scan(refl, rng, -35, 35, step, tier=tier if tier != "gauss"
                                  else "gauss"))
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    cfg = FitConfig()
    segs = [P._Segment(batch, b, cfg, tier) for b in range(len(scans))]
    assert all(s.moving == moving for s in segs)
    singles = [np.array([1.5, 0.01 * b, 0.67]) for b in range(len(scans))]
    grids = P._start_grids(segs, singles)
    for seg, single, grid in zip(segs, singles, grids, strict=True):
        ref = _grid_reference(seg, single)
        assert grid is not None and len(ref) == len(grid[0])
        # the same bearing pairs in the same order of the linear cost (up to near ties)
        got = {(int(a), int(b)): x for x, a, b in zip(*grid, strict=True)}
        want = {(a, b): sol for _, a, b, sol in ref}
        common = got.keys() & want.keys()
        assert len(common) >= len(want) - 2
        for key in common:
            np.testing.assert_allclose(got[key][[0, 1, 3, 4]], np.array(want[key])[[0, 1, 3, 4]],
                                       rtol=1e-9, atol=1e-6)
            np.testing.assert_allclose(got[key][[2, 5]], np.array(want[key])[[2, 5]],
                                       atol=1e-6)
        assert (int(grid[1][0]), int(grid[2][0])) == (ref[0][1], ref[0][2])


@pytest.mark.parametrize("g_cap,same_y", [(math.inf, False), (4.0, False), (math.inf, True)])
def test_grid_sums_fall_back_where_the_assignment_is_not_a_split(rng, g_cap, same_y):
    # a beam whose delay factor is not monotone in the angle (here: made up) does not
    # split the echoes at one place, nor does one with capped factors: those segments
    # get the direct masked sums; a split one (sorted factors) the cumulative sums
    C, J, n = 4, 6, 9
    g = rng.uniform(1.0, 5.0, (C, J, n))
    g[3] = np.abs(np.arange(J)[:, None] - np.linspace(-0.5, J - 0.5, n)[None, :]) + 1.0
    yy = rng.normal(0.0, 10.0, (C, 1 if same_y else J, n))
    ok = np.ones((C, n), dtype=bool)
    ok[1, 7:] = False
    Jc = np.array([6, 5, 6, 6])
    ja, jb = np.triu_indices(J, k=2)
    A, B = P._grid_sums(g, yy, ok, Jc, ja, jb, g_cap)
    yy = np.broadcast_to(yy, g.shape)
    for c in range(C):
        for p, (a, b) in enumerate(zip(ja, jb, strict=True)):
            if b >= Jc[c]:
                continue
            m = (g[c, a] <= g[c, b]) & ok[c]
            mb = ~(g[c, a] <= g[c, b]) & ok[c]
            for sums, mask, j in ((A, m, a), (B, mb, b)):
                G, Y = g[c, j][mask], yy[c, j][mask]
                want = [G.size, G.sum(), (G * G).sum(), Y.sum(), (G * Y).sum(), (Y * Y).sum()]
                np.testing.assert_allclose([s[c, p] for s in sums], want, rtol=1e-12, atol=1e-9)


def test_candidate_chi2_band_decides_as_the_tail_probability():
    # is_candidate evaluates the chi-square tail only near its threshold: the band must
    # hold the crossing for every number of readings
    from scipy.special import chdtrc
    for dof in (1, 2, 5, 17, 60, 300, 3000):
        lo, hi = P._chi2_band(dof)
        assert chdtrc(dof, lo) >= P.CANDIDATE_P > chdtrc(dof, hi)


def test_flat_segments_detail_is_each_segments_own(rng):
    # responsibilities and residuals of rows of several segments (readings end to end)
    # are those of each segment alone, padded with zeros to the longest row
    cfg = FitConfig()
    scans = [pan_scan([Reflector.polar(1.5, -s / 2, 0.67), Reflector.polar(1.5005, s / 2, 0.67)],
                      rng, -30, 30, step) for s, step in ((10.0, 0.3), (16.0, 1.0), (6.0, 2.0))]
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    singles = [P._Segment(batch, b, cfg, "gauss") for b in range(3)]
    group = P._Segments(singles)
    owner = np.array([2, 0, 1, 0])
    x = np.array([[1500.0, -4.0, math.log(0.6), 1500.5, 5.0, math.log(0.7)],
                  [1500.0, -5.0, math.log(0.67), 1500.5, 5.0, math.log(0.67)],
                  [1499.0, -8.0, math.log(0.5), 1501.0, 8.0, math.log(0.8)],
                  [1500.0, 0.0, math.log(0.67), 1500.5, 1.0, math.log(0.67)]])
    c, resp, resid = group.detail(P._unscale(x), owner)
    width = max(s.y.size for s in singles)
    assert resp.shape == (4, 2, width) and resid.shape == (4, width)
    for j, o in enumerate(owner.tolist()):
        cj, rj, ej = singles[o].detail(P._unscale(x[j:j + 1]))
        n = singles[o].y.size
        assert c[j] == pytest.approx(float(cj[0]), rel=1e-12)
        np.testing.assert_allclose(resp[j, :, :n], rj[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(resid[j, :n], ej[0], rtol=1e-9, atol=1e-9)
        assert not resp[j, :, n:].any() and not resid[j, n:].any()


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform"])
def test_pair_cost_floor_bounds_every_pair_and_is_reached(rng, tier):
    # no parameters (random, or optimised from the grid starts) cost less than the floor;
    # readings at the mean of an on-axis, strong (zero-delay, surely detected) reflector
    # reach it: then two copies of it cost the floor plus their kappa prior
    cfg = FitConfig()
    scan = pan_scan([Reflector.polar(1.5, -6.0, 0.67), Reflector.polar(1.5005, 6.0, 0.67)],
                    rng, -30, 30, 0.5, tier=tier if tier != "piston" else "gauss")
    seg = P._Segment(_batch(scan), 0, cfg, tier)
    floor = float(P._pair_cost_floor([seg])[0])
    x = np.column_stack([rng.uniform(1400.0, 1600.0, 400), rng.uniform(-40.0, 40.0, 400),
                         rng.uniform(math.log(0.01), math.log(50.0), 400)])
    x = np.concatenate([x, x[::-1]], axis=1)
    xo, co = P._minimise_batch(seg, x[:8])
    assert np.asarray(seg.cost(P._unscale(x))).min() >= floor
    assert co.min() >= floor and np.asarray(seg.cost(P._unscale(x[:, :3]))).min() >= floor
    n = 30
    on_axis = pack_segments([(np.arange(n) * 0.03, np.zeros(n), np.zeros(n),
                              np.full(n, 0.1), np.full(n, 9000.0))])
    strong = P._Segment(on_axis, 0, cfg, tier)
    q = np.array([[1.5, 0.1, P._LNK_LO]])
    (mean, _, _, _), _ = strong._component(q, strong._readings(None, 1))
    strong.y = mean[0]
    pen = float(P._kappa_penalty(np.exp(q[:, 2]), cfg)[0][0])
    floor = float(P._pair_cost_floor([strong])[0])
    for comps in ([q], [q, q]):
        c = float(np.asarray(strong.cost(comps))[0]) - len(comps) * pen
        assert 0.0 <= c - floor <= 1e-7 * n


def test_hopeless_candidates_are_not_searched_and_the_others_as_before(rng, monkeypatch):
    # a candidate whose pair cannot gain the bar by the cost floor is not searched (its
    # gain reported as that bound, which the search stays below); the others, searched
    # with them in one group, get the result of the search of all (up to the rounding of
    # a group's sums)
    cfg = FitConfig()
    scans = []
    for sep, step, k in ((0.0, 2.0, 0.67), (20.0, 0.3, 0.67), (0.0, 2.0, 2.68),
                         (0.0, 1.0, 0.15), (12.0, 1.0, 0.67), (0.0, 2.0, 0.15),
                         (16.0, 0.5, 0.67)):
        refl = [Reflector.polar(1.5, -sep / 2, k)] + ([Reflector.polar(1.5005, sep / 2, k)]
                                                       if sep else [])
        scans.append(pan_scan(refl, rng, -40, 40, step))
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    segs = [P._Segment(batch, b, cfg, "gauss") for b in range(len(scans))]
    singles = list(fit_batch(batch, "point", "gauss").local)
    got = P._fit_pairs(segs, singles)
    floor = P._pair_cost_floor(segs)
    bars = [max(3.0 * math.log(seg.n), P.MIN_GAIN) for seg in segs]
    monkeypatch.setattr(P, "_pair_cost_floor", lambda s: np.full(len(s), -np.inf))
    full = P._fit_pairs(segs, singles)
    skipped = 0
    for a, b, f, bar in zip(got, full, floor, bars, strict=True):
        if a.cost_single - f <= bar:
            skipped += 1
            assert a.basis.startswith("two reflectors cannot fit enough better than one")
            assert not a.accepted and not b.accepted
            assert a.gain == pytest.approx(a.cost_single - f, abs=1e-9)
            assert b.gain <= a.gain and np.isnan(a.local).all()
        else:
            assert (a.accepted, a.basis) == (b.accepted, b.basis)
            assert a.gain == pytest.approx(b.gain, abs=1e-6)
            np.testing.assert_allclose(a.local, b.local, rtol=1e-7, atol=1e-9)
    assert skipped >= 2 and sum(pf.accepted for pf in got) >= 2
    assert got[0].basis.startswith("two reflectors cannot")     # before a searched one
    # the threshold: a bound just below the bar is not searched, one just above it is
    s0 = np.array([[s[0] / P._SCALE[0], s[1] / P._SCALE[1],
                    math.log(max(float(s[2]), cfg.kappa_min_us))] for s in singles])
    c0 = np.asarray(P._Segments(segs).cost(P._unscale(s0), np.arange(len(segs))))
    over = np.array([-1e-6, 1e-6, 1e-6, -1e-6, 1e-6, -1e-6, 1e-6])
    monkeypatch.setattr(P, "_pair_cost_floor", lambda s: c0 - np.array(bars) - over)
    at_bar = P._fit_pairs(segs, singles)
    assert [pf.basis[15:21] == "cannot" for pf in at_bar] == (over < 0.0).tolist()


def test_unusable_readings_of_candidates_are_left_out(rng):
    # readings with a non-finite time, position or yaw, or a TOF <= 0, do not enter the
    # pair test: the candidates decide as without them
    from dataclasses import replace

    from sonarloc.fit.landmarks import fit_segments
    from sonarloc.fit.segment import Segmenter
    cfg = FitConfig()
    clean = []
    for sep, lo in ((20.0, -40.0), (12.0, -30.0)):
        refl = [Reflector.polar(1.5, -sep / 2, 0.67), Reflector.polar(1.5005, sep / 2, 0.67)]
        clean += list(Segmenter().feed(pan_scan(refl, rng, lo, 40, 0.3)))
    lms = fit_segments(clean, cfg)
    assert all(P.is_candidate(lm, cfg) for lm in lms)
    assert len({len(s.readings) for s in clean}) == len(clean)
    bad = [(0, math.nan), (1, math.inf), (2, math.nan), (3, -math.inf), (4, 0.0), (4, -1.0)]
    dirty = []
    for s in clean:
        r = s.readings
        cols = [c.copy() for c in (r.t_s, r.x_m, r.y_m, r.yaw_rad, r.tof_us)]
        at = np.sort(rng.choice(len(r), len(bad), replace=False)) + np.arange(len(bad))
        for (col, v), j in zip(bad, at, strict=True):
            for c, arr in enumerate(cols):
                cols[c] = np.insert(arr, j, v if c == col else arr[min(j, arr.size - 1)])
        sensor = np.zeros(cols[0].size, dtype=np.int64)
        dirty.append(replace(s, readings=ScanReadings(*cols, sensor)))
    a = P.resolve_pair_groups(clean, lms, cfg)
    b = P.resolve_pair_groups(dirty, fit_segments(clean, cfg), cfg)
    assert [len(g) for g in a] == [len(g) for g in b] and any(len(g) == 2 for g in a)
    for ga, gb in zip(a, b, strict=True):
        for la, lb in zip(ga, gb, strict=True):
            np.testing.assert_array_equal(la.params, lb.params)
            assert la.n_readings == lb.n_readings
            for key in ("pair_basis", "pair_gain", "pair_price"):
                assert la.extra.get(key) == lb.extra.get(key)


def test_lockstep_starts_backtrack_on_their_own_and_take_their_paths_alone(rng, monkeypatch):
    # starts whose line searches backtrack different numbers of times share every call
    # (a call evaluates some starts' first trial of a step and others' shorter ones) and
    # each reaches the optimum, cost and path length it reaches alone
    refl = [Reflector.polar(1.5, -8.0, 0.67), Reflector.polar(1.5005, 8.0, 0.67)]
    seg = P._Segment(_batch(pan_scan(refl, rng, -40, 40, 0.3)), 0, FitConfig(), "gauss")
    starts = np.array([[1500.0, -6.0, math.log(0.5), 1500.0, 6.0, math.log(0.9)],
                       [1490.0, -20.0, math.log(5.0), 1530.0, 25.0, math.log(0.05)],
                       [1500.2, -1.0, math.log(0.3), 1500.2, 1.0, math.log(0.3)],
                       [1460.0, 10.0, math.log(0.01), 1550.0, -30.0, math.log(20.0)]])
    calls: list[int] = []
    cost_grad = P._Segment.cost_grad

    def counting(self, x, owner=None):
        calls.append(x.shape[0])
        return cost_grad(self, x, owner)

    monkeypatch.setattr(P._Segment, "cost_grad", counting)
    xs, cs = P._minimise_batch(seg, starts, maxiter=30)
    n_together = len(calls)
    alone = []
    for x0 in starts:
        calls.clear()
        alone.append((*P._minimise_batch(seg, x0[None, :], maxiter=30), len(calls)))
    # (up to the rounding of batch-wide branches of the model's terms, amplified along
    # a flat valley: 1e-4 here, as in lockstep steps)
    for x, c, (xa, ca, _) in zip(xs, cs, alone, strict=True):
        np.testing.assert_allclose(x, xa[0], rtol=0.0, atol=1e-3)
        assert c == pytest.approx(float(ca[0]), abs=1e-4)
    # the calls of the starts together are as many as the longest search alone needs
    assert n_together == max(n for _, _, n in alone)
    assert len({n for _, _, n in alone}) > 1
    # and the searches near the optimum reach scipy's BFGS optimum (a line search that
    # gave up early would stop short)
    from scipy.optimize import minimize
    for j in (0, 2):
        ref = minimize(lambda v: float(np.asarray(seg.cost(P._unscale(v[None, :])))[0]),
                       starts[j], method="BFGS", options={"gtol": 1e-3, "maxiter": 400})
        assert cs[j] <= ref.fun + 0.1


def test_covariance_only_of_accepted_pairs_each_its_own(rng):
    # the Hessian and kappa profiles are evaluated only for accepted pairs (no test
    # reads them): a rejected pair's covariance is NaN, and each accepted pair of a
    # group gets the covariance of its own search alone (up to the rounding of the sums)
    cfg = FitConfig()
    scans = []
    for sep, k in ((16.0, 0.67), (24.0, 0.67), (0.0, 0.67), (18.0, 0.15), (20.0, 0.67)):
        refl = [Reflector.polar(1.5, -sep / 2, k)] + ([Reflector.polar(1.5005, sep / 2, k)]
                                                       if sep else [])
        scans.append(pan_scan(refl, rng, -40, 40, 0.3))
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    segs = [P._Segment(batch, b, cfg, "gauss") for b in range(len(scans))]
    singles = list(fit_batch(batch, "point", "gauss").local)
    together = P._fit_pairs(segs, singles)
    assert sum(pf.accepted for pf in together) >= 2
    assert any(pf.gain > P.MIN_GAIN and not pf.accepted for pf in together)
    for seg, single, pf in zip(segs, singles, together, strict=True):
        if not pf.accepted:
            assert np.isnan(pf.cov).all() and not pf.ambiguous
            continue
        alone = P._fit_pairs([seg], [single])[0]
        assert np.all(np.isfinite(pf.cov))
        # (the searches' batch-wide sums round differently, which a flat valley
        # amplifies: 7e-8 from main's single fits, 2.2e-6 from those of 2026-11-27,
        # whose bearings moved by 1e-7 rad; another pair's covariance is off by O(1))
        np.testing.assert_allclose(pf.cov, alone.cov, rtol=1e-5, atol=1e-15)


def test_direct_grid_sums_in_node_blocks_are_the_written_out_sums(rng, monkeypatch):
    # _direct_sums forms the assignments for blocks of nodes: any block size gives the
    # masked sums of every ordered pair (A at a where g_a <= g_b, ties at the cap
    # included; B at b where g_b < g_a), real echoes only
    C, J, n = 2, 7, 11
    g = rng.uniform(0.5, 3.0, (C, J, n))
    g[:, :, 3] = 5.0                                  # a tie at every pair
    yy = rng.normal(0.0, 1.0, (C, J, n))
    ok_e = rng.uniform(size=(C, n)) < 0.8
    for chunk in (1, 3 * n, 10 ** 9):
        monkeypatch.setattr(P, "GRID_CHUNK", chunk)
        sa, sb = P._direct_sums(g, yy, ok_e)
        for c in range(C):
            for a in range(J):
                for b in range(J):
                    for out, k, mine in ((sa, a, (g[c, a] <= g[c, b]) & ok_e[c]),
                                         (sb, b, (g[c, b] < g[c, a]) & ok_e[c])):
                        G, Y = g[c, k][mine], yy[c, k][mine]
                        want = [G.size, G.sum(), (G * G).sum(), Y.sum(), (G * Y).sum(),
                                (Y * Y).sum()]
                        np.testing.assert_allclose(out[c, a, b] if out is sa else
                                                   out[c, b, a], want, rtol=1e-12,
                                                   atol=1e-12)
