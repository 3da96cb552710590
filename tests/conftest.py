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


def cli_command(*args: str) -> tuple[list[str], dict[str, str]]:
    """The command line and environment that run ``python -m sonarloc ARGS`` against
    this checkout (for tests that need a Popen of their own)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("MPLBACKEND", "Agg")
    return [sys.executable, "-m", "sonarloc", *args], env


@pytest.fixture
def run_cli():
    """Run ``python -m sonarloc ARGS`` against this checkout; returns CompletedProcess."""

    def run(*args: str, timeout: float = 120.0, check: bool = False,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
        cmd, env = cli_command(*args)
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=cwd)
        if check and proc.returncode != 0:
            raise AssertionError(f"sonarloc {' '.join(args)} failed ({proc.returncode}):\n"
                                 f"{proc.stdout}\n{proc.stderr}")
        return proc

    return run
