"""Reflector kinds, default strengths and the cylinder radius rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.physics import ModuleParams, constants
from sonarloc.physics.reflectors import (
    EDGE_MAX_RANGE_M,
    Reflector,
    ReflectorKind,
    cylinder_kappa_us,
    cylinder_rule_constants,
    default_kappa_us,
    kappa_at_range_us,
    make_reflector,
    max_range_m,
)


def test_paper_defaults() -> None:
    assert default_kappa_us("plane") == 0.15
    assert default_kappa_us("wall") == 0.15
    assert default_kappa_us("corner") == 0.15  # corners act like planes
    assert default_kappa_us("pole") == 0.67
    assert default_kappa_us("rod") == 2.68
    assert default_kappa_us("edge") == 2.68
    for kind, kappa in constants.KAPPA_US.items():  # the lead's table agrees
        assert default_kappa_us(kind) == kappa


def test_cylinder_rule_reproduces_pole_and_rod() -> None:
    np.testing.assert_allclose(cylinder_kappa_us([0.0445, 0.004]), [0.67, 2.68], rtol=1e-9)
    assert default_kappa_us("pole", 0.0445) == pytest.approx(0.67)
    assert default_kappa_us("rod", radius_m=0.004) == pytest.approx(2.68)
    # the paper's levels: plane 13 dB above the pole, pole 12 dB above the rod
    assert 20 * np.log10(2.68 / 0.67) == pytest.approx(12.0, abs=0.1)


@pytest.mark.parametrize("params", [ModuleParams(), ModuleParams(c_mps=300.0),
                                    ModuleParams(carrier_hz=60e3, c_mps=360.0)])
def test_cylinder_rule_constants_solve_the_rule(params: ModuleParams) -> None:
    # the closed form reproduces the paper's pole and rod for every module, and is the
    # root a root finder gives (the oracle)
    from scipy import optimize

    np.testing.assert_allclose(cylinder_kappa_us([0.0445, 0.004], params=params),
                               [0.67, 2.68], rtol=1e-14)
    k = 2 * math.pi * params.carrier_hz / params.c_mps

    def ratio(c: float) -> float:
        f = np.sqrt((k * np.array([0.0445, 0.004])) ** 3
                    / ((k * np.array([0.0445, 0.004])) ** 3 + c ** 3))
        return math.sqrt(1.504 / 0.004) / math.sqrt(1.5445 / 0.0445) * f[0] / f[1] - 4.0

    root = optimize.brentq(ratio, 1e-6, 1e3, xtol=1e-14, rtol=1e-15)
    assert cylinder_rule_constants(params)[1] == pytest.approx(root, rel=1e-13)


def test_cylinder_rule_limits() -> None:
    kappa_inf, c = cylinder_rule_constants()
    assert 0.1 < kappa_inf < 0.15 and 2.0 < c < 4.0
    a = np.geomspace(5e-4, 5.0, 200)
    kap = cylinder_kappa_us(a)
    assert np.all(np.diff(kap) < 0)  # thicker is stronger
    # thick cylinders: geometric optics, kappa ~ a^-1/2 while a << r
    thick = cylinder_kappa_us(np.array([0.1, 0.4]))
    assert thick[0] / thick[1] == pytest.approx(math.sqrt(4 * 1.6 / 1.9), rel=0.01)
    # thin wires: Rayleigh regime, kappa ~ a^-2 (a^-1/2 geometric times (ka)^-3/2)
    thin = cylinder_kappa_us(np.array([1e-4, 2e-4]))
    assert thin[0] / thin[1] == pytest.approx(4.0, rel=0.01)
    assert cylinder_kappa_us(100.0) == pytest.approx(kappa_inf, rel=0.02)


def test_cylinder_strength_falls_with_range() -> None:
    k = cylinder_kappa_us(0.004, np.array([0.5, 1.5, 3.0]))
    assert k[1] == pytest.approx(2.68)
    np.testing.assert_allclose(k, kappa_at_range_us(2.68, "rod", [0.5, 1.5, 3.0], 0.004))
    np.testing.assert_allclose(kappa_at_range_us(0.15, "wall", [0.5, 3.0]), [0.15, 0.15])
    np.testing.assert_allclose(kappa_at_range_us(0.67, "point", 6.0), 0.67 * 2.0)
    # pole given without radius: its default radius
    assert float(kappa_at_range_us(0.67, "pole", 3.0)) == pytest.approx(
        float(cylinder_kappa_us(0.0445, 3.0)))


def test_edges_only_near() -> None:
    assert max_range_m("edge") == EDGE_MAX_RANGE_M == 0.5
    assert max_range_m("wall") == math.inf
    assert make_reflector("edge").max_range_m == 0.5


def test_make_reflector_defaults_and_overrides() -> None:
    r = make_reflector("Pole", radius_m=0.05)
    assert r.kind is ReflectorKind.POLE and r.kappa_us == pytest.approx(
        float(cylinder_kappa_us(0.05)))
    assert make_reflector("rod", kappa_us=1.0).kappa_us == 1.0
    assert make_reflector("point").kappa_us == 0.67
    assert ReflectorKind.parse(" WALL ") is ReflectorKind.WALL
    assert ReflectorKind.POLE.is_cylinder and not ReflectorKind.CORNER.is_cylinder
    assert ReflectorKind.WALL.is_planar
    assert Reflector("rod", 2.68, 0.004).kind is ReflectorKind.ROD  # type: ignore[arg-type]


@pytest.mark.parametrize(("call", "needle"), [
    (lambda: make_reflector("tree"), "got 'tree'"),
    (lambda: make_reflector("rod", radius_m=-0.01),
     "`radius_m` must be non-negative and finite, got -0.01"),
    (lambda: make_reflector("wall", radius_m=0.1), "got 0.1 for a wall"),
    (lambda: make_reflector("pole", kappa_us=0.0),
     "`kappa_us` must be positive and finite, got 0.0"),
    (lambda: cylinder_kappa_us(0.0), "`radius_m` must be positive and finite, got 0.0"),
    (lambda: cylinder_kappa_us(0.01, -1.0), "`range_m` must be positive and finite, got -1.0"),
    (lambda: kappa_at_range_us(0.67, "pole", [1.0, float("nan")]), "got nan"),
    (lambda: default_kappa_us("plane", radius_m=float("inf")), "got inf"),
])
def test_bad_reflector_arguments_name_the_value(call, needle: str) -> None:
    with pytest.raises(ValueError) as err:
        call()
    assert needle in str(err.value)
