import math

import numpy as np
import pytest
from scipy.stats import chi2

from sonarloc import se2
from sonarloc.localize import ekf
from sonarloc.localize.ekf import Feature, Gaussian, Observation, OdomNoise


def numeric_jacobian(f, x, eps=1e-6, angle_index=None):
    x = np.asarray(x, float)
    cols = []
    for i in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[..., i] = eps
        d = f(x + dx) - f(x - dx)
        if angle_index is not None:
            d[..., angle_index] = se2.wrap_angle(d[..., angle_index])
        cols.append(d / (2 * eps))
    return np.stack(cols, axis=-1)


@pytest.fixture
def poses(rng):
    return rng.uniform([-4, -4, -math.pi], [4, 4, math.pi], (40, 3))


@pytest.fixture
def sensors(rng):
    return rng.uniform([-0.3, -0.3, -math.pi], [0.3, 0.3, math.pi], (40, 3))


@pytest.mark.parametrize("radius", [0.0, 0.0445])
def test_point_in_base_jacobian(rng, poses, sensors, radius):
    pts = rng.uniform(-6, 6, (40, 2))
    z, h = ekf.point_in_base(poses, pts, radius, sensors)
    num = numeric_jacobian(lambda p: ekf.point_in_base(p, pts, radius, sensors)[0], poses)
    assert h.shape == (40, 2, 3)
    assert np.allclose(h, num, atol=1e-7)
    # the reflecting point is on the surface, on the transducer's side
    back = se2.transform_points(poses, z)
    assert np.allclose(np.hypot(*(back - pts).T), radius, atol=1e-12)


def test_point_in_base_values():
    z, _ = ekf.point_in_base([1.0, 2.0, math.pi / 2], [1.0, 3.5])
    assert np.allclose(z, [1.5, 0.0])


def test_wall_in_base_jacobian_and_values(rng, poses):
    walls = np.stack([rng.uniform(0, 6, 40), rng.uniform(-math.pi, math.pi, 40)], axis=-1)
    z, h = ekf.wall_in_base(poses, walls)
    num = numeric_jacobian(lambda p: ekf.wall_in_base(p, walls)[0], poses, angle_index=1)
    assert np.allclose(h, num, atol=1e-7)
    assert np.all(z[:, 0] >= 0)
    # agrees with the line transform
    assert np.allclose(z, se2.inverse_transform_line(poses, walls), atol=1e-12)
    # wall x = 3 seen from (1, 0) facing +y: 2 m away, normal at -90 deg
    z1, _ = ekf.wall_in_base([1.0, 0.0, math.pi / 2], [3.0, 0.0])
    assert np.allclose(z1, [2.0, -math.pi / 2])


@pytest.mark.parametrize("radius", [0.0, 0.1])
def test_range_bearing_point_jacobian(rng, poses, sensors, radius):
    pts = rng.uniform(-6, 6, (40, 2))
    z, h = ekf.range_bearing_point(poses, sensors, pts, radius)
    num = numeric_jacobian(lambda p: ekf.range_bearing_point(p, sensors, pts, radius)[0],
                           poses, angle_index=1)
    assert np.allclose(h, num, atol=1e-6)
    z1, _ = ekf.range_bearing_point([0, 0, 0], [0.2, 0, math.pi / 2], [0.2, 1.7], radius)
    assert np.allclose(z1, [1.7 - radius, 0.0])


def test_range_bearing_wall_jacobian(rng, poses, sensors):
    walls = np.stack([rng.uniform(0, 6, 40), rng.uniform(-math.pi, math.pi, 40)], axis=-1)
    z, h = ekf.range_bearing_wall(poses, sensors, walls)
    num = numeric_jacobian(lambda p: ekf.range_bearing_wall(p, sensors, walls)[0], poses,
                           angle_index=1)
    assert np.allclose(h, num, atol=1e-7)
    z1, _ = ekf.range_bearing_wall([1, 0, 0], [0.1, 0.0, 0.3], [3.0, 0.0])
    assert np.allclose(z1, [1.9, -0.3])


def test_predict_mean_and_cov():
    g = Gaussian.from_pose(1.0, 2.0, 0.4, 0.05, 0.02)
    u = np.array([0.3, -0.02, 0.1])
    noise = OdomNoise()
    out = ekf.predict(g, u, noise)
    assert np.allclose(out.mean, se2.compose(g.mean, u))
    f, gj = se2.compose_jacobians(g.mean, u)
    expect = f @ g.cov @ f.T + gj @ noise.cov(u) @ gj.T
    assert np.allclose(out.cov, expect, atol=1e-15)
    assert np.array_equal(out.cov, out.cov.T)


def test_predict_noise_grows_with_distance_and_turn():
    g = Gaussian.from_pose(0, 0, 0, 0.01, 0.01)
    still = ekf.predict(g, [0, 0, 0])
    assert np.allclose(still.cov, g.cov)
    short = ekf.predict(g, [0.1, 0, 0])
    far = ekf.predict(g, [1.0, 0, 0])
    turn = ekf.predict(g, [0, 0, 1.0])
    assert far.cov[0, 0] > short.cov[0, 0] > g.cov[0, 0]
    assert turn.cov[2, 2] > g.cov[2, 2]


def test_odom_noise_splits_consistently():
    # straight motion along x with yaw noise switched off: one step or ten give the same
    noise = OdomNoise(yaw_var_per_m=0.0, yaw_var_per_rad=0.0)
    g = Gaussian.from_pose(0, 0, 0.7, 0.01, 0.01)
    one = ekf.predict(g, [1.0, 0, 0], noise)
    ten = g
    for _ in range(10):
        ten = ekf.predict(ten, [0.1, 0, 0], noise)
    assert np.allclose(one.mean, ten.mean)
    assert np.allclose(one.cov, ten.cov, atol=1e-14)


def test_odom_noise_rejects_negative():
    with pytest.raises(ValueError, match="along_var_per_m"):
        OdomNoise(along_var_per_m=-1.0)


def test_update_shrinks_and_gates():
    g = Gaussian.from_pose(1.0, 1.0, 0.2, 0.1, 0.05)
    feat = Feature("point", [3.0, 2.0])
    z_true, _ = ekf.point_in_base(g.mean, feat.params)
    obs = Observation("point", z_true + [0.01, -0.02], np.eye(2) * 0.02**2)
    post, inn = ekf.update(g, obs, feat)
    assert inn.reason == "accepted"
    assert np.all(np.linalg.eigvalsh(g.cov - post.cov) > -1e-15)  # P+ <= P
    assert np.linalg.det(post.cov) < np.linalg.det(g.cov)
    far = Observation("point", z_true + [1.5, 0.0], np.eye(2) * 0.02**2)
    post2, inn2 = ekf.update(g, far, feat)
    assert inn2.reason == "gated" and inn2.d2 > inn2.gate
    assert post2.mean is g.mean or np.array_equal(post2.mean, g.mean)
    assert np.array_equal(post2.cov, g.cov)
    assert inn2.gate == pytest.approx(chi2.ppf(0.99, 2))


def test_update_wraps_angle_innovation():
    # wall normal measured at +179.9 deg, predicted at -179.9 deg: 0.2 deg apart, not 359.8
    g = Gaussian.from_pose(0.0, 0.0, 0.0, 0.05, 0.05)
    feat = Feature("wall", [2.0, math.radians(-179.9)])
    obs = Observation("line", [2.0, math.radians(179.9)],
                      np.diag([0.01**2, math.radians(1) ** 2]))
    post, inn = ekf.update(g, obs, feat)
    assert inn.reason == "accepted"
    assert abs(inn.nu[1] - math.radians(-0.2)) < 1e-9
    assert -math.pi <= post.mean[2] < math.pi


def test_update_singular_reported_not_raised():
    g = Gaussian.from_pose(0.0, 0.0, 0.0, 0.05, 0.05)
    obs = Observation("point", [1.0, 0.0], np.full((2, 2), np.nan))
    post, inn = ekf.update(g, obs, Feature("point", [1.0, 0.0]))
    assert inn.reason == "singular"
    assert np.array_equal(post.cov, g.cov)
    obs2 = Observation("point", [1.0, 0.0], -np.eye(2))
    post2, inn2 = ekf.update(g, obs2, Feature("point", [1.0, 0.0]), gate_probability=None)
    assert inn2.reason == "singular" and np.array_equal(post2.mean, g.mean)


def test_update_with_delta_equals_update_at_reference_pose():
    """Observation made at an earlier pose: linearising through pose_ref = mean ⊕ delta."""
    g_ref = Gaussian.from_pose(1.0, 0.5, 0.3, 0.03, 0.02)
    u = np.array([0.2, 0.01, 0.05])
    g_now = ekf.predict(g_ref, u, increment_cov=np.zeros((3, 3)))  # exact odometry
    feat = Feature("point", [3.0, 2.0])
    z, _ = ekf.point_in_base(g_ref.mean, feat.params)
    obs = Observation("point", z + [0.004, -0.003], np.eye(2) * 0.01**2)
    ref_post, _ = ekf.update(g_ref, obs, feat)
    expect = ekf.predict(ref_post, u, increment_cov=np.zeros((3, 3)))
    now_post, inn = ekf.update(g_now, obs, feat, delta=se2.inverse(u))
    assert inn.reason == "accepted"
    # equal up to second order in the correction
    assert np.allclose(now_post.mean, expect.mean, atol=2e-5)
    assert np.allclose(now_post.cov, expect.cov, rtol=1e-2, atol=1e-9)
    # ignoring the delay is wrong by about the distance travelled
    wrong, _ = ekf.update(g_now, obs, feat, gate_probability=None)
    assert np.hypot(*(wrong.mean - expect.mean)[:2]) > 10 * np.hypot(
        *(now_post.mean - expect.mean)[:2])


def test_update_delta_cov_inflates_innovation():
    g = Gaussian.from_pose(1.0, 0.5, 0.3, 0.03, 0.02)
    feat = Feature("wall", [4.0, 0.2])
    z, _ = ekf.wall_in_base(g.mean, feat.params)
    obs = Observation("line", z, np.diag([1e-4, 1e-3]))
    d = [-0.1, 0.0, -0.02]
    _, a = ekf.update(g, obs, feat, delta=d)
    _, b = ekf.update(g, obs, feat, delta=d, delta_cov=np.diag([1e-4, 1e-4, 1e-4]))
    assert np.all(np.linalg.eigvalsh(b.S - a.S) > 0)


def test_batched_update_mixes_accept_and_gate():
    g = Gaussian.from_pose(np.zeros(3), np.zeros(3), np.zeros(3), 0.05, 0.02)
    feat = Feature("point", [2.0, 0.0])
    z = np.array([[2.0, 0.0], [2.0, 1.0], [2.01, 0.0]])
    obs = Observation("point", z, np.broadcast_to(np.eye(2) * 1e-4, (3, 2, 2)))
    post, inn = ekf.update(g, obs, feat)
    assert inn.accepted.tolist() == [True, False, True]
    assert np.array_equal(post.cov[1], g.cov[1])
    single, _ = ekf.update(Gaussian(g.mean[2], g.cov[2]),
                           Observation("point", z[2], np.eye(2) * 1e-4), feat)
    assert np.allclose(post.mean[2], single.mean) and np.allclose(post.cov[2], single.cov)


def test_is_spd_and_nees():
    g = Gaussian.from_pose(0.0, 0.0, 0.0, 0.1, 0.1)
    assert bool(g.is_spd())
    bad = Gaussian(g.mean, np.diag([1.0, -1.0, 1.0]))
    assert not bool(bad.is_spd())
    assert ekf.nees(g, [0.1, 0.0, 2 * math.pi]) == pytest.approx(1.0)


def test_gate_values():
    assert ekf.chi2_gate(2) == pytest.approx(9.2103, abs=1e-4)
    assert ekf.chi2_gate(3, 0.95) == pytest.approx(7.8147, abs=1e-4)
    with pytest.raises(ValueError, match="probability"):
        ekf.chi2_gate(2, 1.5)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 7])
def test_gate_is_scipy_stats_quantile(dof):
    # computed from scipy.special (no scipy.stats import in a drive): the same numbers
    from scipy.stats import chi2

    for p in (0.5, 0.9, 0.95, 0.99, 0.999, 1 - 1e-9):
        assert ekf.chi2_gate(dof, p) == float(chi2.ppf(p, dof))


def test_axis_range_wall_jacobian_and_values(rng, poses, sensors):
    walls = np.stack([rng.uniform(0.5, 6, 40), rng.uniform(-math.pi, math.pi, 40)], axis=-1)
    z, h = ekf.axis_range_wall(poses, sensors, walls)
    hit = np.isfinite(z[:, 0])
    assert hit.sum() > 10
    with np.errstate(invalid="ignore"):  # inf - inf where the axis misses the wall
        num = numeric_jacobian(lambda p: ekf.axis_range_wall(p, sensors, walls)[0], poses)
    assert np.allclose(h[hit], num[hit], atol=1e-6)
    # wall x = 3, transducer at (1.1, 0) looking 30 deg off the normal: 1.9 / cos(30 deg)
    z1, _ = ekf.axis_range_wall([1, 0, 0], [0.1, 0.0, math.radians(30)], [3.0, 0.0])
    assert np.allclose(z1, [1.9 / math.cos(math.radians(30)), 0.0])
    z2, _ = ekf.axis_range_wall([1, 0, 0], [0.1, 0.0, math.pi], [3.0, 0.0])
    assert np.isinf(z2[0])


def test_axis_range_of_a_wall_takes_the_beams_width_into_its_variance():
    # The echo comes from anywhere in the beam: the bearing's SD enters the axis range
    # through the ray's slope, d sin(psi) / cos(psi)^2 (the conventional EKF had the
    # range SD alone and was overconfident at oblique walls: NEES 9.5 on room drives).
    cov = np.diag([0.01**2, math.radians(10.0) ** 2])
    wall = Feature("wall", np.array([3.0, 0.0]))
    for psi_deg in (0.0, 30.0, 60.0):
        psi = math.radians(psi_deg)
        obs = Observation("range_axis", np.array([2.0, 0.0]), cov, np.array([0.1, 0.0, psi]))
        r = ekf.measurement_cov(np.array([1.0, 0.0, 0.0]), obs, wall)
        slope = 1.9 * math.sin(psi) / math.cos(psi) ** 2
        assert np.allclose(r, cov + np.diag([slope**2 * cov[1, 1], 0.0]))
        # the ray's slope is the range's derivative with respect to the axis direction
        step = 1e-6
        z_a, _ = ekf.axis_range_wall([1, 0, 0], [0.1, 0.0, psi + step], [3.0, 0.0])
        z_b, _ = ekf.axis_range_wall([1, 0, 0], [0.1, 0.0, psi - step], [3.0, 0.0])
        assert math.isclose((z_a[0] - z_b[0]) / (2 * step), slope, rel_tol=1e-6, abs_tol=1e-9)
    # grazing incidence: one reading pinned the yaw variance to 1e-15 (a single-wall map
    # ended 0.9 m off); now it tells the yaw no more than the beam's width can
    prior = Gaussian(np.array([1.0, 0.0, 0.0]), np.diag([0.05**2, 0.05**2, 0.2**2]))
    psi = math.radians(89.9999)
    obs = Observation("range_axis", np.array([0.0, 0.0]), cov, np.array([0.1, 0.0, psi]))
    z_pred, _ = ekf.axis_range_wall(prior.mean, obs.sensor, wall.params)
    post, innov = ekf.update(prior, Observation("range_axis", z_pred, cov, obs.sensor), wall)
    assert bool(innov.accepted)
    assert post.cov[2, 2] > 0.5 / (1 / 0.2**2 + 1 / cov[1, 1])
    # points, and the other observation kinds, keep their covariance
    point = Feature("point", np.array([3.0, 0.5]))
    obs = Observation("range_axis", np.array([2.0, 0.0]), cov, np.array([0.1, 0.0, 0.5]))
    assert np.array_equal(ekf.measurement_cov(np.zeros(3), obs, point), cov)
    spec = Observation("range_bearing", np.array([2.0, 0.0]), cov, np.array([0.1, 0.0, 0.5]))
    assert np.array_equal(ekf.measurement_cov(np.zeros(3), spec, wall), cov)


def test_single_filter_predict_matches_batched(rng):
    noise = OdomNoise()
    for _ in range(50):
        g = Gaussian.from_pose(*rng.uniform(-3, 3, 3), 0.05, 0.03)
        u = rng.normal(0, [0.2, 0.05, 0.5])
        one = ekf.predict(g, u, noise)
        batch = ekf.predict(Gaussian(g.mean[None], g.cov[None]), u[None], noise)
        assert np.allclose(one.mean, batch.mean[0], atol=1e-14, rtol=0)
        assert np.allclose(one.cov, batch.cov[0], atol=1e-16, rtol=1e-12)


def test_gaussian_of_lists_equals_the_checked_constructor():
    mean, cov = [1.0, -2.5, 0.3], [[0.1, 0.01, 0.0], [0.01, 0.2, -0.02], [0.0, -0.02, 0.05]]
    g, h = ekf.Gaussian.of_lists(mean, cov), ekf.Gaussian(np.array(mean), np.array(cov))
    assert np.array_equal(g.mean, h.mean) and np.array_equal(g.cov, h.cov)
    assert g.mean.dtype == g.cov.dtype == np.float64 and g.cov.shape == (3, 3)
    assert np.array_equal(ekf.predict(g, np.array([0.1, 0.0, 0.01])).cov,
                          ekf.predict(h, np.array([0.1, 0.0, 0.01])).cov)


def test_a_prior_sd_whose_square_overflows_is_a_value_error():
    """sd 1e200: its variance is inf (Python's ``**`` raised OverflowError)."""
    for name, kw in (("sd_xy_m", {"sd_xy_m": 1e200, "sd_yaw_rad": 0.1}),
                     ("sd_yaw_rad", {"sd_xy_m": 0.1, "sd_yaw_rad": 1e160})):
        with pytest.raises(ValueError, match=f"`{name}`"):
            Gaussian.from_pose(0.0, 0.0, 0.0, **kw)
