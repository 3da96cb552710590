"""The batch replay's fast path: segments linearised and associated many at a time."""

import io
import math

import numpy as np
import pytest

from sonarloc import se2
from sonarloc.fit.segment import Segment
from sonarloc.io.logfile import LogWriter, OdomRecord, TruthRecord, iter_log
from sonarloc.io.scancsv import ScanReadings
from sonarloc.localize import batchfuse, echoes, ekf
from sonarloc.localize.echoes import Compressed
from sonarloc.localize.ekf import Gaussian, OdomNoise
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import Localizer
from sonarloc.localize.offline import OfflinePipeline
from sonarloc.localize.replay import replay_log
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = "maps/room.geojson"


@pytest.fixture(scope="module")
def fmap():
    return FeatureMap.from_map(load_map(ROOM))


@pytest.fixture(scope="module")
def ring_log():
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(load_map(ROOM), ring16(), duration_s=14.0, seed=8))
    return buf.getvalue()


def _chain_by_recursion(ref, base, sens, noise):
    """The transducer chain's covariance by the step-by-step recursion (reference)."""
    n = len(base)
    b = se2.between(ref, base)
    mount = se2.between(base, sens)
    nxt = np.vstack([base[1:], ref[None, :]])
    u = se2.between(nxt, base)
    q = noise.cov(u)
    b_next = np.vstack([b[1:], np.zeros((1, 3))])
    j1, j2 = se2.compose_jacobians(b_next, u)
    sigma, a_mat = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    s_next, a_next = np.zeros((3, 3)), np.eye(3)
    for i in range(n - 1, -1, -1):
        sigma[i] = j1[i] @ s_next @ j1[i].T + j2[i] @ q[i] @ j2[i].T
        a_mat[i] = j1[i] @ a_next
        s_next, a_next = sigma[i], a_mat[i]
    k, _ = se2.compose_jacobians(b, mount)
    return k @ a_mat, np.linalg.solve(a_mat, sigma) @ np.swapaxes(k, -1, -2)


def test_sensor_chain_closed_form_matches_the_recursion_and_batches():
    rng = np.random.default_rng(11)
    noise = OdomNoise(along_var_per_m=0.01**2, cross_var_per_m=0.006**2,
                      yaw_var_per_m=math.radians(2.0) ** 2,
                      yaw_var_per_rad=math.radians(2.0) ** 2)
    cases = []
    for n in (1, 4, 7):
        poses = [rng.normal(0, [2.0, 2.0, 3.0])]
        for u in rng.normal(0, [0.08, 0.02, 0.3], (n, 3)):
            poses.append(se2.compose(poses[-1], u))
        base, ref = np.array(poses[:n]), poses[n]
        sens = se2.compose(base, rng.normal(0, [0.2, 0.2, 2.0], (n, 3)))
        rel, p_fac, v_fac = echoes.relative_sensor_chain(ref, base, sens, noise)
        p_ref, v_ref = _chain_by_recursion(ref, base, sens, noise)
        for i in range(n):
            for j in range(i, n):
                np.testing.assert_allclose(p_fac[i] @ v_fac[j], p_ref[i] @ v_ref[j],
                                           rtol=1e-9, atol=1e-15)
        cases.append((ref, base, sens, rel, p_fac, v_fac))
    # a batch padded at the start with copies of the first reading gives the same
    m = 7
    refs = np.array([c[0] for c in cases])
    base_b = np.array([np.vstack([np.repeat(c[1][:1], m - len(c[1]), 0), c[1]]) for c in cases])
    sens_b = np.array([np.vstack([np.repeat(c[2][:1], m - len(c[2]), 0), c[2]]) for c in cases])
    rel_b, p_b, v_b = echoes.relative_sensor_chain(refs, base_b, sens_b, noise)
    for k, (_, base, _, rel, p_fac, v_fac) in enumerate(cases):
        n = len(base)
        np.testing.assert_allclose(rel_b[k, m - n:], rel, atol=1e-12)
        cov_b = np.einsum("iab,jbc->ijac", p_b[k, m - n:], v_b[k, m - n:])
        cov = np.einsum("iab,jbc->ijac", p_fac, v_fac)
        np.testing.assert_allclose(cov_b, cov, rtol=1e-10, atol=1e-16)


@pytest.mark.parametrize("rows", [1, 2, 3])
def test_reduced_update_matches_the_generic_kalman_update(rows):
    rng = np.random.default_rng(rows)
    for _ in range(50):
        a = rng.normal(size=(3, 3))
        state = Gaussian(rng.normal(size=3), a @ a.T * 1e-5 + np.eye(3) * 1e-8)
        c = Compressed(state.mean + rng.normal(0, 1e-3, 3), rng.normal(size=rows),
                       rng.normal(0, 300, (rows, 3)), 0.7, 6)
        ref, innov = echoes.update(state, echoes.EchoObservation(
            np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), 1.0,
            ekf.Feature("wall", np.array([1.0, 0.0])), 0.0, compressed=c))
        out = batchfuse.reduced_update(state, c)
        assert out is not None
        new, d2 = out
        np.testing.assert_allclose(new.mean, ref.mean, atol=1e-12)
        np.testing.assert_allclose(new.cov, ref.cov, rtol=1e-9, atol=1e-18)
        assert d2 + c.resid2 == pytest.approx(float(innov.d2), rel=1e-9)
        assert bool(new.is_spd())
    bad = Compressed(np.zeros(3), np.array([np.nan, 0.0, 0.0]), np.full((3, 3), np.nan), 0.0, 3)
    assert batchfuse.reduced_update(Gaussian(np.zeros(3), np.eye(3)), bad) is None


def test_feature_queries_batch_over_positions(fmap):
    rng = np.random.default_rng(2)
    xy = rng.uniform([-0.5, -0.5], [6.5, 4.5], (5, 4, 2))
    vis = fmap.points_visible_from(xy, 4.0)
    face = fmap.walls_facing(xy, 0.2, 4.0)
    assert vis.shape == (5, 4, fmap.n_points) and face.shape == (5, 4, fmap.n_walls)
    for i in range(5):
        for j in range(4):
            assert np.array_equal(vis[i, j], fmap.points_visible_from(xy[i, j], 4.0))
            assert np.array_equal(face[i, j], fmap.walls_facing(xy[i, j], 0.2, 4.0))


def test_rival_pairs_and_screen_rows_equal_their_pairwise_forms(fmap):
    """The rivals within a segment as index pairs, and the winners' screen rows from
    them, equal the all-pairs forms (every candidate against every other: same segment,
    other point or line) and a winner-by-winner loop."""
    fuser = batchfuse.BatchFuser(fmap, OdomNoise(), 343.0, 0.99, 0.99, 5.0, 0.2, 0.9, 0.5)
    rng = np.random.default_rng(5)
    n_f = fmap.n_points + fmap.n_walls
    for _ in range(20):
        n_seg, n = int(rng.integers(1, 8)), int(rng.integers(3, 7))
        ps = np.sort(rng.integers(0, n_seg, int(rng.integers(1, 25))))
        fs = rng.integers(0, n_f, len(ps))
        pc, pq = fuser._rival_pairs(ps, fs)
        gid = fuser._group[fs]
        pair_of = (ps[:, None] == ps[None, :]) & (gid[:, None] != gid[None, :])
        assert list(zip(pc.tolist(), pq.tolist(), strict=True)) == \
            [tuple(cq) for cq in np.argwhere(pair_of).tolist()]
        C = len(ps)
        hx, nu, r_ii, h = (rng.normal(size=(C, n, 3)), rng.normal(size=(C, n)),
                           rng.random((C, n)), rng.random((C, n)))
        usable = rng.random((C, n)) < 0.8
        passed = usable & (rng.random((C, n)) < 0.7)
        rival_usable = usable & (rng.random((C, n)) < 0.6)
        wp = np.sort(rng.choice(C, int(rng.integers(0, C + 1)), replace=False))
        rows = fuser._screen_rows(wp, (pc, pq), (hx, nu, r_ii), (usable, passed),
                                  rival_usable, h)
        for c, got in zip(wp.tolist(), rows, strict=True):
            sel = usable[c]
            want = list(zip(hx[c][sel].tolist(), nu[c][sel].tolist(), r_ii[c][sel].tolist(),
                            passed[c][sel].tolist(), strict=True))
            for q in np.flatnonzero(pair_of[c]).tolist():
                sq = passed[c] & rival_usable[q] & (h[q] < h[c])
                want += zip(hx[q][sq].tolist(), nu[q][sq].tolist(), r_ii[q][sq].tolist(),
                            passed[q][sq].tolist(), strict=True)
            assert got == want


def test_segment_echoes_of_many_segments_are_each_ones_echoes():
    """SegmentEchoes.from_segments: per segment its echoes (no-echo readings dropped) in
    time order (a stable sort where readings came out of order), the reference time the
    last echo's; segments without an echo left out."""
    rng = np.random.default_rng(3)
    segs = []
    for k in range(30):
        n = int(rng.integers(1, 7))
        t = np.round(np.sort(rng.random(n)) + k, 2)
        if k % 5 == 0 and n > 1:
            t[[0, -1]] = t[[-1, 0]]                        # out of time order
        tof = np.where(rng.random(n) < 0.7, rng.uniform(500, 9000, n), np.nan)
        if k % 7 == 0:
            tof[:] = np.nan                                 # no echo at all
        r = ScanReadings(t, rng.random(n), rng.random(n), rng.random(n), tof,
                         np.zeros(n, dtype=np.int64))
        segs.append(Segment(r, k, "gap"))
    got = batchfuse.SegmentEchoes.from_segments(segs)
    want = []
    for sg in segs:
        r = sg.readings
        data = np.array([r.t_s, r.x_m, r.y_m, r.yaw_rad, r.tof_us])[:, np.isfinite(r.tof_us)]
        if data.shape[1]:
            data = data[:, np.argsort(data[0], kind="stable")]
            want.append((float(data[0, -1]), data))
    assert len(got) == len(want) > 0
    for g, (t_ref, data) in zip(got, want, strict=True):
        assert g.t_ref == t_ref
        assert np.array_equal(g.data, data)
    assert batchfuse.SegmentEchoes.from_segments([]) == []


class Checking(OfflinePipeline):
    """The fast path, each prepared segment also run through the Localizer's own
    one-segment path at the same belief."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.checked = 0
        self.disagree = []

    def _fuse_prepared(self, p, redecide=False):
        loc = self.loc
        if p.outcome != "none" and loc._entries:
            last = loc._entries[-1]
            state = ekf.predict(last.state, se2.between(last.odom, p.odom_ref),
                                loc.config.odom_noise)
            if np.allclose(state.mean, p.x0, atol=1e-12, rtol=0):
                found = loc._associate_echoes(p.chain, math.nan, state)
                self.checked += 1
                if (found is None) != (p.outcome == "unmatched"):
                    self.disagree.append((p.t_ref, p.outcome, found))
                elif found is not None:
                    eo, assoc = found
                    assert (assoc.kind, assoc.index) == (p.kind, p.index)
                    assert len(eo) == p.n_kept
                    c = echoes.compress(eo, state.mean)
                    assert c is not None and p.reduced is not None
                    # the same reduced update (QR is unique up to row signs)
                    np.testing.assert_allclose(p.reduced.rq.T @ p.reduced.rq, c.rq.T @ c.rq,
                                               rtol=1e-6, atol=1e-6 * np.abs(c.rq).max() ** 2)
                    np.testing.assert_allclose(p.reduced.rq.T @ p.reduced.q_nu,
                                               c.rq.T @ c.q_nu, rtol=1e-6,
                                               atol=1e-6 * np.abs(c.rq.T @ c.q_nu).max())
                    # the whitened innovation's squared norm, split into Q's span and the
                    # rest; where H is rank-deficient (a wall: nothing along it) Q's last
                    # column is any unit vector the QR's rounding gives (it differed
                    # between two CPUs), so only the sum is the same there
                    def total(m):
                        return m.resid2 + float(m.q_nu @ m.q_nu)
                    assert total(p.reduced) == pytest.approx(total(c), rel=1e-5, abs=1e-9)
                    sv = np.linalg.svd(c.rq, compute_uv=False)
                    if sv[-1] > 1e-9 * sv[0]:
                        assert p.reduced.resid2 == pytest.approx(c.resid2, rel=1e-5, abs=1e-9)
        return super()._fuse_prepared(p, redecide)


def _run(text, fmap, pipe_cls=OfflinePipeline, **kw):
    loc = Localizer(fmap)
    rows = []
    pipe = pipe_cls(loc, lambda r, e: rows.append((r.t_s, e)), **kw)
    for rec in iter_log(io.StringIO(text)):
        if isinstance(rec, OdomRecord):
            pipe.odom(rec)
        elif rec.__class__.__name__ == "TofRecord":
            pipe.tof(rec)
        elif not isinstance(rec, TruthRecord):
            pipe.finish()
            loc.handle(rec)
    pipe.finish()
    return pipe, loc, rows


def test_one_segment_at_a_time_is_the_localizers_own_path(ring_log, fmap):
    """Prepared at the exact belief (chunks of one segment), the association, the
    readings kept and the reduced update are those of Localizer._associate_echoes and
    echoes.compress."""
    pipe, loc, _ = _run(ring_log, fmap, Checking, linearize_segments=1, chunk_segments=1)
    assert pipe.checked > 100
    assert pipe.disagree == []
    assert loc.stats.accepted > 0.9 * loc.stats.observations


def test_many_at_a_time_stays_close_to_one_at_a_time(ring_log, fmap):
    """Linearised and decided many segments at a time (the defaults: 128, 2 s) at the
    beliefs the odometry predicts: steady rows within 2 mm / 0.15 deg of one-at-a-time,
    nearly the same fusions."""
    truth = {r.t_s: r for r in iter_log(io.StringIO(ring_log)) if isinstance(r, TruthRecord)}
    _, loc1, one = _run(ring_log, fmap, linearize_segments=1, chunk_segments=1)
    _, loc32, many = _run(ring_log, fmap)
    assert [t for t, _ in one] == [t for t, _ in many]
    steady = [(a, b) for (t, a), (_, b) in zip(one, many, strict=True) if t > 5.0]
    d_pos = max(math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) for a, b in steady)
    d_yaw = max(abs(float(se2.wrap_angle(a.yaw_rad - b.yaw_rad))) for a, b in steady)
    assert d_pos < 0.002 and d_yaw < math.radians(0.15)
    assert abs(loc1.stats.accepted - loc32.stats.accepted) <= 0.03 * loc1.stats.accepted

    def rmse(rows):
        return math.sqrt(np.mean([(e.x_m - truth[t].x_m) ** 2 + (e.y_m - truth[t].y_m) ** 2
                                  for t, e in rows if t > 5.0]))
    assert rmse(many) < 0.003 and rmse(many) < rmse(one) + 0.0005


class Recording(OfflinePipeline):
    """The fast path, recording how each prepared segment was fused and how far the
    true belief was from the one it was decided at."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.hows = []

    def _fuse_prepared(self, p, redecide=False):
        loc = self.loc
        last = loc._entries[-1]
        x = ekf.predict(last.state, se2.between(last.odom, p.odom_ref),
                        loc.config.odom_noise).mean
        far = abs(x[0] - p.x0[0]) + abs(x[1] - p.x0[1]) > batchfuse.FAST_DXY_M or \
            abs(float(se2.wrap_angle(x[2] - p.x0[2]))) > batchfuse.FAST_DYAW_RAD
        how = super()._fuse_prepared(p, redecide)
        self.hows.append((p.t_ref, p.outcome, far, redecide, how))
        return how


def test_a_segment_decided_at_a_stale_belief_is_decided_anew(ring_log, fmap):
    """Where the updates decided before it in its chunk moved the belief too far from
    the one a segment was decided at (the first updates after the poor prior), the
    segment is not fused (nor counted) but decided again at the belief now, where it is
    near (first of its decision) and takes its reduced update; the per-segment path is
    left to the few whose update step is too large."""
    pipe, loc, _ = _run(ring_log, fmap, Recording)
    hows = pipe.hows
    stale = [i for i, h in enumerate(hows) if h[4] == "stale"]
    assert stale, "the drive's first updates (a 5 cm / 2 deg prior) leave a stale belief"
    for i in stale:
        t, outcome, far, redecide, _ = hows[i]
        assert far and redecide and outcome != "none"
        t2, _, far2, redecide2, how2 = hows[i + 1]   # the same segment, decided anew
        assert t2 == t and not far2 and not redecide2 and how2 != "stale"
    assert not any(far and how != "stale" and h_out != "none"
                   for _, h_out, far, redecide, how in hows if redecide)
    assert sum(h[4] == "segment" for h in hows) <= 4
    assert loc.stats.observations == sum(h[4] != "stale" for h in hows) == \
        loc.stats.segments


def test_replay_log_fast_switch(ring_log, fmap):
    fast = replay_log(io.StringIO(ring_log), fmap, mode="batch")
    slow = replay_log(io.StringIO(ring_log), fmap, mode="batch", fast=False)
    assert fast.localizer.stats.landmarks == 0 < fast.localizer.stats.segments
    assert slow.localizer.stats.landmarks == fast.localizer.stats.segments
    assert "segments" in fast.summary()
    with pytest.raises(ValueError, match="fast"):
        OfflinePipeline(Localizer(fmap, __import__("sonarloc.localize.localizer", fromlist=[
            "LocalizerConfig"]).LocalizerConfig(kuc_fusion="fit")), fast=True)
    with pytest.raises(ValueError, match="chunk_segments"):
        OfflinePipeline(Localizer(fmap), chunk_segments=0)
