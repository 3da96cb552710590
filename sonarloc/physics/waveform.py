"""Waveform tier: a simulated Polaroid 6500 ranging module.

The module's echo processing is simulated once, for a unit on-axis echo, and the
result is reused for every echo (rectification commutes with positive scaling, so
an echo of relative amplitude ``a`` produces the processed signal ``a * w(t)``):

1. the 16-cycle 49.4 kHz burst, starting (like the paper's analytic model, whose
   rectified echo is a step) at a carrier crest at the echo arrival To;
2. the transducer's transmit/receive response: a broadband part (the electrostatic
   foil follows the drive at once) plus a resonant band-pass at the carrier
   (quality ``transducer_q``, share ``resonant_fraction``) that builds up over the
   first cycles and rings on after the burst;
3. full-wave rectification, scaled so the rectified echo starts at 1;
4. lossy (leaky) integration with time constant ``integrator_tau_us``;
5. threshold detection: the reading is the first time ``a * w(t)`` reaches the
   threshold.

Units: with the scaling in step 3 the processed signal starts as the ramp ``t`` [us]
of eq. 3, so a threshold is expressed as the eq. 3 threshold delay ``u = kappa/a``
[us] (the module's fixed threshold tau over the echo amplitude; see
:func:`crossing_delay_us`).

Calibration against eq. 3 (documented in docs/PHYSICS_MODEL.md):

* the leak ``integrator_tau_us`` is solved for so that the peak of ``w`` equals the
  module's ``detection_limit_us``: an echo is detected exactly when eq. 3 says so
  (``kappa/a <= detection_limit_us``), so arcs and threshold levels are the same in
  every tier;
* with ``transducer_q = 1`` and ``resonant_fraction = 0.5`` the resonant build-up
  cancels the leak's early curvature, so an echo that crosses in the first half
  cycle (``u`` below about 3.4 us, which includes the paper's plane, pole and rod on
  the axis) reads within 0.11 us of eq. 3 (no later than eq. 3 by more than 0.02 us).

What eq. 3 lacks and this shows: as the amplitude falls the crossing moves to the
next ripple crest (jumps of up to one half period, 10.1 us), the slope of the
processed signal decreases so weak echoes read later than eq. 3 (up to about
100 us near the detection limit), and the flatter slope turns amplitude
fluctuation into larger timing spread.  Side lobes come from the piston pattern
used for ``a``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.physics.tof import ModuleParams

SAMPLES_PER_PERIOD = 1000
"""Time resolution of the template: carrier period / 1000 (0.02 us at 49.4 kHz)."""


@dataclass(frozen=True, eq=False)
class WaveformTemplate:
    """The processed echo of a unit on-axis echo, sampled uniformly from To.

    Attributes
    ----------
    dt_us : sample spacing [us].
    processed : (n,) processed signal w(t_i), t_i = i * dt_us, in eq. 3 units [us].
    running_max : (n,) max of ``processed`` over [0, t_i] (non-decreasing).
    integrator_tau_us : calibrated leak time constant of the integrator [us].
    burst_us : duration of the emitted burst [us].
    half_period_us : half the carrier period, the ripple period [us].
    u_step_us : spacing of the threshold grid of ``crossing_table`` [us].
    crossing_table : (m + 1,) exact crossing time at thresholds j * u_step_us [us].
    crossing_slope : (m + 1,) its increment to the next node (0 at the last) [us].
    exact_cells : (m + 1,) True for grid cells across which the crossing jumps (a
        ripple plateau) or moves fast; there the crossing is searched in the template
        instead of interpolated in ``crossing_table``.
    """

    dt_us: float
    processed: NDArray[np.float64]
    running_max: NDArray[np.float64]
    integrator_tau_us: float
    burst_us: float
    half_period_us: float
    u_step_us: float
    crossing_table: NDArray[np.float64]
    crossing_slope: NDArray[np.float64]
    exact_cells: NDArray[np.bool_]

    @property
    def peak_us(self) -> float:
        """Largest value of the processed signal (= the detection limit) [us]."""
        return float(self.running_max[-1])

    @property
    def t_us(self) -> NDArray[np.float64]:
        """(n,) sample times after the echo arrival [us]."""
        return np.arange(self.processed.size, dtype=float) * self.dt_us


def _one_pole(x: NDArray[np.float64], pole: float | complex) -> NDArray[Any]:
    """``y[n] = x[n] + pole * y[n-1]`` from rest, for a stable pole (``|pole| < 1``).

    By recursive doubling: after the pass with ``pole**k`` (k = 1, 2, 4, ...) every
    ``y[n]`` holds the sum over its last ``2k`` inputs, so ``ceil(log2 n)`` vectorised
    passes replace the loop over samples. The coefficients are powers of the pole
    (``|pole|**k <= 1``), so a pass adds rounding (about one unit of the partial
    sums' size), not growth. Real input and pole give a real result, a complex pole
    a complex one.

    Parameters
    ----------
    x : (n,) input.
    pole : the pole (real or complex).

    Returns
    -------
    (n,) output.
    """
    y = x.astype(np.result_type(x, pole))
    k = 1
    while k < y.size:
        y[k:] += pole ** k * y[:-k]
        k *= 2
    return y


def _bandpass(x: NDArray[np.float64], omega: float, q: float, fs_hz: float
              ) -> NDArray[np.float64]:
    """The transducer's resonant band-pass applied to samples ``x`` (from rest).

    The bilinear transform ``s = 2 fs (z - 1) / (z + 1)`` of
    ``H(s) = (omega/q) s / (s^2 + (omega/q) s + omega^2)``: the gain
    ``g = (omega/q) 2 fs / (4 fs^2 + (omega/q) 2 fs + omega^2)``, zeros at z = +-1 and
    the poles ``(2 fs + s_i) / (2 fs - s_i)`` of the analog poles ``s_i``, applied as
    the difference ``g (x[n] - x[n-2])`` followed by one one-pole section per pole
    (:func:`_one_pole`). At 1000 samples per period the poles lie within 0.005 of
    z = 1, where a polynomial denominator (``scipy.signal.bilinear`` / ``lfilter``)
    is ill-conditioned: rounding its coefficients to double moves the output by
    ~1e-11 of its size (q = 1), the exact poles keep it within ~3e-14 (checked
    against a 40-digit recursion). Distinct, double (q = 1/2) and complex poles alike.

    Parameters
    ----------
    x : (n,) input samples.
    omega : resonance [rad/s].
    q : quality factor (> 0).
    fs_hz : sample rate [Hz].

    Returns
    -------
    (n,) output samples.
    """
    k = 2.0 * fs_hz
    bw = omega / q
    gain = bw * k / (k * k + bw * k + omega * omega)
    root = omega * np.sqrt(complex(0.25 / (q * q) - 1.0))
    u = gain * x
    u[2:] -= gain * x[:-2]
    for s_pole in (-0.5 * bw + root, -0.5 * bw - root):
        u = _one_pole(u, (k + s_pole) / (k - s_pole))
    return np.asarray(u.real, dtype=float)


@functools.lru_cache(maxsize=8)
def _rectified_echo(carrier_hz: float, burst_cycles: int, q: float, b: float, n: int
                    ) -> NDArray[np.float64]:
    """Steps 1-3 for the first ``n`` samples (a causal filter: any longer signal starts
    with the same samples)."""
    omega = 2.0 * np.pi * carrier_hz
    dt_us = 1e6 / (carrier_hz * SAMPLES_PER_PERIOD)
    burst_us = burst_cycles * 1e6 / carrier_hz
    t_us = np.arange(n) * dt_us
    drive = np.where(t_us < burst_us, np.cos(omega * t_us * 1e-6), 0.0)
    if b > 0.0:
        echo = (1.0 - b) * drive + b * _bandpass(drive, omega, q, 1e6 / dt_us)
    else:
        echo = drive
    out = np.abs(echo) / (1.0 - b)
    out.setflags(write=False)
    return out


def _processed_unit_echo(
    integrator_tau_us: float, carrier_hz: float, burst_cycles: int, q: float, b: float,
) -> tuple[float, NDArray[np.float64]]:
    """Processed signal of a unit echo for a given leak; returns (dt_us, w)."""
    omega = 2.0 * np.pi * carrier_hz
    dt_us = 1e6 / (carrier_hz * SAMPLES_PER_PERIOD)
    burst_us = burst_cycles * 1e6 / carrier_hz
    ring_us = 2.0 * q / omega * 1e6  # envelope time constant of the resonance
    n = int(np.ceil((burst_us + 12.0 * ring_us + 5.0 * integrator_tau_us) / dt_us)) + 1
    # the band-passed, rectified echo for a power-of-two length (one for all the leaks
    # the calibration tries), cut to n samples
    rect = _rectified_echo(carrier_hz, burst_cycles, q, b, 1 << (n - 1).bit_length())[:n]
    # Trapezoidal leaky integration, w[0] = 0.
    decay = np.exp(-dt_us / integrator_tau_us)
    w = np.zeros(n)
    w[1:] = _one_pole(0.5 * dt_us * (rect[1:] + decay * rect[:-1]), float(decay))
    return dt_us, w


_STORED_LEAKS_US: dict[tuple[float, int, float, float, float], float] = {
    (49.4e3, 16, 1.0, 0.5, 12.0): 8.404799957508134,
}
"""Calibrated leaks (:func:`_calibrate_leak`) by ``(carrier_hz, burst_cycles,
transducer_q, resonant_fraction, detection_limit_us)``: the default module's, stored so
that a process using it does not import scipy.optimize for the root finder (0.12 s CPU,
two thirds of a ``sonarloc fit`` process's set-up). The calibration's own result to
the last bit (x86_64 Linux); tests/physics/test_waveform.py recalibrates every entry.
Other modules are calibrated when first used."""


def _calibrate_leak(carrier_hz: float, burst_cycles: int, q: float, b: float,
                    peak_us: float) -> float:
    """The integrator's leak [us] whose processed unit echo peaks at ``peak_us``
    (a root of the peak's excess, to 1e-9 us)."""
    def excess(tau_us: float) -> float:
        return float(_processed_unit_echo(tau_us, carrier_hz, burst_cycles, q, b)[1].max()
                     - peak_us)

    hi = 1e6 * burst_cycles / carrier_hz  # no leak to speak of within the burst
    if excess(hi) <= 0.0:
        raise ValueError(
            f"`detection_limit_us` {peak_us!r} cannot be reached by a {burst_cycles}-cycle "
            "burst; use a longer burst or a smaller limit"
        )
    from scipy import optimize

    return float(optimize.brentq(excess, 1e-3, hi, xtol=1e-9, rtol=1e-12))


@functools.lru_cache(maxsize=16)
def _template(carrier_hz: float, burst_cycles: int, q: float, b: float,
              peak_us: float) -> WaveformTemplate:
    tau = _STORED_LEAKS_US.get((carrier_hz, burst_cycles, q, b, peak_us))
    if tau is None:
        tau = _calibrate_leak(carrier_hz, burst_cycles, q, b, peak_us)
    dt_us, w = _processed_unit_echo(tau, carrier_hz, burst_cycles, q, b)
    # remove the root finder's last 1e-9 of mismatch, and the scaling's rounding: the
    # peak is the limit exactly (an echo at the limit is detected, as in eq. 3)
    top = int(np.argmax(w))
    w *= peak_us / w[top]
    np.minimum(w, peak_us, out=w)
    w[top] = peak_us
    m = np.maximum.accumulate(w)
    u_step = peak_us / _TABLE_CELLS
    table = _search_crossing(np.arange(_TABLE_CELLS + 1, dtype=float) * u_step, w, m, dt_us)
    # Linear interpolation inside a cell is good to well below dt_us unless the crossing
    # moves by more than a few samples across it (a plateau of the running maximum).
    slope = np.append(np.diff(table), 0.0)
    exact = slope > 4.0 * dt_us
    for arr in (w, m, table, slope, exact):
        arr.setflags(write=False)
    return WaveformTemplate(dt_us, w, m, tau, burst_cycles * 1e6 / carrier_hz,
                            0.5e6 / carrier_hz, u_step, table, slope, exact)


_TABLE_CELLS = 1 << 17
"""Cells of the threshold grid for fast crossing look-ups (about 1e-4 us each)."""


def _search_crossing(u: NDArray[np.float64], w: NDArray[np.float64],
                     m: NDArray[np.float64], dt_us: float) -> NDArray[np.float64]:
    """First crossing of level ``u`` (<= peak) by ``w``, by binary search of ``m``."""
    # The first sample with w >= u starts a new maximum, so it is the first index at
    # which the running maximum reaches u; interpolate w between it and the sample before.
    i = np.clip(np.searchsorted(m, u, side="left"), 1, m.size - 1)
    w0 = w[i - 1]
    w1 = w[i]
    frac = np.clip((u - w0) / np.where(w1 > w0, w1 - w0, 1.0), 0.0, 1.0)
    return np.where(u <= 0.0, 0.0, (i - 1 + frac) * dt_us)


def waveform_template(params: ModuleParams = ModuleParams()) -> WaveformTemplate:
    """The (cached) processed unit echo for a module; computed once per parameter set."""
    return _template(params.carrier_hz, params.burst_cycles, params.transducer_q,
                     params.resonant_fraction, params.detection_limit_us)


def processed_echo(
    t_us: ArrayLike, rel_amp: ArrayLike, params: ModuleParams = ModuleParams()
) -> NDArray[np.float64]:
    """Processed signal a * w(t) of an echo of relative amplitude ``a`` [us units].

    Parameters
    ----------
    t_us : (...,) time after the echo arrival To [us]; 0 before it.
    rel_amp : (...,) echo amplitude relative to the on-axis echo (beam pattern, gain).
    """
    tpl = waveform_template(params)
    t = np.asarray(t_us, dtype=float)
    w = np.interp(t, tpl.t_us, tpl.processed, left=0.0, right=0.0)
    return np.asarray(rel_amp, dtype=float) * w


def crossing_delay_us(
    u_us: ArrayLike, params: ModuleParams = ModuleParams()
) -> NDArray[np.float64]:
    """First time after To at which the processed echo reaches the threshold [us].

    Parameters
    ----------
    u_us : (...,) eq. 3 threshold delay tau/(A0 a) = kappa/a of each echo [us]: the
        threshold in units of the processed signal of a unit echo.

    Returns
    -------
    (...,) crossing time [us]; NaN where ``u_us`` exceeds the peak of the processed
    signal (the echo is not detected) or is NaN. Equals eq. 3's ``u_us`` while the
    crossing falls in the first half cycle, later beyond.

    Examples
    --------
    >>> round(float(crossing_delay_us(0.67)), 2)
    0.64
    """
    tpl = waveform_template(params)
    u = np.asarray(u_us, dtype=float)
    x = np.multiply(u, 1.0 / tpl.u_step_us, out=np.empty_like(u))
    np.fmin(x, _TABLE_CELLS, out=x)  # fmin/fmax also turn NaN into a valid index
    np.fmax(x, 0.0, out=x)
    j = x.astype(np.intp)
    x -= j
    x *= tpl.crossing_slope[j]
    x += tpl.crossing_table[j]
    hard = tpl.exact_cells[j]
    if hard.any():
        x[hard] = _search_crossing(np.clip(u[hard], 0.0, tpl.peak_us), tpl.processed,
                                   tpl.running_max, tpl.dt_us)
    x[~(u <= tpl.running_max[-1])] = np.nan  # not detected (or NaN)
    return x


def waveform_delay_us(
    kappa_us: ArrayLike, rel_amp: ArrayLike, params: ModuleParams = ModuleParams()
) -> NDArray[np.float64]:
    """Noise-free threshold delay of an echo in the waveform tier [us]; NaN if undetected.

    Parameters
    ----------
    kappa_us : (...,) reflector strength tau/A0 [us].
    rel_amp : (...,) relative echo amplitude (beam pattern), broadcast with ``kappa_us``.
    """
    kap = np.asarray(kappa_us, dtype=float)
    a = np.asarray(rel_amp, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(a > 0, kap / np.where(a > 0, a, 1.0), np.inf)
    return crossing_delay_us(u, params)


def eq3_agreement_limit_us(
    params: ModuleParams = ModuleParams(), tolerance_us: float = 0.5
) -> float:
    """Largest eq. 3 delay ``u`` up to which the waveform tier agrees with eq. 3.

    Returns the ``u`` [us] below which |crossing_delay_us(u) - u| <= ``tolerance_us``
    for every smaller ``u`` as well (evaluated on a 0.001 us grid).
    """
    if not (np.isfinite(tolerance_us) and tolerance_us > 0):
        raise ValueError(f"`tolerance_us` must be positive, got {tolerance_us!r}")
    return _agreement_limit(params, float(tolerance_us))


@functools.lru_cache(maxsize=32)
def _agreement_limit(params: ModuleParams, tolerance_us: float) -> float:
    tpl = waveform_template(params)
    u = np.arange(0.0, tpl.peak_us, 1e-3)
    bad = np.abs(crossing_delay_us(u, params) - u) > tolerance_us
    return float(u[np.argmax(bad)] - 1e-3) if bad.any() else tpl.peak_us
