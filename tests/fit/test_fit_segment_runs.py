"""``push_many``'s shortcuts on rotating and panning transducers give exactly the
per-reading segments of tests/fit/segment_reference.py.

A transducer turning past a landmark ends each segment with a run of no-echo readings
(misses of the only open segment, ``Segmenter._miss_run``) that close it by misses, a
time gap, a sweep, or many misses of a beam standing still; those runs are here cut by
chunk boundaries, interrupted by echoes of other landmarks, spikes and readings of
another transducer, and the runs' censoring stops at ``censor_window``.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import segment_reference as ref
from test_fit_segment_equivalence import _assert_same, _scan_pushes

from sonarloc.fit import segment as fast
from sonarloc.fit.synth import ROTATION_SCENE, Reflector, simulate_readings
from sonarloc.io.scancsv import ScanReadings

CHUNKS = (1, 2, 3, 5, 13, 64, 65536)


def _turning(n: int, step_deg: float, rng: np.random.Generator, *, gaps: int = 0,
             spikes: int = 0, other_sensor: float = 0.0, stops: int = 0,
             scene: tuple[Reflector, ...] = ROTATION_SCENE) -> ScanReadings:
    """A transducer at the origin turning ``step_deg`` per ping over ``scene``; ``gaps``
    pauses of 2.5 s, ``spikes`` random echoes, ``other_sensor`` the fraction of readings
    from transducer 1 (its axis 3 deg on; half its echoes lost) and as many from
    transducer 2 (facing backwards, no echo), ``stops`` stretches
    where the turning pauses (the same axis for 30 pings: a beam standing still)."""
    dyaw = np.full(n, step_deg)
    for k in rng.choice(n, stops, replace=False):
        dyaw[k:k + 30] = 0.0
    yaw_deg = np.cumsum(dyaw) + rng.uniform(-180, 180)
    dt = np.full(n, 0.01)
    dt[rng.choice(n, gaps, replace=False)] = 2.5
    u = rng.random(n)
    sensor = (u < other_sensor).astype(np.int64) + (u < 2 * other_sensor)
    scan = simulate_readings(np.cumsum(dt), 0.0, 0.0,
                             np.deg2rad(yaw_deg + np.array([0.0, 3.0, 180.0])[sensor]),
                             scene, rng, sensor=sensor)
    tof = scan.tof_us.copy()
    tof[((sensor == 1) & (rng.random(n) < 0.5)) | (sensor == 2)] = np.nan
    k = rng.choice(n, spikes, replace=False)
    tof[k] = rng.uniform(1500, 20000, spikes)
    return ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof, scan.sensor)


def _closed_by(pushes, kwargs) -> Counter[str]:
    seg = ref.Segmenter(ref.SegmenterConfig(**kwargs))
    out = [s.closed_by for p in pushes for s in seg.push(*p)]
    return Counter(out + [s.closed_by for s in seg.flush()])


@pytest.mark.parametrize("case", ["plain", "coarse swept", "gaps", "spikes", "two sensors",
                                  "stops", "censor 2"])
def test_miss_runs_give_identical_segments(case):
    rng = np.random.default_rng(["plain", "coarse swept", "gaps", "spikes", "two sensors",
                                 "stops", "censor 2"].index(case) + 70)
    kwargs: dict[str, object] = {}
    want = "misses"
    if case == "plain":
        scan = _turning(1500, 1.0, rng)
    elif case == "coarse swept":
        # 3 deg per ping: misses at 3, 6 and 9 deg, then the landmark is off the miss
        # width; the beam sweeps on until sweep_away closes the segment inside a run
        scan = _turning(1500, -3.0, rng, scene=ROTATION_SCENE[::3])
        kwargs = {"sweep_away_deg": 50.0, "miss_limit": 4}
        want = "swept"
    elif case == "gaps":
        scan = _turning(1500, 1.0, rng, gaps=40)
        kwargs = {"max_gap_s": 1.0, "miss_limit": 8}
        want = "gap"
    elif case == "spikes":
        scan = _turning(1500, 1.5, rng, spikes=120)
    elif case == "two sensors":
        # misses of a transducer that has not seen the landmark: not attached
        scan = _turning(1500, 1.0, rng, other_sensor=0.2)
        kwargs = {"sweep_away_deg": 60.0}
    elif case == "stops":
        scan = _turning(1500, 1.0, rng, stops=25)
    else:
        scan = _turning(1500, 2.0, rng, spikes=30)
        kwargs = {"censor_window": 2, "miss_half_width_deg": 20.0, "miss_angle_deg": 12.0}
    pushes = _scan_pushes(scan)
    assert _closed_by(pushes, kwargs)[want] >= 5       # the runs close as intended
    assert _assert_same(pushes, kwargs, chunks=CHUNKS) >= 20


def test_standing_beam_closes_after_many_misses():
    # a fixed transducer whose landmark stops echoing: the run of misses closes the
    # segment after 4 x miss_limit of them (the beam never turns away), in every chunking
    rng = np.random.default_rng(3)
    n = 600
    t = np.arange(n) * 0.05
    scan = simulate_readings(t, 0.0, 0.0, np.zeros(n), [Reflector.polar(1.5, 2.0, 0.67)], rng)
    tof = scan.tof_us.copy()
    for lo in range(20, n, 60):           # the landmark echoes for 20 pings of each 60
        tof[lo:lo + 40] = np.nan
    pushes = _scan_pushes(ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof,
                                       scan.sensor))
    assert _closed_by(pushes, {})["misses"] >= 9
    assert _assert_same(pushes, {}, chunks=CHUNKS) >= 9


def test_long_rotation_in_odd_chunks_gives_identical_segments():
    # the benchmark's scene for 20 turns, in chunk sizes that cut runs everywhere
    rng = np.random.default_rng(2003)
    n = 7200
    scan = simulate_readings(np.arange(n) * 0.01, 0.0, 0.0, np.deg2rad(np.arange(n) * 1.0),
                             ROTATION_SCENE, rng)
    assert _assert_same(_scan_pushes(scan), {}, chunks=(17, 360, 1009)) > 150


def test_miss_run_helpers_keep_the_open_segment_exact():
    # one open segment, then a chunk of no-echo readings turning away: the run attaches
    # the readings of its sensor (up to censor_window), counts the misses and closes
    # where the reference does
    pushes = []
    for k in range(30):
        yaw = math.radians(-12.0 + k)
        tof = 8746.0 + 0.67 * math.exp(yaw ** 2 / (2 * math.radians(5.25) ** 2))
        pushes.append((0.03 * k, 0.0, 0.0, yaw, tof if k < 24 else math.nan, 0))
    seg = fast.Segmenter()
    cols = [np.array(c) for c in zip(*pushes, strict=True)]
    got = seg.push_many(*cols)
    want = ref.Segmenter()
    closed = [s for p in pushes for s in want.push(*p)]
    assert [i for i, _ in got] == [28] and len(closed) == 1   # the 5th miss closes it
    a, b = got[0][1], closed[0]
    assert a.closed_by == b.closed_by == "misses"
    np.testing.assert_array_equal(a.readings.tof_us, b.readings.tof_us)
    assert int(np.isnan(a.readings.tof_us).sum()) == 5
