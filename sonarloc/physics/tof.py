"""First-order threshold-detection TOF model (Kuc 2003, eq. 3) and the module's limits.

The ranging module reports the first time Tm the processed echo exceeds a threshold.
For an echo of relative amplitude ``a`` (beam pattern) from a reflector of strength
``kappa_us`` = tau/A0 the crossing comes ``kappa_us / a`` after the arrival To = 2r/c:

    Tm = To + kappa / a(theta)      (Gaussian beam: To + kappa exp(theta^2 / 2 sigma^2))

An echo whose delay would exceed ``detection_limit_us`` is not detected. Random
effects: a log-normal echo-amplitude fluctuation (turbulence; it makes off-axis
jitter grow and softens the arc edges) and a timing jitter of 5 us SD. The module
counts in 2 us query cycles and reports the first count after the crossing.
All functions broadcast over leading batch axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.physics import constants as k


@dataclass(frozen=True)
class ModuleParams:
    """Parameters of a ranging module and its transducer (defaults: Polaroid 6500/600).

    ``jitter_sd_us`` is the on-axis timing jitter; ``amplitude_fluctuation`` the SD of
    the log echo amplitude (0.25: arcs measured over 100 pings per angle match the
    paper's 18.6/22.8/45 deg); ``detection_limit_us`` the largest threshold delay
    still detected. ``burst_cycles``, ``transducer_q`` and ``resonant_fraction``
    shape the waveform tier's simulated module (``sonarloc.physics.waveform``).
    """

    c_mps: float = k.SPEED_OF_SOUND_MPS
    carrier_hz: float = k.CARRIER_HZ
    diameter_m: float = k.TRANSDUCER_DIAMETER_M
    sigma_deg: float = k.GAUSS_SIGMA_DEG
    detection_limit_us: float = k.DETECTION_LIMIT_US
    jitter_sd_us: float = k.JITTER_SD_US
    amplitude_fluctuation: float = 0.25
    count_period_us: float = k.COUNT_PERIOD_US
    blanking_us: float = k.BLANKING_US
    max_range_m: float = k.MAX_RANGE_M
    burst_cycles: int = k.BURST_CYCLES
    transducer_q: float = k.TRANSDUCER_Q
    resonant_fraction: float = k.RESONANT_FRACTION

    def __post_init__(self) -> None:
        for name in ("c_mps", "carrier_hz", "diameter_m", "sigma_deg", "detection_limit_us",
                     "count_period_us", "max_range_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"`{name}` must be positive, got {value!r}")
        for name in ("jitter_sd_us", "amplitude_fluctuation", "blanking_us"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"`{name}` must be non-negative, got {value!r}")
        if isinstance(self.burst_cycles, bool) or not isinstance(self.burst_cycles, int) \
                or self.burst_cycles < 1:
            raise ValueError(
                f"`burst_cycles` must be a positive integer, got {self.burst_cycles!r}")
        if not (np.isfinite(self.transducer_q) and self.transducer_q > 0):
            raise ValueError(f"`transducer_q` must be positive, got {self.transducer_q!r}")
        if not (np.isfinite(self.resonant_fraction) and 0 <= self.resonant_fraction < 1):
            raise ValueError(
                f"`resonant_fraction` must be in [0, 1), got {self.resonant_fraction!r}"
            )

    @property
    def max_tof_us(self) -> float:
        """Round-trip time of the maximum range."""
        return 2.0 * self.max_range_m / self.c_mps * 1e6


def threshold_delay_us(kappa_us: ArrayLike, rel_amp: ArrayLike) -> NDArray[np.float64]:
    """Delay kappa / a of the threshold crossing after the echo arrival; inf where a <= 0."""
    kap = np.asarray(kappa_us, dtype=float)
    a = np.asarray(rel_amp, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(a > 0, kap / np.where(a > 0, a, 1.0), np.inf)


def eq3_tof_us(
    to_us: ArrayLike, theta_rad: ArrayLike, kappa_us: ArrayLike,
    sigma_deg: float = k.GAUSS_SIGMA_DEG,
) -> NDArray[np.float64]:
    """The paper's eq. 3, Tm = To + kappa exp(theta^2 / (2 sigma^2)), noise-free [us].

    Examples
    --------
    >>> round(float(eq3_tof_us(8522.0, 0.0, 0.67)), 2)
    8522.67
    """
    if not (np.isfinite(sigma_deg) and sigma_deg > 0):
        raise ValueError(f"`sigma_deg` must be positive, got {sigma_deg!r}")
    s = np.deg2rad(sigma_deg)
    t = np.asarray(theta_rad, dtype=float)
    return np.asarray(to_us, dtype=float) + np.asarray(kappa_us, dtype=float) * np.exp(
        t * t / (2.0 * s * s)
    )


def jitter_sd_us(delay_us: ArrayLike, params: ModuleParams = ModuleParams()) -> NDArray[np.float64]:
    """Expected TOF SD [us] of a reading whose (mean) threshold delay is ``delay_us``.

    sqrt(jitter^2 + (amplitude_fluctuation * delay)^2): 5 us on the axis, growing off
    axis as weaker echoes cross later. Use it to weight fits.
    """
    d = np.asarray(delay_us, dtype=float)
    return np.hypot(params.jitter_sd_us, params.amplitude_fluctuation * d)


def quantize_tof_us(
    tm_us: ArrayLike, count_period_us: float = k.COUNT_PERIOD_US
) -> NDArray[np.float64]:
    """Reading reported by the counter: the first count after the true crossing.

    Adds a mean bias of half a period (+1 us) and a uniform error of SD period/sqrt(12).
    NaN (no echo) stays NaN.
    """
    t = np.asarray(tm_us, dtype=float)
    return count_period_us * (np.floor(t / count_period_us) + 1.0)


def sample_echo_delay_us(
    kappa_us: ArrayLike,
    rel_amp: ArrayLike,
    rng: np.random.Generator,
    params: ModuleParams = ModuleParams(),
) -> NDArray[np.float64]:
    """One random threshold delay per echo, with amplitude fluctuation; NaN if undetected.

    Parameters
    ----------
    kappa_us, rel_amp : (...,) reflector strength and beam-pattern echo amplitude.
    rng : source of randomness (seed it for repeatable simulations).
    """
    kap, a = np.broadcast_arrays(np.asarray(kappa_us, float), np.asarray(rel_amp, float))
    gain = np.exp(params.amplitude_fluctuation * rng.standard_normal(kap.shape))
    delay = threshold_delay_us(kap, a * gain)
    return np.where(delay <= params.detection_limit_us, delay, np.nan)


def apply_module(
    tm_us: ArrayLike, rng: np.random.Generator, params: ModuleParams = ModuleParams(),
    axis: int = -1,
) -> NDArray[np.float64]:
    """From candidate crossing times of several echoes to the module's reading.

    The nearest detected crossing wins (first threshold crossing); timing jitter is
    added, then blanking, range gate and counting. ``tm_us`` has the candidate echoes
    along ``axis`` (NaN = not detected); the result drops that axis, NaN = no echo.
    """
    tm = np.asarray(tm_us, dtype=float)
    if tm.ndim == 0:
        tm = tm[None]
    tm = np.moveaxis(tm, axis, -1)
    if tm.shape[-1] == 0:
        first = np.full(tm.shape[:-1], np.nan)
    else:
        filled = np.where(np.isnan(tm), np.inf, tm)
        first = filled.min(axis=-1)
        first = np.where(np.isinf(first), np.nan, first)
    first = first + params.jitter_sd_us * rng.standard_normal(first.shape)
    first = np.where((first >= params.blanking_us) & (first <= params.max_tof_us), first, np.nan)
    return quantize_tof_us(first, params.count_period_us)
