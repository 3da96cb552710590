"""Simulated pings per second against map size, with and without the spatial index.

Maps of 10 .. 10,000 reflectors scattered at a constant density (the map area grows
with the count, so what is near a transducer stays the same): 70 % cylinders (poles,
rods, points), 30 % short wall segments. Each timed call fires one ``ring16`` group
(4 transducers) from a random robot pose inside the map. The brute-force baseline
(``Scene(use_index=False)``) tests every reflector; both give the same readings.

Run: ``python benchmarks/bench_world.py [--quick]``; writes benchmarks/results/world.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, load_average, machine_line  # noqa: E402
from sonarloc.maps import Map, load_map, map_from_geojson  # noqa: E402
from sonarloc.physics.tiers import Tier  # noqa: E402
from sonarloc.world.rig import ring16  # noqa: E402
from sonarloc.world.scene import Scene  # noqa: E402
from sonarloc.world.simulate import module_for_rig, simulate_records  # noqa: E402

DENSITY_PER_M2 = 0.5


def random_map(n: int, rng: np.random.Generator) -> tuple[Map, float]:
    """A map of exactly ``n`` reflectors at constant density; returns it and its side [m]."""
    side = math.sqrt(n / DENSITY_PER_M2)
    feats = []
    n_walls = int(round(0.3 * n))
    for _ in range(n - n_walls):
        kind = str(rng.choice(["pole", "rod", "point"]))
        radius = {"pole": 0.0445, "rod": 0.004, "point": 0.0}[kind]
        feats.append({"type": "Feature", "properties": {"kind": kind, "radius_m": radius},
                      "geometry": {"type": "Point",
                                   "coordinates": rng.uniform(0, side, 2).tolist()}})
    for _ in range(n_walls):
        a = rng.uniform(0, side, 2)
        b = a + rng.uniform(0.5, 2.0) * np.array([math.cos(t := rng.uniform(0, math.pi)),
                                                  math.sin(t)])
        feats.append({"type": "Feature", "properties": {"kind": "wall", "vertices": "none"},
                      "geometry": {"type": "LineString",
                                   "coordinates": [a.tolist(), b.tolist()]}})
    m = map_from_geojson({"type": "FeatureCollection", "features": feats})
    assert len(m.reflectors) == n
    return m, side


def one_run(scene: Scene, poses: np.ndarray, tier: Tier, seed: int) -> tuple[float, float]:
    """Pings/s of one pass over ``poses``, and the mean candidates per ping."""
    rng = np.random.default_rng(seed)
    n_pings = total_c = 0
    t0 = time.perf_counter()
    for p in poses:
        res = scene.ping(p[:, 0], p[:, 1], p[:, 2], rng, tier)
        n_pings += p.shape[0]
        total_c += int(res.n_candidates.sum())
    return n_pings / (time.perf_counter() - t0), total_c / n_pings


def time_configs(configs: dict[str, tuple[Scene, np.ndarray, Tier]], repeats: int
                 ) -> dict[str, tuple[float, float]]:
    """Median pings/s per configuration; runs interleaved so background load hits all alike."""
    rates: dict[str, list[float]] = {k: [] for k in configs}
    cands: dict[str, float] = {}
    for r in range(repeats):
        for key, (scene, poses, tier) in configs.items():
            rate, cands[key] = one_run(scene, poses, tier, r)
            rates[key].append(rate)
    return {k: (float(np.median(v)), cands[k]) for k, v in rates.items()}


def group_poses(side: float, n_calls: int, rng: np.random.Generator) -> np.ndarray:
    """(n_calls, 4, 3) transducer poses of one ring16 firing group at random robot poses."""
    rig = ring16()
    group = [m for m in rig.sensors if m.id in rig.groups[0]]
    out = np.empty((n_calls, len(group), 3))
    margin = min(2.0, side / 4)
    for c in range(n_calls):
        x, y = rng.uniform(margin, side - margin, 2)
        yaw = rng.uniform(-math.pi, math.pi)
        for j, m in enumerate(group):
            a = yaw + math.radians(m.yaw_deg)
            out[c, j] = (x + math.cos(yaw) * m.x_m - math.sin(yaw) * m.y_m,
                         y + math.sin(yaw) * m.x_m + math.cos(yaw) * m.y_m, a)
    return out


def time_records(seconds: float, repeats: int) -> tuple[float, float]:
    """Records/s and pings/s of a full ``simulate_records`` drive (ring16, room map)."""
    room = load_map(ROOT / "maps" / "room.geojson")
    rates, prates = [], []
    for r in range(repeats):
        pings = [0]

        def count(_: object, pings: list[int] = pings) -> None:
            pings[0] += 1

        t0 = time.perf_counter()
        n = sum(1 for _ in simulate_records(room, ring16(), duration_s=seconds, seed=r,
                                            on_ping=count))
        dt = time.perf_counter() - t0
        rates.append(n / dt)
        prates.append(pings[0] / dt)
    return float(np.median(rates)), float(np.median(prates))


Row = tuple[int, float, float, float, float, float, float, float]


def plot(rows: list[Row], path: Path) -> None:
    """Log-log plot of pings/s against reflectors, indexed and brute force."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r[0] for r in rows]
    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=120)
    ax.loglog(n, [r[3] for r in rows], "o-", label="STRtree index (auto tier)")
    ax.loglog(n, [r[7] for r in rows], "s--", label="brute force (auto tier)")
    ax.set_xlabel("reflectors in the map (constant density)")
    ax.set_ylabel("simulated pings per second")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pings and repeats (smoke run)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "world.md"))
    args = ap.parse_args(argv)
    sizes = [10, 100, 1000, 10000]
    n_calls, repeats = (40, 2) if args.quick else (300, 7)
    rng = np.random.default_rng(2003)
    params = module_for_rig(ring16())
    rows: list[Row] = []
    configs: dict[str, tuple[Scene, np.ndarray, Tier]] = {}
    sides: dict[int, float] = {}
    for n in sizes:
        m, sides[n] = random_map(n, rng)
        poses = group_poses(sides[n], n_calls, rng)
        fast, slow = Scene(m, params), Scene(m, params, use_index=False)
        m.tree  # build the index outside the timing  # noqa: B018
        brute_calls = poses if n <= 1000 else poses[: max(10, n_calls // 5)]
        tiers = {"auto": Tier.AUTO, "gauss": Tier.GAUSS, "piston": Tier.PISTON,
                 "waveform": Tier.WAVEFORM}
        for name, tier in tiers.items():
            configs[f"{n}/{name}"] = (fast, poses, tier)
        configs[f"{n}/brute"] = (slow, brute_calls, Tier.AUTO)
        try:
            one_run(fast, poses[:2], Tier.WAVEFORM, 0)  # also warms the tier tables
        except NotImplementedError:
            del configs[f"{n}/waveform"]
    # every size and configuration in each round, so changing load hits all alike
    got = time_configs(configs, repeats)
    for n in sizes:
        (idx_rate, cands), (gauss_rate, _) = got[f"{n}/auto"], got[f"{n}/gauss"]
        piston_rate, brute_rate = got[f"{n}/piston"][0], got[f"{n}/brute"][0]
        wave = got.get(f"{n}/waveform")
        wave_rate = wave[0] if wave is not None else float("nan")
        rows.append((n, sides[n], cands, idx_rate, gauss_rate, piston_rate, wave_rate,
                     brute_rate))
        print(f"{n:>6} reflectors ({sides[n]:.0f} m square): indexed {idx_rate:8.0f} pings/s, "
              f"brute force {brute_rate:8.0f} pings/s, {cands:.1f} candidates/ping",
              file=sys.stderr)
    rec_rate, ping_rate = time_records(5.0 if args.quick else 30.0, repeats)

    base = rows[0][3]
    lines = [
        "# World simulator: pings per second against map size",
        "",
        "Each ping is one transducer of a ring16 firing group (4 transducers per call, "
        "30 ms slot = 5.1 m range gate) at a random pose inside a map of randomly "
        f"scattered reflectors at constant density ({DENSITY_PER_M2} per m², 70 % "
        "cylinders, 30 % wall segments). Median of "
        f"{repeats} rounds of {n_calls} calls (every size and column in each round). "
        "*indexed* = STRtree candidates "
        "(`Scene`), *brute force* = every reflector tested (`Scene(use_index=False)`), "
        "same readings. Tier columns use the index.",
        "",
        "| reflectors | map side (m) | candidates/ping | indexed, auto (pings/s) | "
        "indexed vs 10 | gauss | piston | waveform | brute force, auto (pings/s) | "
        "index speed-up |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n, side, cands, idx, ga, pi, wf, brute in rows:
        wf_text = "n/a" if math.isnan(wf) else f"{wf:.0f}"
        lines.append(f"| {n} | {side:.0f} | {cands:.1f} | {idx:.0f} | {idx / base:.2f} | "
                     f"{ga:.0f} | {pi:.0f} | {wf_text} | {brute:.0f} | {idx / brute:.1f}x |")
    lines += [
        "",
        f"Full `simulate_records` drive (room map, ring16, odometry + truth at 20 Hz, 30 s "
        f"simulated): {rec_rate:.0f} records/s, {ping_rate:.0f} pings/s "
        f"({ping_rate * 0.03 / 4:.0f}x real time for ring16's 133 pings/s).",
        "",
        machine_line(f"{repeats} rounds", SHARED, "absolute rates scale with load; the "
                     "ratios are measured interleaved", quick=args.quick, load=load_average(),
                     load_when="at the end"),
    ]
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    plot(rows, out.with_suffix(".png"))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
