"""Online segmentation: one segment per landmark pass, bounded memory, robust input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.fit.segment import Segmenter, SegmenterConfig
from sonarloc.fit.synth import Reflector, pan_scan, simulate_readings
from sonarloc.io.scancsv import ScanReadings
from tests.conftest import MAPS

FIG5 = [Reflector.polar(1.46, -17, 0.67), Reflector.polar(1.50, 4, 0.15),
        Reflector.polar(1.47, 22, 2.68)]


def _segments(scan, config=None):
    seg = Segmenter(config)
    return list(seg.feed(scan)), seg


def test_fig5_pan_gives_three_segments_in_order(rng):
    scan = pan_scan(FIG5, rng, -40, 40, 0.3)
    segs, seg = _segments(scan)
    assert len(segs) == 3
    ranges = [np.nanmedian(s.readings.tof_us) * 343e-6 / 2 for s in segs]
    np.testing.assert_allclose(ranges, [1.46, 1.50, 1.47], atol=3e-3)
    assert seg.stats.spikes == 0 and seg.open_segments == 0
    # pole and rod get no-echo (or farther-echo) readings on both sides
    for s in (segs[0], segs[2]):
        nan = np.isnan(s.readings.tof_us)
        first, last = np.flatnonzero(~nan)[[0, -1]]
        assert nan[:first].any() and nan[last:].any()


def test_segments_close_as_soon_as_the_landmark_leaves(rng):
    scan = pan_scan([Reflector.polar(1.5, -20, 0.67), Reflector.polar(2.5, 36, 0.67)], rng,
                    -40, 40, 0.5)
    seg = Segmenter()
    closed_at = []
    for i in range(len(scan)):
        out = seg.push(scan.t_s[i], scan.x_m[i], scan.y_m[i], scan.yaw_rad[i], scan.tof_us[i])
        closed_at += [(i, s) for s in out]
    assert len(closed_at) == 1                 # the first pole, before the end of the scan
    i, s = closed_at[0]
    last_echo_yaw = s.readings.yaw_rad[np.isfinite(s.readings.tof_us)][-1]
    cfg = seg.config
    # closed once the beam has turned miss_angle_deg past the last echo (a strong
    # reflector's null must not split it), not later
    assert scan.yaw_rad[i] - last_echo_yaw <= np.deg2rad(
        max(0.5 * cfg.miss_limit, cfg.miss_angle_deg + 0.5)) + 1e-9
    assert len(seg.flush()) == 1


def test_spikes_and_crosstalk_rejected_and_counted(rng):
    scan = pan_scan([Reflector.polar(1.5, 0, 0.67)], rng, -30, 30, 0.3)
    tof = scan.tof_us.copy()
    idx = rng.choice(len(tof), 12, replace=False)
    tof[idx] = rng.uniform(2000, 15000, 12)          # isolated random echoes
    noisy = ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof, scan.sensor)
    segs, seg = _segments(noisy)
    assert len(segs) == 1
    assert seg.stats.spikes >= 10
    assert segs[0].n_echo >= np.isfinite(scan.tof_us).sum() - 12


def test_bad_input_is_counted_not_raised():
    seg = Segmenter()
    assert seg.push(0.0, 0.0, 0.0, 0.0, math.inf) == []
    assert seg.push(0.1, math.nan, 0.0, 0.0, 9000.0) == []
    assert seg.push(0.2, 0.0, 0.0, 0.0, -5.0) == []
    seg.push(0.3, 0.0, 0.0, 0.0, 9000.0)
    assert seg.push(0.1, 0.0, 0.0, 0.0, 9000.0) == []          # older than the last one
    assert seg.stats.bad == 3 and seg.stats.out_of_order == 1
    seg.push(0.3, 0.0, 0.0, 0.0, 9000.0)                        # duplicate time is fine
    assert seg.stats.echoes == 2


def test_memory_bounded_over_a_long_rotating_stream(rng):
    # continuous rotation for 30 turns over 4 landmarks; bearing wraps every turn
    n = 30 * 360
    yaw = np.deg2rad(np.arange(n) * 1.0 + 0.5)
    refl = [Reflector.polar(r, b, 0.67)
            for r, b in ((1.5, 180.0), (2.0, -60.0), (2.5, 45.0), (3.0, 150.0))]
    scan = simulate_readings(np.arange(n) * 0.01, 0.0, 0.0, yaw, refl, rng)
    seg = Segmenter()
    peak = 0
    count = 0
    for i in range(n):
        count += len(seg.push(scan.t_s[i], 0.0, 0.0, scan.yaw_rad[i], scan.tof_us[i]))
        peak = max(peak, seg.open_segments)
    count += len(seg.flush())
    assert peak <= 2
    assert count == 4 * 30          # one segment per landmark and turn, across the wrap


def test_ring_transducers_seeing_one_landmark_are_joined(rng):
    # two transducers 22.5 deg apart on a 0.2 m ring, robot still; a strong wall between
    angles = np.deg2rad([0.0, 22.5])
    t = np.arange(40) * 0.03
    sensor = np.arange(40) % 2
    yaw = angles[sensor] + np.deg2rad(np.repeat(np.arange(20), 2) * 0.5 - 5.0)
    x, y = 0.2 * np.cos(angles[sensor]), 0.2 * np.sin(angles[sensor])
    wall = Reflector.line(1.8, np.deg2rad(11.0), 0.15)
    scan = simulate_readings(t, x, y, yaw, [wall], rng, sensor=sensor)
    segs, _ = _segments(scan)
    assert len(segs) == 1
    assert set(segs[0].readings.sensor.tolist()) == {0, 1}


def test_config_validation():
    with pytest.raises(ValueError, match="gate_us"):
        SegmenterConfig(gate_us=0.0)
    with pytest.raises(ValueError, match="miss_limit"):
        SegmenterConfig(miss_limit=0)
    with pytest.raises(ValueError, match="max_readings"):
        SegmenterConfig(max_readings=2, min_echoes=3)


def test_long_wall_is_cut_into_bounded_segments(rng):
    t = np.arange(3000) * 0.05
    x = 0.02 * np.arange(3000)
    scan = simulate_readings(t, x, 0.0, np.full(3000, np.pi / 2),
                             [Reflector.line(1.0, np.pi / 2, 0.15)], rng)
    segs, seg = _segments(scan, SegmenterConfig(max_readings=200, max_travel_m=0.0))
    assert len(segs) >= 14
    assert max(len(s.readings) for s in segs) <= 200
    assert {s.closed_by for s in segs[:-1]} == {"full"}

_reading = st.tuples(
    st.floats(-1.0, 0.5),                                   # time step (may go back)
    st.floats(-3, 3), st.floats(-3, 3),                     # position
    st.floats(-10, 10),                                     # yaw (any winding)
    st.one_of(st.floats(500, 30000), st.just(math.nan), st.just(math.inf),
              st.floats(-100, 0)),                          # tof
    st.integers(0, 3))                                      # sensor


@settings(max_examples=40, deadline=None)
@given(st.lists(_reading, min_size=0, max_size=300))
def test_any_stream_is_segmented_without_errors(rows):
    from sonarloc.fit.landmarks import fit_segments

    seg = Segmenter(SegmenterConfig(max_open=8))
    t = 0.0
    closed = []
    for dt, x, y, yaw, tof, sensor in rows:
        t += dt
        closed += seg.push(t, x, y, yaw, tof, sensor)
        assert seg.open_segments <= 8
    closed += seg.flush()
    st_ = seg.stats
    assert st_.readings == len(rows)
    assert st_.echoes + st_.no_echo + st_.bad + st_.out_of_order == len(rows)
    for lm in fit_segments(closed):
        if lm.ok:
            assert np.all(np.isfinite(lm.params)) and np.all(np.isfinite(lm.cov))


def _sawtooth(rng: np.random.Generator, sweeps: int, step_deg: float) -> ScanReadings:
    """A pan sweeping -60..60 deg and jumping back, over a pole 1.5 m ahead, ``sweeps``
    times, 30 ms a ping."""
    parts = [pan_scan([Reflector.polar(1.5, 0.0, 0.67)], rng, -60, 60, step_deg)
             for _ in range(sweeps)]
    period = parts[0].t_s[-1] + 0.03
    cat = [np.concatenate([getattr(p, f) + (k * period if f == "t_s" else 0)
                           for k, p in enumerate(parts)])
           for f in ("t_s", "x_m", "y_m", "yaw_rad", "tof_us")]
    return ScanReadings(*cat, np.zeros(len(cat[0]), dtype=np.int64))


def test_a_fast_pan_keeps_each_pass_in_its_own_segment(rng):
    """3 deg a ping leaves fewer than ``miss_limit`` readings within the miss half-width
    after the last echo, so misses alone never close the pass and the next sweep's
    echoes join it, a sweep later; ``sweep_away_deg`` closes it once the beam has
    turned twice the beam half-width away, one segment per pass."""
    scan = _sawtooth(rng, 3, 3.0)
    merged, _ = _segments(scan)
    assert len(merged) == 1
    assert merged[0].readings.t_s[-1] - merged[0].readings.t_s[0] > 2.0
    cfg = SegmenterConfig(sweep_away_deg=50.0)
    segs, seg = _segments(scan, cfg)
    assert len(segs) == 3
    assert [s.closed_by for s in segs] == ["swept", "swept", "flush"]
    period = (len(scan) // 3) * 0.03
    for k, s in enumerate(segs):
        t = s.readings.t_s[np.isfinite(s.readings.tof_us)]
        assert k * period <= t[0] and t[-1] < (k + 1) * period     # one pass each
    assert sum(s.n_echo for s in segs) == merged[0].n_echo
    assert seg.open_segments == 0


def test_sweep_away_spares_fixed_transducers(rng):
    """A transducer that keeps pointing at its landmark never triggers the rule: the
    same segments with and without it."""
    t = 0.1 * np.arange(60)
    yaw = np.zeros_like(t)
    scan = simulate_readings(t, 0.3 * t, np.zeros_like(t), yaw,
                             [Reflector.point(3.0, 0.05, 0.67)], rng, tier="gauss")
    plain, _ = _segments(scan, SegmenterConfig(max_readings=8))
    swept, _ = _segments(scan, SegmenterConfig(max_readings=8, sweep_away_deg=50.0))
    assert [len(s.readings) for s in plain] == [len(s.readings) for s in swept]
    assert all(s.closed_by != "swept" for s in swept)


def _echo_keys(segs) -> list[tuple[float, int]]:
    """(t, sensor) of every echo of the segments, with repeats."""
    return [(t, k) for s in segs for t, k, tof in zip(s.readings.t_s.tolist(),
                                                       s.readings.sensor.tolist(),
                                                       s.readings.tof_us.tolist(), strict=True)
            if math.isfinite(tof)]


@pytest.mark.parametrize("cap", [0.5, 1.0])
def test_a_long_pass_is_cut_by_travel_without_losing_an_echo(rng, cap):
    """Two ring transducers 10 deg apart follow a wall for 5 m (odometry error grows with
    the distance: one fit cannot explain so long a pass). ``max_travel_m`` cuts the pass
    into segments each taken within the cap of its first echo; the echo beyond a cap
    opens the next segment, so every echo of the wall is in exactly one segment."""
    n = 500
    t = 0.05 * np.arange(n)
    sensor = np.arange(n) % 2
    x = 0.01 * np.arange(n)
    yaw = np.pi / 2 + np.deg2rad(10.0) * (sensor - 0.5)
    scan = simulate_readings(t, x, 0.05 * sensor, yaw, [Reflector.line(1.2, np.pi / 2, 0.15)],
                             rng, sensor=sensor)
    echoes = sorted((t, k) for t, k, tof in zip(scan.t_s.tolist(), scan.sensor.tolist(),
                                                  scan.tof_us.tolist(), strict=True)
                    if math.isfinite(tof))
    assert len(echoes) > 0.9 * n
    segs, seg = _segments(scan, SegmenterConfig(max_travel_m=cap))
    assert sorted(_echo_keys(segs)) == echoes          # each echo once, none lost
    assert seg.stats.spikes == 0
    assert len(segs) >= math.floor(4.99 / cap)
    assert [s.closed_by for s in segs] == ["travel"] * (len(segs) - 1) + ["flush"]
    for s in segs:
        e = np.isfinite(s.readings.tof_us)
        x0, y0 = s.readings.x_m[e][0], s.readings.y_m[e][0]
        travel = np.hypot(s.readings.x_m[e] - x0, s.readings.y_m[e] - y0)
        assert travel.max() <= cap
        assert travel.max() > cap - 0.05 or s is segs[-1]   # cut at the cap, not before


def _pass_at(rng, look_deg: float, n: int = 200) -> ScanReadings:
    """A transducer driving 0.28 m/s along +x, pinged every 0.12 s (a ring16 transducer
    on the simulator's default drive), looking ``look_deg`` off its path (beyond 90:
    backwards) at a pole 3 m along its axis from x = 0.8 m: the pole drifts across the
    beam for 1.5-2.5 m of travel, approached (or left behind) by ~3 cm a ping."""
    t = 0.12 * np.arange(n)
    a = math.radians(look_deg)
    pole = Reflector.point(0.8 + 3.0 * math.cos(a), 3.0 * math.sin(a), 0.67)
    return simulate_readings(t, 0.28 * t, 0.0, np.full(n, a), [pole], rng)


@pytest.mark.parametrize("look_deg", [25.0, 155.0])
@pytest.mark.parametrize("one_by_one", [False, True])
def test_the_piece_after_a_travel_cut_takes_no_echo_of_the_piece_before(rng, look_deg,
                                                                      one_by_one):
    """A pass cut by ``max_travel_m`` goes on in the next piece: the readings of its
    sensor before that piece's first echo are the previous piece's echoes of the same
    pole, each ~3 cm farther (approaching) or nearer (leaving) than the next. Neither a
    farther reflector that won (no-echo readings for the piece: until session 14 up to
    seven, on the beam's axis, which the fit read as "not detected there", pushing
    kappa up and the range down with too small SDs) nor a nearer one that hid it
    (``occluded``)."""
    scan = _pass_at(rng, look_deg)
    if one_by_one:
        seg = Segmenter()
        segs = [s for row in zip(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us,
                                 scan.sensor, strict=True) for s in seg.push(*row)]
        segs += seg.flush()
    else:
        segs, _ = _segments(scan)
    assert len(segs) >= 2 and segs[0].closed_by == "travel"
    echoes = set(_echo_keys(segs))
    for before, s in zip(segs, segs[1:], strict=False):
        if before.closed_by != "travel":
            continue
        r = s.readings
        nan = [(t, k) for t, k, tof in zip(r.t_s.tolist(), r.sensor.tolist(),
                                           r.tof_us.tolist(), strict=True)
               if not math.isfinite(tof)]
        assert not echoes.intersection(nan)
        assert np.isfinite(r.tof_us[0])             # it starts with its first echo
        assert not s.occluded[0]


def test_a_pan_never_travels(rng):
    """A transducer panning on the spot (and a ring turning in place, whose transducers
    move 0.4 m at most) gives the same segments whatever the travel cap."""
    scans = [pan_scan(FIG5, rng, -40, 40, 0.3, repeat=3)]
    n = 1200   # a ring of 4 transducers 0.2 m from the centre, turning 1 deg a ping
    sensor = np.arange(n) % 4
    yaw = np.deg2rad(np.arange(n) * 1.0) + sensor * np.pi / 2
    scans.append(simulate_readings(0.03 * np.arange(n), 0.2 * np.cos(yaw), 0.2 * np.sin(yaw),
                                   yaw, [Reflector.polar(r, b, 0.67) for r, b in
                                         ((1.5, 180.0), (2.0, -60.0), (2.5, 45.0))], rng,
                                   sensor=sensor))
    for scan, cap in zip(scans, (1e-6, 0.5), strict=True):
        off, _ = _segments(scan, SegmenterConfig(max_travel_m=0.0))
        on, _ = _segments(scan, SegmenterConfig(max_travel_m=cap))
        assert len(off) > 2
        assert [s.closed_by for s in on] == [s.closed_by for s in off]
        for a, b in zip(on, off, strict=True):
            np.testing.assert_array_equal(a.readings.t_s, b.readings.t_s)
            np.testing.assert_array_equal(a.readings.tof_us, b.readings.tof_us)


def test_travel_cap_must_not_be_negative():
    with pytest.raises(ValueError, match="max_travel_m"):
        SegmenterConfig(max_travel_m=-1.0)
    with pytest.raises(ValueError, match="max_travel_m"):
        SegmenterConfig(max_travel_m=math.nan)
    assert SegmenterConfig(max_travel_m=math.inf).max_travel_m == math.inf


def test_sweep_away_must_be_positive():
    with pytest.raises(ValueError, match="sweep_away_deg"):
        SegmenterConfig(sweep_away_deg=0.0)


def test_an_echo_two_segments_match_is_no_miss_of_the_one_it_skips():
    """Ring neighbours can open two segments on one wall (room drive, seed 4: transducer
    7 at -108 deg opens a second one at 22.65 s); each echo then joins the better match.
    The other segment matches it too, so it must not take it as a farther reflector
    winning (a NaN row: the wall "not detected"): transducer 8 faces the wall squarely
    at 2.2-2.5 m and echoes it at every ping, its range growing as the robot drives
    away. Those NaN rows made the fit tilt the wall by 10 deg to explain them."""
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.simulate import simulate_scan

    sim = simulate_scan(load_map(MAPS / "room.geojson"), rig_by_name("ring16"),
                        duration_s=26.0, seed=4)
    scan = sim.readings
    at = {(float(t), int(k)): i for i, (t, k) in enumerate(zip(scan.t_s, scan.sensor,
                                                                strict=True))}
    s8 = np.flatnonzero((scan.sensor == 8) & (scan.t_s > 24.3) & (scan.t_s < 25.4))
    assert np.isfinite(scan.tof_us[s8]).all() and (sim.reflector[s8] == 0).all()
    (seg,) = [s for s in Segmenter().feed(scan)
              if any(at[(float(t), int(k))] == s8[0] and np.isfinite(tof) for t, k, tof
                     in zip(s.readings.t_s, s.readings.sensor, s.readings.tof_us,
                            strict=True))]
    rows = np.array([at[(float(t), int(k))] for t, k in zip(seg.readings.t_s,
                                                            seg.readings.sensor, strict=True)])
    nan = np.isnan(seg.readings.tof_us)
    # its no-echo rows are readings without an echo of the wall (there are some: the
    # other transducer's edge of the beam)
    assert nan.any()
    assert not (sim.reflector[rows[nan]] == 0).any()
