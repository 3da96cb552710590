"""Moving segments: a wall seen squarely by one transducer up to its end (the no-echo
readings past the end say nothing about the wall's strength, ``select.past_wall_ends``),
and an OK single landmark against the two arms of its U (``pair._ARMS_OF_ONE_U``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.fit.landmarks import fit_scan, fit_segments, weak_wall
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.pair import resolve_pair_groups
from sonarloc.fit.result import FitStatus
from sonarloc.fit.segment import Segmenter, SegmenterConfig
from sonarloc.fit.synth import Reflector, simulate_readings
from sonarloc.maps import load_map
from sonarloc.world.rig import rig_by_name
from sonarloc.world.simulate import simulate_scan
from tests.conftest import MAPS

RHO_M = 2.0


def _drive_past_wall_end(alpha_deg: float, half_length_m: float, seed: int = 1):
    """A robot driving 1.2 m along +y with one transducer facing a wall (tilted
    ``alpha_deg`` to the path) squarely; the wall ends on the way (the foot of the
    normal leaves it)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 6.0, 0.1)
    y = -0.6 + 0.2 * t
    alpha = math.radians(alpha_deg)
    wall = Reflector.line(RHO_M, alpha, 0.15, half_length_m=half_length_m)
    return simulate_readings(t, 0.0, y, alpha, [wall], rng)


@pytest.mark.parametrize(("alpha_deg", "half_length_m"), [(8.0, 0.35), (-12.0, 0.3),
                                                          (5.0, 0.25)])
def test_wall_seen_squarely_to_its_end_is_a_wall_not_a_weak_one(alpha_deg, half_length_m):
    scan = _drive_past_wall_end(alpha_deg, half_length_m)
    echo = np.isfinite(scan.tof_us)
    assert echo.sum() >= 10 and (~echo).sum() >= 10     # the wall ends within the drive
    lms = fit_scan(scan).landmarks
    walls = [lm for lm in lms if lm.kind == "line"]
    assert len(walls) == 1, lms
    lm = walls[0]
    # its no-echo readings lie past the wall's end: none of them counted
    assert lm.extra["n_past_wall_end"] == lm.extra["n_noecho"] > 0
    assert lm.status is FitStatus.OK, lm.reason
    sd = np.sqrt(np.diag(lm.cov))
    assert abs(lm.params[0] - RHO_M) < 4 * sd[0] + 1e-3
    assert abs(math.degrees(lm.params[1]) - alpha_deg) < math.degrees(4 * sd[1]) + 0.2


def test_weak_wall_needs_a_significantly_weak_strength():
    assert weak_wall("line", 11.0, 0.8)              # 11 us: far weaker than any wall
    assert not weak_wall("line", 4.3, 17.0)          # the TOFs do not fix kappa
    assert not weak_wall("line", 0.5, 0.01)          # within walls' range
    assert not weak_wall("point", 11.0, 0.8)         # points may be weak
    np.testing.assert_array_equal(
        weak_wall(np.array(["line", "line", "point"]), [11.0, 4.3, 11.0], [0.8, 17.0, 0.8]),
        [True, False, False])


def test_ok_single_is_not_replaced_by_the_two_arms_of_its_u():
    # a moving ring's segment (room drive, odometry poses) whose single fit is OK and
    # whose accepted pair would be two PARTIAL halves (neither minimum seen): odometry
    # error bends the U; the single landmark stays. (With the odometry's SD at its
    # default the walk explains the bend and the single is no pair candidate at all;
    # at half of it the chi-square is strained.)
    scan = simulate_scan(load_map(MAPS / "room.geojson"), rig_by_name("ring16"),
                         frame="odom", duration_s=63.0, seed=3).readings
    # the whole pass (13 s, 2.7 m): no travel cap
    segs = Segmenter(SegmenterConfig(max_travel_m=0.0)).feed_block(scan)
    (seg,) = [s for s in segs if abs(s.readings.t_s[0] - 54.48) < 1e-6]
    assert fit_segments([seg])[0].ok
    single = fit_segments([seg], odometry_sd_deg_per_m=0.5)[0]
    assert single.status is FitStatus.OK
    (group,) = resolve_pair_groups([seg], [single], FitConfig())
    assert len(group) == 1 and group[0].status is FitStatus.OK
    basis = str(group[0].extra["pair_basis"])
    assert basis.startswith("two reflectors") and "not taken" in basis


def test_readings_kept_past_a_walls_ends_stay_in_front():
    # a wall seen squarely on the middle of the drive (no echo before or after it) and two
    # missed echoes on it: the readings past both ends go, the two missed echoes stay,
    # moved to the front of the no-echo columns (fit_batch cuts a chunk's columns to the
    # readings' count: a hole before them used to cut them off)
    from sonarloc.fit.lsq import pack_flat
    from sonarloc.fit.select import select_models

    scan = _drive_past_wall_end(0.0, 0.3)
    tof = scan.tof_us.copy()
    echo = np.flatnonzero(np.isfinite(tof))
    assert echo[0] > 0 and echo[-1] < tof.size - 1        # silent before and after
    missed = echo[[len(echo) // 3, 2 * len(echo) // 3]]
    tof[missed] = np.nan
    batch = pack_flat(np.zeros(tof.size, dtype=np.int64), scan.t_s, scan.x_m, scan.y_m,
                      scan.yaw_rad, tof)
    sel, fitted = select_models(batch, FitConfig())
    assert sel.kind[0] == "line"
    n_kept = int(fitted.ne_valid[0].sum())
    assert n_kept == 2 and fitted.ne_valid[0, :n_kept].all()
    kept = {(round(float(x), 9), round(float(y), 9))
            for x, y in zip(fitted.ne_px[0, :2], fitted.ne_py[0, :2], strict=True)}
    ref = batch.ref_xy[0]
    assert kept == {(round(float(scan.x_m[i] - ref[0]), 9), round(float(scan.y_m[i] - ref[1]), 9))
                    for i in missed}
    assert sel.extra[0]["n_past_wall_end"] == int((~np.isfinite(scan.tof_us)).sum())
