import math

import numpy as np
import pytest

from sonarloc.maps import build_map, load_map, map_from_geojson
from sonarloc.physics.reflectors import kappa_at_range_us
from sonarloc.physics.tiers import Tier
from sonarloc.physics.tof import ModuleParams
from sonarloc.world.rig import pan_angles_deg
from sonarloc.world.scene import Scene, reach_half_angle_rad, sector_bounds
from tests.conftest import MAPS

QUIET = ModuleParams(jitter_sd_us=0.0, amplitude_fluctuation=0.0)


def fc(*features):
    return {"type": "FeatureCollection", "features": list(features)}


def pt(x, y, kind="pole", **props):
    return {"type": "Feature", "properties": {"kind": kind, **props},
            "geometry": {"type": "Point", "coordinates": [x, y]}}


def line(coords, kind="wall", **props):
    return {"type": "Feature", "properties": {"kind": kind, **props},
            "geometry": {"type": "LineString", "coordinates": coords}}


def pan_scan(scene, rng, start=-40.0, stop=40.0, step=0.3, tier=Tier.AUTO):
    ang = pan_angles_deg(start, stop, step)
    res = scene.ping(np.zeros(ang.size), 0.0, np.deg2rad(ang), rng, tier)
    return ang, res


def minimum_of_curve(ang, tof):
    """Vertex of a parabola fitted to a U-shaped TOF segment (the curve minimum)."""
    c = np.polyfit(ang, tof, 2)
    return np.polyval(c, -c[1] / (2 * c[0])), -c[1] / (2 * c[0])


def test_fig5_scene_minima_and_occlusion(rng):
    """Kuc 2003 Fig. 5: one pan -40..40 deg at 0.3 deg, one ping per angle, default tier."""
    fig5 = load_map(MAPS / "paper_fig5.geojson")
    ang, res = pan_scan(Scene(fig5), rng)
    assert ang.size == 267
    expected = {0: (8523.0, -17.0), 1: (8746.0, 4.0), 2: (8583.0, 22.0)}  # pole, plane, rod
    for idx, (tm_paper, bearing) in expected.items():
        sel = res.reflector == idx
        assert sel.sum() > 30, (idx, sel.sum())
        if idx == 1:  # the plane's curve is flat: its level, not a parabola
            tm, _ = float(np.median(res.tof_us[sel])), None
        else:
            tm, vertex = minimum_of_curve(ang[sel], res.tof_us[sel])
            assert vertex == pytest.approx(bearing, abs=3.0)
        assert tm == pytest.approx(tm_paper, abs=4.0), idx
    # The plane alone is seen over a wide arc; in the scene the nearer pole and rod win
    # on both sides of it (nearest echo wins), leaving three distinct regions.
    alone = Scene(build_map([fig5.features[1]]))
    quiet_full = Scene(fig5, QUIET).predict_tof_us(np.zeros(ang.size), 0.0, np.deg2rad(ang))[1]
    plane_alone = np.isfinite(alone.with_params(QUIET).predict_tof_us(
        np.zeros(ang.size), 0.0, np.deg2rad(ang))[0])
    hidden = plane_alone & (quiet_full != 1)
    assert np.sum(hidden & (quiet_full == 0)) > 10  # behind the pole's arc
    assert np.sum(hidden & (quiet_full == 2)) > 10  # behind the rod's arc
    order = [r for j, r in enumerate(quiet_full) if r >= 0 and (j == 0 or r != quiet_full[j - 1])]
    assert order == [0, 1, 2]
    # alone, the plane's arc (side lobes included) is far wider than what is left of it
    assert np.sum(plane_alone) * 0.3 > 25
    assert np.sum(plane_alone) > np.sum(quiet_full == 1) + 30


def test_arrival_time_is_two_range_over_c():
    m = map_from_geojson(fc(pt(1.55, 0.0, "pole", radius_m=0.05, kappa_us=0.67)))
    tm, winner = Scene(m, QUIET).predict_tof_us(0.0, 0.0, 0.0, Tier.GAUSS)
    assert winner[0] == 0
    assert tm[0] == pytest.approx(2 * 1.5 / 343.0 * 1e6 + 0.67, abs=1e-6)  # kappa at 1.5 m


def test_cylinder_strength_falls_off_with_range():
    # the map's kappa holds at 1.5 m; nearer cylinders are stronger, farther weaker
    m = map_from_geojson(fc(pt(0.0, 0.0, "rod", radius_m=0.004), pt(0.0, 10.0, "pole")))
    scene = Scene(m, QUIET)
    for dist in (0.5, 1.504, 3.0):
        cand = scene.candidates(dist, 0.0, math.pi)
        assert cand.reflector.tolist() == [0]
        expect = kappa_at_range_us(2.68, "rod", dist - 0.004, 0.004)
        assert cand.kappa_us[0] == pytest.approx(float(expect))
    assert scene.candidates(1.504, 0.0, math.pi).kappa_us[0] == pytest.approx(2.68)
    assert scene.candidates(0.5, 0.0, math.pi).kappa_us[0] < 2.68
    # a radius-less pole falls off like the paper's pole; a plane does not change
    cand = scene.candidates(0.0, 9.5, math.pi / 2)
    assert cand.reflector.tolist() == [1]
    assert cand.kappa_us[0] == pytest.approx(float(kappa_at_range_us(0.67, "pole", 0.5)))
    wall = Scene(map_from_geojson(fc(line([[1.0, -1.0], [1.0, 1.0]], vertices="none"))), QUIET)
    assert wall.candidates(0.0, 0.0, 0.0).kappa_us[0] == pytest.approx(0.15)
    assert wall.candidates(-2.0, 0.0, 0.0).kappa_us[0] == pytest.approx(0.15)


def test_line_of_sight_blocked_by_nearer_geometry():
    wall = line([[2.0, -1.0], [2.0, 1.0]])
    pole = pt(1.0, 0.0, "pole", radius_m=0.1)
    scene = Scene(map_from_geojson(fc(wall, pole)))
    cand = scene.candidates(0.0, 0.0, 0.0)
    kinds = [scene.map.reflectors[i].kind for i in cand.reflector]
    assert kinds == ["pole"]  # the wall's normal-incidence point is behind the pole
    # a short wall in front hides a pole behind it
    scene = Scene(map_from_geojson(fc(line([[1.0, -0.3], [1.0, 0.3]], vertices="none"),
                                      pt(2.0, 0.05, "rod", radius_m=0.004))))
    assert [scene.map.reflectors[i].kind for i in scene.candidates(0, 0, 0).reflector] == \
        ["wall"]
    # moved sideways the rod is in sight again
    cand = scene.candidates(0.0, 1.0, -math.atan2(0.95, 2.0))
    assert "rod" in [scene.map.reflectors[i].kind for i in cand.reflector]


def test_nearest_echo_wins(rng):
    # a pole 1 m away 4 deg off axis, a wall 2 m away on the axis: the pole wins
    m = map_from_geojson(fc(line([[2.0, -3.0], [2.0, 3.0]], vertices="none"),
                            pt(math.cos(math.radians(4)), math.sin(math.radians(4)),
                               "pole", radius_m=0.0)))
    res = Scene(m).ping(np.zeros(200), 0.0, 0.0, rng)
    assert np.all(res.reflector == 1)
    np.testing.assert_allclose(res.tof_us, 2 / 343 * 1e6, atol=40)
    # if the pole is too weak to be detected the wall's echo comes through
    m2 = map_from_geojson(fc(line([[2.0, -3.0], [2.0, 3.0]], vertices="none"),
                             pt(1.0, 0.0, "point", kappa_us=100.0)))
    res2 = Scene(m2).ping(np.zeros(50), 0.0, 0.0, rng)
    assert np.all(res2.reflector == 0)
    np.testing.assert_allclose(res2.tof_us, 4 / 343 * 1e6, atol=40)


def test_edges_only_within_half_a_metre():
    # a free wall end at the origin of the x axis; the wall runs away along +y
    m = map_from_geojson(fc(line([[0.0, 0.0], [0.0, 3.0]], vertices="edge")))
    scene = Scene(m, QUIET)
    for dist, seen in ((0.3, True), (0.45, True), (0.55, False), (1.0, False)):
        cand = scene.candidates(dist * math.cos(-2.5), dist * math.sin(-2.5), -2.5 + math.pi)
        kinds = [m.reflectors[i].kind for i in cand.reflector]
        assert ("edge" in kinds) is seen, (dist, kinds)


def test_walls_echo_only_within_the_segment():
    m = map_from_geojson(fc(line([[2.0, 0.5], [2.0, 2.0]], vertices="none")))
    scene = Scene(m, QUIET)
    # facing the wall's line below its end: the normal-incidence point is off the segment
    assert len(scene.candidates(0.0, 0.0, 0.0)) == 0
    tm, winner = scene.predict_tof_us(0.0, 0.0, 0.0)
    assert np.isnan(tm[0]) and winner[0] == -1
    # slide up until the foot point is on the segment
    cand = scene.candidates(0.0, 0.6, 0.0)
    assert len(cand) == 1 and cand.range_m[0] == pytest.approx(2.0)
    assert (cand.qx_m[0], cand.qy_m[0]) == pytest.approx((2.0, 0.6))


def test_corner_seen_from_inside_edge_from_outside():
    m = map_from_geojson(fc(line([[2.0, 0.0], [0.0, 0.0], [0.0, 2.0]])))  # vertex at origin
    scene = Scene(m, QUIET)

    def kinds_from(x, y):
        yaw = math.atan2(-y, -x)
        return [m.reflectors[i].kind for i in scene.candidates(x, y, yaw).reflector]

    assert "corner" in kinds_from(1.0, 1.0) and "edge" not in kinds_from(1.0, 1.0)
    assert "edge" in kinds_from(-0.3, -0.3) and "corner" not in kinds_from(-0.3, -0.3)
    assert kinds_from(-1.0, -1.0) == []  # edge too far, walls seen edge-on from behind
    # the corner echoes like a plane-strength point at the vertex
    tm, w = scene.predict_tof_us(np.ones(3), np.ones(3), np.deg2rad([-135, -143, -127]))
    assert [m.reflectors[i].kind for i in w] == ["corner"] * 3
    np.testing.assert_allclose(tm, 2 * math.sqrt(2) / 343e-6 + 0.15 * np.exp(
        np.deg2rad([0, 8, 8]) ** 2 / (2 * np.deg2rad(5.25) ** 2)), atol=1e-6)


def test_index_and_brute_force_agree(rng):
    pts = rng.uniform(-6, 6, (150, 2))
    feats = [pt(*p, kind=k, radius_m=r) for p, k, r in
             zip(pts[:100], rng.choice(["pole", "rod", "point"], 100),
                 rng.uniform(0, 0.1, 100), strict=True)]
    feats += [line([p.tolist(), (p + rng.uniform(-1.5, 1.5, 2)).tolist()]) for p in pts[100:]]
    m = map_from_geojson(fc(*feats))
    poses = rng.uniform(-5, 5, (64, 3))
    fast, slow = Scene(m), Scene(m, use_index=False)
    a = fast.candidates(poses[:, 0], poses[:, 1], poses[:, 2])
    b = slow.candidates(poses[:, 0], poses[:, 1], poses[:, 2])
    assert len(a) > 50
    np.testing.assert_array_equal(a.ping, b.ping)
    np.testing.assert_array_equal(a.reflector, b.reflector)
    np.testing.assert_allclose(a.range_m, b.range_m)
    ra = fast.ping(poses[:, 0], poses[:, 1], poses[:, 2], np.random.default_rng(5))
    rb = slow.ping(poses[:, 0], poses[:, 1], poses[:, 2], np.random.default_rng(5))
    np.testing.assert_array_equal(ra.tof_us, rb.tof_us)
    np.testing.assert_array_equal(ra.reflector, rb.reflector)
    assert np.isfinite(ra.tof_us).sum() > 10


def test_winner_tier_recorded(rng):
    fig5 = load_map(MAPS / "paper_fig5.geojson")
    for tier in (Tier.GAUSS, Tier.PISTON, Tier.WAVEFORM):
        _, res = pan_scan(Scene(fig5), rng, tier=tier)
        got = set(res.tier[res.reflector >= 0].tolist())
        assert got == {int(tier)}
        assert np.all(res.tier[res.reflector < 0] == -1)
    _, res = pan_scan(Scene(fig5), rng, tier=Tier.AUTO)
    used = set(res.tier[res.reflector >= 0].tolist())
    assert {int(Tier.GAUSS), int(Tier.PISTON)} <= used  # side lobes need the piston pattern
    assert used <= {int(Tier.GAUSS), int(Tier.PISTON), int(Tier.WAVEFORM)}


def test_sector_bounds_contain_the_sector(rng):
    for _ in range(200):
        x, y, yaw = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-7, 7)
        r, h = rng.uniform(0.1, 10), rng.uniform(0.01, 3.2)
        b = sector_bounds(x, y, yaw, r, h)[0]
        a = yaw + np.linspace(-min(h, np.pi), min(h, np.pi), 400)
        px, py = x + r * np.cos(a), y + r * np.sin(a)
        assert np.all((px >= b[0] - 1e-9) & (px <= b[2] + 1e-9))
        assert np.all((py >= b[1] - 1e-9) & (py <= b[3] + 1e-9))
        # and it is tight: the sector's extreme points touch the box
        ex = np.r_[px, x]
        ey = np.r_[py, y]
        assert ex.min() == pytest.approx(b[0], abs=1e-2 * r) and ey.max() == pytest.approx(
            b[3], abs=1e-2 * r)


def test_reach_half_angle_covers_side_lobes_of_strong_reflectors():
    plane = math.degrees(reach_half_angle_rad(0.15))
    rod = math.degrees(reach_half_angle_rad(2.68))
    assert 20 < plane < 35 and rod < plane
    with pytest.raises(ValueError, match="kappa_us"):
        reach_half_angle_rad(-1.0)


def test_candidate_work_does_not_grow_with_map_size():
    """The coarse query returns what is near the beam: same density, 30x the area, same work."""
    rng = np.random.default_rng(9)
    work = []
    for n in (100, 3000):
        side = math.sqrt(n / 0.5)
        m = map_from_geojson(fc(*[pt(*rng.uniform(0, side, 2).tolist(), kind="pole",
                                     radius_m=0.05) for _ in range(n)]))
        scene = Scene(m, ModuleParams(max_range_m=5.0))
        xy = rng.uniform(side / 2 - 3, side / 2 + 3, (200, 2))
        yaw = rng.uniform(-np.pi, np.pi, 200)
        pairs = m.query_bounds(sector_bounds(xy[:, 0], xy[:, 1], yaw, 5.05,
                                             scene.half_angle_rad))
        work.append(pairs.shape[1] / 200)
    assert work[1] < 2.0 * work[0] + 2
    assert work[1] < 100  # of 3000 reflectors
