"""The simulated world: scenes from maps, sonar rigs, a robot, and simulated logs.

* :mod:`sonarloc.world.scene` -- echo geometry, occlusion and readings (:class:`Scene`);
* :mod:`sonarloc.world.rig` -- pan and ring rigs, JSON rig files;
* :mod:`sonarloc.world.robot` -- differential drive along a route, wheel odometry;
* :mod:`sonarloc.world.simulate` -- :func:`simulate_records`, :func:`simulate_scan`.
"""

from sonarloc.world.rig import PanRig, Rig, RingRig, load_rig, ring16, ring_rig, save_rig
from sonarloc.world.robot import DriveParams, OdometryModel, Pose2, Robot, Route
from sonarloc.world.scene import EchoCandidates, PingResult, Scene
from sonarloc.world.simulate import (
    PingTruth,
    SimulatedScan,
    simulate_records,
    simulate_scan,
)

__all__ = [
    "DriveParams", "EchoCandidates", "OdometryModel", "PanRig", "PingResult", "PingTruth",
    "Pose2", "Rig", "RingRig", "Robot", "Route", "Scene", "SimulatedScan", "load_rig",
    "ring16", "ring_rig", "save_rig", "simulate_records", "simulate_scan",
]
