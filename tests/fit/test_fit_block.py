"""Segments end to end (:class:`SegmentBlock`): the segmenter's ``feed_block`` and the
fitter's flat path give the same segments and landmarks, to the last bit, as a list of
:class:`Segment` objects (``feed``, ``fit_segments`` of the list)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sonarloc.fit.landmarks import _resolve, fit_scan, fit_segments
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.segment import Segment, SegmentBlock, Segmenter, SegmenterConfig
from sonarloc.fit.synth import Reflector, pan_scan, rotation_scan, simulate_readings
from sonarloc.io.scancsv import ScanReadings
from tests.conftest import MAPS

FIELDS = ("t_s", "x_m", "y_m", "yaw_rad", "tof_us", "sensor")


def _bits(v: object) -> object:
    """A value with every float as its bits (NaN == NaN, -0.0 != 0.0) and dicts in order."""
    if isinstance(v, np.ndarray):
        return (str(v.dtype), v.shape, v.tobytes())
    if isinstance(v, float):
        return v.hex()
    if isinstance(v, dict):
        return [(k, _bits(x)) for k, x in v.items()]
    if isinstance(v, (tuple, list)):
        return [_bits(x) for x in v]
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return [(f.name, _bits(getattr(v, f.name))) for f in dataclasses.fields(v)]
    return (type(v).__name__, repr(v))


def _scans() -> dict[str, ScanReadings]:
    rng = np.random.default_rng(21)
    out = {
        # a wall whose trailing end a pole hides, and a pole
        "occluded": pan_scan([Reflector.polar(1.5, 0.0, 0.15), Reflector.polar(1.2, 15.0, 0.67)],
                             rng, -40, 40, 0.3),
        # two poles merged into one segment (the pair and split stages run)
        "merged": pan_scan([Reflector.polar(1.5, -10.0, 0.67),
                            Reflector.polar(1.505, 10.0, 0.67)], rng, -40, 40, 0.3),
        "rotation": rotation_scan(3000, rng),
    }
    # spikes (single echoes far off any arc; 1-echo segments with min_echoes 1) and
    # NaN poses (dropped by the segmenter)
    scan = pan_scan([Reflector.polar(1.46, -17, 0.67)], rng, -40, 40, 0.3)
    tof, x = scan.tof_us.copy(), scan.x_m.copy()
    tof[rng.choice(len(tof), 15, replace=False)] = rng.uniform(1500, 12000, 15)
    x[7::31] = np.nan
    out["spikes"] = ScanReadings(scan.t_s, x, scan.y_m, scan.yaw_rad, tof, scan.sensor)
    return out


@pytest.mark.parametrize("name", ["occluded", "merged", "rotation"])
def test_block_of_join_and_indexing_give_the_segments(name):
    segs = list(Segmenter().feed(_scans()[name]))
    assert len(segs) >= (1 if name == "merged" else 2)
    k = len(segs) // 2
    for block in (SegmentBlock.of(segs),
                  SegmentBlock.join([SegmentBlock.of(segs[:k]), SegmentBlock.of([]),
                                     SegmentBlock.of(segs[k:])])):
        assert len(block) == len(segs)
        assert _bits(list(block)) == _bits(segs)
        assert _bits(block[-1]) == _bits(segs[-1]) and _bits(block[-2:]) == _bits(segs[-2:])
        with pytest.raises(IndexError):
            block[len(segs)]
    assert len(SegmentBlock.of([])) == 0 and list(SegmentBlock.of([])) == []


def test_block_checks_its_bounds():
    r = ScanReadings(*(np.zeros(3) for _ in range(5)), np.zeros(3, dtype=np.int64))
    SegmentBlock(r, [0, 1, 3], [0, 1], ["gap", "flush"], [(False, False)] * 2)
    for bounds in ([0, 1, 2], [1, 1, 3], [0, 3]):
        with pytest.raises(ValueError, match="do not fit"):
            SegmentBlock(r, bounds, [0, 1], ["gap", "flush"], [(False, False)] * 2)


@pytest.mark.parametrize("name", ["occluded", "merged", "rotation", "spikes"])
@pytest.mark.parametrize("min_echoes", [3, 1])
def test_fit_segments_of_a_block_equals_the_list(name, min_echoes):
    # min_echoes 1: segments with 1-2 echoes take the fallback path
    scan = _scans()[name]
    block = Segmenter(SegmenterConfig(min_echoes=min_echoes)).feed_block(scan)
    segs = list(block)
    assert any(s.occluded != (False, False) for s in segs) or name != "occluded"
    assert any(s.n_echo < 3 for s in segs) or (name, min_echoes) != ("spikes", 1)
    lms = fit_segments(block)
    assert _bits(lms) == _bits(fit_segments(segs))
    ends = {(False, False): None, (True, False): "first", (False, True): "last",
            (True, True): "both"}
    for s, lm in zip(segs, lms, strict=True):
        assert (lm.extra["seg_id"], lm.extra["closed_by"], lm.extra.get("occluded")) == \
            (s.seg_id, s.closed_by, ends[s.occluded])
    # and as plain arrays (no segment fields in extra)
    tuples = [s.arrays() for s in segs]
    got = fit_segments(tuples)
    assert all("seg_id" not in lm.extra for lm in got)
    assert [lm.params.tobytes() for lm in got] == [lm.params.tobytes()
                                                   for lm in fit_segments(segs)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_scan_equals_the_segment_list_path(seed):
    refl = [Reflector.polar(1.5, -10.0, 0.67), Reflector.polar(1.505, 10.0, 0.67)]
    scan = pan_scan(refl, np.random.default_rng(seed), -40, 40, 0.3)
    cfg = FitConfig()
    segs = list(Segmenter().feed(scan))
    want = _resolve(segs, fit_segments(segs, cfg), cfg)
    got = fit_scan(scan, cfg).landmarks
    assert _bits(got) == _bits(want)
    assert all(isinstance(s, Segment) for s in segs)


def _echo_sensors(readings: ScanReadings) -> tuple[int, ...]:
    return tuple(sorted({int(s) for s in readings.sensor[np.isfinite(readings.tof_us)]}))


@pytest.mark.parametrize("ids", [(0, 0), (7, 7), (3, 5), (2, 40), (-1, 0)])
def test_landmark_sensors_are_those_with_echoes(ids):
    # one transducer, or two taking turns on one pan: each landmark names the
    # transducers whose echoes it was fitted to
    scan = pan_scan([Reflector.polar(1.5, -15.0, 0.67), Reflector.polar(2.0, 20.0, 0.15)],
                    np.random.default_rng(4), -40, 40, 0.3)
    sensor = np.where(np.arange(len(scan)) % 2 == 0, ids[0], ids[1])
    scan = ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us, sensor)
    segs = list(Segmenter().feed(scan))
    assert len(segs) == 2
    lms = fit_segments(segs)
    assert [lm.sensors for lm in lms] == [_echo_sensors(s.readings) for s in segs]
    assert {lm.sensors for lm in lms} == {tuple(sorted(set(ids)))}


def test_bad_readings_and_short_segments_leave_the_others_alone():
    # readings the fitter must drop (NaN pose, inf / negative TOF) and a segment with two
    # echoes (not fitted) among others: the others' landmarks are those of their clean
    # readings alone, to the last bit, but for the count of dropped readings
    rng = np.random.default_rng(8)
    segs = list(Segmenter().feed(pan_scan([Reflector.polar(1.5, -15.0, 0.67),
                                           Reflector.polar(2.0, 20.0, 0.15)],
                                          rng, -40, 40, 0.3)))
    a, b = (s.arrays() for s in segs)
    bad = [np.array(c, dtype=float) for c in a]
    bad[1][3], bad[4][5], bad[4][9] = np.nan, np.inf, -1.0
    short = tuple(c[np.flatnonzero(np.isfinite(b[4]))[:2]] for c in b)
    got = fit_segments([tuple(bad), short, b])
    want = fit_segments([tuple(np.delete(c, [3, 5, 9]) for c in bad), b])
    assert got[1].status.value == "too_few_points"
    assert got[0].extra.pop("n_bad_input") == 3 and want[0].extra.pop("n_bad_input") == 0
    assert _bits([got[0], got[2]]) == _bits(want)


def test_landmark_extras_agree_with_its_fields_and_readings():
    # a pan (two points and a wall, from the origin) and a drive past a wall (moving:
    # the odometry term) in one call: the SDs in extra are those of the covariance,
    # the counts those of the readings, the odometry term only on the moving segment
    rng = np.random.default_rng(12)
    segs = list(Segmenter().feed(pan_scan([Reflector.polar(1.5, -25.0, 0.67),
                                           Reflector.polar(1.2, 0.0, 0.67),
                                           Reflector.polar(2.0, 25.0, 0.15)],
                                          rng, -50, 50, 0.3)))
    t = np.arange(200) * 0.02
    drive = simulate_readings(t, np.linspace(-0.6, 0.6, 200), 0.0,
                              np.pi / 2 + np.deg2rad(12.0) * np.sin(2 * np.pi * t / 1.3),
                              [Reflector.line(1.5, np.deg2rad(93.0), 0.15)], rng)
    segs += list(Segmenter().feed(drive))
    lms = fit_segments(segs)
    moved = [bool(np.ptp(s.readings.x_m) > 0.02) for s in segs]
    assert sum(moved) >= 1 and not all(moved)
    for s, lm, m in zip(segs, lms, moved, strict=True):
        tof = s.readings.tof_us
        assert lm.extra["n_noecho"] == int(np.isnan(tof).sum())
        assert lm.extra["n_spikes"] == int(np.isfinite(tof).sum()) - lm.n_readings
        assert ("odom_range_sd_m" in lm.extra) == ("odom_bearing_sd_deg" in lm.extra) == m
        assert lm.extra["kappa_sd_us"] == pytest.approx(math.sqrt(lm.cov[2, 2]), rel=1e-9)
        if lm.kind == "point":   # SDs along and across the line of sight
            u = np.array([math.cos(lm.bearing_rad), math.sin(lm.bearing_rad)])
            v = np.array([-u[1], u[0]])
            sd_r, sd_b = math.sqrt(u @ lm.cov[:2, :2] @ u), \
                math.sqrt(v @ lm.cov[:2, :2] @ v) / lm.range_m
        elif not m:               # a wall seen from the origin: (rho, alpha) = (r, phi)
            sd_r, sd_b = math.sqrt(lm.cov[0, 0]), math.sqrt(lm.cov[1, 1])
        else:
            continue
        assert lm.extra["range_sd_m"] == pytest.approx(sd_r, rel=1e-6)
        assert lm.extra["bearing_sd_deg"] == pytest.approx(math.degrees(sd_b), rel=1e-6)


def test_fit_scan_equals_the_segment_list_path_with_cuts():
    # the world simulator's ring16 drive through the room: 16 transducers, a moving
    # robot, walls running into corners cut in two (split_unresolved on the block)
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.simulate import simulate_scan

    scan = simulate_scan(load_map(MAPS / "room.geojson"), rig_by_name("ring16"),
                         duration_s=20.0, seed=5).readings
    cfg = FitConfig()
    whole = SegmenterConfig(max_travel_m=0.0)   # whole passes: walls into corners
    segs = list(Segmenter(whole).feed(scan))
    want = _resolve(segs, fit_segments(segs, cfg), cfg)
    got = fit_scan(scan, cfg, whole).landmarks
    assert sum("split_of" in lm.extra for lm in got) >= 2
    assert _bits(got) == _bits(want)
    # and with the travel cap's shorter segments
    segs = list(Segmenter().feed(scan))
    assert any(s.closed_by == "travel" for s in segs)
    assert _bits(fit_scan(scan, cfg).landmarks) == _bits(_resolve(segs, fit_segments(segs, cfg),
                                                                  cfg))
