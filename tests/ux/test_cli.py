"""The `sonarloc` shell itself: behaviour common to every command."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from conftest import MAPS, cli_command

from sonarloc.cli import stdout_reader_gone


def test_a_reader_that_stops_early_is_not_an_error(tmp_path: Path, run_cli):
    # `sonarloc fit SCAN --jsonl | head`: the reader closes the pipe; the command stops
    # quietly with 128 + SIGPIPE, as shell tools do, instead of "error: Broken pipe"
    # (or Python's "Exception ignored ... BrokenPipeError" when it was the last flush).
    scan = tmp_path / "scan.csv"
    run_cli("simulate", "--map", str(MAPS / "paper_fig5.geojson"), "--rig", "pan",
            "--at", "0,0,0", "--out", str(tmp_path / "log.jsonl"), "--scan-csv", str(scan),
            check=True)
    for output in ("--json", "--jsonl"):
        cmd, env = cli_command("fit", str(scan), output)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.close()  # gone before the first byte, as `| head -0` would be
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=120) == 141 and err == "", (output, proc.returncode, err)


def test_only_a_closed_stdout_counts_as_the_reader_gone(monkeypatch, tmp_path: Path):
    # A broken pipe from a device's socket stays an error: the quiet exit needs stdout
    # itself to be a pipe without a reader.
    read_end, write_end = os.pipe()
    with open(write_end, "w") as out:
        monkeypatch.setattr(sys, "stdout", out)
        assert not stdout_reader_gone()
        os.close(read_end)
        assert stdout_reader_gone()
    with open(tmp_path / "out.txt", "w") as out:
        monkeypatch.setattr(sys, "stdout", out)
        assert not stdout_reader_gone()
