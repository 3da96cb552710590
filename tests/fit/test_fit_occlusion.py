"""Segments whose arc ends are hidden by nearer reflectors (the paper's Fig. 5 plane)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarloc.fit.landmarks import fit_scan
from sonarloc.fit.result import FitStatus
from sonarloc.fit.segment import Segmenter
from sonarloc.fit.synth import Reflector, pan_scan
from tests.conftest import MAPS


def _fig5(seed: int, tier: str):
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.simulate import simulate_scan

    world = load_map(MAPS / "paper_fig5.geojson")
    return simulate_scan(world, rig_by_name("pan", pan=(-40, 40, 0.3)), at=(0.0, 0.0, 0.0),
                         tier=tier, seed=seed).readings


def test_segmenter_marks_arc_ends_hidden_by_nearer_echoes():
    segs = list(Segmenter().feed(_fig5(0, "auto")))
    assert len(segs) == 3
    pole, plane, rod = segs
    assert plane.occluded == (True, True)
    assert pole.occluded == (False, False) and rod.occluded == (False, False)


def test_one_end_occluded(rng):
    # a pole in front of the right half of a wall's arc: the wall's trailing end hidden
    scan = pan_scan([Reflector.polar(1.5, 0.0, 0.15), Reflector.polar(1.2, 15.0, 0.67)],
                    rng, -40, 40, 0.3)
    segs = list(Segmenter().feed(scan))
    wall = max(segs, key=lambda s: s.readings.tof_us[np.isfinite(s.readings.tof_us)].mean())
    assert wall.occluded == (False, True)


@pytest.mark.parametrize("seed", [3, 5, 7, 8, 11])
def test_fig5_plane_between_pole_and_rod_is_not_ok(seed):
    # seeds where the plane used to come out OK as a pole-strength point (kappa 0.3-1)
    lms = fit_scan(_fig5(seed, "auto")).landmarks
    assert len(lms) == 3
    pole, plane, rod = lms
    assert pole.ok and rod.ok and pole.kind == rod.kind == "point"
    assert pole.kappa_us < rod.kappa_us
    assert plane.status is FitStatus.FLAT
    assert "occluded on both sides" in plane.reason or "lower bound" in plane.reason
    assert abs(plane.range_m - 1.5) < 2e-3          # its range is still good
    assert math.isfinite(plane.kappa_us)
