"""Simulated echoes per second for each physics tier, and each tier's error.

Two workloads, each timed for the tiers gauss, piston, waveform and auto:

* ``paper scan``: the paper's experiment (Kuc 2003, Sec. III) -- plane, pole and rod
  at 1.5 m, -40..40 deg in 0.3 deg steps, 100 pings per angle; one echo per ping.
* ``clutter``: pings with 8 candidate echoes each, reflector strengths drawn from a
  room's mix (walls/corners 0.15 us, poles 0.67 us, rods/edges 2.68 us, thin rods up
  to 8 us) at off-axis angles uniform within each one's reach
  (:func:`~sonarloc.physics.tiers.max_detection_angle_rad`, as the world's spatial
  index prunes them); the module keeps the first echo.

A timed call is ``echo_delays_us`` + ``apply_module`` (random gain, model, jitter,
first echo, blanking, range gate, counting). Configurations run interleaved, the
median of the repeats is reported, and every rate is also given as a ratio to the
gauss tier of the same run. Error columns compare each tier's noise-free delay
with the waveform tier's (the most complete model) on the same echoes.

Run: ``python benchmarks/bench_physics.py [--quick]``; writes
benchmarks/results/physics.md and physics.png.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, machine_line  # noqa: E402
from sonarloc.physics.sound import tof_from_range_us  # noqa: E402
from sonarloc.physics.tiers import (  # noqa: E402
    auto_tables,
    echo_delays_us,
    max_detection_angle_rad,
)
from sonarloc.physics.tof import ModuleParams, apply_module  # noqa: E402
from sonarloc.physics.waveform import crossing_delay_us, waveform_template  # noqa: E402

TIERS = ("gauss", "piston", "waveform", "auto")
PAPER_KAPPA_US = (0.15, 0.67, 2.68)
CLUTTER_KAPPA_US = np.array([0.15, 0.15, 0.67, 2.68, 2.68, 5.0, 8.0])
CLUTTER_WEIGHTS = np.array([0.35, 0.10, 0.25, 0.15, 0.05, 0.05, 0.05])


def paper_workload(pings: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta, kappa) of shape (3 objects * angles, pings, 1): one echo per ping."""
    theta_deg = np.arange(-133, 134) * 0.3
    th = np.deg2rad(np.repeat(theta_deg, pings))
    theta = np.concatenate([th, th, th])
    kappa = np.repeat(np.array(PAPER_KAPPA_US), th.size)
    return theta[:, None], kappa[:, None]


def clutter_workload(n_pings: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(theta, kappa) of shape (n_pings, 8): candidate echoes within reach."""
    kappa = rng.choice(CLUTTER_KAPPA_US, size=(n_pings, 8), p=CLUTTER_WEIGHTS)
    reach = max_detection_angle_rad(kappa)
    theta = rng.uniform(-1.0, 1.0, kappa.shape) * reach
    return theta, kappa


def one_pass(theta: np.ndarray, kappa: np.ndarray, to_us: np.ndarray, tier: str,
             seed: int) -> float:
    """Pings per second of one pass (pings along axis 0, candidates along the last axis)."""
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    delay, _ = echo_delays_us(theta, kappa, tier, rng)
    apply_module(to_us + delay, rng, axis=-1)
    return theta.shape[0] / (time.perf_counter() - t0)


def time_tiers(workloads: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
               repeats: int) -> dict[tuple[str, str], float]:
    """Median pings/s per (workload, tier); interleaved so background load hits all alike."""
    rates: dict[tuple[str, str], list[float]] = {}
    for r in range(repeats):
        for name, (theta, kappa, to_us) in workloads.items():
            for tier in TIERS:
                rates.setdefault((name, tier), []).append(one_pass(theta, kappa, to_us, tier, r))
    return {k: float(np.median(v)) for k, v in rates.items()}


def tier_errors(theta: np.ndarray, kappa: np.ndarray) -> dict[str, tuple[float, float, float]]:
    """Per tier: (RMS, max) |delay - waveform delay| [us] over echoes both detect, and the
    fraction of echoes whose detection differs from the waveform tier. Noise-free gain."""
    params = ModuleParams(amplitude_fluctuation=0.0)
    ref, _ = echo_delays_us(theta, kappa, "waveform", np.random.default_rng(0), params)
    out = {}
    for tier in TIERS:
        d, _ = echo_delays_us(theta, kappa, tier, np.random.default_rng(0), params)
        both = ~np.isnan(d) & ~np.isnan(ref)
        diff = np.abs(d[both] - ref[both])
        mismatch = float(np.mean(np.isnan(d) != np.isnan(ref)))
        out[tier] = (float(np.sqrt(np.mean(diff ** 2))), float(diff.max()), mismatch)
    return out


def auto_shares(theta: np.ndarray, kappa: np.ndarray) -> tuple[float, float, float]:
    _, used = echo_delays_us(theta, kappa, "auto", np.random.default_rng(0))
    counts = np.bincount(used.ravel(), minlength=3)[:3]
    return tuple(float(c) for c in counts / counts.sum())  # type: ignore[return-value]


def write_plot(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tpl = waveform_template()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    t = tpl.t_us
    ax[0].plot(t, tpl.processed, lw=0.8, label="processed echo w(t)")
    ax[0].plot(t, tpl.running_max, lw=0.8, label="running max")
    ax[0].plot(t[t < 14], t[t < 14], "k--", lw=0.8, label="eq. 3 ramp")
    ax[0].set(xlim=(0, 420), xlabel="time after To [us]", ylabel="signal [us of eq. 3 ramp]",
              title="simulated 6500 module, unit echo")
    ax[0].legend(fontsize=8)
    u = np.linspace(0.0, 12.0, 20001)
    ax[1].plot(u, crossing_delay_us(u), label="waveform tier")
    ax[1].plot(u, u, "k--", label="eq. 3")
    ax[1].axvline(auto_tables().waveform_from_us, color="grey", lw=0.8, ls=":",
                  label="auto: waveform beyond")
    ax[1].set(ylim=(0, 130), xlabel="eq. 3 threshold delay kappa/a [us]",
              ylabel="threshold delay [us]", title="delay against echo weakness")
    ax[1].legend(fontsize=8)
    params = ModuleParams(amplitude_fluctuation=0.0)
    th = np.deg2rad(np.linspace(-25, 25, 2001))
    for kap, name, colour in zip(PAPER_KAPPA_US, ("plane", "pole", "rod"), ("C0", "C1", "C2"),
                                 strict=True):
        for tier, style in (("piston", "--"), ("auto", "-")):
            d, _ = echo_delays_us(th, kap, tier, np.random.default_rng(0), params)
            ax[2].plot(np.rad2deg(th), d, style, color=colour, lw=0.9,
                       label=f"{name} {tier}" if tier == "auto" else None)
    ax[2].set(ylim=(0, 80), xlabel="bearing [deg]", ylabel="Tm - To [us]",
              title="noise-free scans at 1.5 m (dashed: piston eq. 3)")
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, 3 repeats")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "physics.md")
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 15)
    pings = 10 if args.quick else 100
    n_clutter = 20_000 if args.quick else 200_000
    rng = np.random.default_rng(2003)
    to_us = np.float64(tof_from_range_us(1.5))
    p_theta, p_kappa = paper_workload(pings)
    c_theta, c_kappa = clutter_workload(n_clutter, rng)
    c_to = tof_from_range_us(rng.uniform(0.3, 5.0, c_kappa.shape))
    workloads = {"paper scan": (p_theta, p_kappa, np.full(p_kappa.shape, to_us)),
                 "clutter": (c_theta, c_kappa, c_to)}
    echo_delays_us(p_theta[:10], p_kappa[:10], "auto", rng)  # build tables outside timing
    rates = time_tiers(workloads, repeats)
    errors = {name: tier_errors(th, ka) for name, (th, ka, _) in workloads.items()}
    shares = {name: auto_shares(th, ka) for name, (th, ka, _) in workloads.items()}

    lines = [
        "# Physics tiers: simulated pings per second and error",
        "",
        "Timed call: `echo_delays_us` + `apply_module` (gain, model, jitter, first echo, "
        "counting). Rates are medians of the repeats; *x gauss* is the ratio to the gauss "
        "tier in the same run. Errors: noise-free delay against the waveform tier (the "
        "most complete model) over echoes both detect; *det. differs*: share of echoes "
        "whose detection differs from the waveform tier.",
        "",
        "| workload | tier | echoes/ping | pings/s | x gauss | RMS err [us] | max err [us] "
        "| det. differs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, (theta, _, _) in workloads.items():
        g = rates[(name, "gauss")]
        for tier in TIERS:
            rms, mx, mis = errors[name][tier]
            lines.append(f"| {name} | {tier} | {theta.shape[-1]} | {rates[(name, tier)]:,.0f} "
                         f"| {rates[(name, tier)] / g:.2f} | {rms:.2f} | {mx:.2f} "
                         f"| {100 * mis:.2f} % |")
    lines += ["", "Share of echoes by model in the auto tier:", "",
              "| workload | gauss | piston | waveform |", "|---|---|---|---|"]
    for name, (sg, sp, sw) in shares.items():
        lines.append(f"| {name} | {100 * sg:.1f} % | {100 * sp:.1f} % | {100 * sw:.1f} % |")
    n_p = p_theta.shape[0]
    lines += [
        "",
        machine_line(f"repeats {repeats}", f"paper scan {n_p:,} pings, clutter "
                     f"{n_clutter:,} pings", SHARED,
                     quick=args.quick),
        "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    write_plot(args.out.with_suffix(".png"))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
