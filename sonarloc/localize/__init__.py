"""EKF localization against a 2-D landmark map (frames per REP-103/105: map, odom, base_link).

* :mod:`~sonarloc.localize.se2`: planar pose algebra.
* :mod:`~sonarloc.localize.ekf`: the pure filter core (``predict``, ``update`` over a
  frozen :class:`Gaussian`).
* :mod:`~sonarloc.localize.features`: the map as arrays of points and wall segments.
* :mod:`~sonarloc.localize.associate`: chi-square gated, ambiguity-rejecting association.
* :mod:`~sonarloc.localize.echoes`: reading-level fusion, each reading of an associated
  segment a time of flight predicted by the forward model.
* :mod:`~sonarloc.localize.localizer`: the :class:`Localizer` (thin state, message routing,
  delayed fits by rewind-and-replay, status).
* :mod:`~sonarloc.localize.relocalize`: global relocalization from recent fits (when lost
  or started without a prior).
"""

from sonarloc.localize.associate import Association, AssociationConfig, associate
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
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import (
    FusionOutcome,
    Localizer,
    LocalizerConfig,
    LocalizerStats,
    PoseEstimate,
)
from sonarloc.localize.relocalize import Relocalization, RelocalizeConfig, Relocalizer

__all__ = [
    "GATE_PROBABILITY", "Association", "AssociationConfig", "Feature", "FeatureMap",
    "FusionOutcome", "Gaussian", "Innovation", "Localizer", "LocalizerConfig", "LocalizerStats",
    "Observation", "OdomNoise", "PoseEstimate", "Relocalization", "RelocalizeConfig",
    "Relocalizer", "associate", "chi2_gate", "predict", "update",
]
