"""Beam patterns of the circular piston transducer and its Gaussian approximation.

All angles are off-axis angles in radians; patterns are relative *echo* amplitudes
(transmit times receive), 1 on the axis, and broadcast over any array shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import j1

from sonarloc.physics.constants import (
    CARRIER_HZ,
    GAUSS_SIGMA_DEG,
    SPEED_OF_SOUND_MPS,
    TRANSDUCER_DIAMETER_M,
)


def _check_positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"`{name}` must be positive, got {value!r}")


def piston_x(
    theta_rad: ArrayLike,
    diameter_m: float = TRANSDUCER_DIAMETER_M,
    freq_hz: float = CARRIER_HZ,
    c_mps: float = SPEED_OF_SOUND_MPS,
) -> NDArray[np.float64]:
    """Argument x = pi d sin(theta) / lambda of the piston directivity, shape of ``theta_rad``."""
    _check_positive("diameter_m", diameter_m)
    _check_positive("freq_hz", freq_hz)
    _check_positive("c_mps", c_mps)
    scale = np.pi * diameter_m * freq_hz / c_mps  # pi d / lambda
    x = np.sin(np.asarray(theta_rad, dtype=float))
    x *= scale
    return x


def piston_one_way(
    theta_rad: ArrayLike,
    diameter_m: float = TRANSDUCER_DIAMETER_M,
    freq_hz: float = CARRIER_HZ,
    c_mps: float = SPEED_OF_SOUND_MPS,
) -> NDArray[np.float64]:
    """One-way (transmit) directivity 2 J1(x)/x, signed; 1 on the axis.

    Examples
    --------
    >>> round(float(piston_one_way(0.0)), 6)
    1.0
    """
    x = np.asarray(piston_x(theta_rad, diameter_m, freq_hz, c_mps))
    d = j1(x)
    d *= 2.0
    # J1(x) ~ x/2 keeps full relative precision for tiny x; only x == 0 needs the limit.
    return np.asarray(np.divide(d, x, out=np.ones_like(x), where=x != 0.0))


def piston_echo(
    theta_rad: ArrayLike,
    diameter_m: float = TRANSDUCER_DIAMETER_M,
    freq_hz: float = CARRIER_HZ,
    c_mps: float = SPEED_OF_SOUND_MPS,
) -> NDArray[np.float64]:
    """Transmit/receive echo amplitude (2 J1(x)/x)^2, in [0, 1] (reciprocity)."""
    d = piston_one_way(theta_rad, diameter_m, freq_hz, c_mps)
    d *= d
    return d


def gaussian_echo(theta_rad: ArrayLike, sigma_deg: float = GAUSS_SIGMA_DEG) -> NDArray[np.float64]:
    """Gaussian main-lobe approximation exp(-theta^2 / (2 sigma^2)) of the echo amplitude.

    Good only over the central main lobe (|theta| below about 10 deg); it has no nulls
    and no side lobes.
    """
    _check_positive("sigma_deg", sigma_deg)
    sigma = np.deg2rad(sigma_deg)
    t = np.asarray(theta_rad, dtype=float)
    return np.exp(-(t * t) / (2.0 * sigma * sigma))


def first_null_rad(
    diameter_m: float = TRANSDUCER_DIAMETER_M,
    freq_hz: float = CARRIER_HZ,
    c_mps: float = SPEED_OF_SOUND_MPS,
) -> float:
    """Off-axis angle of the first null, asin(3.8317 lambda / (pi d)) (about 14 deg).

    Returns pi/2 when the transducer is too small to have a null.
    """
    _check_positive("diameter_m", diameter_m)
    _check_positive("freq_hz", freq_hz)
    _check_positive("c_mps", c_mps)
    s = 3.831705970207512 * (c_mps / freq_hz) / (np.pi * diameter_m)
    return float(np.arcsin(s)) if s < 1.0 else float(np.pi / 2)
