"""The machine line at the foot of every benchmark's results file.

Each ``benchmarks/bench_<topic>.py`` ends ``results/<topic>.md`` with one line that says
where, when and how its numbers were measured, so that runs on different machines and
days can be told apart. :func:`machine_line` writes it with the same facts, in the same
order, for every benchmark, then the script's own details::

    Machine: x86_64, AMD EPYC (2 CPUs), Python 3.11.7, numpy 2.4.6; 2026-11-29; full
    run; load average 1.2 at the start; python-can 4.6.1; 3 repeats; shared machine:
    other jobs may run.

(one line in the file). The line is found again by its label: ``bench_fit.py`` and
``bench_localize.py`` splice their results files at ``"\\nMachine: "``, so the label
starts a line and the line holds no line break.

This module imports nothing from ``sonarloc`` (``bench_replay.py`` imports it before
putting the baseline's code on ``sys.path``) and numpy only when the line is written.
"""

from __future__ import annotations

import datetime
import math
import os
import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")

SHARED = "shared machine: other jobs may run"
"""The caveat of a benchmark run on a machine shared with other jobs (a detail for
:func:`machine_line`; the script adds which of its numbers suffer and which do not)."""


def cpu_model(cpuinfo: Path = CPUINFO) -> str:
    """The processor's model name, or ``""`` where nothing says it.

    The first ``model name`` of ``cpuinfo`` (Linux), else :func:`platform.processor`
    (often empty on Linux, ``"arm"`` or ``"i386"`` on macOS); white space folded.
    """
    try:
        text = cpuinfo.read_text(encoding="utf-8", errors="replace")
    except OSError:
        text = ""
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "model name" and value.strip():
            return " ".join(value.split())
    return " ".join(platform.processor().split())


def load_average() -> float | None:
    """The 1-minute load average now, or None where the system keeps none (Windows)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def machine_line(*details: str, quick: bool, load: float | None = None,
                 load_when: str = "at the start", label: str = "Machine") -> str:
    """One line on the machine and the run, for the foot of a results file.

    Parameters
    ----------
    *details
        The script's own facts and notes, in order, after the common ones: library
        versions, seeds, repeats, the run's length, the shared-machine caveat. Empty ones
        are left out; a trailing full stop is dropped (the line ends with one).
    quick
        A ``--quick`` (smoke) run rather than a full one.
    load
        The 1-minute load average the script measured (:func:`load_average`); None or
        NaN: not measured, nothing said.
    load_when
        When ``load`` was measured: ``"at the start"``, ``"at the end"``.
    label
        The line's first words, before ``": "``; readers of the results files find the
        line by it.

    Returns
    -------
    str
        ``"<label>: <arch>, <CPU model> (<n> CPUs), Python <v>, numpy <v>; <date>;
        quick|full run[; load average <x> <load_when>][; <detail>]...."``, no line break.
        The CPU model and count are left out where the system does not say them.

    Raises
    ------
    ValueError
        If ``label`` is empty or the label or a detail holds a line break.
    """
    import numpy as np

    if not label.strip():
        raise ValueError(f"`label` must not be empty, got {label!r}")
    for name, text in (("label", label), *(("details", d) for d in details)):
        if "\n" in text or "\r" in text:
            raise ValueError(f"`{name}` must be one line, got {text!r}")
    hardware = ", ".join(x for x in (platform.machine(), cpu_model()) if x) or "unknown"
    cpus = os.cpu_count()
    if cpus:
        hardware += f" ({cpus} CPUs)"
    parts = [f"{hardware}, Python {platform.python_version()}, numpy {np.__version__}",
             datetime.date.today().isoformat(), "quick run" if quick else "full run"]
    if load is not None and math.isfinite(load):
        parts.append(f"load average {load:.1f} {load_when}".rstrip())
    parts += [d.strip().rstrip(".") for d in details if d.strip().rstrip(".")]
    return f"{label}: " + "; ".join(parts) + "."
