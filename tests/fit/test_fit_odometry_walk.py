"""The odometry's random pose error in the status test of moving segments
(:func:`sonarloc.fit.odomcov.odometry_chi2`): a single reflector seen over a bent
odometry path passes, two merged reflectors still do not."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from sonarloc.fit import odomcov
from sonarloc.fit.landmarks import fit_segments
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.pair import is_candidate
from sonarloc.fit.result import FitStatus
from sonarloc.fit.synth import Reflector, simulate_readings
from sonarloc.world.robot import Pose2, Robot, Route


def _drive(seed, reflectors, length_m=4.0, radius_m=4.0, mount_m=0.2, hz=8.0):
    """A right-looking transducer on the simulator's robot (default odometry) driving a
    left arc: readings from the true poses, returned with the odometry's poses and the
    true ones."""
    a = np.linspace(0.0, length_m / radius_m, 60)
    route = Route(np.c_[radius_m * np.sin(a), radius_m * (1.0 - np.cos(a))])
    robot = Robot.at_route_start(route, rng=np.random.default_rng(seed))
    truth: list[Pose2] = []
    odom: list[Pose2] = []
    while not robot.finished and robot.t_s < 30.0:
        robot.advance_to(robot.t_s + 1.0 / hz)
        truth.append(robot.truth)
        odom.append(robot.odom)

    def transducer(poses):
        yaw = np.array([p.yaw for p in poses]) - math.pi / 2
        return (np.array([p.x for p in poses]) + mount_m * np.cos(yaw),
                np.array([p.y for p in poses]) + mount_m * np.sin(yaw), yaw)

    t = np.arange(1, len(truth) + 1) / hz
    xt, yt, wt = transducer(truth)
    tof = simulate_readings(t, xt, yt, wt, reflectors, np.random.default_rng(seed + 100)).tof_us
    return (t, *transducer(odom), tof), (t, xt, yt, wt, tof)


def test_wall_on_an_odometry_path_passes_with_the_walk():
    # one wall, 55 echoes over 4 m of a turning drive: the odometry's heading walk bends
    # the path by millimetres, tens of microseconds of TOF; the jitter-only test fails it
    seg, true_seg = _drive(1, [Reflector("line", 1.2, -math.pi / 2 + 0.25, 0.15)])
    cfg = FitConfig()
    exact = fit_segments([true_seg], cfg, 0.0)[0]
    assert exact.ok and exact.kind == "line"                 # with the true poses
    without = fit_segments([seg], cfg, 0.0)[0]
    assert without.status is FitStatus.UNRESOLVED and "chi2" in without.reason
    assert "chi2_odom" not in without.extra
    lm = fit_segments([seg], cfg)[0]
    assert lm.ok and lm.kind == "line"
    chi2 = float(lm.extra["chi2_odom"])   # type: ignore[arg-type]
    assert chi2 < 0.6 * float(lm.extra["chi2"])  # type: ignore[arg-type]
    assert lm.extra["chi2"] == without.extra["chi2"]     # the fit itself is the same
    np.testing.assert_array_equal(lm.params, without.params)
    # the walk widens the covariance: the range and bearing errors stay within 3 SDs
    rng = float(lm.extra["range_sd_m"])  # type: ignore[arg-type]
    assert rng > float(without.extra["range_sd_m"])  # type: ignore[arg-type]
    assert abs(lm.bearing_rad - exact.bearing_rad) < 3.0 * math.radians(
        float(lm.extra["bearing_sd_deg"]))  # type: ignore[arg-type]


def test_two_poles_on_an_odometry_path_stay_unresolved():
    # two poles 1.2 m apart along the path merged into one segment: the walk's freedom
    # (with its prior) does not explain a second reflector
    poles = [Reflector("point", 1.0, -1.5, 0.67), Reflector("point", 2.2, -1.3, 0.67)]
    for seed in (0, 1):
        seg, _ = _drive(seed, poles)
        lm = fit_segments([seg], FitConfig())[0]
        assert lm.status is FitStatus.UNRESOLVED
        assert float(lm.extra["chi2_odom"]) > 400.0  # type: ignore[arg-type]


def test_runs_test_reads_what_the_walk_leaves():
    # one wall on an odometry path: the walk bends the path smoothly, so the residuals
    # run in blocks with the jitter alone (read so, the wall is two reflectors merged);
    # with the walk profiled out the blocks are gone
    wall = [Reflector("line", 1.2, -math.pi / 2 + 0.25, 0.15)]
    for seed in (2, 6, 7):
        seg, _ = _drive(seed, wall)
        lm = fit_segments([seg], FitConfig())[0]
        assert float(lm.extra["runs_z"]) < -4.0   # type: ignore[arg-type]
        assert float(lm.extra["runs_z_odom"]) > -2.0   # type: ignore[arg-type]
        assert "residuals run in blocks" not in lm.reason
    assert fit_segments([seg], FitConfig(), 0.0)[0].reason.startswith(
        "residuals run in blocks")
    # two poles merged: their blocks stay
    poles = [Reflector("point", 1.0, -1.5, 0.67), Reflector("point", 2.2, -1.3, 0.67)]
    for seed in (0, 1):
        seg, _ = _drive(seed, poles)
        lm = fit_segments([seg], FitConfig())[0]
        assert float(lm.extra["runs_z_odom"]) < -2.5   # type: ignore[arg-type]


def test_walk_modes_carry_a_brownian_paths_variance():
    # the Karhunen-Loeve modes of a unit Brownian path on [0, L]: the variance at s is s
    # (95 % of it in WALK_TERMS modes at the far end), the mean over [0, s] has variance
    # s/3 at s = L
    L = np.array([[2.0]])
    s = np.array([[0.5, 1.0, 2.0]])
    modes = [odomcov._walk_modes(s, L, k) for k in range(200)]
    var = sum(v * v for v, _ in modes)
    np.testing.assert_allclose(var, s, rtol=0.02)
    mean_var = sum(m * m for _, m in modes)
    np.testing.assert_allclose(mean_var[0, 2], 2.0 / 3.0, rtol=0.02)
    few = sum(v * v for v, _ in modes[:odomcov.WALK_TERMS])
    assert 0.9 * 2.0 < few[0, 2] < 2.0


def test_pair_candidates_read_the_odometry_chi2():
    # an OK point whose jitter-only chi-square is strained but whose odometry-aware one
    # is not is no two-reflector candidate (the odometry's misfit is no second reflector)
    seg, _ = _drive(3, [Reflector("point", 1.0, -1.5, 0.67)])
    cfg = FitConfig()
    lm = fit_segments([seg], cfg)[0]
    assert lm.kind == "point" and lm.n_readings >= 2 * cfg.min_echoes
    assert "chi2_odom" in lm.extra                    # moving: the status test's
    dof = lm.n_readings - 3
    jitter_only = {k: v for k, v in lm.extra.items() if k != "chi2_odom"}
    strained = replace(lm, status=FitStatus.OK, extra={**jitter_only, "chi2": 3.0 * dof,
                                                       "runs_z": 0.0})
    assert is_candidate(strained, cfg)
    explained = replace(strained, extra={**strained.extra, "chi2_odom": 1.0 * dof})
    assert not is_candidate(explained, cfg)
    # residuals in blocks: the walk makes them so; with it profiled out the chi-square
    # decides (without it, the runs test still makes a candidate)
    blocks = replace(explained, extra={**explained.extra, "runs_z": -6.0})
    assert not is_candidate(blocks, cfg)
    assert is_candidate(replace(blocks, extra={**jitter_only, "chi2": 1.0 * dof,
                                               "runs_z": -6.0}), cfg)


def test_travel_is_the_path_not_the_mount_jumps():
    # two transducers 0.4 m apart on a robot driving straight at 0.3 m/s, firing in
    # turn: the travel is 0.3 m/s times the time, not the zigzag between the mounts
    t = np.arange(20) * 0.05
    sensor = np.arange(20) % 2
    x = 0.3 * t
    y = np.where(sensor == 0, 0.2, -0.2)
    seg = np.zeros(20, dtype=np.int64)
    travel = odomcov.travel_from_start(seg, t, x, y, sensor, 1)
    np.testing.assert_allclose(travel, 0.3 * t, atol=1e-12)
    # one segment's speed does not leak into another's
    seg2 = np.r_[seg, np.ones(20, dtype=np.int64)]
    both = odomcov.travel_from_start(seg2, np.r_[t, t + 5.0], np.r_[x, 2.0 * x],
                                     np.r_[y, y], np.r_[sensor, sensor], 2)
    np.testing.assert_allclose(both, np.r_[0.3 * t, 0.6 * t], atol=1e-12)


def test_walk_intensities_are_the_simulators_odometry():
    # derived from the world simulator's default odometry, not tuned: a change there
    # must be carried here (or the status test models another robot's odometry)
    from sonarloc.fit import odomcov
    from sonarloc.world.robot import DriveParams, OdometryModel

    assert odomcov.WHEEL_NOISE_M_PER_SQRT_M == OdometryModel().noise_m_per_sqrt_m
    assert odomcov.WHEELBASE_M == DriveParams().wheelbase_m
