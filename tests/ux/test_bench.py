"""`sonarloc bench`: finds benchmarks, runs main(argv), gathers results/README.md."""

from __future__ import annotations

from pathlib import Path

from sonarloc.report.benchmarks import collect_results, find_benchmarks_dir, list_benchmarks

BENCH = '''
import sys
from pathlib import Path

def main(argv):
    quick = "--quick" in argv
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "{topic}.md").write_text(
        "# {topic} speed\\n\\n| method | time |\\n|---|---|\\n| a | {} |\\n\\n"
        "machine x, quick={}\\n".format(1 if quick else 2, quick))
    print("noise on stdout")
    return 0
'''

BROKEN = '''
def main(argv):
    raise RuntimeError("boom in the benchmark")
'''


def _tree(tmp_path: Path) -> Path:
    bench = tmp_path / "benchmarks"
    bench.mkdir()
    for topic in ("alpha", "beta"):
        (bench / f"bench_{topic}.py").write_text(BENCH.replace("{topic}", topic))
    return bench


def test_find_and_list(tmp_path: Path):
    bench = _tree(tmp_path)
    assert find_benchmarks_dir(tmp_path) == bench
    assert list(list_benchmarks(bench)) == ["alpha", "beta"]


def test_cli_runs_only_quick_and_gathers(tmp_path: Path, run_cli):
    bench = _tree(tmp_path)
    proc = run_cli("bench", "--dir", str(bench), "--only", "beta", "--quick")
    assert proc.returncode == 0, proc.stderr
    assert not (bench / "results" / "alpha.md").exists()
    beta = (bench / "results" / "beta.md").read_text()  # no full run yet: the quick table
    assert "| a | 1 |" in beta and "quick=True" in beta
    assert "| a | 1 |" in proc.stdout and "noise on stdout" not in proc.stdout
    # a full run of everything gathers results/README.md
    proc = run_cli("bench", "--dir", str(bench))
    assert proc.returncode == 0, proc.stderr
    readme = (bench / "results" / "README.md").read_text()
    assert readme.index("## alpha speed") < readme.index("## beta speed")
    assert "| a | 2 |" in readme and "| a | 1 |" not in readme
    # a quick run prints its tables, then the full run's files come back untouched
    proc = run_cli("bench", "--dir", str(bench), "--quick")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("| a | 1 |") == 2
    assert "| a | 2 |" in (bench / "results" / "alpha.md").read_text()
    assert (bench / "results" / "README.md").read_text() == readme
    assert "| a | 2 |" in collect_results(bench)


def test_cli_failures_are_reported(tmp_path: Path, run_cli):
    bench = _tree(tmp_path)
    (bench / "bench_gamma.py").write_text(BROKEN)
    proc = run_cli("bench", "--dir", str(bench))
    assert proc.returncode == 1
    assert "RuntimeError: boom in the benchmark" in proc.stderr
    assert "1 benchmark(s) failed: gamma" in proc.stderr
    assert (bench / "results" / "alpha.md").exists()  # the others still ran
    proc = run_cli("bench", "--dir", str(bench), "--only", "nosuch")
    assert proc.returncode == 2 and "nosuch" in proc.stderr and "alpha" in proc.stderr


def test_cli_without_a_source_tree(tmp_path: Path, run_cli):
    proc = run_cli("bench", "--dir", str(tmp_path / "nowhere"))
    assert proc.returncode == 2
    assert "no benchmarks/ folder" in proc.stderr and "source tree" in proc.stderr
