"""A one-line progress bar on stderr, drawn only when stderr is a terminal."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``with Progress(total, "drive") as p: p.update(done)`` — silent unless on a tty.

    Redraws at most ``hz`` times a second, so calling :meth:`update` per reading is cheap.
    """

    def __init__(self, total: float, label: str = "", stream: TextIO | None = None,
                 enabled: bool | None = None, hz: float = 8.0, unit: str = "s"):
        if not (total > 0):
            raise ValueError(f"`total` must be positive, got {total!r}")
        self.total, self.label, self.unit = float(total), label, unit
        self.stream = stream if stream is not None else sys.stderr
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(isatty and isatty()) if enabled is None else enabled
        self._period = 1.0 / hz
        self._last = -1e9
        self._t0 = time.perf_counter()
        self._shown = False

    def update(self, done: float, note: str = "") -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if now - self._last < self._period and done < self.total:
            return
        self._last = now
        frac = min(max(done / self.total, 0.0), 1.0)
        width = 28
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        elapsed = now - self._t0
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        text = (f"\r{self.label} [{bar}] {done:.0f}/{self.total:.0f} {self.unit} "
                f"{elapsed:.0f}s elapsed, ~{eta:.0f}s left {note}")
        self.stream.write(text[:120].ljust(100))
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self.enabled and self._shown:
            self.stream.write("\r" + " " * 100 + "\r")
            self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
