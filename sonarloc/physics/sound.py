"""Speed of sound in air."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def speed_of_sound_mps(temperature_c: ArrayLike) -> NDArray[np.float64]:
    """Speed of sound in dry air, c = 331.3 + 0.606 T  [m/s].

    Parameters
    ----------
    temperature_c : (...,) air temperature in degrees Celsius, in [-50, 60].

    Examples
    --------
    >>> float(speed_of_sound_mps(19.8))
    343.2988
    """
    t = np.asarray(temperature_c, dtype=float)
    if not np.all(np.isfinite(t)) or np.any((t < -50.0) | (t > 60.0)):
        raise ValueError(f"`temperature_c` must be within [-50, 60] degC, got {temperature_c!r}")
    return 331.3 + 0.606 * t


AIR_C_RANGE_MPS = (250.0, 450.0)
"""Speeds of sound [m/s] a sonar in air can meet, with a margin: 301 m/s at -50 degC to
368 m/s at 60 degC in dry air (:func:`speed_of_sound_mps`), a few m/s more in humid air.
A value outside is a typo or a unit error (``3.43``, ``3430``, ``1e308``), which the
fit would otherwise turn into landmarks at the wrong range marked ``ok``."""


def check_air_speed_of_sound(c_mps: float, name: str = "c_mps") -> float:
    """``c_mps`` as a float if it is a speed of sound in air (:data:`AIR_C_RANGE_MPS`);
    ValueError naming ``name`` otherwise."""
    lo, hi = AIR_C_RANGE_MPS
    c = float(c_mps)
    if not lo <= c <= hi:     # (NaN fails too)
        raise ValueError(f"{name} must be within [{lo:g}, {hi:g}] m/s (sound in air: "
                         f"301 m/s at -50 degC to 368 m/s at 60 degC), got {c_mps!r}")
    return c


def range_from_tof_m(tof_us: ArrayLike, c_mps: float = 343.0) -> NDArray[np.float64]:
    """Range to the reflector, r = c To / 2, from a round-trip time in microseconds."""
    return np.asarray(tof_us, dtype=float) * 1e-6 * c_mps / 2.0


def tof_from_range_us(range_m: ArrayLike, c_mps: float = 343.0) -> NDArray[np.float64]:
    """Round-trip time To = 2 r / c in microseconds."""
    return 2.0 * np.asarray(range_m, dtype=float) / c_mps * 1e6
