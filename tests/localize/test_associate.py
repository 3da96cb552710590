import math

import numpy as np
import pytest

from sonarloc.localize import ekf
from sonarloc.localize.associate import AssociationConfig, associate
from sonarloc.localize.ekf import Gaussian, Observation
from sonarloc.localize.features import FeatureMap

ROOM = np.array([[[0, 0], [8, 0]], [[8, 0], [8, 5]], [[8, 5], [0, 5]], [[0, 5], [0, 0]]], float)


@pytest.fixture
def fmap():
    return FeatureMap.build(
        [[2.5, 2.0], [4.0, 1.8], [4.05, 1.85], [0.0, 0.0], [8.0, 0.0]], ROOM,
        point_radius_m=[0.0445, 0.004, 0.0445, 0.0, 0.0],
        point_kind=("pole", "rod", "pole", "corner", "corner"),
        point_cone_rad=[[np.nan, np.nan], [np.nan, np.nan], [np.nan, np.nan],
                        [0.0, math.pi / 2], [math.pi, math.pi / 2]])


def obs_of(kind, state, feature, noise=(0.0, 0.0), kappa=math.nan, sensor=(0.2, 0.0, 0.0),
           cov=None):
    cov = np.diag([0.005**2, 0.005**2]) if cov is None else cov
    proto = Observation(kind, [0.0, 0.0], cov, np.array(sensor))
    z, _ = ekf.measure(state.mean, proto, feature)
    return Observation(kind, z + np.asarray(noise), cov, np.array(sensor), kappa, 0.02**2)


def test_lines_of_segments(fmap):
    assert np.allclose(fmap.wall_line[0], [0.0, -math.pi / 2]) or \
        np.allclose(fmap.wall_line[0], [0.0, math.pi / 2])
    assert np.allclose(fmap.wall_line[1], [8.0, 0.0])
    assert np.allclose(fmap.wall_line[2], [5.0, math.pi / 2])


def test_matches_wall_and_pole(fmap):
    g = Gaussian.from_pose(3.0, 1.0, 0.3, 0.03, math.radians(1))
    a = associate(g, obs_of("line", g, fmap.wall(1), kappa=0.15), fmap)
    assert a.matched and a.kind == "wall" and a.index == 1 and a.dof == 2
    b = associate(g, obs_of("point", g, fmap.point(0), kappa=0.67), fmap)
    assert b.matched and b.kind == "point" and b.index == 0
    assert b.gate == pytest.approx(ekf.chi2_gate(2))
    strict = AssociationConfig(kappa_mode="gate")
    c = associate(g, obs_of("point", g, fmap.point(0), kappa=0.67), fmap, strict)
    assert c.matched and c.dof == 3 and c.gate == pytest.approx(ekf.chi2_gate(3))


def test_kappa_separates_pole_from_rod(fmap):
    # rod at (4.0, 1.8) and pole at (4.05, 1.85) are 7 cm apart: position alone is ambiguous
    g = Gaussian.from_pose(3.0, 1.0, 0.0, 0.05, math.radians(2))
    mid = 0.5 * (fmap.point(1).params + fmap.point(2).params)
    from sonarloc.localize.ekf import Feature
    blind = associate(g, obs_of("point", g, Feature("point", mid)), fmap)
    assert blind.status == "ambiguous" and blind.n_gated >= 2
    rod = associate(g, obs_of("point", g, Feature("point", mid), kappa=2.68), fmap)
    assert rod.matched and rod.index == 1
    pole = associate(g, obs_of("point", g, Feature("point", mid), kappa=0.67), fmap)
    assert pole.matched and pole.index == 2


def test_wrong_strength_rejects_only_in_gate_mode(fmap):
    g = Gaussian.from_pose(3.0, 1.0, 0.3, 0.03, math.radians(1))
    obs = obs_of("line", g, fmap.wall(1), kappa=20.0)  # a wall fitted as a very weak echo
    assert associate(g, obs, fmap).matched
    assert associate(g, obs, fmap, AssociationConfig(kappa_mode="gate")).status == "gated"


def test_outlier_gated_and_nothing_visible(fmap):
    g = Gaussian.from_pose(3.0, 1.0, 0.0, 0.01, math.radians(0.5))
    a = associate(g, obs_of("point", g, fmap.point(0), noise=(0.4, 0.4)), fmap)
    assert a.status == "gated" and a.d2 > a.gate
    empty = FeatureMap.build(walls=ROOM)
    assert associate(g, obs_of("point", g, fmap.point(0)), empty).status == "no_candidate"


def test_corner_seen_only_from_inside(fmap):
    inside = fmap.points_visible_from([1.0, 1.0])
    assert inside[3]  # corner at origin, walls along +x and +y
    outside = fmap.points_visible_from([-1.0, 1.0])
    assert not outside[3]


def test_wall_extent(fmap):
    facing = fmap.walls_facing([3.0, 1.0])
    assert facing.tolist() == [True, True, True, True]
    short = FeatureMap.build(walls=[[[0, 0], [1, 0]]])
    assert not short.walls_facing([3.0, 1.0])[0]
    assert short.walls_facing([1.1, 1.0], margin_m=0.2)[0]


def test_wrap_before_gating():
    # a wall whose normal sits at +-180 deg in base_link
    fm = FeatureMap.build(walls=[[[0, -3], [0, 3]]])
    g = Gaussian.from_pose(2.0, 0.0, math.radians(0.05), 0.01, math.radians(0.5))
    obs = Observation("line", [2.0, math.radians(179.97)],
                      np.diag([0.005**2, math.radians(0.5) ** 2]))
    a = associate(g, obs, fm)
    assert a.matched and a.d2 < 1.0


def test_conventional_range_bearing(fmap):
    g = Gaussian.from_pose(3.0, 1.0, 0.0, 0.02, math.radians(1))
    cov = np.diag([0.01**2, math.radians(10) ** 2])
    sensor = (0.2, 0.0, -math.pi / 2)  # looking at the wall y = 0 from 1 m
    obs = Observation("range_bearing", [1.0, 0.0], cov, np.array(sensor))
    a = associate(g, obs, fmap)
    assert a.matched and a.kind == "wall" and a.index == 0


def test_config_validation():
    with pytest.raises(ValueError, match="gate_probability"):
        AssociationConfig(gate_probability=1.0)


def test_ray_hits_walls(fmap):
    hit = fmap.walls_hit_by_ray([3.0, 1.0], 0.0)
    assert hit.tolist() == [False, True, False, False]
    short = FeatureMap.build(walls=[[[5, -1], [5, 1]]])
    assert short.walls_hit_by_ray([0.0, 0.0], math.radians(5))[0]
    assert not short.walls_hit_by_ray([0.0, 0.0], math.radians(20))[0]
    assert not short.walls_hit_by_ray([0.0, 0.0], math.pi)[0]


@pytest.mark.parametrize("var", [1e100, 1e150, 1e200])
def test_a_numerically_singular_belief_is_not_matched_and_does_not_raise(fmap, var):
    """x and y perfectly correlated with variances of 1e150 m²: the innovation
    covariance is singular to rounding (np.linalg.solve raised "Singular matrix"; at
    1e100 a garbage distance matched). Nothing is matched, nothing raised."""
    g = Gaussian(np.array([1.0, 1.0, 0.3]),
                 np.array([[var, var, 0.0], [var, var, 0.0], [0.0, 0.0, 1e-3]]))
    for kind in ("point", "line"):
        a = associate(g, Observation(kind, [1.0, 0.1], np.diag([1e-6, 1e-6])), fmap)
        assert not a.matched, kind
