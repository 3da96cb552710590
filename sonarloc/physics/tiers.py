"""Model tiers: the cheapest model that explains a reading, and which one was used.

* ``gauss``    eq. 3 with the Gaussian main lobe (no side lobes, no ripple);
* ``piston``   eq. 3 with the piston pattern (nulls and side lobes);
* ``waveform`` the simulated ranging module (ripple jumps, decreasing slope);
* ``auto``     per reflector and reading: Gaussian where it matches the piston
               pattern, piston where it does not (off-axis, strong reflectors).
"""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.physics.beam import gaussian_echo, piston_echo
from sonarloc.physics.tof import ModuleParams, sample_echo_delay_us


class Tier(enum.IntEnum):
    """Model tier codes (small ints so per-reading tier arrays stay compact)."""

    GAUSS = 0
    PISTON = 1
    WAVEFORM = 2
    AUTO = 3

    @classmethod
    def parse(cls, name: str | Tier) -> Tier:
        if isinstance(name, Tier):
            return name
        try:
            return cls[str(name).upper()]
        except KeyError:
            raise ValueError(
                f"`tier` must be one of gauss, piston, waveform, auto; got {name!r}"
            ) from None

    @property
    def label(self) -> str:
        return self.name.lower()


GAUSS_TOLERANCE_US = 0.5
"""Largest noise-free delay error (us) for which ``auto`` accepts the Gaussian beam."""


def gauss_valid_rad(kappa_us: ArrayLike, params: ModuleParams = ModuleParams(),
                    tolerance_us: float = GAUSS_TOLERANCE_US) -> NDArray[np.float64]:
    """Largest off-axis angle below which the Gaussian delay is within tolerance of piston's.

    Shape of ``kappa_us``. Computed on a fine grid of the main lobe.
    """
    grid = np.deg2rad(np.linspace(0.0, 30.0, 601))
    g = gaussian_echo(grid, params.sigma_deg)
    p = piston_echo(grid, params.diameter_m, params.carrier_hz, params.c_mps)
    with np.errstate(divide="ignore"):
        mismatch = np.abs(1.0 / g - np.where(p > 0, 1.0 / np.maximum(p, 1e-300), np.inf))
    kap = np.asarray(kappa_us, dtype=float)[..., None]
    bad = kap * mismatch[None if kap.ndim == 1 else ...] > tolerance_us
    first_bad = np.where(bad.any(axis=-1), bad.argmax(axis=-1), grid.size - 1)
    return grid[np.maximum(first_bad - 1, 0)]


def echo_delays_us(
    theta_rad: ArrayLike,
    kappa_us: ArrayLike,
    tier: Tier | str,
    rng: np.random.Generator,
    params: ModuleParams = ModuleParams(),
) -> tuple[NDArray[np.float64], NDArray[np.int8]]:
    """Random threshold delays of echoes and the tier that produced each.

    Parameters
    ----------
    theta_rad : (...,) off-axis angle of each echo (transducer axis to reflecting point).
    kappa_us : (...,) reflector strength tau/A0, broadcast with ``theta_rad``.
    tier : model tier, or ``auto``.

    Returns
    -------
    delay_us : (...,) delay after the arrival To; NaN where the echo is not detected.
    tier_used : (...,) :class:`Tier` code per echo.
    """
    t = Tier.parse(tier)
    theta, kap = np.broadcast_arrays(np.asarray(theta_rad, float), np.asarray(kappa_us, float))
    if t is Tier.WAVEFORM:
        raise NotImplementedError("waveform tier: see sonarloc.physics.waveform")
    if t is Tier.GAUSS:
        used = np.full(theta.shape, Tier.GAUSS, dtype=np.int8)
    elif t is Tier.PISTON:
        used = np.full(theta.shape, Tier.PISTON, dtype=np.int8)
    else:
        use_gauss = np.abs(theta) <= gauss_valid_rad(kap, params)
        used = np.where(use_gauss, Tier.GAUSS, Tier.PISTON).astype(np.int8)
    amp = np.where(
        used == Tier.GAUSS,
        gaussian_echo(theta, params.sigma_deg),
        piston_echo(theta, params.diameter_m, params.carrier_hz, params.c_mps),
    )
    return sample_echo_delay_us(kap, amp, rng, params), used
