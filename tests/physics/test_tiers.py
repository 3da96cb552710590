"""Model tiers: gauss / piston / waveform / auto, the auto rule and its record."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.physics.beam import gaussian_echo, piston_echo
from sonarloc.physics.tiers import (
    GAUSS_TOLERANCE_US,
    WAVEFORM_TOLERANCE_US,
    Tier,
    auto_tables,
    echo_delays_us,
    gauss_valid_rad,
    max_detection_angle_rad,
)
from sonarloc.physics.tof import ModuleParams


def test_tier_parse_and_label() -> None:
    assert Tier.parse("Waveform") is Tier.WAVEFORM
    assert Tier.parse(Tier.AUTO) is Tier.AUTO
    assert [t.label for t in Tier] == ["gauss", "piston", "waveform", "auto"]
    with pytest.raises(ValueError, match="'exact'"):
        Tier.parse("exact")


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform"])
def test_fixed_tiers_record_themselves(tier: str) -> None:
    theta = np.deg2rad(np.linspace(-30, 30, 101))
    _, used = echo_delays_us(theta, 0.67, tier, np.random.default_rng(0))
    assert np.all(used == Tier.parse(tier))


def test_same_seed_same_gain_in_every_tier() -> None:
    """On the axis all tiers agree (the waveform within 0.11 us): one gain draw per echo."""
    theta = np.zeros(1000)
    out = {t: echo_delays_us(theta, 0.67, t, np.random.default_rng(9))[0]
           for t in ("gauss", "piston", "waveform", "auto")}
    np.testing.assert_array_equal(out["gauss"], out["piston"])
    np.testing.assert_allclose(out["waveform"], out["piston"], atol=0.11)
    np.testing.assert_array_equal(out["auto"], out["gauss"])


def test_gauss_valid_region() -> None:
    deg = np.rad2deg(gauss_valid_rad(np.array([0.01, 0.15, 0.67, 2.68, 10.0])))
    assert np.all(np.diff(deg) < 0)  # weaker reflectors: narrower valid region
    assert deg[0] < 13.7  # never past the piston's first null
    for kappa, lim in zip([0.01, 0.15, 0.67, 2.68, 10.0], np.deg2rad(deg), strict=True):
        th = np.linspace(0.0, lim, 500)
        err = kappa * np.abs(1 / gaussian_echo(th) - 1 / piston_echo(th))
        assert err.max() <= GAUSS_TOLERANCE_US
        beyond = lim + np.deg2rad(0.05)
        assert kappa * abs(1 / gaussian_echo(beyond) - 1 / piston_echo(beyond)) > \
            GAUSS_TOLERANCE_US * 0.9


def _auto_vs_waveform(theta: np.ndarray, kappa: np.ndarray, seed: int) -> tuple:
    da, ua = echo_delays_us(theta, kappa, "auto", np.random.default_rng(seed))
    dw, _ = echo_delays_us(theta, kappa, "waveform", np.random.default_rng(seed))
    return da, ua, dw


def test_auto_within_tolerance_of_full_model() -> None:
    """auto never differs from the most complete model (waveform) by more than the
    sum of its two tolerances, and detects exactly the same echoes."""
    rng = np.random.default_rng(5)
    theta = rng.uniform(-np.pi / 2, np.pi / 2, 200_000)
    kappa = np.exp(rng.uniform(np.log(0.01), np.log(30.0), theta.size))
    da, ua, dw = _auto_vs_waveform(theta, kappa, 3)
    np.testing.assert_array_equal(np.isnan(da), np.isnan(dw))
    ok = ~np.isnan(da)
    assert np.max(np.abs(da[ok] - dw[ok])) <= GAUSS_TOLERANCE_US + WAVEFORM_TOLERANCE_US
    exact = ok & (ua == Tier.WAVEFORM)
    np.testing.assert_array_equal(da[exact], dw[exact])
    assert set(np.unique(ua)) == {Tier.GAUSS, Tier.PISTON, Tier.WAVEFORM}


@settings(max_examples=80, deadline=None)
@given(theta_deg=st.floats(-90, 90), kappa=st.floats(0.005, 50.0), seed=st.integers(0, 2**32 - 1))
def test_auto_matches_full_model_property(theta_deg: float, kappa: float, seed: int) -> None:
    da, _, dw = _auto_vs_waveform(np.full(8, np.deg2rad(theta_deg)), np.full(8, kappa), seed)
    assert np.array_equal(np.isnan(da), np.isnan(dw))
    ok = ~np.isnan(da)
    assert np.all(np.abs(da[ok] - dw[ok]) <= GAUSS_TOLERANCE_US + WAVEFORM_TOLERANCE_US)


def test_auto_picks_the_expected_tier() -> None:
    params = ModuleParams(amplitude_fluctuation=0.0)
    u_w = auto_tables(params).waveform_from_us
    rng = np.random.default_rng(0)
    cases = [
        (0.0, 0.67, Tier.GAUSS),     # on the axis: Gaussian
        (5.0, 0.67, Tier.GAUSS),     # inside the main lobe
        (10.5, 0.15, Tier.PISTON),   # plane near the null: Gaussian wrong, delay still small
        (20.0, 0.005, Tier.PISTON),  # very strong reflector in the side lobe, small delay
        (18.5, 0.15, Tier.WAVEFORM),  # plane side lobe: weak echo, waveform changes answer
        (10.0, 0.67, Tier.WAVEFORM),  # pole near its arc edge
        (40.0, 0.67, Tier.GAUSS),    # undetectable in every tier: cheapest says "no echo"
    ]
    for deg, kappa, expect in cases:
        delay, used = echo_delays_us(np.deg2rad(deg), kappa, "auto", rng, params)
        assert Tier(int(used)) is expect, (deg, kappa)
        u = kappa / piston_echo(np.deg2rad(deg))
        if expect is Tier.WAVEFORM:
            assert u > u_w
        if deg == 40.0:
            assert np.isnan(delay)


def test_auto_uses_waveform_only_for_weak_echoes(paper_scans) -> None:
    """Default-tier pole scan: waveform readings are off axis and late."""
    sc = paper_scans["pole"]
    wave = sc.tier == Tier.WAVEFORM
    assert wave.any() and (sc.tier == Tier.GAUSS).any()
    theta = np.broadcast_to(sc.theta_deg[:, None], sc.tier.shape)
    assert np.min(np.abs(theta[wave])) > 4.0
    assert np.nanmin(sc.delay_us[wave]) > 3.0
    assert np.nanmax(sc.delay_us[sc.tier == Tier.GAUSS]) < 3.4


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform", "auto"])
@pytest.mark.parametrize(("theta_shape", "kappa_shape"), [
    ((), ()), ((7,), ()), ((7,), (7,)), ((3, 4), (4,)), ((2, 1, 5), (3, 1)), ((0,), ()),
])
def test_batch_shapes_broadcast(tier: str, theta_shape: tuple, kappa_shape: tuple) -> None:
    rng = np.random.default_rng(1)
    theta = np.deg2rad(rng.uniform(-20, 20, theta_shape))
    kappa = rng.uniform(0.1, 3.0, kappa_shape)
    delay, used = echo_delays_us(theta, kappa, tier, np.random.default_rng(2))
    shape = np.broadcast_shapes(np.shape(theta), np.shape(kappa))
    assert delay.shape == shape and used.shape == shape
    assert used.dtype == np.int8
    # element-wise identical to the flat computation with the same draws
    flat, _ = echo_delays_us(np.broadcast_to(theta, shape).ravel(),
                             np.broadcast_to(kappa, shape).ravel(), tier,
                             np.random.default_rng(2))
    np.testing.assert_array_equal(delay.ravel(), flat)


def test_max_detection_angle() -> None:
    deg = np.rad2deg(max_detection_angle_rad(np.array([0.15, 0.67, 2.68, 100.0]), gain_sd=0.0))
    # noise-free: the plane reaches into its side lobe (-38 dB at 20.6 deg)
    assert deg[0] == pytest.approx(20.6, abs=0.1)
    assert 10.5 < deg[1] < 15.0 and 8.0 < deg[2] < deg[1]
    assert deg[3] == 0.0
    rng = np.random.default_rng(3)
    theta = rng.uniform(-np.pi / 2, np.pi / 2, 100_000)
    for kappa, lim in zip([0.15, 0.67, 2.68], max_detection_angle_rad([0.15, 0.67, 2.68]),
                          strict=True):
        for tier in ("gauss", "piston", "waveform", "auto"):
            d, _ = echo_delays_us(theta, kappa, tier, rng)
            assert np.all(np.abs(theta[~np.isnan(d)]) <= lim)


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"theta_rad": [0.0, np.nan], "kappa_us": 0.67}, "nan at index (1,)"),
    ({"theta_rad": 0.0, "kappa_us": -0.5}, "-0.5"),
    ({"theta_rad": [0.0, 0.1], "kappa_us": [0.67, 0.0]}, "0.0 at index (1,)"),
    ({"theta_rad": 0.0, "kappa_us": np.inf}, "inf"),
])
def test_bad_arguments_name_the_value(kwargs: dict, needle: str) -> None:
    with pytest.raises(ValueError, match="theta_rad|kappa_us") as err:
        echo_delays_us(tier="auto", rng=np.random.default_rng(0), **kwargs)
    assert needle in str(err.value)
    with pytest.raises(ValueError, match="-1.0"):
        gauss_valid_rad(-1.0)
    with pytest.raises(ValueError, match="gain_sd"):
        max_detection_angle_rad(0.67, gain_sd=-1.0)


def test_tabulated_piston_matches_exact() -> None:
    from sonarloc.physics.tiers import tabulated_piston_echo

    theta = np.random.default_rng(6).uniform(-np.pi, np.pi, 200_000)
    np.testing.assert_allclose(tabulated_piston_echo(theta), piston_echo(theta), atol=2e-7)
    assert float(tabulated_piston_echo(0.0)) == 1.0
    assert tabulated_piston_echo(np.zeros((2, 3))).shape == (2, 3)


@pytest.mark.parametrize("tier", ["gauss", "piston", "waveform", "auto"])
def test_delay_moments_match_monte_carlo(tier: str) -> None:
    from sonarloc.physics.tiers import delay_moments_us

    theta = np.deg2rad(np.array([0.0, 4.0, 8.0, 9.0, 10.5, 18.5]))
    kappa = np.array([2.68, 0.67, 0.67, 2.68, 0.67, 0.15])
    m = delay_moments_us(theta, kappa, tier)
    n = 40_000
    d, _ = echo_delays_us(np.repeat(theta[:, None], n, 1), kappa[:, None], tier,
                          np.random.default_rng(8))
    det = ~np.isnan(d)
    p_mc = det.mean(axis=1)
    np.testing.assert_allclose(m.p_detect, p_mc, atol=0.01)
    for j in np.flatnonzero(p_mc > 0.05):
        x = d[j][det[j]]
        se = x.std() / np.sqrt(x.size)
        assert m.mean_us[j] == pytest.approx(x.mean(), abs=5 * se + 0.05)
        assert m.sd_us[j] == pytest.approx(x.std(), rel=0.05, abs=0.05)


def test_delay_moments_noise_free_and_errors() -> None:
    from sonarloc.physics.tiers import delay_moments_us

    params = ModuleParams(amplitude_fluctuation=0.0)
    m = delay_moments_us(np.deg2rad([0.0, 30.0]), 0.67, "piston", params)
    np.testing.assert_allclose(m.p_detect, [1.0, 0.0])
    assert m.mean_us[0] == pytest.approx(0.67, abs=1e-6) and m.sd_us[0] == 0.0
    assert np.isnan(m.mean_us[1])
    with pytest.raises(ValueError, match="`n_nodes` must be an integer >= 3, got 2"):
        delay_moments_us(0.0, 0.67, n_nodes=2)
