"""Run the repository's benchmarks and gather their tables (``sonarloc bench``).

Each ``benchmarks/bench_<topic>.py`` exposes ``main(argv) -> int`` and writes
``benchmarks/results/<topic>.md`` (a markdown table and a line with machine, date and
parameters), sometimes ``<topic>.png``. The benchmarks live in the source tree, not in the
installed package: :func:`find_benchmarks_dir` looks next to the package and upwards from
the working directory.
"""

from __future__ import annotations

import importlib.util
import io
import sys
import time
import traceback
from collections.abc import Sequence
from contextlib import redirect_stdout
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sonarloc.errors import SonarlocError

README_NAME = "README.md"


class BenchmarksNotFound(SonarlocError):
    """No ``benchmarks/`` folder: sonarloc was installed without its source tree."""


def find_benchmarks_dir(start: Path | None = None) -> Path:
    """The ``benchmarks/`` folder of the source tree sonarloc runs from.

    Tried in order: ``start`` (itself or its ``benchmarks/``), the folder above the
    imported package (an editable install or a checkout on ``PYTHONPATH``), then the
    working directory and its parents.
    """
    candidates: list[Path] = []
    if start is not None:
        candidates += [start, start / "benchmarks"]
    else:
        import sonarloc

        candidates.append(Path(sonarloc.__file__).resolve().parent.parent / "benchmarks")
        cwd = Path.cwd().resolve()
        candidates += [d / "benchmarks" for d in (cwd, *cwd.parents)]
    for c in candidates:
        if c.is_dir() and any(c.glob("bench_*.py")):
            return c
    where = str(start) if start is not None else "next to the sonarloc package or above " \
        f"{Path.cwd()}"
    raise BenchmarksNotFound(
        f"no benchmarks/ folder with bench_*.py found {where}: the benchmarks ship with the "
        "source tree (git clone the repository and run `sonarloc bench` inside it, or pass "
        "--dir PATH)")


def list_benchmarks(bench_dir: Path) -> dict[str, Path]:
    """Topic name -> script, e.g. ``{"fit": .../bench_fit.py}``, sorted by name."""
    return {p.stem.removeprefix("bench_"): p for p in sorted(bench_dir.glob("bench_*.py"))}


@dataclass
class BenchRun:
    topic: str
    status: int
    seconds: float
    error: str = ""
    output: str = ""


def run_benchmark(script: Path, quick: bool, echo: bool = False) -> BenchRun:
    """Import ``script`` and call its ``main(argv)``; exceptions become a failed run."""
    topic = script.stem.removeprefix("bench_")
    t0 = time.perf_counter()
    buffer = io.StringIO()
    sys_path = list(sys.path)
    try:
        sys.path.insert(0, str(script.parent))  # benchmarks may share helper modules
        spec = importlib.util.spec_from_file_location(f"_sonarloc_bench_{topic}", script)
        if spec is None or spec.loader is None:
            raise ImportError(f"cannot load {script}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        main = getattr(module, "main", None)
        if not callable(main):
            return BenchRun(topic, 2, time.perf_counter() - t0,
                            f"{script.name} has no main(argv) function")
        argv = ["--quick"] if quick else []
        if echo:
            status = main(argv)
        else:
            with redirect_stdout(buffer):
                status = main(argv)
        status = int(status or 0)
        return BenchRun(topic, status, time.perf_counter() - t0,
                        "" if status == 0 else f"main() returned {status}", buffer.getvalue())
    except SystemExit as err:  # argparse inside a benchmark
        code = err.code if isinstance(err.code, int) else 1
        return BenchRun(topic, code, time.perf_counter() - t0,
                        "" if code == 0 else f"exited with {err.code}", buffer.getvalue())
    except Exception as err:
        tb = traceback.format_exc(limit=-3)
        return BenchRun(topic, 1, time.perf_counter() - t0,
                        f"{type(err).__name__}: {err}\n{tb}", buffer.getvalue())
    finally:
        sys.path[:] = sys_path


def collect_results(bench_dir: Path, topics: Sequence[str] | None = None) -> str:
    """The markdown of ``results/README.md``: every ``results/<topic>.md`` in one page."""
    results = bench_dir / "results"
    files = sorted(p for p in results.glob("*.md") if p.name != README_NAME)
    if topics is not None:
        files = [p for p in files if p.stem in topics]
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    parts = ["# sonarloc benchmark results", "",
             f"Gathered by `sonarloc bench` on {stamp} from `benchmarks/results/*.md`. Each "
             "section is written by `benchmarks/bench_<topic>.py` (run it alone with "
             "`python benchmarks/bench_<topic>.py [--quick]`); its last line says the "
             "machine, date and parameters of that run.", ""]
    if not files:
        parts.append("No results yet: run `sonarloc bench`.")
    for p in files:
        body = p.read_text(encoding="utf-8").strip()
        lines = body.splitlines()
        if lines and lines[0].startswith("# "):  # demote the topic's headings one level
            fenced = False
            for i, line in enumerate(lines):
                fenced ^= line.startswith("```")
                if not fenced and line.startswith("#"):
                    lines[i] = "#" + line
            body = "\n".join(lines)
        else:
            body = f"## {p.stem}\n\n{body}"
        parts += [body, ""]
        png = p.with_suffix(".png")
        if png.exists():
            parts += [f"![{p.stem}]({png.name})", ""]
    return "\n".join(parts).rstrip() + "\n"
