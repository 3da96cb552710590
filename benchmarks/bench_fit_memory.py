"""Peak memory and CPU of `sonarloc fit` on a large scan CSV, by the lines it reads at a time.

`sonarloc fit` reads and fits a scan CSV a block of lines at a time (``--block-rows``,
default :data:`sonarloc.io.scancsv.BLOCK_ROWS`) and writes the landmarks as they come. The
baseline, measured in the same run, is one block holding the whole file: what the command
did before ``--block-rows`` (the whole file parsed, then segmented and fitted in one batch). The
scan is a continuous rotation over the eight reflectors of bench_fit.py section 4
(:func:`sonarloc.fit.synth.rotation_scan`). Each run is a fresh process reporting its own
peak resident set and CPU time; medians of the repeats, alternating the block sizes. The
JSON output of every block size is compared with the baseline's: byte for byte, and
landmark by landmark (kind, status, readings; the largest change of range and bearing:
the fits of a smaller batch converge a little differently).

Run: ``python benchmarks/bench_fit_memory.py [--quick] [--lines N]``; writes
benchmarks/results/fit_memory.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from benchmarks._machine import SHARED, machine_line  # noqa: E402
from sonarloc.fit.synth import rotation_scan  # noqa: E402
from sonarloc.io.scancsv import BLOCK_ROWS, write_scan_csv  # noqa: E402

# a child process: `sonarloc fit` as the command line runs it, then its own peak resident
# set (VmHWM, KiB: that of its own address space; ru_maxrss would carry the forking
# parent's) and CPU seconds on stderr's last line
_CHILD = """
import resource, sys
from sonarloc.cli import main
code = main(sys.argv[1:])
ru = resource.getrusage(resource.RUSAGE_SELF)
hwm = next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM"))
print(f"PEAK {hwm} CPU {ru.ru_utime + ru.ru_stime}", file=sys.stderr)
sys.exit(code)
"""


def run_fit(csv: Path, block_rows: int, out: Path) -> tuple[float, float]:
    """Peak RSS (MB) and CPU (s) of one `sonarloc fit CSV --json --block-rows N`."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with open(out, "w") as handle:
        proc = subprocess.run([sys.executable, "-c", _CHILD, "fit", str(csv), "--json",
                               "--block-rows", str(block_rows)], stdout=handle,
                              stderr=subprocess.PIPE, text=True, env=env, check=True)
    fields = proc.stderr.strip().splitlines()[-1].split()
    return int(fields[1]) / 1024.0, float(fields[3])


def measure(n_lines: int, blocks: Sequence[int], repeats: int, tmp: Path
            ) -> list[dict[str, float | str]]:
    csv = tmp / "rotation.csv"
    write_scan_csv(csv, rotation_scan(n_lines, np.random.default_rng(2014)))
    size_mb = csv.stat().st_size / 1e6
    whole = n_lines + 1
    sizes = [whole, *blocks]
    peak: dict[int, list[float]] = {b: [] for b in sizes}
    cpu: dict[int, list[float]] = {b: [] for b in sizes}
    for _ in range(repeats):        # alternating, so the host's load hits every size alike
        for b in sizes:
            p, c = run_fit(csv, b, tmp / f"out_{b}.json")
            peak[b].append(p)
            cpu[b].append(c)
    base = (tmp / f"out_{whole}.json").read_bytes()
    base_lms = json.loads(base)["landmarks"]
    rows: list[dict[str, float | str]] = []
    for b in sizes:
        rows.append({
            "block": "whole file (one block: the command before `--block-rows`)" if b == whole
            else f"{b:,}" + (" (default)" if b == BLOCK_ROWS else ""),
            "blocks": float(-(-n_lines // b)), "peak": statistics.median(peak[b]),
            "cpu": statistics.median(cpu[b]), "file_mb": size_mb, "n": float(len(base_lms)),
            "same": "yes" if (tmp / f"out_{b}.json").read_bytes() == base else "no",
            **_differences(base_lms, json.loads((tmp / f"out_{b}.json").read_text())[
                "landmarks"])})
    return rows


def _differences(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> dict[str, float]:
    """Landmarks of ``b`` against ``a``: how many differ in kind, status or readings (all
    of ``a`` if the counts differ), the largest range (mm) and bearing (deg) change."""
    if len(a) != len(b):
        return {"kind_diff": float(len(a)), "d_range_mm": np.inf, "d_bearing_deg": np.inf,
                "d_bearing_sd": np.inf}
    pairs = list(zip(a, b, strict=True))
    keys = ("kind", "status", "n_readings")

    def largest(key: str, wrap: bool = False, sd: str = "") -> float:
        d = [(float(x[key]) - float(y[key])) / (float(x[sd]) if sd else 1.0)
             for x, y in pairs if x[key] is not None and y[key] is not None
             and (not sd or x.get(sd) not in (None, 0.0))]
        return max((abs((v + 180.0) % 360.0 - 180.0) if wrap else abs(v) for v in d),
                   default=0.0)

    return {"kind_diff": float(sum(any(x[k] != y[k] for k in keys) for x, y in pairs)),
            "d_range_mm": 1e3 * largest("range_m"),
            "d_bearing_deg": largest("bearing_deg", wrap=True),
            "d_bearing_sd": largest("bearing_deg", sd="bearing_sd_deg")}


def table(rows: list[dict[str, float | str]], n_lines: int, repeats: int) -> list[str]:
    base = rows[0]
    lines = [f"## `sonarloc fit` on a {n_lines:,}-line scan CSV ({float(base['file_mb']):.0f} "
             f"MB, continuous rotation), by lines read at a time",
             "", f"Medians of {repeats} fresh processes per block size, alternating. Peak: "
             "the process's peak resident set (Python, numpy and scipy take ~60 MB of it "
             "before the file is opened). CPU: user + system of the whole command. JSON: "
             "the output against the whole file's: byte for byte, landmarks differing in kind, "
             "status or readings, the largest change of a range and a bearing.", "",
             "| lines per block | blocks | peak RSS (MB) | peak vs whole file | CPU (s) | "
             "CPU vs whole file | JSON identical | landmarks differing | largest range "
             "change (mm) | largest bearing change (deg) | largest bearing change (its SDs) |",
             "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['block']} | {int(float(r['blocks']))} | {float(r['peak']):.0f} | "
                     f"{float(r['peak']) / float(base['peak']):.2f}x | {float(r['cpu']):.2f} | "
                     f"{float(r['cpu']) / float(base['cpu']):.2f}x | {r['same']} | "
                     f"{int(float(r['kind_diff']))} of {int(float(base['n']))} | "
                     f"{float(r['d_range_mm']):.2g} | {float(r['d_bearing_deg']):.2g} | "
                     f"{float(r['d_bearing_sd']):.2g} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smaller file, one repeat")
    ap.add_argument("--lines", type=int, help="lines of the scan CSV (default 1,000,000; "
                                              "--quick 60,000)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "fit_memory.md"))
    args = ap.parse_args(argv)
    n = args.lines or (60_000 if args.quick else 1_000_000)
    repeats = 1 if args.quick else 3
    blocks = [b for b in (BLOCK_ROWS, BLOCK_ROWS // 4, BLOCK_ROWS // 16) if b < n] or [n // 4]
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(n, blocks, repeats, Path(tmp))
    lines = ["# `sonarloc fit`: memory against the lines read at a time", "",
             *table(rows, n, repeats), "",
             machine_line(f"{repeats} repeat(s)", SHARED, "CPU times are noisy, peaks less so",
                          quick=args.quick)]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    return 0 if all(float(r["kind_diff"]) == 0 for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
