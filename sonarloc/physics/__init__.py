"""Pure physics of the Polaroid sonar: beam patterns, TOF models, reflectors.

Nothing here does I/O or keeps state; every function broadcasts over batch axes.
Model tiers (gauss, piston, waveform, auto) are in :mod:`sonarloc.physics.tiers`,
the simulated ranging module in :mod:`sonarloc.physics.waveform`, reflector kinds and
strengths in :mod:`sonarloc.physics.reflectors`.
"""

from sonarloc.physics.beam import first_null_rad, gaussian_echo, piston_echo, piston_one_way
from sonarloc.physics.reflectors import (
    Reflector,
    ReflectorKind,
    cylinder_kappa_us,
    default_kappa_us,
    kappa_at_range_us,
    make_reflector,
)
from sonarloc.physics.sound import range_from_tof_m, speed_of_sound_mps, tof_from_range_us
from sonarloc.physics.tiers import Tier, echo_delays_us
from sonarloc.physics.tof import (
    ModuleParams,
    apply_module,
    eq3_tof_us,
    jitter_sd_us,
    quantize_tof_us,
    sample_echo_delay_us,
    threshold_delay_us,
)
from sonarloc.physics.waveform import crossing_delay_us, processed_echo, waveform_delay_us

__all__ = [
    "ModuleParams", "Reflector", "ReflectorKind", "Tier", "apply_module", "crossing_delay_us",
    "cylinder_kappa_us", "default_kappa_us", "echo_delays_us", "eq3_tof_us", "first_null_rad",
    "gaussian_echo", "jitter_sd_us", "kappa_at_range_us", "make_reflector", "piston_echo",
    "piston_one_way", "processed_echo", "quantize_tof_us", "range_from_tof_m",
    "sample_echo_delay_us", "speed_of_sound_mps", "threshold_delay_us", "tof_from_range_us",
    "waveform_delay_us",
]
