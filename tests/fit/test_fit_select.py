"""Model selection (sonarloc.fit.select): the screened re-bracketing of other tiers."""

from __future__ import annotations

import numpy as np
import pytest

from sonarloc.fit import select as S
from sonarloc.fit.landmarks import fit_segments
from sonarloc.fit.segment import Segmenter
from sonarloc.fit.synth import rotation_scan


@pytest.fixture(scope="module")
def rotation_segments():
    """Segments of a continuous rotation (1 deg per ping) over the scene of
    benchmarks/bench_fit.py section 4: far rods and poles partly hidden by nearer
    reflectors, whose Gaussian fits sit in another basin of the waveform tier."""
    return list(Segmenter().feed(rotation_scan(14400, np.random.default_rng(2003))))


def test_rebracketing_only_far_worse_refinements_keeps_the_choices(rotation_segments,
                                                                  monkeypatch):
    # REBRACKET_DCOST (100) skips the fresh brackets of refinements that stayed a few
    # tens above their bar: on this scan the tiers, kinds, statuses and fits are those
    # of bracketing everything that stayed 10 above it (the rule before 2026-11-21), at
    # a fraction of the brackets
    rows: list[int] = []
    fit_batch = S.fit_batch

    def counting(batch, kind, tier, cfg, *args, **kwargs):
        if tier != "gauss" and kwargs.get("start") is None:
            rows.append(batch.size if kwargs.get("rows") is None else len(kwargs["rows"]))
        return fit_batch(batch, kind, tier, cfg, *args, **kwargs)

    monkeypatch.setattr(S, "fit_batch", counting)
    now = fit_segments(rotation_segments)
    n_now = sum(rows)
    rows.clear()
    monkeypatch.setattr(S, "REBRACKET_DCOST", 10.0)
    before = fit_segments(rotation_segments)
    assert 0 < n_now < 0.5 * sum(rows)
    for a, b in zip(now, before, strict=True):
        assert (a.kind, a.tier, a.status) == (b.kind, b.tier, b.status)
        np.testing.assert_allclose(a.params, b.params, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-15)
    # the re-bracketing itself still changes tiers here (Gaussian fits in a wrong basin)
    monkeypatch.setattr(S, "_rebracket", lambda batch, idx, alt, bar, cfg: alt)
    plain = fit_segments(rotation_segments)
    changed = [a.extra["tier_basis"] for a, p in zip(now, plain, strict=True)
               if a.tier != p.tier]
    assert changed and all("fits the data better" in str(c) for c in changed)


def test_tier_predictions_share_the_beam_of_piston_and_waveform(rotation_segments):
    # the tiers with the same beam (piston, waveform) share its pattern and detection
    # probabilities: every tier's predictions are those it gets computed on its own
    from sonarloc.fit.landmarks import _arrays
    from sonarloc.fit.lsq import FitConfig, fit_batch, pack_segments

    cfg = FitConfig()
    batch = pack_segments([_arrays(s)[:5] for s in rotation_segments[:60]])
    sel = S.Selection.from_fit(fit_batch(batch, "point", "gauss", cfg))
    idx = np.arange(0, batch.size, 2)
    both = S._tier_predictions(batch, sel, idx, "point", ("gauss", "waveform", "piston"), cfg)
    for tier in ("gauss", "waveform", "piston"):
        (d, p), = S._tier_predictions(batch, sel, idx, "point", (tier,), cfg).values()
        np.testing.assert_array_equal(both[tier][0], d)
        np.testing.assert_array_equal(both[tier][1], p)
    # and the tiers do predict differently (the test would see a shared delay)
    assert not np.array_equal(both["waveform"][0], both["piston"][0])
    assert not np.array_equal(both["gauss"][1], both["piston"][1])


def test_tier_extras_name_the_fitted_alternatives_in_order(rotation_segments):
    # dcost_<tier> where that tier was fitted (a finite gain), nowhere else; each
    # segment's keys in the order tier_basis, dcost_waveform, dcost_piston
    lms = fit_segments(rotation_segments[:600])
    order = ["tier_basis", "dcost_waveform", "dcost_piston"]
    seen = set()
    for lm in lms:
        keys = [k for k in lm.extra if k in order]
        if not keys:        # too few echoes for a fit: no model selection
            continue
        assert keys == [k for k in order if k in keys]
        for k in keys[1:]:
            assert isinstance(lm.extra[k], float) and np.isfinite(lm.extra[k])
            seen.add(k)
        # "gauss: ..." (the tiers agree, or the residuals do not lean): none fitted
        assert (len(keys) > 1) != str(lm.extra["tier_basis"]).startswith("gauss:")
    assert seen == {"dcost_waveform", "dcost_piston"}
