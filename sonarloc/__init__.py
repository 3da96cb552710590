"""sonarloc: mobile-robot localization with time-of-flight sonar.

Stages, each a subpackage: ``physics`` (beam and TOF models), ``world`` (simulated
scenes, rigs, robot), ``fit`` (landmarks from TOF curves), ``localize`` (EKF),
``maps`` (GeoJSON maps, map building), ``io`` (protocols, drivers, log files).
"""

__version__ = "0.1.0"
