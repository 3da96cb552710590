"""``push_many`` passes over the pairs of a reading and a segment's last echo that its
numpy tests (``Segmenter._skip_bits``) find surely idle: the segments stay exactly those
of tests/fit/segment_reference.py, at the edge of the gate too, where numpy's and math's
last bits differ."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_fit_segment_equivalence import Push, _assert_same, _streams

from sonarloc.fit import segment as fast
from sonarloc.io.scancsv import ScanReadings


@settings(max_examples=80, deadline=None)
@given(_streams(), st.sampled_from([0, 2, 8]), st.sampled_from([2, 64]),
       st.integers(2, 40), st.sampled_from([0.0, 0.2, 1.0]))
def test_random_streams_with_skipped_pairs_give_identical_segments(pushes, censor, max_open,
                                                                   chunk, travel):
    # the skip bits for every chunk of two readings or more (not only long chunks)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fast, "_SKIP_MIN", 2)
        _assert_same(pushes, {"censor_window": censor, "max_open": max_open,
                              "min_echoes": 2, "max_gap_s": 1.0, "max_travel_m": travel},
                     chunks=(chunk, 65536))


def test_echoes_at_the_edge_of_the_gate_are_matched_as_the_reference_does():
    """A ring neighbour's echo off the landmark's axis (the miss test passes it over)
    whose beam holds the arc point on the line through both transducers, at a range a
    hair inside or outside the gate: joined to the segment or not, exactly as the
    reference, whether its pair was tested in numpy or not."""
    rng = np.random.default_rng(12)
    seg = fast.Segmenter()
    beam, gate = seg._beam, seg._gate_m
    pushes: list[Push] = []
    for k in range(400):
        t0 = 10.0 * k
        lyaw = rng.uniform(-math.pi, math.pi)
        lR = rng.uniform(0.5, 3.0)
        for j in range(3):   # a landmark at lR on the first transducer's axis
            pushes.append((t0 + 0.03 * j, 0.0, 0.0, lyaw,
                           lR / seg._m_per_us + seg._half_count_us, 0))
        # the next transducer d behind the first, on the line to an arc point b off the
        # axis (beyond the miss width), its axis turned further away from the landmark
        b = seg._arc[rng.choice([0, 1, 5, 6])]
        d = rng.uniform(0.05, 0.4)
        u = lyaw + b
        yaw = u + math.copysign(rng.uniform(0.0, 0.5) * beam, b)
        excess = rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-9.0, -3.0)
        R = lR + d + gate * (1.0 + excess)
        pushes.append((t0 + 0.09, -d * math.cos(u), -d * math.sin(u), yaw,
                       R / seg._m_per_us + seg._half_count_us, 1))
    assert _assert_same(pushes, {"min_echoes": 3}) == 400
    cols = [np.array(c) for c in zip(*pushes, strict=True)]
    closed = fast.Segmenter(fast.SegmenterConfig(min_echoes=3)).feed_block(
        ScanReadings(*cols[:5], cols[5].astype(np.int64)))
    joined = sum(s.n_echo == 4 for s in closed)
    assert 100 < joined < 300      # both sides of the gate


def test_echoes_on_negative_zero_axes_give_identical_segments():
    # axes and positions of -0.0 (as a log may hold) beside +0.0 and tiny angles: the
    # segments' landmark offsets from cos and sin of the axis, as the reference's
    rng = np.random.default_rng(3)
    pushes: list[Push] = []
    for k in range(300):
        yaw = (-0.0, 0.0, 1e-300, -1e-300)[k % 4]
        x = 0.01 * (k // 4)
        tof = 2e6 * (1.5 - x) / 343.0 + rng.normal(0.0, 3.0)
        pushes.append((0.05 * k, x, (-0.0, 0.0)[k % 3 == 0], yaw,
                       tof if rng.random() < 0.8 else math.nan, k % 2))
    assert _assert_same(pushes, {"min_echoes": 2}, chunks=(1, 5, 300)) >= 1
