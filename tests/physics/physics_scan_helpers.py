"""Helpers for the physics tests: the paper's single-object scans (Kuc 2003, Sec. III)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sonarloc.physics.sound import tof_from_range_us
from sonarloc.physics.tiers import echo_delays_us
from sonarloc.physics.tof import ModuleParams, apply_module

PAPER_RANGE_M = 1.5
PAPER_KAPPA_US = {"plane": 0.15, "pole": 0.67, "rod": 2.68}
PAPER_ARC_DEG = {"plane": 45.0, "pole": 22.8, "rod": 18.6}
PAPER_LEVEL_DB = {"plane": -38.0, "pole": -25.0, "rod": -13.0}


@dataclass(frozen=True)
class Scan:
    """A rotational scan of one object: readings (n_angles, pings) and tiers used."""

    theta_deg: NDArray[np.float64]
    to_us: float
    delay_us: NDArray[np.float64]
    tier: NDArray[np.int8]
    reading_us: NDArray[np.float64]

    def arc_deg(self) -> float:
        """Angular extent over which any ping detected an echo."""
        hit = ~np.all(np.isnan(self.reading_us), axis=1)
        return float(np.ptp(self.theta_deg[hit])) if hit.any() else 0.0


def scan_object(kappa_us: float, tier: str = "auto", *, seed: int = 1,
                params: ModuleParams = ModuleParams(), step_deg: float = 0.3,
                pings: int = 100, range_m: float = PAPER_RANGE_M) -> Scan:
    """The paper's experiment: -40..40 deg in ``step_deg`` steps, ``pings`` per angle."""
    rng = np.random.default_rng(seed)
    n = int(np.floor(40.0 / step_deg + 1e-9))
    theta_deg = np.round(np.arange(-n, n + 1) * step_deg, 6)  # symmetric, holds 0
    to_us = float(tof_from_range_us(range_m, params.c_mps))
    theta = np.broadcast_to(np.deg2rad(theta_deg)[:, None], (theta_deg.size, pings))
    delay, used = echo_delays_us(theta, kappa_us, tier, rng, params)
    reading = apply_module((to_us + delay)[..., None], rng, params, axis=-1)
    return Scan(theta_deg, to_us, delay, used, reading)
