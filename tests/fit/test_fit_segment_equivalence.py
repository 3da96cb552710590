"""The segmenter's inline per-reading loop, and its batch form ``push_many``, give
exactly the segments of its plain form.

``segment_reference.py`` holds the segmenter as it was before the loop was written out
(session 3). All are fed the same readings (the batch replay's own pushes on simulated
ring and pan drives, the fitting stage's hard cases, a long continuous rotation, and
random streams), ``push_many`` in chunks of several sizes, and must return the same
segments, closed by the same reading, for the same reason, with the same readings to the
last bit, and the same counters.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
import segment_reference as ref
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.fit import segment as fast
from sonarloc.fit.synth import Reflector, pan_scan, rotation_scan, simulate_readings
from sonarloc.io.logfile import LogWriter, SensorMount
from sonarloc.io.scancsv import ScanReadings
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import LocalizerConfig
from sonarloc.localize.replay import replay_log
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import PanRig, ring16
from sonarloc.world.simulate import simulate_records

ROOT = Path(__file__).resolve().parents[2]

Push = tuple[float, float, float, float, float, int]


def _run(module, config, pushes: list[Push]):
    seg = module.Segmenter(config)
    out = []
    for i, args in enumerate(pushes):
        out += [(i, s) for s in seg.push(*args)]
    out += [(len(pushes), s) for s in seg.flush()]
    return out, seg


def _run_many(config, pushes: list[Push], chunk: int):
    seg = fast.Segmenter(config)
    cols = [np.array(c) for c in zip(*pushes, strict=True)] if pushes else [np.zeros(0)] * 6
    out = seg.push_many(*cols, chunk=chunk)
    out += [(len(pushes), s) for s in seg.flush()]
    return out, seg


def _run_block(config, pushes: list[Push], chunk: int):
    """``feed_block`` (as fit_scan), its segments with the closing index of ``want``
    (a block does not keep it; the order and the segments are compared)."""
    seg = fast.Segmenter(config)
    cols = [np.array(c) for c in zip(*pushes, strict=True)] if pushes else [np.zeros(0)] * 6
    block = seg.feed_block(ScanReadings(*cols[:5], cols[5].astype(np.int64)), chunk=chunk)
    assert isinstance(block, fast.SegmentBlock) and len(block.bounds) == len(block) + 1
    return list(block), seg


def _assert_same(pushes: list[Push], config_kwargs: dict,
                 chunks: tuple[int, ...] = (1, 7, 65536)) -> int:
    """Reference against the online form, ``push_many`` and ``feed_block`` in each of
    ``chunks``."""
    want, seg_ref = _run(ref, ref.SegmenterConfig(**config_kwargs), pushes)
    config = fast.SegmenterConfig(**config_kwargs)
    for got, seg_new in [_run(fast, config, pushes),
                         *(_run_many(config, pushes, c) for c in chunks)]:
        _compare(got, seg_new, want, seg_ref)
    for c in chunks:
        segs, seg_new = _run_block(config, pushes, c)
        _compare([(i, s) for (i, _), s in zip(want, segs, strict=True)], seg_new, want, seg_ref)
    return len(want)


def _compare(got, seg_new, want, seg_ref) -> None:
    assert len(got) == len(want)
    for (i_new, a), (i_ref, b) in zip(got, want, strict=True):
        assert (i_new, a.seg_id, a.closed_by, a.occluded) == \
            (i_ref, b.seg_id, b.closed_by, b.occluded)
        for name in ("t_s", "x_m", "y_m", "yaw_rad", "tof_us", "sensor"):
            u, v = getattr(a.readings, name), getattr(b.readings, name)
            assert u.dtype == v.dtype and u.shape == v.shape
            np.testing.assert_array_equal(u, v)     # NaN == NaN, otherwise bit-equal
    assert vars(seg_new.stats) == vars(seg_ref.stats)
    assert seg_new.open_segments == seg_ref.open_segments == 0
    return len(got)


def _replay_pushes(monkeypatch: pytest.MonkeyPatch, world, rig, duration_s: float, seed: int
                   ) -> tuple[list[Push], dict]:
    """The readings the batch replay of a simulated drive pushes, and its settings."""
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(world, rig, duration_s=duration_s, seed=seed))
    pushes: list[Push] = []
    configs = []
    orig_push, orig_many, orig_init = (fast.Segmenter.push, fast.Segmenter.push_many,
                                       fast.Segmenter.__init__)

    def init(self, config=None, module=None):
        orig_init(self, config, module)
        configs.append(self.config)

    def push(self, *args):
        pushes.append(tuple(args))
        return orig_push(self, *args)

    def push_many(self, *cols, **kwargs):
        pushes.extend(zip(*(np.asarray(c).tolist() for c in cols), strict=True))
        return orig_many(self, *cols, **kwargs)

    monkeypatch.setattr(fast.Segmenter, "__init__", init)
    monkeypatch.setattr(fast.Segmenter, "push", push)
    monkeypatch.setattr(fast.Segmenter, "push_many", push_many)
    replay_log(io.StringIO(buf.getvalue()), FeatureMap.from_map(world),
               config=LocalizerConfig(method="kuc"))
    monkeypatch.undo()
    assert len(configs) == 1
    cfg = configs[0]
    kwargs = {f: getattr(cfg, f) for f in cfg.__dataclass_fields__}
    return [(float(t), float(x), float(y), float(a), float(z), int(s))
            for t, x, y, a, z, s in pushes], kwargs


@pytest.mark.parametrize("rig_name", ["ring16", "pan"])
def test_replay_pushes_give_identical_segments(monkeypatch, rig_name):
    world = load_map(ROOT / "maps" / "room.geojson")
    rig = ring16() if rig_name == "ring16" else \
        PanRig(SensorMount(0, 0.1, 0.0, 0.0), (-90.0, 90.0, 1.5), 1, 0.03)
    pushes, kwargs = _replay_pushes(monkeypatch, world, rig, 12.0, 7)
    assert len(pushes) > 300
    if rig_name == "pan":
        assert kwargs["sweep_away_deg"] is not None     # the swept test is exercised
    n = _assert_same(pushes, kwargs, chunks=(1, 50, 65536))
    assert n > 20
    # and with the edge settings: few open segments, short segments, no censoring
    _assert_same(pushes, {**kwargs, "max_open": 3, "max_readings": 6, "censor_window": 0},
                 chunks=(33,))


def _scan_pushes(scan) -> list[Push]:
    return list(zip(scan.t_s.tolist(), scan.x_m.tolist(), scan.y_m.tolist(),
                    scan.yaw_rad.tolist(), scan.tof_us.tolist(), scan.sensor.tolist(),
                    strict=True))


def _hard_scans() -> dict[str, object]:
    """Scans of tests/fit/test_fit_hard_cases.py (seeded): spikes and cross-talk, a
    coarse pan, continuous rotation through +-180 deg, a moving nodding sensor, NaN /
    inf / negative values with every time twice, two reflectors a few degrees apart."""
    rng = np.random.default_rng(11)
    out: dict[str, object] = {}
    scan = pan_scan([Reflector.polar(1.46, -17, 0.67), Reflector.polar(1.47, 22, 2.68)],
                    rng, -40, 40, 0.3)
    tof = scan.tof_us.copy()
    spikes = rng.choice(len(tof), 15, replace=False)
    tof[spikes] = rng.uniform(1500, 12000, 15)
    inside = np.flatnonzero(np.isfinite(scan.tof_us))[::17]
    tof[inside] = scan.tof_us[inside] - rng.uniform(20, 35, inside.size)
    out["spikes"] = ScanReadings(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof,
                                 scan.sensor)
    out["coarse"] = pan_scan([Reflector.polar(2.0, 12.0, 0.67)], rng, -40, 40, 2.0)
    n = 3 * 720
    out["rotation"] = simulate_readings(
        np.arange(n) * 0.03, 0.0, 0.0, np.deg2rad(np.arange(n) * 0.5 - 180.0),
        [Reflector.polar(r, b, 0.67) for r, b in ((1.5, 180.0), (2.0, -60.0), (2.5, 45.0))],
        rng)
    t = np.arange(0, 12.0, 0.04)
    out["moving"] = simulate_readings(
        t, -1.0 + 0.25 * t, 0.0, np.pi / 2 + np.deg2rad(15.0) * np.sin(2 * np.pi * t / 3.0),
        [Reflector.point(0.0, 1.2, 0.67), Reflector.line(2.2, np.deg2rad(95.0), 0.15)], rng)
    scan = pan_scan([Reflector.polar(1.5, 0.0, 0.67)], rng, -30, 30, 0.3)
    tof, x, t = scan.tof_us.copy(), scan.x_m.copy(), scan.t_s.copy()
    tof[::9] = np.inf
    tof[5::13] = -1.0
    x[7::31] = np.nan
    t[1::2] = t[0::2][: len(t[1::2])]
    out["junk"] = ScanReadings(t, x, scan.y_m, scan.yaw_rad, tof, scan.sensor)
    out["close pair"] = pan_scan([Reflector.polar(1.5, -2.0, 0.67),
                                  Reflector.polar(1.53, 3.0, 0.67)], rng, -40, 40, 0.3)
    return out


@pytest.mark.parametrize("name", ["spikes", "coarse", "rotation", "moving", "junk",
                                  "close pair"])
@pytest.mark.parametrize("sweep", [None, 50.0])
def test_hard_case_scans_give_identical_segments(name, sweep):
    pushes = _scan_pushes(_hard_scans()[name])
    assert _assert_same(pushes, {"sweep_away_deg": sweep}, chunks=(1, 64, 65536)) >= 1


def test_long_rotation_and_feed_give_identical_segments():
    # the large-CSV benchmark's scan (continuous rotation, 1 deg per ping, 8 reflectors,
    # 60 turns), through the reference, push_many in chunks, and feed (as fit_scan)
    scan = rotation_scan(21600, np.random.default_rng(2003))
    pushes = _scan_pushes(scan)
    assert _assert_same(pushes, {}, chunks=(1000, 65536)) > 400
    want, _ = _run(ref, ref.SegmenterConfig(), pushes)
    seg = fast.Segmenter()
    got = [(0, s) for s in seg.feed(scan, chunk=5000)]
    _compare(got, seg, [(0, s) for _, s in want], _run(ref, ref.SegmenterConfig(), pushes)[1])


@st.composite
def _streams(draw) -> list[Push]:
    """Random readings: a few reflectors seen from a wandering ring / pan, spikes, gaps,
    time going backwards, bad values, pan-style repeated positions."""
    n = draw(st.integers(1, 160))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    still = draw(st.booleans())
    turn = draw(st.sampled_from([0.0, 1.0, -1.5, 3.0]))  # deg per ping, through +-180
    t = np.cumsum(rng.choice([0.0, 0.01, 0.03, 0.3, 2.5], n, p=[0.05, 0.4, 0.4, 0.1, 0.05]))
    if draw(st.booleans()):
        k = rng.integers(0, n)
        t[k] -= 1.0                                          # goes backwards once
    sensor = rng.integers(0, 4, n)
    base = np.zeros((n, 2)) if still else np.cumsum(rng.normal(0, 0.02, (n, 2)), axis=0)
    yaw = sensor * (math.pi / 2) + rng.normal(0, 0.3, n) if not still else \
        np.linspace(-1.5, 1.5, n) + rng.normal(0, 0.01, n)
    if turn:   # a rotating pan: whole numbers of degrees, exact repeats of the angles
        yaw = np.deg2rad(rng.integers(-180, 180) + turn * np.arange(n))
        sensor = np.where(rng.random(n) < 0.9, 0, sensor)
    refl = rng.uniform(-2, 2, (3, 2))
    tof = np.full(n, np.nan)
    for i in range(n):
        d = refl - base[i]
        ang = np.arctan2(d[:, 1], d[:, 0]) - yaw[i]
        ang = (ang + math.pi) % (2 * math.pi) - math.pi
        seen = np.abs(ang) < math.radians(22)
        if seen.any() and rng.random() < 0.85:
            r = np.hypot(d[seen, 0], d[seen, 1]).min()
            tof[i] = 2e6 * r / 343.0 + rng.normal(0, 5) * (rng.random() < 0.8)
        elif rng.random() < 0.1:
            tof[i] = rng.uniform(1000, 20000)               # spike
    bad = rng.random(n) < 0.03
    tof[bad] = rng.choice([np.inf, -5.0, 0.0], int(bad.sum()))
    xs = base[:, 0].copy()
    xs[rng.random(n) < 0.01] = np.nan
    return [(float(t[i]), float(xs[i]), float(base[i, 1]), float(yaw[i]), float(tof[i]),
             int(sensor[i])) for i in range(n)]


@settings(max_examples=150, deadline=None)
@given(_streams(), st.sampled_from([None, 50.0]), st.sampled_from([0, 1, 2, 8]),
       st.sampled_from([2, 64]), st.sampled_from([3, 400]), st.integers(1, 40),
       st.sampled_from([0.0, 0.05, 0.2, 1.0]))
def test_random_streams_give_identical_segments(pushes, sweep, censor, max_open, max_readings,
                                                chunk, travel):
    _assert_same(pushes, {"sweep_away_deg": sweep, "censor_window": censor,
                          "max_open": max_open, "max_readings": max_readings,
                          "min_echoes": 2, "max_gap_s": 1.0, "max_travel_m": travel},
                 chunks=(chunk, 65536))


def test_push_many_checks_its_arguments():
    seg = fast.Segmenter()
    with pytest.raises(ValueError, match="`tof_us` has length 2"):
        seg.push_many([0.0], [0.0], [0.0], [0.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="`chunk` must be a positive integer"):
        seg.push_many([0.0], [0.0], [0.0], [0.0], [1.0], chunk=0)
    assert seg.push_many([], [], [], [], []) == [] and seg.stats.readings == 0


def test_push_many_keeps_only_open_segments_between_chunks():
    # a long stream in chunks: between chunks the segmenter holds its open segments
    # (as row tuples, no reference to the chunk) and at most censor_window recent
    # readings per sensor, whatever the length of the stream
    rng = np.random.default_rng(5)
    n = 20000
    yaw = np.deg2rad(np.arange(n) * 1.0)
    scan = simulate_readings(np.arange(n) * 0.01, 0.0, 0.0, yaw,
                             [Reflector.polar(1.5, 0.0, 0.67), Reflector.polar(2.0, 90, 0.67)],
                             rng)
    seg = fast.Segmenter()
    most_open = 0
    for lo in range(0, n, 997):
        part = slice(lo, lo + 997)
        seg.push_many(scan.t_s[part], scan.x_m[part], scan.y_m[part], scan.yaw_rad[part],
                      scan.tof_us[part], scan.sensor[part])
        assert seg._chunk is None
        assert all(isinstance(r, tuple) for s in seg._open for r in s.rows)
        assert all(len(d) <= seg.config.censor_window for d in seg._recent.values())
        most_open = max(most_open, seg.open_segments)
    assert 0 < most_open <= 3 and seg.stats.segments > 100


@settings(max_examples=60, deadline=None)
@given(_streams(), st.sampled_from([None, 50.0]), st.sampled_from([0, 2, 8]),
       st.lists(st.integers(0, 30), min_size=1, max_size=12))
def test_push_and_push_many_mixed_give_identical_segments(pushes, sweep, censor, cuts):
    # pieces of one stream alternately through push (one by one) and push_many: the
    # state carried between them (open segments, recent readings) is the same
    kwargs = {"sweep_away_deg": sweep, "censor_window": censor, "min_echoes": 2,
              "max_gap_s": 1.0}
    want, seg_ref = _run(ref, ref.SegmenterConfig(**kwargs), pushes)
    seg = fast.Segmenter(fast.SegmenterConfig(**kwargs))
    got: list = []
    lo, k = 0, 0
    while lo < len(pushes):
        hi = min(len(pushes), lo + cuts[k % len(cuts)] + 1)
        if k % 2:
            cols = [np.array(c) for c in zip(*pushes[lo:hi], strict=True)]
            got += [(lo + i, s) for i, s in seg.push_many(*cols)]
        else:
            for i in range(lo, hi):
                got += [(i, s) for s in seg.push(*pushes[i])]
        lo, k = hi, k + 1
    got += [(len(pushes), s) for s in seg.flush()]
    _compare(got, seg, want, seg_ref)


def test_parallax_at_the_edge_of_the_beams_gives_identical_segments():
    """A ring transducer beside the one that saw a landmark may cover it although its
    axis is more than two beam half-widths away (the new transducer sits elsewhere):
    _step skips the arc test only when the angle exceeds 2 beam + asin(d / lR), d the
    distance between the transducers. Readings placed on both sides of that bound."""
    rng = np.random.default_rng(11)
    seg = fast.Segmenter()
    beam = seg._beam
    pushes: list[Push] = []
    beyond = 0     # new axis more than 2 beams from the last one: parallax needed
    for k in range(400):
        t0 = 10.0 * k
        lyaw = rng.uniform(-math.pi, math.pi)
        lR = rng.uniform(0.3, 3.0)
        for j in range(3):   # the first transducer's echoes of a landmark at lR
            pushes.append((t0 + 0.03 * j, 0.0, 0.0, lyaw,
                           lR / seg._m_per_us + seg._half_count_us, 0))
        # a point of the arc, seen from a transducer at distance r along phi, near the
        # edge of its beam (off), its axis then at phi - off
        a = rng.uniform(-1.0, 1.0) * beam
        ax, ay = lR * math.cos(lyaw + a), lR * math.sin(lyaw + a)
        off = rng.uniform(0.9, 1.02) * beam * rng.choice([-1.0, 1.0])
        phi = lyaw + a + rng.uniform(-0.6, 0.6)
        r = rng.uniform(0.3, 1.5) * lR
        x, y, yaw = ax - r * math.cos(phi), ay - r * math.sin(phi), phi - off
        d_ang = abs((lyaw - yaw + math.pi) % (2 * math.pi) - math.pi)
        beyond += d_ang > 2 * beam and abs(off) <= beam
        R = r + rng.uniform(-0.5, 0.5) * seg._gate_m
        pushes.append((t0 + 0.09, x, y, yaw, R / seg._m_per_us + seg._half_count_us, 1))
    assert beyond > 20
    n = _assert_same(pushes, {"min_echoes": 3})
    assert n > 300
