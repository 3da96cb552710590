"""The fit result: one landmark with its covariance and a status that says why.

This type is the contract between ``fit`` (which makes them) and ``localize`` /
``maps`` (which consume them). Fits never raise on numerical trouble; a result
whose ``status`` is not ``OK`` carries a human-readable ``reason``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2


class FitStatus(enum.Enum):
    OK = "ok"
    TOO_FEW_POINTS = "too_few_points"
    FLAT = "flat"                 # curve too flat for its bearing (strong plane, tiny arc)
    PARTIAL = "partial"           # minimum outside the covered arc: bearing is bounded only
    UNRESOLVED = "unresolved"     # overlapping reflectors or point/line not separable
    NO_ECHO = "no_echo"
    BAD_INPUT = "bad_input"       # NaN/inf, inconsistent lengths after cleaning


@dataclass(frozen=True)
class Landmark:
    """A fitted landmark in the frame of the readings' poses (``odom`` for a robot).

    ``params``: (x_m, y_m, kappa_us) for ``kind == "point"``, (rho_m, alpha_rad,
    kappa_us) for ``"line"`` (the wall x cos(alpha) + y sin(alpha) = rho, rho >= 0);
    ``cov``: their 3x3 covariance (alpha in radians).

    ``ref_t_s`` / ``ref_pose``: time and transducer pose (x_m, y_m, yaw_rad) of the
    segment's reference reading (its last); ``range_m`` / ``bearing_rad`` are seen from
    there (bearing: frame angle to the reflecting point, or of the wall normal).
    """

    kind: Literal["point", "line"]
    params: NDArray[np.float64]
    cov: NDArray[np.float64]
    range_m: float
    bearing_rad: float
    n_readings: int
    ref_t_s: float
    ref_pose: tuple[float, float, float]
    status: FitStatus = FitStatus.OK
    reason: str = ""
    tier: str = "gauss"
    rms_us: float = float("nan")
    sensors: tuple[int, ...] = ()
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status is FitStatus.OK

    @classmethod
    def _from_fields(cls, fields: dict[str, object]) -> Landmark:
        """A landmark from a dict of *all* its fields, as unpickling builds one: the
        frozen dataclass's ``__init__`` sets the 14 fields one by one through
        ``object.__setattr__`` (~5-10 us a landmark; the fitter makes thousands per
        scan). For the fitter's own use; ``fields`` is taken over, not copied."""
        obj = object.__new__(cls)
        obj.__dict__.update(fields)
        return obj

    def transformed(self, pose: ArrayLike) -> Landmark:
        """This landmark moved into the parent frame of ``pose`` (x_m, y_m, yaw_rad).

        E.g. a fit in ``odom`` moved into ``map`` by the ``map -> odom`` transform.
        Parameters and covariance are rotated and shifted; the transform's own
        uncertainty is not added.
        """
        t = np.asarray(pose, dtype=float)
        p = np.array(self.params, dtype=float)
        J = np.eye(3)
        if self.kind == "point":
            p[:2] = se2.transform_points(t, p[:2])
            J[:2, :2] = se2.rotation(t[2])
        else:
            line = se2.transform_line(t, p[:2])
            alpha = line[1]
            J[0, 1] = -t[0] * np.sin(alpha) + t[1] * np.cos(alpha)
            if abs(float(se2.wrap_angle(alpha - p[1] - t[2]))) > np.pi / 2:  # normal flipped
                J[0] *= -1.0
            p[:2] = line
        ref = se2.compose(t, self.ref_pose)
        return replace(self, params=p, cov=J @ self.cov @ J.T,
                       ref_pose=(float(ref[0]), float(ref[1]), float(ref[2])),
                       bearing_rad=float(se2.wrap_angle(self.bearing_rad + t[2])))

    @property
    def kappa_us(self) -> float:
        return float(self.params[2])
