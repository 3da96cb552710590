"""Point landmarks from a moving robot: the trilaterated start of a long pass
(``lsq._path_start``), echoes taken back after a spike refit (``lsq._readmit``), and a
batch that made the tier score's projection singular."""

from __future__ import annotations

import collections
import math
from pathlib import Path

import numpy as np
import pytest

from sonarloc.fit.landmarks import fit_segments
from sonarloc.fit.lsq import FitConfig, _readmit, _solve, _trilaterate, fit_batch, pack_segments
from sonarloc.fit.model import to_frame
from sonarloc.fit.result import FitStatus
from sonarloc.fit.segment import Segmenter, SegmenterConfig
from sonarloc.fit.synth import Reflector, simulate_readings
from sonarloc.maps import load_map
from sonarloc.world.rig import rig_by_name
from sonarloc.world.simulate import scan_from_pings, simulate_records
from tests.conftest import MAPS


def _pass_by(seed: int = 0, sweep_deg: float = 8.0, kappa_us: float = 0.15):
    """A transducer on a robot driving 4 m along +x past a point (of strength
    ``kappa_us``) 1.3 m off its path, aimed at it with a +-``sweep_deg`` pan."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 16.0, 0.1)
    x = -2.0 + 0.25 * t
    yaw = np.arctan2(1.3, -x) + np.radians(sweep_deg) * np.sin(2 * np.pi * t / 1.6)
    return simulate_readings(t, x, 0.0, yaw, [Reflector.point(0.0, 1.3, kappa_us)], rng)


def _batch(scan):
    return pack_segments([(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us)])


def _y(batch, cfg):
    """The readings as the fitter takes them (see ``lsq._fit_direct``)."""
    y = batch.tof_us - 0.5 * cfg.module.count_period_us
    use = batch.valid & np.isfinite(y)
    return np.where(use, y, 0.0), use


def test_trilateration_finds_the_point_from_the_path():
    cfg = FitConfig()
    b = _batch(_pass_by())
    y, use = _y(b, cfg)
    q, ok = _trilaterate(b, y, use, cfg)
    assert ok.all()
    # relative to the reference (the last echo's transducer); the delays (a few us,
    # neglected) and the jitter leave millimetres
    truth = np.array([0.0, 1.3]) - b.ref_xy[0]
    assert np.hypot(*(q[0] - truth)) < 5e-3


def test_trilateration_is_not_trusted_without_a_baseline():
    """A pan from one spot (and a radial approach) cannot place the point by ranges."""
    cfg = FitConfig()
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 8.0, 0.1)
    yaw = np.radians(90.0 + 10.0 * np.sin(t))
    pan = simulate_readings(t, 0.0, 0.0, yaw, [Reflector.point(0.0, 1.3, 0.15)], rng)
    radial = simulate_readings(t, 0.0, -0.1 * t, np.radians(90.0),
                               [Reflector.point(0.0, 1.3, 0.15)], rng)
    for scan in (pan, radial):
        b = _batch(scan)
        y, use = _y(b, cfg)
        assert use.sum() >= 10
        assert not _trilaterate(b, y, use, cfg)[1].any()


def test_readmit_takes_back_good_echoes_not_spikes():
    cfg = FitConfig()
    scan = _pass_by(2)
    tof = scan.tof_us.copy()
    echo = np.flatnonzero(np.isfinite(tof))
    tof[echo[40]] += 400.0                                    # a spike
    b = pack_segments([(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad, tof)])
    y, use = _y(b, cfg)
    cols = np.flatnonzero(use[0])
    dropped = np.zeros_like(use)
    dropped[0, cols[[0, 1, 2, 40, 90]]] = True                # three good ones, the spike, one
    st, _ = _solve("point", "gauss", b, y, use & ~dropped, cfg)
    st2, use2 = _readmit("point", "gauss", st, b, y, use & ~dropped, dropped, cfg)
    assert use2[0, cols[[0, 1, 2, 90]]].all()                # the good echoes are back
    assert not use2[0, cols[40]]                              # the spike stays out
    gain = st.full_cost(use & ~dropped)[0] - st2.full_cost(use2)[0]
    assert gain + cfg.outlier_sigma ** 2 * 4 > 0              # the robust cost fell
    # nothing dropped that fits: the state is kept as it is
    st3, use3 = _readmit("point", "gauss", st2, b, y, use2, dropped & ~use2, cfg)
    assert st3 is st2 and use3 is use2


@pytest.fixture(scope="module")
def room_drive_true_poses():
    """The first 30 s of a ring16 drive through the room (seed 3), with the true poses,
    segmented; the simulator's reflector of each reading."""
    room = load_map(MAPS / "room.geojson")
    pings: list = []
    for _ in simulate_records(room, rig_by_name("ring16"), duration_s=30.0, seed=3,
                              on_ping=pings.append):
        pass
    sim = scan_from_pings(pings, "map")
    # whole passes (the corners' 13 and 20 s): no travel cap
    return room, sim, Segmenter(SegmenterConfig(max_travel_m=0.0)).feed_block(sim.readings)


def test_room_corners_passed_by_a_ring_are_points(room_drive_true_poses):
    """Two corners seen for 13 and 20 s by 2 and 7 ring transducers (nearest 1.3 m, the
    reference 3.5 m away) were bracketed to the wrong place: fitted as walls,
    ``UNRESOLVED``, with a fifth of their echoes dropped as spikes; each is a point
    within a centimetre of the corner, every echo its own (the simulator's truth)."""
    room, sim, segs = room_drive_true_poses
    key = {(float(t), int(k)): i for i, (t, k) in enumerate(
        zip(sim.readings.t_s, sim.readings.sensor, strict=True))}
    corners = []
    for seg in segs:
        r = seg.readings
        fin = np.isfinite(r.tof_us)
        if fin.sum() < 60:
            continue
        idx = [key[(float(t), int(k))] for t, k in zip(r.t_s[fin], r.sensor[fin], strict=True)]
        (own, n_own), = collections.Counter(sim.reflector[idx].tolist()).most_common(1)
        if room.reflectors[own].kind == "corner" and n_own == fin.sum():
            corners.append((seg, room.reflectors[own].geometry))
    assert len(corners) == 4
    segments = [seg for seg, _ in corners]
    b = pack_segments([seg.arrays() for seg in segments])
    fit = fit_batch(b, "point", "gauss", FitConfig())
    xy = to_frame("point", fit.local, fit.cov, b.ref_xy)[0][:, :2]
    for k, (seg, corner) in enumerate(corners):
        n = int(np.isfinite(seg.readings.tof_us).sum())
        assert math.hypot(xy[k, 0] - corner.x, xy[k, 1] - corner.y) < 0.01
        assert fit.n_used[k] >= 0.97 * n
    for lm in fit_segments(segments):
        assert lm.kind == "point" and lm.status is FitStatus.OK, (lm.kind, lm.reason)


def test_proportional_jacobian_columns_do_not_raise():
    """Two segments of a ring16 room drive (true poses) whose batch made the tier score's
    3x3 projection exactly singular (range and kappa columns proportional in one of them:
    every used echo at the same off-axis angle): ``LinAlgError`` from ``fit_segments``
    until session 13; each fitted alone did not raise. The readings as they were
    (helper seg13's reduction)."""
    import csv

    from sonarloc.io.scancsv import read_scan_csv

    path = Path(__file__).parent / "data" / "collinear_columns.csv"
    scan = read_scan_csv(path)
    with path.open() as f:
        seg = np.array([int(row["segment"]) for row in csv.DictReader(f)])
    segments = [scan.select(seg == k) for k in (0, 1)]
    both = fit_segments(segments, None, 0.0)
    alone = [fit_segments([s], None, 0.0)[0] for s in segments]
    for lm, ref in zip(both, alone, strict=True):
        assert (lm.kind, lm.status) == (ref.kind, ref.status)
        assert np.all(np.isfinite(lm.params))
    assert both[1].status is FitStatus.OK
