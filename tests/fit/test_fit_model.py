"""The fitter's forward model: derivatives against finite differences, special cases."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import log_ndtr

from sonarloc.fit import model as M
from sonarloc.physics import ModuleParams, jitter_sd_us

MOD = ModuleParams()


@pytest.mark.parametrize("kind", ["point", "line"])
def test_geometry_derivatives_match_finite_differences(kind, rng):
    px, py = rng.normal(0, 0.3, 20), rng.normal(0, 0.3, 20)
    yaw = rng.uniform(-np.pi, np.pi, 20)
    r, phi = 1.7, 0.4
    geo = M.geometry(kind, r, phi, px, py, yaw)
    h = 1e-6
    for name, dr, dp in (("r", h, 0.0), ("phi", 0.0, h)):
        up = M.geometry(kind, r + dr, phi + dp, px, py, yaw)
        dn = M.geometry(kind, r - dr, phi - dp, px, py, yaw)
        num_R = (up.R - dn.R) / (2 * h)
        num_t = M.wrap_angle(up.theta - dn.theta) / (2 * h)
        np.testing.assert_allclose(geo.dR_dr if name == "r" else geo.dR_dphi, num_R,
                                   atol=1e-6, rtol=1e-6)
        np.testing.assert_allclose(geo.dtheta_dr if name == "r" else geo.dtheta_dphi, num_t,
                                   atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("kind", ["point", "line"])
def test_range_angle_is_geometry_without_derivatives(kind, rng):
    # the grid's nodes (B, G, N) broadcast as in _node_profile; the same numbers, bit for
    # bit (the bracket must not move), angles wrapped across +-pi
    px, py = rng.normal(0, 0.5, (4, 1, 30)), rng.normal(0, 0.5, (4, 1, 30))
    yaw = rng.uniform(-np.pi, np.pi, (4, 1, 30))
    r = rng.uniform(0.5, 3.0, (4, 1, 1))
    phi = rng.uniform(-np.pi, np.pi, (4, 9, 1))
    R, theta = M.range_angle(kind, r, phi, px, py, yaw)
    geo = M.geometry(kind, r, phi, px, py, yaw, moving=True)
    assert R.shape == theta.shape == (4, 9, 30)
    np.testing.assert_array_equal(R, geo.R)
    np.testing.assert_array_equal(theta, geo.theta)
    assert np.abs(theta).max() <= np.pi


def test_stationary_point_equals_line_and_pan_angle():
    yaw = np.deg2rad(np.linspace(-30, 30, 7))
    z = np.zeros(7)
    a = M.geometry("point", 1.5, 0.2, z, z, yaw)
    b = M.geometry("line", 1.5, 0.2, z, z, yaw)
    np.testing.assert_allclose(a.R, 1.5)
    np.testing.assert_allclose(a.theta, b.theta)
    np.testing.assert_allclose(a.theta, 0.2 - yaw)


def test_geometry_wraps_bearing():
    g = M.geometry("point", 2.0, np.deg2rad(179.0), np.zeros(1), np.zeros(1),
                   np.array([np.deg2rad(-179.0)]))
    assert np.rad2deg(g.theta[0]) == pytest.approx(-2.0)


@pytest.mark.parametrize("tier", ["gauss", "piston"])
def test_beam_delay_derivative_and_log(tier):
    th = np.deg2rad(np.linspace(-12, 12, 49))
    g, dg, lng = M.beam_delay_factor(th, tier, MOD)
    h = 1e-7
    num = (M.beam_delay_factor(th + h, tier, MOD)[0] - M.beam_delay_factor(th - h, tier, MOD)[0])
    np.testing.assert_allclose(dg, num / (2 * h), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(lng, np.log(g), rtol=1e-12, atol=1e-12)
    assert g.min() == pytest.approx(1.0)


def test_gauss_delay_is_paper_eq3():
    th = np.deg2rad(np.array([0.0, 5.25, 10.0]))
    g, _, _ = M.beam_delay_factor(th, "gauss", MOD)
    np.testing.assert_allclose(g, np.exp(th**2 / (2 * np.deg2rad(5.25) ** 2)))


def test_piston_behind_and_at_null_is_capped_not_infinite():
    null = np.arcsin(3.8317 * (MOD.c_mps / MOD.carrier_hz) / (np.pi * MOD.diameter_m))
    g, dg, lng = M.beam_delay_factor(np.array([null, np.pi, -2.0]), "piston", MOD)
    assert np.all(np.isfinite(g)) and np.all(np.isfinite(dg)) and np.all(np.isfinite(lng))
    assert np.all(g > 1e6)


def test_probit_terms_match_scipy_everywhere():
    v = np.linspace(-40, 40, 801)
    lp, mills, info = M.probit_terms(v)
    np.testing.assert_allclose(lp, log_ndtr(v), rtol=1e-8, atol=1e-11)
    exact_mills = np.exp(-0.5 * v * v - 0.5 * np.log(2 * np.pi) - log_ndtr(v))
    np.testing.assert_allclose(mills, exact_mills, rtol=1e-6, atol=1e-10)
    exact_info = np.exp(-v * v - np.log(2 * np.pi) - log_ndtr(v) - log_ndtr(-v))
    np.testing.assert_allclose(info, exact_info, rtol=1e-6, atol=1e-10)


def test_truncated_mean_delay_and_derivative():
    kap = 0.67
    g = np.exp(np.linspace(0, 4, 41))
    lng = np.log(g)
    z = M.detection_z(kap, lng, MOD)
    mean, d = M.mean_delay(kap, g, MOD, z)
    # far inside the arc: the untruncated log-normal mean u exp(s^2/2)
    s = MOD.amplitude_fluctuation
    assert mean[0] == pytest.approx(kap * np.exp(s * s / 2), rel=1e-9)
    # never above the detection limit: it is the mean of delays <= L
    assert np.all(mean <= MOD.detection_limit_us)
    # Monte Carlo check at the arc edge
    rng = np.random.default_rng(5)
    u = 11.0
    delays = u / np.exp(s * rng.standard_normal(400_000))
    delays = delays[delays <= MOD.detection_limit_us]
    m_edge, _ = M.mean_delay(u, 1.0, MOD, M.detection_z(u, 0.0, MOD))
    assert float(m_edge) == pytest.approx(delays.mean(), rel=2e-3)
    # derivative by u = kappa g against finite differences
    h = 1e-6
    up, _ = M.mean_delay(kap, g * (1 + h), MOD, M.detection_z(kap, lng + np.log1p(h), MOD))
    dn, _ = M.mean_delay(kap, g * (1 - h), MOD, M.detection_z(kap, lng + np.log1p(-h), MOD))
    np.testing.assert_allclose(d, (up - dn) / (2 * h * kap * g), rtol=1e-4)


def test_variance_is_physics_jitter_plus_counting():
    d = np.linspace(0, 12, 13)
    np.testing.assert_allclose(M.tof_variance_us2(d, MOD),
                               jitter_sd_us(d, MOD) ** 2 + MOD.count_period_us**2 / 12)


@pytest.mark.parametrize("kind", ["point", "line"])
def test_to_frame_jacobian_and_line_sign(kind):
    local = np.array([1.2, 2.5, 0.7])
    ref = np.array([0.4, -2.0])
    out, cov, J = M.to_frame(kind, local, np.eye(3), ref)
    h = 1e-7
    num = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        a = M.to_frame(kind, local + d, np.eye(3), ref)[0]
        b = M.to_frame(kind, local - d, np.eye(3), ref)[0]
        diff = a - b
        if kind == "line":
            diff[1] = M.wrap_angle(diff[1])
        num[:, k] = diff / (2 * h)
    np.testing.assert_allclose(J, num, atol=1e-6)
    np.testing.assert_allclose(cov, J @ J.T)
    if kind == "line":
        assert out[0] >= 0
        # the wall contains the reflecting point seen from ref
        foot = ref + local[0] * np.array([np.cos(local[1]), np.sin(local[1])])
        assert foot @ np.array([np.cos(out[1]), np.sin(out[1])]) == pytest.approx(out[0])


def test_fast_detection_terms_match_reference():
    z = np.linspace(-30, 30, 601)
    log_p, dlogp, info, curv = M.noecho_terms(z)
    ref_lp, ref_mills, ref_info = M.probit_terms(z)
    np.testing.assert_allclose(log_p, ref_lp, rtol=1e-8, atol=2e-12)
    np.testing.assert_allclose(dlogp, ref_mills, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(info, ref_info, rtol=1e-6, atol=1e-10)
    # observed curvature: second derivative of -log Phi(z)
    h = 1e-4
    num = -(M.noecho_terms(z + h)[0] - 2 * log_p + M.noecho_terms(z - h)[0]) / h**2
    away = np.abs(np.abs(z) - 7.0) > 2 * h     # the exact/constant switch at |z| = 7
    np.testing.assert_allclose(curv[away], num[away], rtol=1e-3, atol=1e-5)
    et = M.echo_terms(1.0, np.exp(0.25 * z + np.log(MOD.detection_limit_us)), z, MOD)
    e_lp, e_mills, e_info = M.probit_terms(-z)
    np.testing.assert_allclose(et.log_p, e_lp, rtol=1e-8, atol=2e-12)
    np.testing.assert_allclose(-et.dlogp_dz, e_mills, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(et.info, e_info, rtol=1e-6, atol=1e-10)
    assert np.all(et.curv >= -1e-12) and np.all(curv >= -1e-12)


def test_piston_table_matches_bessel_functions():
    th = np.deg2rad(np.linspace(-60, 60, 4801))
    g, dg, lng = M.beam_delay_factor(th, "piston", MOD)
    ge, dge, lnge = M.piston_delay_factor_exact(th, MOD)
    main = np.abs(th) < np.deg2rad(13.0)          # main lobe: tight
    np.testing.assert_allclose(lng[main], lnge[main], rtol=0, atol=1e-7)
    np.testing.assert_allclose(dg[main], dge[main], rtol=1e-5, atol=1e-6)
    lobes = (np.abs(th) > np.deg2rad(15.0)) & (np.abs(th) < np.deg2rad(25.0))
    np.testing.assert_allclose(lng[lobes], lnge[lobes], rtol=0, atol=1e-4)


def test_waveform_delay_table_matches_monte_carlo():
    from sonarloc.physics.waveform import crossing_delay_us

    tab = M.waveform_delay_table(MOD)
    rng = np.random.default_rng(11)
    for u in (0.67, 4.0, 11.0):
        v = u / np.exp(MOD.amplitude_fluctuation * rng.standard_normal(400_000))
        w = crossing_delay_us(v, MOD)
        w = w[np.isfinite(w)]
        m, _, var = tab.lookup(np.array([u]))
        assert float(m[0]) == pytest.approx(w.mean(), rel=0.01, abs=0.01)
        assert float(np.sqrt(var[0])) == pytest.approx(w.std(), rel=0.03, abs=0.01)
    u = np.geomspace(0.01, 40.0, 4001)
    m, dm, _ = tab.lookup(u)
    np.testing.assert_allclose(dm[1:-1], np.gradient(m, u)[1:-1], rtol=2e-3, atol=1e-3)
    assert np.all(np.diff(m) >= -1e-9)          # later for weaker echoes


def test_waveform_delay_table_is_the_plain_kernel_sums():
    # the table is built in place to save temporaries: the same numbers, to the last
    # bit, as the kernel sums written out
    from sonarloc.physics.waveform import crossing_delay_us, waveform_template

    for params in (MOD, ModuleParams(amplitude_fluctuation=0.4, detection_limit_us=9.0)):
        tab = M.waveform_delay_table(params)
        s = M.sigma_a(params)
        peak = float(waveform_template(params).running_max[-1])
        span = np.log(peak / 1e-3)
        edges = np.unique(np.log(peak) - np.concatenate(
            [[span], np.geomspace(span, 1e-9, 2500), [0.0]]))
        y, dy = 0.5 * (edges[1:] + edges[:-1]), np.diff(edges)
        W = crossing_delay_us(np.exp(y), params)
        W = np.where(np.isfinite(W), W, 0.0)
        x = np.linspace(np.log(1e-3), np.log(params.detection_limit_us) + 6.0 * s, 512)
        a = (x[:, None] - y[None, :]) / s
        k = np.exp(-0.5 * a * a) * dy[None, :]
        dk = -a / s * k
        D, N, E2 = k.sum(1), (k * W).sum(1), (k * W * W).sum(1)
        Dp, Np = dk.sum(1), (dk * W).sum(1)
        mean = N / D
        np.testing.assert_array_equal(tab.mean, mean)
        np.testing.assert_array_equal(tab.dmean_dx, (Np * D - N * Dp) / (D * D))
        np.testing.assert_array_equal(tab.var, np.maximum(E2 / D - mean * mean, 0.0))
        assert (tab.x0, tab.dx) == (float(x[0]), float(x[1] - x[0]))


def test_log_sf32_matches_log_ndtr_everywhere():
    from scipy.special import log_ndtr

    z = np.concatenate([np.linspace(-40.0, 40.0, 400001), [0.0, -0.0, 1e-8, -1e-8]])
    z32 = z.astype(np.float32)
    got = M.log_sf32(z32)
    assert got.dtype == np.float32
    ref = log_ndtr(-z32.astype(float))
    err = np.abs(got.astype(float) - ref)
    # float32 rounding: absolute error below 5e-7 where |log Phi| < 1, relative beyond
    # (the tails, to |z| = 40: no underflow)
    assert np.all(err <= 5e-7 * np.maximum(np.abs(ref), 1.0))
    assert np.all(np.isfinite(got)) and np.all(got <= 0.0)


def test_log_sf32_coefficients_are_the_fit():
    # shipped as constants (the fit costs ~45 ms per process): they must be its result,
    # and the same float32 numbers the model uses
    fitted = M.fit_log_erfc_poly()
    np.testing.assert_allclose(M._LOG_ERFC_POLY, fitted, rtol=1e-9, atol=1e-15)
    assert np.array(M._LOG_ERFC_POLY32).tobytes() == np.float32(fitted).tobytes()
    assert len(M.fit_log_erfc_poly(M._SF_DEGREE - 1)) == len(fitted) - 1


def test_log_sf32_is_elementwise(rng):
    # the float32 model pass puts the echoes' and the no-echo readings' margins through
    # one call: each entry's value must not depend on the others (to the last bit)
    z = (rng.normal(size=(7, 23)) * 6.0).astype(np.float32)
    zn = (rng.normal(size=(7, 11)) * 6.0).astype(np.float32)
    both = M.log_sf32(np.concatenate([z, -zn], axis=1))
    assert both[:, :23].tobytes() == M.log_sf32(z).tobytes()
    assert both[:, 23:].tobytes() == M.log_sf32(-zn).tobytes()
    assert both[2:3, 5:9].tobytes() == M.log_sf32(z[2:3, 5:9].copy()).tobytes()


def test_truncation_ratio32_matches_exact_ratio():
    from scipy.special import log_ndtr

    from sonarloc.fit.lsq import _truncation_ratio32

    s = M.sigma_a(MOD)
    z = np.linspace(-12.0, 40.0, 50001)
    l0 = log_ndtr(-z)
    m = np.exp(-0.5 * z * z - 0.5 * np.log(2 * np.pi) - l0)
    r = _truncation_ratio32((m - z).astype(np.float32), m.astype(np.float32),
                            (m * (m - z)).astype(np.float32), s)
    exact = log_ndtr(-z - s) - l0
    assert np.abs(np.log(r.astype(float)) - exact).max() < 3e-6
    # the delay of a detected echo it gives: the float64 model's, to 3e-6 relative
    g = np.exp(0.25 * z[::100] + np.log(MOD.detection_limit_us))
    et = M.echo_terms(1.0, g, z[::100], MOD)
    mine = g * np.exp(0.5 * s * s) * r[::100].astype(float)
    np.testing.assert_allclose(mine, et.delay, rtol=3e-6)


def test_mills_ratio32_and_its_excess_hold_in_the_upper_tail():
    # m = phi(z) / Phi(-z) and m - z (whose product is the curvature of -log P(echo))
    # for every z a fit may visit: far beyond the detection limit m - z ~ 1/z is a small
    # difference, which the continued fraction keeps (as a float32 difference it is off
    # by ~100 % at z = 90)
    from scipy.special import erfcx

    z = np.concatenate([np.linspace(-12.0, 120.0, 132001), [M.Z_CF, np.nextafter(
        np.float32(M.Z_CF), np.float32(0.0))]]).astype(np.float32)
    m, h = M.mills_ratio32(z, M.log_sf32(z))
    assert m.dtype == h.dtype == np.float32
    zf = z.astype(float)
    exact = np.sqrt(2.0 / np.pi) / erfcx(zf / np.sqrt(2.0))                # m
    # (the exponent's float32 rounding: ~|z^2/2| 6e-8 of m)
    np.testing.assert_allclose(m, exact, rtol=1e-5)
    # the excess and the curvature: a float32 difference below Z_CF (to ~5e-5 of
    # itself just below), the continued fraction from there on (float64's m - z
    # cancels too beyond ~1e3, not here)
    far = zf >= M.Z_CF
    up = (zf > 0.0) & ~far
    np.testing.assert_allclose(h[up], (exact - zf)[up], rtol=6e-5)
    np.testing.assert_allclose(h[far], (exact - zf)[far], rtol=1e-6)
    curv = exact * (exact - zf)
    mid = (zf > -8.0) & ~far
    np.testing.assert_allclose((m * h)[mid], curv[mid], rtol=6e-5)
    np.testing.assert_allclose((m * h)[far], curv[far], rtol=2e-6)
    # the continued fraction alone
    np.testing.assert_allclose(M.mills_excess_cf32(z[far]), (exact - zf)[far], rtol=3e-7)


def test_truncated_slope32_far_beyond_the_detection_limit():
    # d mean delay / d kappa of a detected echo, float32 pass against float64, for
    # margins from inside the arc to far beyond the detection limit (where it is ~1/z^2
    # of the delay over kappa and the written-out form cancels in float32)
    from sonarloc.fit.lsq import _truncated_slope_far32, _truncation_ratio32

    s = M.sigma_a(MOD)
    z = np.linspace(-10.0, 110.0, 24001).astype(np.float32)
    lp = M.log_sf32(z)
    m, h = M.mills_ratio32(z, lp)
    dm = m * h
    ratio = _truncation_ratio32(h, m, dm, s)
    g = np.ones_like(z)
    scale = float(np.exp(0.5 * s * s))
    m1 = np.exp(z * np.float32(-s) - np.float32(0.5 * s * s)) * m
    jk = (ratio + (ratio * m - m1) * np.float32(1.0 / s)) * np.float32(scale)
    _truncated_slope_far32(jk, z, h, ratio, g, scale, s)
    et = M.echo_terms(1.0, np.ones(z.shape), z.astype(float), MOD)   # kappa g = 1
    # the written-out form's float32 error grows to 0.15 % just below Z_CF (as in the
    # float32 passes of pans since session 5); from there on the excess' difference
    # holds it to 1e-4 (the written-out form: 100 % at z = 80)
    near = z < M.Z_CF
    np.testing.assert_allclose(jk[near], et.ddelay_du[near], rtol=2e-3)
    np.testing.assert_allclose(jk[~near], et.ddelay_du[~near], rtol=1e-4)


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform"])
def test_mean_delay_is_echo_terms_delay(tier, rng):
    # the same numbers as echo_terms' delay fields, across the arc edge and beyond it
    # (the waveform tier's skips the detection terms: its table is truncated already)
    kap = rng.uniform(0.1, 3.0, (50, 1))
    g, _, lg = M.beam_delay_factor(rng.uniform(-0.6, 0.6, (50, 30)), tier, MOD,
                                   derivative=False)
    z = M.detection_z(kap, lg, MOD)
    assert z.min() < -7.0 and z.max() > 7.0
    et = M.echo_terms(kap, g, z, MOD, want_info=False, tier=tier)
    mean, d = M.mean_delay(kap, g, MOD, z, tier)
    np.testing.assert_array_equal(mean, et.delay)
    np.testing.assert_array_equal(d, et.ddelay_du)
    if tier != "waveform":      # and the truncation matters for the others
        assert not np.array_equal(mean, M.mean_delay(kap, g, MOD, None, tier)[0])
