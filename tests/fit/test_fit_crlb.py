"""Cramér–Rao bound: PHYSICS.md's numbers, the fitter reaching it, odd geometries."""

from __future__ import annotations

import numpy as np
import pytest

from sonarloc.fit.crlb import crlb, local_params
from sonarloc.fit.lsq import fit_batch, pack_segments
from sonarloc.fit.synth import Reflector, pan_scan

YAW = np.deg2rad(np.arange(-40, 40.001, 0.3))
Z = np.zeros_like(YAW)


@pytest.mark.parametrize(("kappa", "bearing_deg"), [(0.15, 0.30), (0.67, 0.36), (2.68, 0.47)])
def test_tof_only_bound_matches_physics_notes(kappa, bearing_deg):
    b = crlb("point", [1.5, 0.0, kappa], Z, Z, YAW, detection=False)
    assert np.rad2deg(b.bearing_sd_rad) == pytest.approx(bearing_deg, abs=0.03)
    assert 0.08e-3 < b.range_sd_m < 0.27e-3


def test_detection_events_add_information():
    for kappa in (0.15, 0.67, 2.68):
        tof = crlb("point", [1.5, 0.0, kappa], Z, Z, YAW, detection=False)
        full = crlb("point", [1.5, 0.0, kappa], Z, Z, YAW)
        assert full.bearing_sd_rad < tof.bearing_sd_rad
        assert full.n_echo == pytest.approx(tof.n_echo)


def test_fitter_reaches_the_bound(rng):
    segs = [pan_scan([Reflector.polar(1.5, 0.0, 0.67)], rng, -25, 25, 0.3) for _ in range(150)]
    batch = pack_segments([(s.t_s, s.x_m, s.y_m, s.yaw_rad, s.tof_us) for s in segs])
    f = fit_batch(batch, "point", "gauss")
    yaw = segs[0].yaw_rad
    b = crlb("point", [1.5, 0.0, 0.67], 0 * yaw, 0 * yaw, yaw)
    rmse_b = np.sqrt(np.mean(f.local[:, 1] ** 2))
    rmse_r = np.sqrt(np.mean((f.local[:, 0] - 1.5) ** 2))
    assert 0.75 < rmse_b / b.bearing_sd_rad < 1.25
    assert 0.75 < rmse_r / b.range_sd_m < 1.25


def test_batch_axes_and_frames():
    params = np.array([[1.0, 0.5, 0.67], [2.0, -1.0, 2.68]])
    yaw = np.stack([YAW + np.arctan2(0.5, 1.0), YAW + np.arctan2(-1.0, 2.0)])
    both = crlb("point", params, 0 * yaw, 0 * yaw, yaw)
    assert both.cov.shape == (2, 3, 3) and both.n_echo.shape == (2,)
    one = crlb("point", params[1], 0 * yaw[1], 0 * yaw[1], yaw[1])
    np.testing.assert_allclose(both.cov[1], one.cov, rtol=1e-10, atol=1e-12)
    # from one spot a wall and a point through the same reflecting point bound alike
    wall = crlb("line", [np.hypot(1.0, 0.5), np.arctan2(0.5, 1.0), 0.67], 0 * yaw[0],
                0 * yaw[0], yaw[0])
    np.testing.assert_allclose(wall.cov_local, both.cov_local[0], rtol=1e-8, atol=1e-12)


def test_moving_pass_and_degenerate_geometry():
    t = np.linspace(0, 6, 120)
    x = -0.9 + 0.3 * t
    b = crlb("point", [0.0, 1.2, 0.67], x, 0 * x, np.full_like(x, np.pi / 2))
    assert np.all(np.isfinite(b.cov)) and b.n_echo > 10
    assert np.rad2deg(b.bearing_sd_rad) < 2.0
    # one fixed axis from one spot: bearing and kappa cannot be separated
    still = crlb("point", [1.5, 0.0, 0.67], np.zeros(20), np.zeros(20), np.full(20, 0.05))
    assert not np.isfinite(still.bearing_sd_rad) or np.rad2deg(still.bearing_sd_rad) > 5.0
    assert np.isfinite(still.range_sd_m) or np.isinf(still.range_sd_m)


def test_local_params_roundtrip_and_errors():
    lp = local_params("line", [2.0, np.pi / 2, 0.1], [0.0, 3.0])   # behind the wall
    np.testing.assert_allclose(lp, [1.0, -np.pi / 2, 0.1], atol=1e-12)
    with pytest.raises(ValueError, match="kind"):
        crlb("blob", [1, 0, 1], Z, Z, YAW)
    with pytest.raises(ValueError, match="params"):
        crlb("point", [1, 0], Z, Z, YAW)
