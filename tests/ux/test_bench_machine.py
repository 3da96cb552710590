"""benchmarks/_machine.py: the machine line at the foot of every results file."""

from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path

import numpy as np
import pytest

from benchmarks import _machine
from benchmarks._machine import cpu_model, machine_line

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC   7B13 64-Core Processor
flags\t\t: fpu vme

processor\t: 1
model name\t: AMD EPYC   7B13 64-Core Processor
"""


def test_line_holds_the_common_facts_then_the_details():
    line = machine_line("python-can 4.6.1", "seed 2003", "shared machine: other jobs may run.",
                        quick=False, load=1.234)
    assert line.startswith("Machine: ") and "\n" not in line
    assert f"({os.cpu_count()} CPUs)" in line
    assert f"Python {platform.python_version()}" in line
    assert f"numpy {np.__version__}" in line
    assert datetime.date.today().isoformat() in line
    assert "; full run; load average 1.2 at the start; python-can 4.6.1; seed 2003; " \
           "shared machine: other jobs may run." in line
    assert line.endswith("run.") and not line.endswith("..")


def test_quick_label_and_no_load():
    line = machine_line(quick=True, label="Map building and relocalization sections")
    assert line.startswith("Map building and relocalization sections: ")
    assert line.endswith("; quick run.") and "load average" not in line
    assert "load average" not in machine_line(quick=True, load=float("nan"))
    assert "2.0 at the end" in machine_line(quick=True, load=2.0, load_when="at the end")


@pytest.mark.parametrize("kwargs", [{"label": ""}, {"label": "Machine\nx"}])
def test_bad_label(kwargs):
    with pytest.raises(ValueError, match="label"):
        machine_line(quick=True, **kwargs)


def test_detail_with_a_line_break():
    with pytest.raises(ValueError, match="details"):
        machine_line("one\nMachine: two", quick=True)


def test_cpu_model_from_cpuinfo_or_platform(tmp_path: Path, monkeypatch):
    info = tmp_path / "cpuinfo"
    info.write_text(CPUINFO)
    assert cpu_model(info) == "AMD EPYC 7B13 64-Core Processor"
    info.write_text("processor\t: 0\nCPU part\t: 0xd0c\n")   # no model name (some ARM)
    monkeypatch.setattr(platform, "processor", lambda: "aarch64")
    assert cpu_model(info) == "aarch64"
    monkeypatch.setattr(platform, "processor", lambda: "")
    assert cpu_model(tmp_path / "missing") == ""
    # nothing known about the CPU: the line says the architecture only
    monkeypatch.setattr(_machine, "cpu_model", lambda: "")
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    assert machine_line(quick=True).startswith("Machine: x86_64, Python ")
