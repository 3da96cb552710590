"""Shared fixtures: seeded RNGs and running the ``sonarloc`` command in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
MAPS = REPO / "maps"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20031)


@pytest.fixture
def run_cli():
    """Run ``python -m sonarloc ARGS`` against this checkout; returns CompletedProcess."""

    def run(*args: str, timeout: float = 120.0, check: bool = False,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        env.setdefault("MPLBACKEND", "Agg")
        proc = subprocess.run([sys.executable, "-m", "sonarloc", *args], capture_output=True,
                              text=True, timeout=timeout, env=env, cwd=cwd)
        if check and proc.returncode != 0:
            raise AssertionError(f"sonarloc {' '.join(args)} failed ({proc.returncode}):\n"
                                 f"{proc.stdout}\n{proc.stderr}")
        return proc

    return run
