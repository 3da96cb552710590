"""Peer check against FilterPy, SPD over a million steps, and NEES consistency."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from sonarloc import se2
from sonarloc.localize import ekf
from sonarloc.localize.ekf import Feature, Gaussian, Observation, OdomNoise

filterpy_kalman = pytest.importorskip("filterpy.kalman")


class _PoseEKF(filterpy_kalman.ExtendedKalmanFilter):
    """FilterPy's EKF with the same motion model: x ⊕ u."""

    def predict_x(self, u=0):
        self.x = se2.compose(self.x[:, 0], u)[:, None]


def _filterpy_run(g0, steps, noise):
    f = _PoseEKF(dim_x=3, dim_z=2)
    f.x = g0.mean.copy()[:, None]
    f.P = g0.cov.copy()
    out = []
    for kind, payload in steps:
        if kind == "predict":
            u = payload
            fj, gj = se2.compose_jacobians(f.x[:, 0], u)
            f.F = fj
            f.Q = gj @ noise.cov(u) @ gj.T
            f.predict(u=u)
        else:
            obs, feat = payload

            def hx(x, obs=obs, feat=feat):
                return ekf.measure(x[:, 0], obs, feat)[0][:, None]

            def hjac(x, obs=obs, feat=feat):
                return ekf.measure(x[:, 0], obs, feat)[1]

            def residual(a, b, obs=obs):
                return ekf.innovation(a[:, 0], b[:, 0], obs.angle_index)[:, None]

            f.update(obs.z[:, None], hjac, hx, R=obs.cov, residual=residual)
        out.append((f.x[:, 0].copy(), f.P.copy()))
    return out


def test_agrees_with_filterpy_ekf(rng):
    noise = OdomNoise()
    g = Gaussian.from_pose(1.0, 0.5, 0.3, 0.05, math.radians(3))
    points = rng.uniform(-4, 4, (5, 2))
    walls = np.array([[5.0, 0.0], [4.0, math.pi / 2], [5.0, math.pi], [4.0, -math.pi / 2]])
    steps = []
    truth = g.mean.copy()
    for k in range(300):
        u = np.array([0.05, 0.0, 0.02]) + rng.normal(0, [0.005, 0.002, 0.01])
        truth = se2.compose(truth, u)
        steps.append(("predict", u))
        which = k % 5
        sensor = np.array([0.15, 0.05, rng.uniform(-math.pi, math.pi)])
        if which == 0:
            feat = Feature("point", points[k % 5])
            obs_kind = "point"
        elif which == 1:
            feat = Feature("wall", walls[k % 4])
            obs_kind = "line"
        elif which == 2:
            feat = Feature("point", points[k % 5], 0.05)
            obs_kind = "range_bearing"
        elif which == 3:
            feat = Feature("wall", walls[k % 4])
            obs_kind = "range_bearing"
        else:
            continue
        zt = ekf.measure(truth, Observation(obs_kind, [0.0, 0.0], np.eye(2), sensor), feat)[0]
        cov = np.diag([0.01**2, math.radians(2) ** 2]) if obs_kind != "point" else \
            np.array([[1e-4, 2e-5], [2e-5, 3e-4]])
        z = zt + rng.multivariate_normal([0, 0], cov)
        steps.append(("update", (Observation(obs_kind, z, cov, sensor), feat)))
    ref = _filterpy_run(g, steps, noise)
    state = g
    worst_x = worst_p = 0.0
    for (kind, payload), (fx, fp) in zip(steps, ref, strict=True):
        if kind == "predict":
            state = ekf.predict(state, payload, noise)
        else:
            state, _ = ekf.update(state, *payload, gate_probability=None)
        dx = state.mean - fx
        dx[2] = se2.wrap_angle(dx[2])
        worst_x = max(worst_x, float(np.max(np.abs(dx))))
        worst_p = max(worst_p, float(np.max(np.abs(state.cov - fp))))
    assert worst_x < 1e-9
    assert worst_p < 1e-9


def _long_loop(n_batch, n_steps, rng):
    """Predict + update over a batch of filters; returns the final states and a flag per step."""
    noise = OdomNoise()
    g = Gaussian.from_pose(rng.uniform(-3, 3, n_batch), rng.uniform(-3, 3, n_batch),
                           rng.uniform(-3, 3, n_batch), 0.1, 0.1)
    feats = [Feature("point", [0.5, 4.0], 0.04), Feature("wall", [5.0, 0.3]),
             Feature("point", [-4.0, -1.0])]
    all_spd = True
    for k in range(n_steps):
        # increments from standing still to big jumps; observations from sloppy to razor sharp
        scale = 10.0 ** rng.uniform(-4, 0, n_batch)[:, None]
        u = rng.normal(0, 1, (n_batch, 3)) * scale
        g = ekf.predict(g, u, noise)
        sharp = 10.0 ** rng.uniform(-6, -1, n_batch)
        kind = k % 3
        cov = np.zeros((n_batch, 2, 2))
        cov[:, 0, 0] = sharp**2
        cov[:, 1, 1] = (sharp * 3) ** 2 if kind != 0 else sharp**2
        cov[:, 0, 1] = cov[:, 1, 0] = 0.5 * np.sqrt(cov[:, 0, 0] * cov[:, 1, 1]) * (kind == 0)
        obs_kind = ("point", "line", "range_bearing")[kind]
        sensor = np.array([0.2, 0.0, 0.5])
        zt = ekf.measure(g.mean, Observation(obs_kind, np.zeros((n_batch, 2)), cov, sensor),
                         feats[kind])[0]
        z = zt + rng.normal(0, 1, (n_batch, 2)) * np.sqrt(cov[:, [0, 1], [0, 1]]) \
            + rng.normal(0, 0.02, (n_batch, 2))
        g, _ = ekf.update(g, Observation(obs_kind, z, cov, sensor), feats[kind],
                          gate_probability=None)
        if k % 50 == 0:
            all_spd &= bool(np.all(g.is_spd()))
    return g, all_spd


def test_spd_over_a_million_steps(rng):
    """1000 filters x 1000 predict/update steps = 1e6 steps, stays SPD and finite."""
    g, all_spd = _long_loop(1000, 1000, rng)
    assert all_spd
    assert np.all(g.is_spd())
    assert np.all(np.isfinite(g.mean))
    eig = np.linalg.eigvalsh(g.cov)
    assert np.all(eig > 0)


def simulate_nees(rng, n_runs, n_steps, delay_steps=0, mode="exact"):
    """Monte-Carlo drives with model-exact noise; returns NEES (n_steps, n_runs)."""
    noise = OdomNoise(along_var_per_m=0.02**2, cross_var_per_m=0.01**2,
                      yaw_var_per_m=math.radians(2) ** 2, yaw_var_per_rad=math.radians(2) ** 2)
    points = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [0.0, -3.0], [2.0, 2.0]])
    walls = np.array([[4.0, 0.0], [4.0, math.pi / 2], [4.0, math.pi], [4.0, -math.pi / 2]])
    truth = np.tile([1.0, 0.0, math.pi / 2], (n_runs, 1))
    g0 = Gaussian.from_pose(truth[:, 0], truth[:, 1], truth[:, 2], 0.05, math.radians(2))
    truth = truth + rng.normal(0, 1, truth.shape) * [0.05, 0.05, math.radians(2)]
    g = g0
    hist_truth = [truth]
    hist_u = []
    hist_q = []
    out = np.zeros((n_steps, n_runs))
    for k in range(n_steps):
        u_true = np.array([0.05, 0.0, 0.05])  # circle of radius 1 m
        q = noise.cov(np.broadcast_to(u_true, (n_runs, 3)))
        v = np.einsum("nij,nj->ni", np.linalg.cholesky(q), rng.normal(0, 1, (n_runs, 3)))
        u_meas = u_true + v
        truth = se2.compose(truth, u_true)
        g = ekf.predict(g, u_meas, increment_cov=q)
        hist_truth.append(truth)
        hist_u.append(u_meas)
        hist_q.append(q)
        # one observation every max(delay_steps, 1) steps, of the pose delay_steps back
        if k >= delay_steps and k % max(delay_steps, 1) == 0:
            ref_truth = hist_truth[-1 - delay_steps]
            kw = {}
            if delay_steps:
                inc = np.zeros((n_runs, 3))
                inc_cov = np.zeros((n_runs, 3, 3))
                for uu, qq in zip(hist_u[-delay_steps:], hist_q[-delay_steps:], strict=True):
                    inc, inc_cov = ekf.chain_increments(inc, inc_cov, uu, qq)
                delta, delta_cov, cross = ekf.since_reference(g.mean, inc, inc_cov)
                if mode == "exact":
                    kw = {"delta": delta, "delta_cov": delta_cov, "delta_cross": cross}
                elif mode == "independent":
                    kw = {"delta": delta, "delta_cov": delta_cov}
                elif mode == "through":
                    kw = {"delta": delta}
            idx = k // max(delay_steps, 1)
            if idx % 2:
                feat = Feature("point", points[idx % 5])
                z = ekf.point_in_base(ref_truth, feat.params)[0]
                cov = np.array([[0.02**2, 0.0], [0.0, 0.01**2]])
                obs_kind = "point"
            else:
                feat = Feature("wall", walls[idx % 4])
                z = ekf.wall_in_base(ref_truth, feat.params)[0]
                cov = np.diag([0.01**2, math.radians(3) ** 2])
                obs_kind = "line"
            z = z + rng.multivariate_normal([0, 0], cov, n_runs)
            g, _ = ekf.update(g, Observation(obs_kind, z, cov), feat, gate_probability=None,
                              **kw)
        out[k] = ekf.nees(g, truth)
    return out


def nees_band(n_runs, dof=3, p=0.95):
    return (chi2.ppf((1 - p) / 2, dof * n_runs) / n_runs,
            chi2.ppf((1 + p) / 2, dof * n_runs) / n_runs)


def check_consistent(nees, n_runs):
    lo, hi = nees_band(n_runs)
    avg = nees.mean(axis=1)
    inside = np.mean((avg >= lo) & (avg <= hi))
    return avg, inside, (lo, hi)


def test_nees_consistent(rng):
    n_runs = 100
    nees = simulate_nees(rng, n_runs, 200)
    avg, inside, band = check_consistent(nees, n_runs)
    assert inside >= 0.85, (inside, band, avg.mean())
    assert 2.7 < avg.mean() < 3.3


def test_nees_with_delayed_observations(rng):
    """Each observation refers to the pose 4 steps back (no update in between): linearised
    through the inverse odometry increment with its noise and cross-covariance, the filter
    is consistent; ignoring the delay is not."""
    n_runs = 100
    nees = simulate_nees(rng, n_runs, 400, delay_steps=4, mode="exact")
    avg, inside, band = check_consistent(nees, n_runs)
    assert inside >= 0.85, (inside, band, avg.mean())
    assert 2.7 < avg.mean() < 3.3
    ignored = simulate_nees(rng, n_runs, 400, delay_steps=4, mode="ignore")
    assert ignored.mean() > 3 * nees.mean()


@pytest.mark.slow
def test_nees_consistent_large(rng):
    n_runs = 500
    nees = simulate_nees(rng, n_runs, 1000)
    avg, inside, band = check_consistent(nees, n_runs)
    assert inside >= 0.9, (inside, band, avg.mean())
    assert 2.85 < avg.mean() < 3.15


def test_increment_chain_and_inverse_covariance(rng):
    """Monte-Carlo check of chain_increments / invert_increment against sampled noise."""
    a, b = np.array([0.3, 0.05, 0.4]), np.array([0.2, -0.1, -0.3])
    ca = np.diag([1e-4, 4e-5, 3e-4])
    cb = np.array([[2e-4, 1e-5, 0], [1e-5, 1e-4, 2e-5], [0, 2e-5, 5e-4]])
    ab, cab = ekf.chain_increments(a, ca, b, cb)
    inv, cinv = ekf.invert_increment(ab, cab)
    n = 200_000
    sa = a + rng.multivariate_normal(np.zeros(3), ca, n)
    sb = b + rng.multivariate_normal(np.zeros(3), cb, n)
    samples = se2.inverse(se2.compose(sa, sb))
    d = samples - inv
    d[:, 2] = se2.wrap_angle(d[:, 2])
    emp = np.cov(d.T)
    assert np.allclose(emp, cinv, rtol=0.05, atol=2e-6)
