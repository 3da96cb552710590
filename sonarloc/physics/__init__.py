"""Pure physics of the Polaroid sonar: beam patterns, TOF models, reflectors.

Nothing here does I/O or keeps state; every function broadcasts over batch axes.
"""

from sonarloc.physics.beam import first_null_rad, gaussian_echo, piston_echo, piston_one_way
from sonarloc.physics.sound import range_from_tof_m, speed_of_sound_mps, tof_from_range_us
from sonarloc.physics.tof import (
    ModuleParams,
    apply_module,
    eq3_tof_us,
    jitter_sd_us,
    quantize_tof_us,
    sample_echo_delay_us,
    threshold_delay_us,
)

__all__ = [
    "ModuleParams", "apply_module", "eq3_tof_us", "first_null_rad", "gaussian_echo",
    "jitter_sd_us", "piston_echo", "piston_one_way", "quantize_tof_us", "range_from_tof_m",
    "sample_echo_delay_us", "speed_of_sound_mps", "threshold_delay_us", "tof_from_range_us",
]
