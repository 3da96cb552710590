"""Batch replay speed of ``sonarloc localize``: this checkout against a baseline commit.

The drives of ``bench_localize.py`` (room with the ring of 16 transducers, room with
the panning transducer, pole field with the ring; seeds 100..) are simulated once,
then replayed (method ``kuc``, batch: :func:`sonarloc.localize.replay.replay_log`) by
both code versions in the same run: each repeat starts one fresh process per version,
the baseline first on even repeats and this checkout first on odd ones, and times
every replay in CPU time (the process's own: other jobs on a shared machine do not
count). The first replay of a process is the *cold* one (the physics tables and the
delay table of the forward model are built then, as in a single ``sonarloc localize``
run); the others are *warm*. Reported: median log time / CPU time per scenario, the
cold speed, the steady position / yaw RMSE of both versions (after the 5 s warm-up)
and the largest difference between their pose rows.

Run: ``python benchmarks/bench_replay.py [--baseline REF] [--repeats N] [--seeds N]
[--quick]``; the baseline is extracted with ``git archive`` into a temporary folder.
Writes benchmarks/results/replay.md.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, machine_line  # noqa: E402

#: main on 2026-11-21, before the replay speed work.
DEFAULT_BASELINE = "f7b51e7"
SCENARIOS = ("room, ring16", "room, panning transducer", "pole field, ring16")
WARMUP_S = 5.0


def _worker(repo: str, logdir: str, repeats: int, out: str) -> int:
    """Replay every log of ``logdir`` with the code of ``repo``; timings and rows."""
    sys.path.insert(0, repo)
    sys.path.insert(0, str(Path(repo) / "benchmarks"))
    import bench_localize as bl  # the version's own scenarios (same maps)

    from sonarloc.localize import ekf
    from sonarloc.localize.features import FeatureMap
    from sonarloc.localize.localizer import LocalizerConfig
    from sonarloc.localize.replay import replay_log

    ekf.chi2_gate(2)  # scipy.stats imported outside the timings (as bench_localize)
    maps = {sc.name: FeatureMap.from_map(sc.world) for sc in bl.scenarios()}
    index = json.loads((Path(logdir) / "index.json").read_text())
    result: dict = {"cold": None, "runs": {}, "rows": {}}

    def replay(name: str, path: str, keep: list | None = None) -> tuple[float, float]:
        text = Path(path).read_text()
        c0 = time.process_time()
        res = replay_log(io.StringIO(text), maps[name], config=LocalizerConfig(method="kuc"),
                         on_estimate=None if keep is None else
                         (lambda rec, est: keep.append([rec.t_s, *est.state.mean.tolist()])))
        return time.process_time() - c0, res.log_duration_s

    first = index[0]
    result["cold"] = replay(first["scenario"], first["path"])
    for entry in index:
        rows: list = []
        runs = [replay(entry["scenario"], entry["path"], rows)]
        runs += [replay(entry["scenario"], entry["path"]) for _ in range(repeats)]
        result["runs"].setdefault(entry["scenario"], []).extend(runs[1:] if repeats else runs)
        result["rows"][entry["path"]] = rows
    Path(out).write_text(json.dumps(result))
    return 0


def _steady(rows: np.ndarray, truth: dict[float, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Position and yaw errors of the rows after the warm-up."""
    tru = np.array([truth[t] for t in rows[:, 0]])
    err = rows[:, 1:] - tru
    err[:, 2] = (err[:, 2] + math.pi) % (2 * math.pi) - math.pi
    steady = rows[:, 0] > WARMUP_S
    return np.hypot(err[steady, 0], err[steady, 1]), err[steady, 2]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--baseline", default=DEFAULT_BASELINE,
                    help=f"git commit to compare with (default {DEFAULT_BASELINE})")
    ap.add_argument("--repeats", type=int, default=None,
                    help="processes per version (default 3, quick 1)")
    ap.add_argument("--seeds", type=int, default=None, help="drives per scenario (default 5)")
    ap.add_argument("--quick", action="store_true", help="one 20 s drive per scenario")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "replay.md"))
    ap.add_argument("--worker", nargs=4, metavar=("REPO", "LOGDIR", "REPEATS", "OUT"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        repo, logdir, reps, out = args.worker
        return _worker(repo, logdir, int(reps), out)
    quick = args.quick
    n_seeds = args.seeds or (1 if quick else 5)
    repeats = args.repeats or (1 if quick else 3)
    duration = 20.0 if quick else None

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_localize as bl

    try:
        sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.baseline],
                             capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as err:
        print(f"bench_replay needs a git checkout with commit {args.baseline!r}: {err}",
              file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="sonarloc-bench-replay-") as tmp:
        base_dir = Path(tmp) / "baseline"
        base_dir.mkdir()
        here = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain",
                                "--untracked-files=no", "--", "sonarloc", "benchmarks/*.py"],
                               capture_output=True, text=True, check=True).stdout.strip()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", sha],
                                 capture_output=True, check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(base_dir, filter="data")
        # the drives, simulated once by this checkout
        index, truths = [], {}
        for sc in bl.scenarios():
            for seed in range(n_seeds):
                text = bl.simulate_text(sc, 100 + seed, duration)
                path = Path(tmp) / f"{len(index)}.jsonl"
                path.write_text(text)
                index.append({"scenario": sc.name, "path": str(path)})
                truths[str(path)] = bl.truth_of(text)
        (Path(tmp) / "index.json").write_text(json.dumps(index))
        versions = {"baseline": str(base_dir), "this": str(ROOT)}
        outs: dict[str, list[dict]] = {k: [] for k in versions}
        for r in range(repeats):
            for k in (list(versions) if r % 2 == 0 else list(versions)[::-1]):
                out = Path(tmp) / f"{k}-{r}.json"
                subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker",
                                versions[k], tmp, "1", str(out)], check=True)
                outs[k].append(json.loads(out.read_text()))
                print(f"repeat {r + 1}/{repeats}: {k} done", file=sys.stderr)

    def speeds(k: str, name: str) -> list[float]:
        return [d / c for o in outs[k] for c, d in o["runs"][name]]

    def slowest(k: str, name: str) -> float:
        """The slowest drive: each drive's median over the processes, the least."""
        per = zip(*([d / c for c, d in o["runs"][name]] for o in outs[k]), strict=True)
        return min(statistics.median(v) for v in per)

    lines = ["# Batch replay speed: this checkout against the baseline", "",
             f"`sonarloc localize`'s batch replay (method kuc) of {n_seeds} simulated "
             f"drive(s) per scenario ({'20 s' if quick else 'one lap of the route'}, seeds "
             f"100..), by the baseline {sha} and this checkout {here}"
             f"{' (with uncommitted changes to the code)' if dirty else ''} in the same run: "
             f"{repeats} fresh process(es) per version, alternating (baseline first on "
             "even repeats); every replay timed in CPU time (the process's own). *Warm*: "
             "replays after the first in a process (delay table built), median over "
             "drives and repeats; *cold*: the first replay of a process (the room/ring16 "
             "drive, seed 100: physics tables and the delay table built during it), median "
             "over processes; *slowest drive*: the least of the drives' warm speeds (each "
             "the median over the processes). Steady RMSE over all drives after a "
             f"{WARMUP_S:g} s warm-up; pose difference: largest over all pose rows (the "
             "warm-up included).", "",
             "| scenario | baseline warm | this warm | ratio | slowest drive (baseline / "
             "this) | baseline steady RMSE (mm / deg) | this steady RMSE (mm / deg) | "
             "largest pose difference (mm / deg) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in SCENARIOS:
        sb, st = statistics.median(speeds("baseline", name)), statistics.median(
            speeds("this", name))
        errs = {}
        dpos = dyaw = 0.0
        for k in versions:
            pos, yaw = [], []
            for path, rows in outs[k][0]["rows"].items():
                if not any(e["path"] == path and e["scenario"] == name for e in index):
                    continue
                p, y = _steady(np.array(rows), truths[path])
                pos.append(p)
                yaw.append(y)
            pc, yc = np.concatenate(pos), np.concatenate(yaw)
            errs[k] = (1000 * math.sqrt(float(np.mean(pc**2))),
                       math.degrees(math.sqrt(float(np.mean(yc**2)))))
        for path, rows in outs["this"][0]["rows"].items():
            if not any(e["path"] == path and e["scenario"] == name for e in index):
                continue
            a, b = np.array(outs["baseline"][0]["rows"][path]), np.array(rows)
            if a.shape != b.shape:
                dpos = dyaw = math.inf
                continue
            d = b[:, 1:] - a[:, 1:]
            dpos = max(dpos, 1000 * float(np.max(np.hypot(d[:, 0], d[:, 1]), initial=0.0)))
            dyaw = max(dyaw, math.degrees(float(np.max(
                np.abs((d[:, 2] + math.pi) % (2 * math.pi) - math.pi), initial=0.0))))
        lines.append(f"| {name} | {sb:.0f}x | {st:.0f}x | {st / sb:.2f} | "
                     f"{slowest('baseline', name):.0f}x / {slowest('this', name):.0f}x | "
                     f"{errs['baseline'][0]:.3f} / {errs['baseline'][1]:.3f} | "
                     f"{errs['this'][0]:.3f} / {errs['this'][1]:.3f} | "
                     f"{dpos:.1f} / {dyaw:.2f} |")
    cold = {k: statistics.median(o["cold"][1] / o["cold"][0] for o in outs[k]) for k in versions}
    cold_cpu = {k: statistics.median(o["cold"][0] for o in outs[k]) for k in versions}
    lines += ["", f"Cold (first replay in a process, room/ring16 seed 100): baseline "
              f"{cold['baseline']:.0f}x ({cold_cpu['baseline']:.2f} s CPU), this "
              f"{cold['this']:.0f}x ({cold_cpu['this']:.2f} s CPU).", "",
              machine_line(f"{n_seeds} seed(s)", f"{repeats} repeat(s)", SHARED, "absolute "
                           "speeds vary from run to run; the ratios come from the same run",
                           quick=quick)]
    text = "\n".join(lines) + "\n"
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
