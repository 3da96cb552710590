"""EKF localization against a 2-D landmark map (frames per REP-103/105: map, odom, base_link).

* :mod:`~sonarloc.localize.se2`: planar pose algebra.
* :mod:`~sonarloc.localize.ekf`: the pure filter core (``predict``, ``update`` over a
  frozen :class:`Gaussian`).
"""

from sonarloc.localize.ekf import (
    GATE_PROBABILITY,
    Feature,
    Gaussian,
    Innovation,
    Observation,
    OdomNoise,
    chi2_gate,
    predict,
    update,
)

__all__ = [
    "GATE_PROBABILITY", "Feature", "Gaussian", "Innovation", "Observation", "OdomNoise",
    "chi2_gate", "predict", "update",
]
