import math

import numpy as np
import pytest
from shapely.geometry import LineString, Point

from sonarloc.maps import load_map
from sonarloc.world.robot import DriveParams, OdometryModel, Pose2, Robot, Route
from tests.conftest import MAPS


def drive(route, odometry, seed=3, laps=1.0):
    robot = Robot.at_route_start(route, odometry=odometry, rng=np.random.default_rng(seed))
    start = robot.truth
    dev, t = [], 0.0
    line = LineString(route.points)
    while t < laps * route.length / robot.drive.speed_mps:
        t += 0.5
        robot.advance_to(t)
        dev.append(line.distance(Point(robot.truth.x, robot.truth.y)))
    return robot, start, np.array(dev)


def odom_in_map(start: Pose2, odom: Pose2) -> Pose2:
    return start.compose(odom.x, odom.y, odom.yaw)


def test_follows_the_route_and_perfect_odometry_matches_truth():
    route = Route(load_map(MAPS / "room.geojson").route)
    assert route.closed and route.length > 15
    robot, start, dev = drive(route, OdometryModel.perfect())
    assert dev.max() < 0.2  # cuts corners by less than the lookahead allows
    assert robot.distance_m == pytest.approx(route.length, rel=0.05)
    est = odom_in_map(start, robot.odom)
    assert (est.x, est.y) == pytest.approx((robot.truth.x, robot.truth.y), abs=1e-9)
    assert math.cos(est.yaw - robot.truth.yaw) == pytest.approx(1.0)
    # one lap's time brings it back near the start (a bit ahead: it cuts corners)
    assert math.hypot(robot.truth.x - start.x, robot.truth.y - start.y) < 0.6


def test_odometry_drifts_plausibly_and_is_seeded():
    route = Route(load_map(MAPS / "room.geojson").route)
    robot, start, _ = drive(route, OdometryModel())
    est = odom_in_map(start, robot.odom)
    err = math.hypot(est.x - robot.truth.x, est.y - robot.truth.y)
    yaw_err = abs(math.degrees(math.atan2(math.sin(est.yaw - robot.truth.yaw),
                                          math.cos(est.yaw - robot.truth.yaw))))
    # about 17 m with 1 % wheelbase and 0.2 % scale errors: decimetres, some degrees
    assert 0.05 < err < 1.5
    assert 3 < yaw_err < 15
    again, _, _ = drive(route, OdometryModel())
    assert again.odom == robot.odom
    other, _, _ = drive(route, OdometryModel(), seed=4)
    assert other.odom != robot.odom
    # the wheelbase error alone turns a full lap (360 deg of turning) into ~3.6 deg of error
    wb, _, _ = drive(route, OdometryModel(0.0, 0.0, 0.01, 0.0))
    e = odom_in_map(start, wb.odom).yaw - wb.truth.yaw
    assert abs(math.degrees(math.atan2(math.sin(e), math.cos(e)))) == pytest.approx(3.6, rel=0.2)


def test_open_route_stops_at_the_end():
    route = Route(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0]]))
    assert not route.closed
    robot = Robot.at_route_start(route, odometry=OdometryModel.perfect())
    robot.advance_to(60.0)
    assert robot.finished
    assert math.hypot(robot.truth.x - 3.0, robot.truth.y - 2.0) < 0.15


def test_still_robot_and_bad_arguments():
    robot = Robot(Pose2(1.0, 2.0, 0.5))
    robot.advance_to(5.0)
    assert robot.truth == Pose2(1.0, 2.0, 0.5) and robot.odom == Pose2(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="speed_mps"):
        DriveParams(speed_mps=0.0)
    with pytest.raises(ValueError, match="wheelbase_error"):
        OdometryModel(wheelbase_error=0.9)
    with pytest.raises(ValueError, match="route needs two distinct points"):
        Route(np.array([[1.0, 1.0], [1.0, 1.0]]))
