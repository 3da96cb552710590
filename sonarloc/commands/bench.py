"""Run the speed-against-error benchmarks and gather their tables.

Runs every benchmarks/bench_<topic>.py of the source tree (or those named by --only),
each writing benchmarks/results/<topic>.md, then gathers all results into
benchmarks/results/README.md and prints it. The benchmarks are not part of the installed
package: run this inside a checkout of the repository (or pass --dir).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true",
                        help="pass --quick to each benchmark (fewer repeats): a smoke test "
                             "whose tables are printed, after which the results/ files of "
                             "the last full run are put back")
    parser.add_argument("--only", action="append", metavar="NAME", default=[],
                        help="run only this benchmark (topic name, e.g. `fit` for "
                             "bench_fit.py); repeatable")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.add_argument("--no-run", action="store_true",
                        help="do not run anything: gather the existing results only")
    parser.add_argument("--dir", type=Path, help="the benchmarks/ folder (default: found "
                                                 "next to the package or above the cwd)")
    parser.add_argument("--verbose", action="store_true", help="show the benchmarks' output")


def run(args: argparse.Namespace) -> int:
    from sonarloc.report.benchmarks import (
        README_NAME,
        collect_results,
        find_benchmarks_dir,
        list_benchmarks,
        run_benchmark,
    )

    bench_dir = find_benchmarks_dir(args.dir)
    available = list_benchmarks(bench_dir)
    if args.list:
        for name, path in available.items():
            print(f"{name}\t{path}")
        return 0
    wanted = [n.removeprefix("bench_").removesuffix(".py") for n in args.only]
    unknown = [n for n in wanted if n not in available]
    if unknown:
        raise ValueError(f"`--only` names no benchmark: {', '.join(unknown)} (have: "
                         f"{', '.join(available)})")
    chosen = {n: available[n] for n in (wanted or available)}
    failed = []
    results = bench_dir / "results"
    saved = ({p: p.read_bytes() for p in results.iterdir() if p.is_file()}
             if args.quick and results.is_dir() and not args.no_run else {})
    quick_tables: list[str] = []
    if not args.no_run:
        tty = sys.stderr.isatty()
        for i, (name, script) in enumerate(chosen.items(), start=1):
            print(f"[{i}/{len(chosen)}] {name} ({script.name}"
                  f"{' --quick' if args.quick else ''}) ...", file=sys.stderr, end="" if tty
                  else "\n", flush=True)
            result = run_benchmark(script, args.quick, echo=args.verbose)
            verdict = "ok" if result.status == 0 else "FAILED"
            print(f"{' ' if tty else '    '}{verdict} in {result.seconds:.1f} s",
                  file=sys.stderr)
            if result.status != 0:
                failed.append(name)
                print(f"    {result.error.strip()}", file=sys.stderr)
            table = results / f"{name}.md"
            if args.quick and table.exists():
                quick_tables.append(table.read_text(encoding="utf-8"))
    if args.quick and not args.no_run:
        for path, data in saved.items():  # the committed full-run results come back
            path.write_bytes(data)
        print("\n".join(quick_tables))
        print(f"quick run: tables above; {results} keeps the last full run's results",
              file=sys.stderr)
        if failed:
            print(f"sonarloc bench: {len(failed)} benchmark(s) failed: {', '.join(failed)}",
                  file=sys.stderr)
        return 1 if failed else 0
    results.mkdir(exist_ok=True)
    text = collect_results(bench_dir)
    (results / README_NAME).write_text(text, encoding="utf-8")
    print(text)
    print(f"gathered into {results / README_NAME}", file=sys.stderr)
    if failed:
        print(f"sonarloc bench: {len(failed)} benchmark(s) failed: {', '.join(failed)}",
              file=sys.stderr)
        return 1
    return 0
