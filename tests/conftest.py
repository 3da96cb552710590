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


def _cli_command(*args: str) -> tuple[list[str], dict[str, str]]:
    """The command line and environment that run ``python -m sonarloc ARGS`` against
    this checkout."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("MPLBACKEND", "Agg")
    return [sys.executable, "-m", "sonarloc", *args], env


@pytest.fixture
def cli_command():
    """``cli_command(*ARGS) -> (argv, env)`` of ``python -m sonarloc ARGS`` against this
    checkout, for a test that needs a Popen of its own."""
    return _cli_command


@pytest.fixture
def run_cli():
    """Run ``python -m sonarloc ARGS`` against this checkout; returns CompletedProcess."""

    def run(*args: str, timeout: float = 120.0, check: bool = False,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
        cmd, env = _cli_command(*args)
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=cwd)
        if check and proc.returncode != 0:
            raise AssertionError(f"sonarloc {' '.join(args)} failed ({proc.returncode}):\n"
                                 f"{proc.stdout}\n{proc.stderr}")
        return proc

    return run
