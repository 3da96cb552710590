"""Adversarial inputs to the fitting path, as a robot in the field can produce them.

The issue's demand: no input may make the fitter raise or return NaN marked as success,
and a fit that cannot be trusted says why. Seeded cases from the session-15 sweep (the
full sweep and its repro files: /work/scratch/fuzz15/), each run through
:func:`fit_scan` and :class:`OnlineFitter` in blocks, and the regressions of what it
found.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from sonarloc.fit.landmarks import OnlineFitter, fit_scan, fit_segments
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import Segmenter
from sonarloc.fit.synth import Reflector, pan_scan, rotation_scan
from sonarloc.io.scancsv import ScanReadings
from sonarloc.physics.tof import ModuleParams

# Absurd inputs (TOFs of 1e300 us, poses 1e7 m out) overflow float32 passes on the way to
# their BAD_INPUT / FLAT statuses: numpy's warnings are expected here, the statuses are
# what these tests check.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

_MOD = ModuleParams()
REACH = (0.25 * _MOD.blanking_us * 1e-6 * _MOD.c_mps, 2.0 * _MOD.max_range_m)
"""Ranges [m] an OK landmark may have: from half the range the module's blanking hides
to twice its maximum range (:func:`sonarloc.fit.model.module_reach_m`)."""


def check_invariants(landmarks: list[Landmark]) -> None:
    """What every result must satisfy, whatever the input: ``OK`` means finite
    parameters, range and bearing, a symmetric positive semi-definite covariance, a range
    the module can measure and at least 3 readings; anything else has a reason.

    Semi-definite up to rounding: a wall's (rho, alpha) covariance far from the frame's
    origin is ill-conditioned by its parameterisation (rho's SD grows with alpha's times
    the distance; at 1e5 m its eigenvalues span 20 decades, beyond float64's resolution,
    and the smallest comes out as +-1e-16 of the largest)."""
    for lm in landmarks:
        if not lm.ok:
            assert lm.reason, lm
            continue
        assert np.all(np.isfinite(lm.params)) and np.all(np.isfinite(lm.cov)), lm
        assert math.isfinite(lm.range_m) and math.isfinite(lm.bearing_rad), lm
        assert REACH[0] <= lm.range_m <= REACH[1], lm
        cov = np.asarray(lm.cov)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=0.0)
        ev = np.linalg.eigvalsh(cov)
        assert ev.min() >= -1e-12 * abs(ev).max(), (ev, lm)
        assert lm.n_readings >= 3, lm
        for key in ("range_sd_m", "bearing_sd_deg", "kappa_sd_us"):
            assert math.isfinite(float(lm.extra[key])), (key, lm)  # type: ignore[arg-type]


def _readings(t, x, y, yaw, tof, sensor=0) -> ScanReadings:
    n = len(t)
    f = [np.broadcast_to(np.asarray(a, dtype=float), (n,)).copy() for a in (t, x, y, yaw, tof)]
    return ScanReadings(*f, np.broadcast_to(np.asarray(sensor, dtype=np.int64), (n,)).copy())


def _pan(seed: int = 1) -> ScanReadings:
    refl = [Reflector.polar(1.5, 4.0, 0.67), Reflector.polar(2.5, -30.0, 0.15)]
    return pan_scan(refl, np.random.default_rng(seed), -60, 60, 0.5)


def _with(scan: ScanReadings, **arrays: object) -> ScanReadings:
    fields = {f: getattr(scan, f) for f, _ in ScanReadings.FIELDS}
    n = len(scan)
    for name, v in arrays.items():
        dtype = np.int64 if name == "sensor" else np.float64
        fields[name] = np.broadcast_to(np.asarray(v, dtype=dtype), (n,)).copy()
    return ScanReadings(**fields)  # type: ignore[arg-type]


def _sprinkle(value: float) -> Callable[[np.random.Generator], ScanReadings]:
    def make(rng: np.random.Generator) -> ScanReadings:
        scan = _pan(int(rng.integers(100)))
        tof = scan.tof_us.copy()
        tof[rng.random(len(tof)) < 0.15] = value
        return _with(scan, tof_us=tof)
    return make


def _noise(rng: np.random.Generator) -> ScanReadings:
    n = 3000
    return _readings(np.cumsum(rng.uniform(0, 0.05, n)), rng.normal(0, 1, n),
                     rng.normal(0, 1, n), rng.uniform(-10, 10, n),
                     np.where(rng.random(n) < 0.2, np.nan, rng.uniform(0, 70000, n)),
                     rng.integers(0, 16, n))


def _still(rng: np.random.Generator) -> ScanReadings:
    # a robot standing still staring at a wall: thousands of identical readings
    n = 4000
    return _readings(np.arange(n) * 0.1, 0, 0, 0.0, 8745.0 + rng.integers(0, 2, n) * 2.0)


CASES: dict[str, Callable[[np.random.Generator], ScanReadings]] = {
    "noise": _noise,
    "still at a wall": _still,
    "tof 1e-3 us sprinkled": _sprinkle(1e-3),
    "tof denormal sprinkled": _sprinkle(5e-324),
    "tof 1e7 us sprinkled": _sprinkle(1e7),
    "tof 1e300 us sprinkled": _sprinkle(1e300),
    "tof at the max range sprinkled": _sprinkle(_MOD.max_tof_us),
    "tof in ms": lambda rng: _with(s := _pan(int(rng.integers(100))), tof_us=s.tof_us * 1e-3),
    "tof in ns": lambda rng: _with(s := _pan(int(rng.integers(100))), tof_us=s.tof_us * 1e3),
    "far from the origin": lambda rng: _with(s := _pan(), x_m=s.x_m + 1e6, y_m=s.y_m - 7e5),
    "yaw turning by whole turns": lambda rng: _with(
        s := _pan(), yaw_rad=s.yaw_rad + 2 * np.pi * rng.integers(-3, 4, len(s))),
    "yaw 1e16 rad": lambda rng: _with(s := _pan(), yaw_rad=s.yaw_rad + 1e16),
    "one time stamp": lambda rng: _with(_pan(), t_s=0.0),
    "times shuffled": lambda rng: _with(s := _pan(), t_s=rng.permutation(s.t_s)),
    "sensor ids at int64's ends": lambda rng: _with(
        s := _pan(), sensor=np.where(rng.random(len(s)) < 0.5, 2**63 - 1, -(2**63))),
    "a sensor per reading": lambda rng: _with(s := _pan(), sensor=np.arange(len(s)) * 2**40),
    "rotation far away, spun": lambda rng: _with(
        s := rotation_scan(2000, rng), x_m=s.x_m + 1e7, yaw_rad=s.yaw_rad + np.deg2rad(1e4)),
    "exactly 5 identical": lambda rng: _readings(np.arange(5) * 0.1, 0, 0, 0.0, 8745.0),
}


@pytest.mark.parametrize("name", list(CASES))
def test_adversarial_inputs_keep_the_invariants(name):
    scan = CASES[name](np.random.default_rng(15))
    whole = fit_scan(scan).landmarks
    check_invariants(whole)
    fitter = OnlineFitter()
    blocks: list[Landmark] = []
    for a in range(0, len(scan), 397):
        blocks += fitter.push_block(scan.select(slice(a, a + 397)),
                                    flush=a + 397 >= len(scan))
    check_invariants(blocks)
    # straight into fit_segments, in pieces of 1-12 readings (too few echoes, none, junk)
    cuts = np.cumsum(np.random.default_rng(5).integers(1, 13, 200))
    pieces = [scan.select(slice(a, b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True)
              if a < len(scan)]
    check_invariants(fit_segments(pieces))


def test_push_one_reading_at_a_time_keeps_the_invariants():
    scan = CASES["sensor ids at int64's ends"](np.random.default_rng(15))
    fitter = OnlineFitter()
    out: list[Landmark] = []
    for row in zip(*(getattr(scan, f).tolist() for f, _ in ScanReadings.FIELDS), strict=True):
        out += fitter.push(*row)
    out += fitter.flush()
    check_invariants(out)
    assert out and {s for lm in out for s in lm.sensors} <= {2**63 - 1, -(2**63)}


def test_fits_out_of_the_modules_reach_are_not_ok():
    # a pan logged in milliseconds: a pole and a wall a millimetre or two away (the
    # fit's range bound); readings of 1e7 us: a wall 1.7 km away. Both were OK.
    pan = _pan()
    lms = fit_scan(_with(pan, tof_us=pan.tof_us * 1e-3)).landmarks
    assert lms and all(lm.status is FitStatus.BAD_INPUT for lm in lms)
    assert all("outside what the module measures" in lm.reason for lm in lms)
    lms = fit_scan(_sprinkle(1e7)(np.random.default_rng(3))).landmarks
    far = [lm for lm in lms if lm.range_m > 1000.0]
    assert far and not any(lm.ok for lm in far)
    assert any(lm.ok and abs(lm.range_m - 1.5) < 0.01 for lm in lms)   # the pole stays


@pytest.mark.parametrize("ids", [(0, 2**61), (-(2**63), 2**63 - 1)])
def test_sensor_ids_far_apart_are_reported_exactly(ids):
    # two transducers per segment, several segments: the (segment, sensor) keys
    # overflowed int64, silently (wrong ids) or with OverflowError
    pan = _pan()
    sensor = np.where(np.arange(len(pan)) % 2, ids[1], ids[0])
    segs = [_with(pan, sensor=sensor)] * 6
    lms = fit_segments(segs)
    assert [lm.sensors for lm in lms] == [ids] * 6


def test_sensor_ids_beyond_2_53_survive_blocks_and_push():
    # a segment spanning two blocks (or fed reading by reading) went through float64:
    # 2**53 + 1 came back as 2**53
    sid = 2**53 + 1
    scan = _with(_pan(), sensor=sid)
    fitter = OnlineFitter()
    lms = fitter.push_block(scan.select(slice(0, 150))) + fitter.push_block(
        scan.select(slice(150, None)), flush=True)
    assert lms and all(lm.sensors == (sid,) for lm in lms)
    seg = Segmenter()
    closed = [s for row in zip(*(getattr(scan, f).tolist() for f, _ in ScanReadings.FIELDS),
                               strict=True) for s in seg.push(*row)] + seg.flush()
    assert closed and all((s.readings.sensor == sid).all() for s in closed)
    with pytest.raises(ValueError, match="`sensor` must be a 64-bit integer"):
        seg.push(100.0, 0.0, 0.0, 0.0, 5000.0, 2**64)


def test_a_segment_of_unusable_readings_says_so():
    pan = _pan()
    (lm,) = fit_segments([_with(pan, tof_us=-pan.tof_us)])
    assert lm.status is FitStatus.BAD_INPUT and "no usable echo" in lm.reason
    (lm,) = fit_segments([_with(pan, x_m=np.nan)])
    assert lm.status is FitStatus.BAD_INPUT


@pytest.mark.parametrize("shape", [(), (241, 1), (5,)])
def test_segment_arrays_of_the_wrong_shape_raise_value_error(shape):
    pan = _pan()
    bad = np.zeros(shape)
    with pytest.raises(ValueError, match="1-D arrays of one length"):
        fit_segments([(pan.t_s, bad, pan.y_m, pan.yaw_rad, pan.tof_us)])
