"""The ``"profile"`` refinement (``FitConfig.profile()``): same answer as the converged
echoes-only fit, calibrated covariance, sound on the hard cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_fit_hard_cases import check_invariants
from test_fit_lsq import _pan_batch

from sonarloc.fit import model as M
from sonarloc.fit.landmarks import fit_scan
from sonarloc.fit.lsq import FitConfig, fit_batch
from sonarloc.fit.synth import Reflector, pan_scan, simulate_readings
from sonarloc.io.scancsv import ScanReadings


def _sd(f):
    return np.sqrt(np.einsum("bkk->bk", f.cov))


def test_profile_preset_and_validation():
    c = FitConfig.profile()
    assert c.method == "profile" and c.grid_step_deg == 12.0 and c.detection
    assert FitConfig.profile(profile_evals=2).profile_evals == 2
    with pytest.raises(ValueError, match="method"):
        FitConfig(method="newton")
    with pytest.raises(ValueError, match="profile_evals"):
        FitConfig(profile_evals=0)


@pytest.mark.parametrize(("kappa", "bearing", "step"), [(0.67, 8.0, 0.5), (2.68, -15.0, 1.0)])
def test_profile_is_the_converged_echoes_only_fit(rng, kappa, bearing, step):
    # the same objective (echo TOF terms, jitter weights, untruncated delays) minimised
    # by converged Fisher scoring: the stencils land within a fraction of an SD of it
    # (the rest: three stencils, and weights held at the bracket's start)
    batch = _pan_batch(rng, 60, 1.5, bearing, kappa, step=step)
    ref = fit_batch(batch, "point", "gauss", FitConfig(detection=False, rounds=3,
                                                       start="grid"))
    f = fit_batch(batch, "point", "gauss", FitConfig.profile())
    assert np.all(np.isfinite(f.local)) and np.all(np.isfinite(f.cov))
    # echoes alone can leave two near-equal minima on a short, coarse U: the reflector
    # and the degenerate "weak reflector far off-axis" (kappa near the prior's lower edge,
    # a bearing SD of tens of degrees: FLAT); compare where the reference is not there
    same = ((ref.local[:, 2] > 2 * FitConfig().kappa_lo_us)
            & (np.rad2deg(_sd(ref)[:, 1]) < FitConfig().flat_bearing_sd_deg))
    assert same.mean() > 0.6    # a rod at 1 deg steps: about a third FLAT on echoes alone
    ref, f, batch_f = ref.take(np.flatnonzero(same)), f.take(np.flatnonzero(same)), f
    sd = _sd(ref)
    d = np.abs(f.local - ref.local) / sd
    assert np.all(np.median(d, axis=0) < [0.05, 0.1, 0.2]), np.median(d, axis=0)
    assert np.all(np.quantile(d, 0.9, axis=0) < [0.2, 0.4, 0.5]), np.quantile(d, 0.9, axis=0)
    assert np.all(d < 1.0), d.max(0)
    # the reported covariance is that of the same objective
    ratio = _sd(f) / sd
    assert np.all(np.abs(np.median(ratio, axis=0) - 1.0) < 0.1), np.median(ratio, axis=0)
    assert np.all(np.quantile(ratio, 0.9, axis=0) < 1.3), np.quantile(ratio, 0.9, axis=0)
    assert np.all((ratio > 0.3) & (ratio < 3.0)), (ratio.min(0), ratio.max(0))
    # and the default (with detection terms: more information) agrees within the SDs
    full = fit_batch(batch, "point", "gauss")
    okp = np.rad2deg(_sd(batch_f)[:, 1]) < FitConfig().flat_bearing_sd_deg
    dd = np.abs(batch_f.local - full.local)[okp, :2]
    assert np.all(dd < 4.0 * np.hypot(_sd(batch_f), _sd(full))[okp, :2])
    assert batch_f.converged.mean() > 0.7


def test_profile_covariance_is_calibrated(rng):
    # Monte Carlo: reported SD against the actual error, bearing and range, over the
    # segments a pipeline would call OK (bearing SD below flat_bearing_sd_deg). The
    # echoes-only Gauss-Newton covariance is somewhat conservative in bearing (the jitter
    # model ignores that the arc edges' delays are truncated at the detection limit);
    # the same holds for the converged echoes-only fit
    batch = _pan_batch(rng, 300, 2.0, 5.0, 0.67, span=30.0, step=0.5)
    f = fit_batch(batch, "point", "gauss", FitConfig.profile())
    err = f.local - np.array([2.0, np.deg2rad(5.0), 0.67])
    err[:, 1] = M.wrap_angle(err[:, 1])
    sd = _sd(f)
    ok = np.rad2deg(sd[:, 1]) < FitConfig().flat_bearing_sd_deg
    assert ok.mean() > 0.9
    for k in (0, 1):
        e, s = err[ok, k], sd[ok, k]
        ratio = np.sqrt(np.mean(s ** 2)) / np.sqrt(np.mean(e ** 2))
        assert 0.7 <= ratio <= 1.5, (k, ratio)
        z = e / s
        assert 0.6 <= np.sqrt(np.mean(z * z)) <= 1.3, (k, np.sqrt(np.mean(z * z)))
        assert abs(z.mean()) < 0.3
    assert np.rad2deg(np.sqrt(np.mean(err[ok, 1] ** 2))) < 1.5


def test_profile_moving_sensor(rng):
    # a side-looking sensor driving past a pole: the geometry's range follows the fit
    t = np.arange(0.0, 8.0, 0.05)
    segs = []
    for _ in range(20):
        x = -1.2 + 0.3 * t + float(rng.uniform(-0.1, 0.1))
        sc = simulate_readings(t, x, 0.0, np.full_like(t, math.pi / 2),
                               [Reflector.point(0.0, 1.2, 0.67)], rng)
        segs.append(sc)
    rep = [fit_scan(sc, FitConfig.profile()).landmarks for sc in segs]
    for lms in rep:
        check_invariants(lms)
        ok = [lm for lm in lms if lm.ok and lm.kind == "point"]
        for lm in ok:
            sd = np.sqrt(np.diag(lm.cov))
            assert abs(lm.params[0]) < 4 * sd[0] + 0.01
            assert abs(lm.params[1] - 1.2) < 4 * sd[1] + 0.01
    assert sum(any(lm.ok for lm in lms) for lms in rep) >= 15


def _hard_scans(rng):
    """(scan, truth [(range_m, bearing_deg)] or None (no single-point truth))."""
    out = [
        (pan_scan([Reflector.polar(1.5, 4.0, 0.15)], rng, -40, 40, 0.3), None),      # wall
        (pan_scan([Reflector.polar(1.5, 45.0, 0.67)], rng, -40, 40, 0.3), [(1.5, 45.0)]),
        (pan_scan([Reflector.polar(4.0, 10.0, 2.68)], rng, -40, 40, 3.0), [(4.0, 10.0)]),
        (pan_scan([Reflector.polar(1.5, -3.0, 0.67), Reflector.polar(1.503, 3.0, 0.67)], rng,
                  -40, 40, 0.3), [(1.5, -3.0), (1.503, 3.0)]),
        (pan_scan([Reflector.polar(2.0, 12.0, 0.67)], rng, -40, 40, 2.0), [(2.0, 12.0)]),
        (pan_scan([Reflector.polar(1.5, 0.0, 0.67)], rng, -40, 40, 0.3, tier="waveform"),
         [(1.5, 0.0)]),
    ]
    sc = pan_scan([Reflector.polar(1.46, -17, 0.67), Reflector.polar(1.47, 22, 2.68)], rng,
                  -40, 40, 0.3)
    tof = sc.tof_us.copy()
    spikes = rng.choice(len(tof), 15, replace=False)
    tof[spikes] = rng.uniform(1500, 12000, 15)
    tof[3] = np.inf
    tof[7] = np.nan
    out.append((ScanReadings(sc.t_s, sc.x_m, sc.y_m, sc.yaw_rad, tof, sc.sensor),
                [(1.46, -17.0), (1.47, 22.0)]))
    n = 720
    yaw = np.deg2rad(np.arange(n) * 0.5 - 180.0)
    truth = [(1.5, 180.0), (2.0, -60.0), (2.5, 45.0)]
    out.append((simulate_readings(np.arange(n) * 0.03, 0.0, 0.0, yaw,
                                  [Reflector.polar(r, b, 0.67) for r, b in truth], rng), truth))
    t = np.arange(0, 12.0, 0.04)
    yaw = np.pi / 2 + np.deg2rad(15.0) * np.sin(2 * np.pi * t / 3.0)
    out.append((simulate_readings(t, -1.0 + 0.25 * t, 0.0, yaw,
                                  [Reflector.point(0.0, 1.2, 0.67),
                                   Reflector.line(2.2, np.deg2rad(95.0), 0.15)], rng), None))
    return out


def test_profile_never_diverges_on_the_hard_cases(rng):
    # no exception, no NaN marked OK, and every OK point landmark of a pan on a
    # reflector (within 10 deg and 5 cm: what the benchmark calls a divergence)
    n_ok = 0
    for scan, truth in _hard_scans(rng):
        lms = fit_scan(scan, FitConfig.profile()).landmarks
        check_invariants(lms)
        assert lms
        for lm in lms:
            assert np.all(np.isfinite(lm.params)), lm
            if lm.ok and truth is not None and lm.kind == "point":
                n_ok += 1
                assert any(abs((math.degrees(lm.bearing_rad) - b + 180) % 360 - 180) < 10
                           and abs(lm.range_m - r) < 0.05 for r, b in truth), lm
    assert n_ok >= 6
