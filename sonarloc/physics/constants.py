"""Nominal parameters of the Polaroid 6500 ranging module and 600-series transducer.

Values and their sources are in ../shared/PHYSICS.md (R. Kuc, IEEE T-RA 19(2), 2003).
"""

from __future__ import annotations

SPEED_OF_SOUND_MPS = 343.0
"""Speed of sound used by the paper (about 20 degC)."""

CARRIER_HZ = 49.4e3
"""Burst frequency F0."""

BURST_CYCLES = 16
"""Cycles per ping (pulse about 324 us)."""

TRANSDUCER_Q = 1.0
"""Quality of the transducer's resonant band-pass (waveform tier): broad, as befits an
electrostatic foil transducer."""

RESONANT_FRACTION = 0.5
"""Share of the transducer response that is resonant (the rest follows the drive at
once). With ``TRANSDUCER_Q`` it makes the waveform tier's first half cycle agree with
eq. 3 within 0.11 us (see ``sonarloc.physics.waveform``)."""

TRANSDUCER_DIAMETER_M = 0.036
"""Piston diameter d of the 600-series electrostatic transducer."""

GAUSS_SIGMA_DEG = 5.25
"""Width of the Gaussian approximation to the echo (transmit/receive) main lobe."""

DETECTION_LIMIT_US = 12.0
"""Largest threshold delay kappa/rel_amp still detected (derived from the paper's arcs)."""

JITTER_SD_US = 5.0
"""On-axis TOF jitter from air turbulence (0.9 mm of range)."""

JITTER_AMPLITUDE_FRACTION = 0.5
"""Relative echo-amplitude fluctuation that turns into delay jitter off axis.

A delay kappa/a fluctuates by this fraction of itself, so the jitter grows from
5 us on axis to about 7.8 us at the edge of the detected arc (delay 12 us).
"""

COUNT_PERIOD_US = 2.0
"""Query cycle of the TOF counter: a reading is the first count after the crossing."""

BLANKING_US = 900.0
"""Receiver blanking after the burst: nothing nearer than about 0.15 m (6 in) is seen."""

MAX_RANGE_M = 10.67
"""Longest range of the module (35 ft)."""

KAPPA_US = {"plane": 0.15, "wall": 0.15, "corner": 0.15, "pole": 0.67, "rod": 2.68, "edge": 2.68,
            "point": 0.67}
"""Default reflecting strength (threshold delay coefficient tau/A0) by reflector kind.

plane/pole/rod are the paper's values at 1.5 m; corners act like planes; an edge is
a weak diffracting point (seen only within ~0.5 m, see ``EDGE_MAX_RANGE_M``).
"""

EDGE_MAX_RANGE_M = 0.5
"""Edges produce detectable echoes only nearer than this."""
