"""Waveform tier: the simulated ranging module and what it adds to eq. 3."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.physics.beam import piston_echo
from sonarloc.physics.tiers import echo_delays_us
from sonarloc.physics.tof import ModuleParams
from sonarloc.physics.waveform import (
    crossing_delay_us,
    eq3_agreement_limit_us,
    processed_echo,
    waveform_delay_us,
    waveform_template,
)

HALF_PERIOD_US = 1e6 / 49.4e3 / 2  # 10.12 us


def test_template_calibrated_to_detection_limit() -> None:
    tpl = waveform_template()
    assert tpl.peak_us == pytest.approx(12.0, abs=1e-9)
    assert tpl.half_period_us == pytest.approx(HALF_PERIOD_US)
    assert tpl.burst_us == pytest.approx(16 / 49.4e3 * 1e6)  # 323.9 us
    assert 5.0 < tpl.integrator_tau_us < 15.0
    # the processed signal peaks inside the burst and decays after it
    t_peak = tpl.t_us[np.argmax(tpl.processed)]
    assert 0.5 * tpl.burst_us < t_peak <= tpl.burst_us + 1.0
    assert tpl.processed[-1] < 0.01 * tpl.peak_us
    # a different limit gives a different leak, same peak
    tpl9 = waveform_template(ModuleParams(detection_limit_us=9.0))
    assert tpl9.peak_us == pytest.approx(9.0)
    assert tpl9.integrator_tau_us < tpl.integrator_tau_us


def test_processed_echo_starts_as_eq3_ramp_and_scales_with_amplitude() -> None:
    t = np.array([0.1, 0.5, 1.0])
    np.testing.assert_allclose(processed_echo(t, 1.0), t, rtol=0.07)
    np.testing.assert_allclose(processed_echo(t, 0.3), 0.3 * processed_echo(t, 1.0))
    assert float(processed_echo(-1.0, 1.0)) == 0.0


@pytest.mark.parametrize("kappa_us", [0.05, 0.15, 0.67, 1.5, 2.68])
def test_waveform_equals_eq3_on_axis(kappa_us: float) -> None:
    assert float(waveform_delay_us(kappa_us, 1.0)) == pytest.approx(kappa_us, abs=0.11)


def test_agreement_with_eq3_ends_at_first_ripple_crest() -> None:
    u_w = eq3_agreement_limit_us()
    assert 3.0 < u_w < 4.0
    u = np.linspace(0.01, u_w, 2000)
    assert np.max(np.abs(crossing_delay_us(u) - u)) <= 0.5
    # just beyond: the crossing has moved on to the next half cycle
    assert float(crossing_delay_us(u_w + 0.2)) > u_w + 0.2 + 2.0


def test_half_period_jumps_as_amplitude_falls() -> None:
    """Ripple: a slight fall in amplitude moves the crossing to the next half cycle."""
    # threshold delay kappa/a, rising as a falls; dense near the detection limit (12 us)
    u = np.concatenate([np.linspace(0.0, 11.9, 400_001), 12.0 - np.geomspace(0.1, 1e-6, 400_001)])
    t = crossing_delay_us(u)
    steps = np.diff(t)
    jumps = steps[steps > 1.0]
    assert jumps.size >= 8
    # jumps grow towards one half period as the processed signal flattens
    assert np.all(np.diff(jumps) > 0)
    assert jumps[0] > 2.0
    np.testing.assert_allclose(jumps[-4:], HALF_PERIOD_US, rtol=0.02)
    assert np.all(jumps < HALF_PERIOD_US + 0.1)


def test_half_period_jumps_visible_in_a_pole_scan() -> None:
    params = ModuleParams(amplitude_fluctuation=0.0)
    theta = np.deg2rad(np.arange(0.0, 12.0, 0.01))
    delay, _ = echo_delays_us(theta, 0.67, "waveform", np.random.default_rng(0), params)
    d = delay[~np.isnan(delay)]
    steps = np.diff(d)
    assert np.all(steps >= -1e-9)  # monotone away from the axis
    big = steps[steps > 2.0]
    assert big.size >= 2
    assert np.any(np.abs(big - HALF_PERIOD_US) < 1.5)


@pytest.mark.parametrize("u", [4.0, 6.0, 8.0, 10.0, 11.0, 11.9])
def test_weak_echoes_later_than_eq3(u: float) -> None:
    assert float(crossing_delay_us(u)) > u + 3.0


def test_lateness_grows_towards_detection_limit() -> None:
    u = np.array([2.0, 5.0, 9.0, 11.5, 11.95])
    late = crossing_delay_us(u) - u
    assert np.all(np.diff(late) > 0)
    assert late[-1] > 40.0  # the weakest echoes cross deep into the echo


def test_detection_same_as_eq3() -> None:
    u = np.array([11.99, 12.0, 12.01, 50.0, np.inf, np.nan])
    t = crossing_delay_us(u)
    assert np.all(np.isfinite(t[:2]))
    assert np.all(np.isnan(t[2:]))


def test_side_lobes_of_strong_reflector() -> None:
    params = ModuleParams(amplitude_fluctuation=0.0)
    theta = np.deg2rad(18.5)  # peak of the first side lobe (-35 dB)
    assert float(piston_echo(theta)) == pytest.approx(10 ** (-35.1 / 20), rel=0.02)
    plane, _ = echo_delays_us(theta, 0.15, "waveform", np.random.default_rng(0), params)
    pole, _ = echo_delays_us(theta, 0.67, "waveform", np.random.default_rng(0), params)
    assert float(plane) > 15.0  # detected, late
    assert np.isnan(pole)


def test_off_axis_jitter_grows_faster_than_eq3() -> None:
    """Amplitude fluctuation turns into more timing spread on the flatter slope."""
    rng = np.random.default_rng(2)
    gain = np.exp(0.25 * rng.standard_normal(20000))
    for u in (1.0, 8.0):
        wave = crossing_delay_us(u / gain)
        eq3 = np.where(u / gain <= 12.0, u / gain, np.nan)
        ok = ~np.isnan(wave) & ~np.isnan(eq3)
        sd_w, sd_e = np.std(wave[ok]), np.std(eq3[ok])
        if u == 1.0:
            assert sd_w == pytest.approx(sd_e, rel=0.1)
            near = sd_w
        else:
            assert sd_w > 2.0 * sd_e
            assert sd_w > 10.0 * near


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 12.0), min_size=2, max_size=40))
def test_crossing_monotone_in_threshold(us: list[float]) -> None:
    u = np.sort(np.asarray(us))
    t = crossing_delay_us(u)
    assert np.all(np.diff(t) >= -1e-9)
    assert np.all(t >= u - 0.11)  # never meaningfully earlier than eq. 3


def test_table_lookup_matches_template_search() -> None:
    tpl = waveform_template()
    u = np.random.default_rng(4).uniform(0.0, 12.0, 5000)
    t = crossing_delay_us(u)
    # direct definition: first sample where the processed signal reaches u
    idx = np.searchsorted(tpl.running_max, u)
    np.testing.assert_allclose(t, idx * tpl.dt_us, atol=tpl.dt_us + 0.01)


def _drive(p: ModuleParams, n: int) -> tuple[float, np.ndarray]:
    """Sample spacing [us] and the first ``n`` samples of the unit burst."""
    dt_us = 1e6 / (p.carrier_hz * 1000)
    t_us = np.arange(n) * dt_us
    omega = 2 * np.pi * p.carrier_hz
    return dt_us, np.where(t_us < p.burst_cycles * 1e6 / p.carrier_hz,
                           np.cos(omega * t_us * 1e-6), 0.0)


def test_cached_band_passed_echo_is_the_direct_computation() -> None:
    # the calibration reuses one band-passed echo of a power-of-two length for every
    # leak it tries; a causal filter gives the same first n samples to the last bit
    from sonarloc.physics import waveform as W

    p = ModuleParams()
    omega = 2 * np.pi * p.carrier_hz
    q, b = p.transducer_q, p.resonant_fraction
    peaks = []
    for tau in (1.0, 60.0):
        dt_us, w = W._processed_unit_echo(tau, p.carrier_hz, p.burst_cycles, q, b)
        n = w.size
        _, drive = _drive(p, n)
        rect = np.abs((1 - b) * drive + b * W._bandpass(drive, omega, q, 1e6 / dt_us)) / (1 - b)
        decay = np.exp(-dt_us / tau)
        want = np.zeros(n)
        want[1:] = W._one_pole(0.5 * dt_us * (rect[1:] + decay * rect[:-1]), float(decay))
        np.testing.assert_array_equal(w, want)
        peaks.append(w.max())
    assert peaks[0] < peaks[1]      # the peak grows with the leak's time constant


@pytest.mark.parametrize("pole", [np.exp(-20.0), -0.5, 0.5, 0.99, 0.9999,
                                  0.997 * np.exp(0.0054j), 0.9 * np.exp(2.5j)])
@pytest.mark.parametrize("n", [1, 2, 3, 1000, 4097])
def test_one_pole_is_scipy_lfilter(pole: complex, n: int) -> None:
    from scipy import signal  # the oracle (the package does not import it)

    from sonarloc.physics.waveform import _one_pole

    x = np.random.default_rng(n).normal(size=n) + 0.3
    got = _one_pole(x, pole)
    want = signal.lfilter([1.0], [1.0, -pole], x)
    assert got.dtype == want.dtype
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.max(np.abs(want)))


@pytest.mark.parametrize("q", [0.3, 0.5, 1.0, 5.0, 40.0])
def test_bandpass_is_scipy_bilinear_lfilter(q: float) -> None:
    # at 20 samples per period the polynomial form is well conditioned: scipy's
    # bilinear + lfilter and the exact poles agree to rounding
    from scipy import signal

    from sonarloc.physics.waveform import _bandpass

    omega, fs = 2 * np.pi * 49.4e3, 20 * 49.4e3
    t = np.arange(3000) / fs
    x = np.where(t < 16 / 49.4e3, np.cos(omega * t), 0.0)
    x[::7] += np.random.default_rng(3).normal(size=x[::7].size)   # not only a burst
    num, den = signal.bilinear([omega / q, 0.0], [1.0, omega / q, omega * omega], fs=fs)
    want = signal.lfilter(num, den, x)
    np.testing.assert_allclose(_bandpass(x, omega, q, fs), want, rtol=0,
                               atol=1e-12 * np.max(np.abs(want)))


def _bandpass_40_digits(x: np.ndarray, omega: float, q: float, fs: float) -> np.ndarray:
    """The bilinear band-pass's recursion in 40-digit decimal arithmetic."""
    from decimal import Decimal, localcontext

    with localcontext() as ctx:
        ctx.prec = 40
        k, w = 2 * Decimal(fs), Decimal(omega)
        bw = w / Decimal(q)
        a0 = k * k + bw * k + w * w
        g, a1, a2 = bw * k / a0, 2 * (w * w - k * k) / a0, (k * k - bw * k + w * w) / a0
        y1 = y2 = x1 = x2 = Decimal(0)
        out = []
        for xn in map(Decimal, x.tolist()):
            yn = g * (xn - x2) - a1 * y1 - a2 * y2
            out.append(float(yn))
            y2, y1, x2, x1 = y1, yn, x1, xn
    return np.array(out)


@pytest.mark.parametrize("q", [0.5, 1.0, 5.0])
def test_bandpass_at_template_rate_is_the_exact_filter(q: float) -> None:
    # at 1000 samples per period the poles lie within 0.005 of z = 1: rounding the
    # polynomial coefficients (scipy.signal.bilinear) moves lfilter's output by up to
    # ~6e-11 of its size (q = 5); the exact poles stay at rounding level of the
    # 40-digit recursion
    from scipy import signal

    from sonarloc.physics.waveform import _bandpass

    p = ModuleParams(transducer_q=q)
    omega = 2 * np.pi * p.carrier_hz
    dt_us, x = _drive(p, 20000)
    fs = 1e6 / dt_us
    got = _bandpass(x, omega, q, fs)
    exact = _bandpass_40_digits(x, omega, q, fs)
    scale = np.max(np.abs(exact))
    assert np.max(np.abs(got - exact)) < 1e-12 * scale
    num, den = signal.bilinear([omega / q, 0.0], [1.0, omega / q, omega * omega], fs=fs)
    assert np.max(np.abs(got - signal.lfilter(num, den, x))) < 1e-10 * scale


@pytest.mark.parametrize("limit_us", [12.0, 10.0, 9.85, 12.5])
@pytest.mark.parametrize("q", [0.5, 1.0, 3.0])
def test_template_peak_is_the_detection_limit_exactly(limit_us: float, q: float) -> None:
    # an echo at the limit is detected in every tier: the scaled template's peak must
    # not round below (or above) it (scaling alone rounds it off for (12, 3), (10, 0.5),
    # (12.5, 1), ...; at (9.85, 1) five samples of the flat top round above it)
    tpl = waveform_template(ModuleParams(detection_limit_us=limit_us, transducer_q=q))
    assert tpl.peak_us == limit_us
    assert tpl.processed.max() == limit_us
    assert np.isfinite(crossing_delay_us(limit_us, ModuleParams(detection_limit_us=limit_us,
                                                                transducer_q=q)))


def test_stored_leaks_are_the_calibration() -> None:
    from sonarloc.physics import waveform as W

    for key, tau in W._STORED_LEAKS_US.items():
        # the root finder's tolerance (its last digits may differ on another platform;
        # here the stored value is its result to the last bit)
        assert W._calibrate_leak(*key) == pytest.approx(tau, rel=0, abs=1e-9)
    p = ModuleParams()
    key = (p.carrier_hz, p.burst_cycles, p.transducer_q, p.resonant_fraction,
           p.detection_limit_us)
    assert key in W._STORED_LEAKS_US            # the default module's is stored


def test_default_template_needs_no_calibration(monkeypatch: pytest.MonkeyPatch) -> None:
    from sonarloc.physics import waveform as W

    def fail(*args: object) -> float:
        raise AssertionError(f"calibrated {args}")

    monkeypatch.setattr(W, "_calibrate_leak", fail)
    W._template.cache_clear()
    try:
        tpl = W.waveform_template()
        assert tpl.peak_us == 12.0
        with pytest.raises(AssertionError, match="calibrated"):
            W.waveform_template(ModuleParams(detection_limit_us=11.0))
    finally:
        W._template.cache_clear()
