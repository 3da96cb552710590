"""Eq. 3, the module's limits (first echo wins, blanking, range gate, counting), parameters."""

from __future__ import annotations

import numpy as np
import pytest

from sonarloc.physics.tof import (
    ModuleParams,
    apply_module,
    eq3_tof_us,
    jitter_sd_us,
    quantize_tof_us,
    sample_echo_delay_us,
    threshold_delay_us,
)


def test_eq3_paper_values() -> None:
    # the paper's fits: Tm0 = To + kappa on the axis
    assert float(eq3_tof_us(8522.0, 0.0, 0.67)) == pytest.approx(8522.67)
    sigma = np.deg2rad(5.25)
    assert float(eq3_tof_us(8580.0, sigma, 2.68)) == pytest.approx(8580 + 2.68 * np.exp(0.5))
    out = eq3_tof_us(np.array([[8500.0], [8600.0]]), np.array([0.0, 0.1, 0.2]), 0.15)
    assert out.shape == (2, 3)


def test_threshold_delay_and_detection_limit() -> None:
    np.testing.assert_allclose(threshold_delay_us(0.67, [1.0, 0.5, 0.0]), [0.67, 1.34, np.inf])
    rng = np.random.default_rng(0)
    params = ModuleParams(amplitude_fluctuation=0.0)
    d = sample_echo_delay_us(0.67, np.array([1.0, 0.67 / 12.0, 0.67 / 12.1]), rng, params)
    assert d[0] == pytest.approx(0.67) and d[1] == pytest.approx(12.0) and np.isnan(d[2])


def test_jitter_model_grows_off_axis() -> None:
    sd = jitter_sd_us(np.array([0.0, 0.67, 12.0]))
    assert sd[0] == pytest.approx(5.0)
    assert sd[2] == pytest.approx(np.hypot(5.0, 3.0))
    assert np.all(np.diff(sd) > 0)


def test_quantize_first_count_after_crossing() -> None:
    np.testing.assert_array_equal(quantize_tof_us([0.0, 0.1, 1.99, 2.0, np.nan]),
                                  [2.0, 2.0, 2.0, 4.0, np.nan])
    assert float(quantize_tof_us(8523.3, 1.0)) == 8524.0


def test_first_echo_wins() -> None:
    params = ModuleParams(jitter_sd_us=0.0)
    tm = np.array([[9000.0, 8600.0, np.nan], [np.nan, np.nan, np.nan]])
    out = apply_module(tm, np.random.default_rng(0), params)
    assert out[0] == 8602.0 and np.isnan(out[1])
    # candidates along another axis
    out0 = apply_module(tm.T, np.random.default_rng(0), params, axis=0)
    np.testing.assert_array_equal(out0, out)


def test_blanking_and_range_gate() -> None:
    params = ModuleParams(jitter_sd_us=0.0, blanking_us=900.0, max_range_m=5.0)
    tm = np.array([[500.0], [1000.0], [params.max_tof_us - 10.0], [params.max_tof_us + 10.0]])
    out = apply_module(tm, np.random.default_rng(0), params)
    assert np.isnan(out[0]) and np.isfinite(out[1]) and np.isfinite(out[2]) and np.isnan(out[3])
    assert params.max_tof_us == pytest.approx(2 * 5.0 / 343.0 * 1e6)


@pytest.mark.parametrize("shape", [(5,), (3, 4), (2, 3, 1)])
def test_apply_module_shapes(shape: tuple) -> None:
    tm = np.full(shape + (3,), 8700.0)
    out = apply_module(tm, np.random.default_rng(0))
    assert out.shape == shape
    assert apply_module(np.empty(shape + (0,)), np.random.default_rng(0)).shape == shape


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"c_mps": -343.0}, "`c_mps` must be positive, got -343.0"),
    ({"sigma_deg": 0.0}, "`sigma_deg` must be positive, got 0.0"),
    ({"jitter_sd_us": -5.0}, "`jitter_sd_us` must be non-negative, got -5.0"),
    ({"amplitude_fluctuation": float("nan")}, "`amplitude_fluctuation` must be non-negative"),
    ({"burst_cycles": 0}, "`burst_cycles` must be a positive integer, got 0"),
    ({"burst_cycles": 16.5}, "got 16.5"),
    ({"transducer_q": -1.0}, "`transducer_q` must be positive, got -1.0"),
    ({"resonant_fraction": 1.0}, "`resonant_fraction` must be in [0, 1), got 1.0"),
])
def test_module_params_errors_name_the_value(kwargs: dict, needle: str) -> None:
    with pytest.raises(ValueError) as err:
        ModuleParams(**kwargs)
    assert needle in str(err.value)


def test_module_params_hashable_and_frozen() -> None:
    a, b = ModuleParams(), ModuleParams()
    assert a == b and hash(a) == hash(b)
    with pytest.raises(AttributeError):
        a.c_mps = 300.0  # type: ignore[misc]
