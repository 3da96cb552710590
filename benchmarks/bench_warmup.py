"""The first call that fits and fuses, with and without `LocalizerNode.warm_up()`.

The fitter's tables (beam and delay tables) and the fusion's delay table are built
lazily, once per process, by the first calls that need them. Each run is a fresh
process (so no table is left over from another run): it feeds a 12 s room drive (ring
of 16, seed 0) record by record to a `LocalizerNode`, after `node.warm_up()` or not, and
measures the calling thread's CPU time (`time.thread_time`) of every call: the first
call that fits landmarks (and fuses them), the worst call of the run, and the warm-up's
own CPU time. Cold and warm runs alternate; medians over the repeats.

Run: ``python benchmarks/bench_warmup.py [--quick]``; writes
benchmarks/results/warmup.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, load_average, machine_line  # noqa: E402

_RUN = r"""
import json, sys, time
from sonarloc.api import LocalizerNode
from sonarloc.localize.features import FeatureMap
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import rig_by_name
from sonarloc.world.simulate import simulate_records

world = load_map(sys.argv[1])
recs = list(simulate_records(world, rig_by_name("ring16"), duration_s=12.0, seed=0))
node = LocalizerNode(FeatureMap.from_map(world))
c0 = time.thread_time()
if sys.argv[2] == "warm":
    node.warm_up()
warm_s = time.thread_time() - c0
first = worst = 0.0
for rec in recs:
    fitted = node.localizer.stats.landmarks
    c0 = time.thread_time()
    node.feed(rec)
    dt = time.thread_time() - c0
    worst = max(worst, dt)
    if not first and node.localizer.stats.landmarks > fitted:
        first = dt
print(json.dumps({"first_ms": first * 1e3, "worst_ms": worst * 1e3, "warm_up_s": warm_s,
                  "fused": node.localizer.stats.accepted}))
"""


def run_once(mode: str) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _RUN, str(ROOT / "maps" / "room.geojson"),
                          mode], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 repeats instead of 7")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(list(argv) if argv is not None else None)
    repeats = 2 if args.quick else 7
    load = load_average()
    runs: dict[str, list[dict[str, float]]] = {"cold": [], "warm": []}
    for _ in range(repeats):
        for mode in runs:           # alternating, so both see the same load
            r = run_once(mode)
            runs[mode].append(r)
            print(f"{mode}: first {r['first_ms']:.1f} ms, worst {r['worst_ms']:.1f} ms, "
                  f"warm-up {r['warm_up_s']:.3f} s", file=sys.stderr)

    def med(mode: str, key: str) -> float:
        return statistics.median(r[key] for r in runs[mode])

    rows = [f"| {label} | {med(mode, 'first_ms'):.1f} | {med(mode, 'worst_ms'):.1f} | "
            f"{med(mode, 'warm_up_s'):.3f} | {med(mode, 'fused'):.0f} |"
            for mode, label in (("cold", "no warm-up"), ("warm", "`node.warm_up()` first"))]
    text = "\n".join([
        "# The first call that fits and fuses, with and without `warm_up()`",
        "",
        "A fresh process per run feeds a 12 s room drive (ring of 16, seed 0) record by "
        "record to a `LocalizerNode`, after `node.warm_up()` or not. CPU of the calling "
        "thread (`time.thread_time`): *first fitting call*: the first call in which "
        "landmarks were fitted (and fused); *worst call*: the run's slowest call; "
        "*warm-up*: `node.warm_up()` itself, before the first record. The drive is "
        "simulated in the same process first (the simulator fills some of the physics "
        "caches the fitter shares: a robot's cold node pays more). Medians over "
        f"{repeats} runs each, cold and warm alternating.",
        "",
        "| node | first fitting call (ms) | worst call (ms) | warm-up (s) | fused |",
        "|---|---:|---:|---:|---:|",
        *rows,
        "",
        machine_line(f"{repeats} repeats", SHARED,
                     quick=args.quick, load=load),
        "",
    ])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "warmup.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
