"""The examples that need no hardware run, and say what they should."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"


def run_example(name: str, *args: str, cwd: Path, timeout: float = 120.0
                ) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("MPLBACKEND", "Agg")
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=cwd)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def test_every_example_is_covered():
    names = {p.name for p in EXAMPLES.glob("*.py")}
    assert names == {"fit_paper_scene.py", "drive_ring.py", "build_map.py",
                     "read_serial_sonar.py", "embed_node.py"}


# options that have no default: flags, and the "also write this" ones (off unless given)
NO_DEFAULT = {"--help", "--quiet", "fit_paper_scene.py --plot", "read_serial_sonar.py --out"}


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.py")))
def test_help_states_the_defaults(tmp_path: Path, name: str):
    # `python examples/NAME.py --help` is how README sends a user in: every option with a
    # default says it (they read "--seed SEED", with no word on what it is or its value).
    out = run_example(name, "--help", cwd=tmp_path).stdout
    options = out[out.index("options:"):]
    blocks = {m[1]: m[0] for m in re.finditer(r"^  (--[a-z-]+).*(?:\n {6,}\S.*)*", options,
                                              re.M)}
    assert "--seed" in blocks or "--duration" in blocks, out
    for option, text in blocks.items():
        if option not in NO_DEFAULT and f"{name} {option}" not in NO_DEFAULT:
            assert "(default " in text, f"{name} {option}: {text}"


def test_fit_paper_scene(tmp_path: Path):
    out = run_example("fit_paper_scene.py", "--plot", "fig5.png", cwd=tmp_path).stdout
    rows = {m[0]: m for m in re.findall(
        r"^(pole|plane|rod)\s+([\d.]+)\s+([\d.]+)\s+(-?[\d.]+)\s+(-?[\d.]+)", out, re.M)}
    assert set(rows) == {"pole", "plane", "rod"}, out
    for name, fit_r, paper_r, fit_b, paper_b in rows.values():
        assert abs(float(fit_r) - float(paper_r)) < 0.005, name  # range within 5 mm
        assert abs(float(fit_b) - float(paper_b)) < 1.5, name     # bearing within 1.5 deg
    assert (tmp_path / "fig5.png").stat().st_size > 20_000


def test_drive_ring(tmp_path: Path):
    out = run_example("drive_ring.py", "--duration", "6", "--out", "ring.png",
                      cwd=tmp_path).stdout
    assert "pose RMSE" in out and "121 poses" in out
    assert (tmp_path / "ring.png").exists()


def test_build_map(tmp_path: Path):
    out = run_example("build_map.py", "--duration", "25", "--out", "built.geojson",
                      cwd=tmp_path).stdout
    assert "localized on the built map" in out
    from sonarloc.maps.geojson import load_map

    built = load_map(tmp_path / "built.geojson")  # the built map loads as a map
    assert len(built) > 0
    near = [float(d) for d in re.findall(r"nearest true \w+\s+([\d.]+) cm away", out)]
    assert near and min(near) < 3.0


def test_read_serial_sonar_from_a_simulated_module(tmp_path: Path):
    out = run_example("read_serial_sonar.py", "--duration", "1.5", "--out", "rec.jsonl",
                      cwd=tmp_path).stdout
    assert "simulated module on /dev/pts/" in out
    m = re.search(r"^(\d+) readings \((\d+) echoes\)", out, re.M)
    assert m and int(m[1]) > 50 and int(m[2]) > 10
    assert re.search(r"crc 0, skipped 0 B, gaps 0", out)
    from sonarloc.io.logfile import TofRecord, iter_log

    assert sum(isinstance(r, TofRecord) for r in iter_log(tmp_path / "rec.jsonl")) == int(m[1])


@pytest.mark.parametrize("seed", [1])
def test_embed_node(tmp_path: Path, seed: int):
    out = run_example("embed_node.py", "--duration", "12", "--seed", str(seed),
                      cwd=tmp_path).stdout
    errors = [float(e) for e in re.findall(r"error\s+([\d.]+) cm", out)]
    assert len(errors) == 13
    assert errors[-1] < 5.0  # after 12 s with landmarks the estimate is within 5 cm
    assert "map->odom" in out and "fused" in out
    shown = re.findall(r"^  t=.*$", out, re.M)  # the last landmarks, with their numbers
    assert shown and not any("nan" in line for line in shown), out


def test_embed_node_with_a_fit_worker(tmp_path: Path):
    # the robot's setting (README of the example): fits in a background worker, the
    # same estimate quality at the end, the worker's batches counted
    out = run_example("embed_node.py", "--duration", "12", "--fit-workers", "1",
                      cwd=tmp_path).stdout
    errors = [float(e) for e in re.findall(r"error\s+([\d.]+) cm", out)]
    assert len(errors) == 13 and errors[-1] < 5.0, out
    assert re.search(r"\b[1-9]\d* fit batches in workers", out), out
