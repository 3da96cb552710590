"""Odometry error inside a segment in the landmark covariance (sonarloc.fit.odomcov)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.fit import odomcov
from sonarloc.fit.landmarks import fit_scan, fit_segments
from sonarloc.fit.lsq import FitConfig, fit_batch, pack_segments
from sonarloc.fit.synth import Reflector, pan_scan, simulate_readings


def _drive_by(rng, n=200, length_m=1.2, pole=False):
    # a side-looking transducer driving past a wall 1.5 m away, tilted 3 deg (or a pole)
    t = np.arange(n) * 0.02
    x = np.linspace(-0.5 * length_m, 0.5 * length_m, n)
    yaw = np.full(n, np.pi / 2) + np.deg2rad(12.0) * np.sin(2 * np.pi * t / 1.3)
    ref = (Reflector.polar(1.2, 95.0, 0.67) if pole
           else Reflector.line(1.5, np.deg2rad(93.0), 0.15))
    return simulate_readings(t, x, 0.0, yaw, [ref], rng)


def test_bend_zero_is_identity_and_pans_get_nothing(rng):
    scan = pan_scan([Reflector.polar(1.5, 3.0, 0.67)], rng, -30, 30, 0.5)
    batch = pack_segments([(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us)])
    same = odomcov.bend(batch, 0.0)
    assert np.array_equal(same.px, batch.px) and np.array_equal(same.yaw, batch.yaw)
    fit = fit_batch(batch, "point", "gauss")
    assert np.all(odomcov.odometry_covariance(batch, fit, FitConfig()) == 0.0)


def test_sensitivity_is_linear_and_grows_with_the_sd(rng):
    scan = _drive_by(rng)
    batch = pack_segments([(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us)])
    fit = fit_batch(batch, "line", "gauss")
    c1 = odomcov.odometry_covariance(batch, fit, FitConfig(), 1.0)[0]
    c2 = odomcov.odometry_covariance(batch, fit, FitConfig(), 2.0)[0]
    assert c1[1, 1] > 0 and c1[0, 0] > 0
    assert c2 == pytest.approx(4.0 * c1, rel=1e-9, abs=1e-18)
    # linear regime: a 10x larger bend moves the fit 10x as far (within 10 %)
    eps = math.radians(1.0)
    bent = fit_batch(odomcov.bend(batch, 10 * odomcov._EPS), "line", "gauss", start=fit)
    s_big = (bent.local[0, 1] - fit.local[0, 1]) / (10 * odomcov._EPS)
    assert s_big * s_big * eps * eps == pytest.approx(c1[1, 1], rel=0.1)


def test_landmarks_carry_the_odometry_term(rng):
    scan = _drive_by(rng)
    lms0 = fit_scan(scan, odometry_sd_deg_per_m=0.0).landmarks
    lms1 = fit_scan(scan).landmarks
    w0 = max(lms0, key=lambda lm: lm.n_readings)
    w1 = max(lms1, key=lambda lm: lm.n_readings)
    assert w0.kind == w1.kind == "line"
    assert "odom_bearing_sd_deg" in w1.extra and "odom_bearing_sd_deg" not in w0.extra
    sd0, sd1 = (float(w.extra["bearing_sd_deg"]) for w in (w0, w1))
    odo = float(w1.extra["odom_bearing_sd_deg"])
    assert sd1 == pytest.approx(math.hypot(sd0, odo), rel=1e-6)
    assert np.allclose(w0.params, w1.params)            # only the covariance changes
    with pytest.raises(ValueError, match="odometry_sd_deg_per_m"):
        fit_segments([scan], odometry_sd_deg_per_m=-1.0)


@pytest.mark.parametrize("kind", ["line", "point"])
def test_sensitivity_is_the_derivative_of_the_optimum(rng, kind):
    # against a tightly converged central difference of refits, on short segments (0.3 m
    # driven, 40 readings); a refit at the fit's own tolerance barely moves for a bend
    # small enough to be linear (the way before session 9: bearing SDs ~0.7x, ranges
    # down to 0.01x of these)
    scans = [_drive_by(rng, 40, 0.3, pole=kind == "point") for _ in range(8)]
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in scans])
    fit = fit_batch(batch, kind, "gauss")
    assert fit.converged.all()
    cov = odomcov.odometry_covariance(batch, fit, FitConfig(), 1.0)
    tight = FitConfig(tolerance=1e-12, iterations=200)
    eps = 3e-3
    plus, minus = (fit_batch(odomcov.bend(batch, e), kind, "gauss", tight, start=fit)
                   for e in (eps, -eps))
    ref_sd = np.abs(plus.local - minus.local) / (2 * eps) * math.radians(1.0)
    assert np.sqrt(cov[:, 1, 1]) == pytest.approx(ref_sd[:, 1], rel=0.05)     # bearing
    assert np.sqrt(cov[:, 0, 0]) == pytest.approx(ref_sd[:, 0], rel=0.25)     # range
