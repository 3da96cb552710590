"""Beam patterns (piston, Gaussian) and the speed of sound."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import jn_zeros

from sonarloc.physics.beam import first_null_rad, gaussian_echo, piston_echo, piston_one_way
from sonarloc.physics.sound import range_from_tof_m, speed_of_sound_mps, tof_from_range_us


def test_first_null_near_14_deg() -> None:
    null = first_null_rad()
    assert np.rad2deg(null) == pytest.approx(14.0, abs=0.5)  # paper: asin(1.22 lambda/d)
    x1 = jn_zeros(1, 1)[0]  # 3.8317, first zero of J1
    wavelength = 343.0 / 49.4e3
    assert null == pytest.approx(np.arcsin(x1 * wavelength / (np.pi * 0.036)), rel=1e-12)
    assert float(piston_echo(null)) < 1e-12
    assert float(piston_echo(null - 0.01)) > 0 and float(piston_one_way(null + 0.01)) < 0


def test_first_null_moves_with_frequency_and_size() -> None:
    assert first_null_rad(freq_hz=60e3) < first_null_rad()
    assert first_null_rad(diameter_m=0.05) < first_null_rad()
    assert first_null_rad(diameter_m=0.005) == pytest.approx(np.pi / 2)  # no null


def test_side_lobe_near_18_deg_at_minus_35_db() -> None:
    th = np.deg2rad(np.linspace(14.5, 25.0, 2001))
    p = piston_echo(th)
    peak_deg = np.rad2deg(th[np.argmax(p)])
    assert 17.0 <= peak_deg <= 20.0
    assert 20 * np.log10(p.max()) == pytest.approx(-35.0, abs=0.5)


def test_gaussian_fits_main_lobe_only() -> None:
    centre = np.deg2rad(np.linspace(0, 5, 50))
    np.testing.assert_allclose(gaussian_echo(centre), piston_echo(centre), atol=0.05)
    assert float(gaussian_echo(np.deg2rad(5.25))) == pytest.approx(np.exp(-0.5))
    # beyond the null the Gaussian has no side lobes
    assert float(gaussian_echo(np.deg2rad(18.5))) < 0.2 * float(piston_echo(np.deg2rad(18.5)))


@pytest.mark.parametrize("shape", [(), (3,), (2, 5), (4, 1, 3)])
def test_patterns_broadcast(shape: tuple) -> None:
    th = np.deg2rad(np.random.default_rng(0).uniform(-30, 30, shape))
    for f in (piston_echo, piston_one_way, gaussian_echo):
        out = f(th)
        assert out.shape == shape
    assert np.all((piston_echo(th) >= 0) & (piston_echo(th) <= 1))
    np.testing.assert_allclose(piston_echo(th), piston_echo(-th))


@pytest.mark.parametrize(("call", "needle"), [
    (lambda: piston_echo(0.1, diameter_m=-0.036), "`diameter_m` must be positive, got -0.036"),
    (lambda: piston_echo(0.1, freq_hz=0.0), "`freq_hz` must be positive, got 0.0"),
    (lambda: gaussian_echo(0.1, sigma_deg=float("nan")), "`sigma_deg` must be positive, got nan"),
    (lambda: first_null_rad(c_mps=-343.0), "`c_mps` must be positive, got -343.0"),
])
def test_beam_errors_name_the_value(call, needle: str) -> None:
    with pytest.raises(ValueError) as err:
        call()
    assert needle in str(err.value)


def test_speed_of_sound_from_temperature() -> None:
    assert float(speed_of_sound_mps(0.0)) == pytest.approx(331.3)
    assert float(speed_of_sound_mps(19.8)) == pytest.approx(343.3, abs=0.01)
    c = speed_of_sound_mps(np.array([[-10.0, 0.0], [20.0, 35.0]]))
    assert c.shape == (2, 2)
    assert np.all(np.diff(c.ravel()) > 0)
    # 1.5 m: 10 degC colder air delays the echo by 157 us (1.8 %, 27 mm of range)
    to_warm = tof_from_range_us(1.5, float(speed_of_sound_mps(20.0)))
    to_cold = tof_from_range_us(1.5, float(speed_of_sound_mps(10.0)))
    assert to_cold - to_warm == pytest.approx(156.9, abs=0.1)


@pytest.mark.parametrize("bad", [-60.0, 70.0, float("nan")])
def test_speed_of_sound_rejects_bad_temperature(bad: float) -> None:
    with pytest.raises(ValueError, match="temperature_c") as err:
        speed_of_sound_mps(bad)
    assert repr(bad) in str(err.value)


def test_range_tof_round_trip() -> None:
    r = np.array([0.2, 1.46, 1.5, 10.0])
    np.testing.assert_allclose(range_from_tof_m(tof_from_range_us(r)), r)
    # the paper's fits: To 8522/8746/8580 us -> 1.462/1.500/1.471 m
    np.testing.assert_allclose(range_from_tof_m([8522, 8746, 8580]), [1.462, 1.500, 1.471],
                               atol=0.0005)
