"""CAN log files (``candump -L`` format and every other python-can log format).

``candump:FILE.log`` reads the frames with python-can's own
:class:`can.CanutilsLogReader` and decodes them like a live bus. A line no reader
can parse (a damaged log) is skipped and counted (``malformed_lines``; the first
line numbers are kept in :attr:`CandumpDriver.malformed`): the reader is restarted
on the next line, so one bad line never ends a long log. Other suffixes
(``.asc``, ``.blf``, ``.trc``, ``.csv``, ...) go through :class:`can.LogReader`.
Writing is :class:`can.CanutilsLogWriter` (see ``serve-sim --candump``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import can

from sonarloc.errors import DeviceError
from sonarloc.io.drivers.base import Driver, Pacer, RecordCallback, sleep_until
from sonarloc.io.protocol.canbus import CanDecoder
from sonarloc.io.protocol.messages import DecoderStats
from sonarloc.io.protocol.records import RecordAssembler

_PARSE_ERRORS = (ValueError, IndexError, TypeError, KeyError)


class _NumberedLines:
    """A text file as an iterator of lines that knows its line number."""

    def __init__(self, handle: IO[str]):
        self.handle = handle
        self.lineno = 0

    def __iter__(self) -> _NumberedLines:
        return self

    def __next__(self) -> str:
        line = self.handle.readline()
        if not line:
            raise StopIteration
        self.lineno += 1
        return line

    def close(self) -> None:
        self.handle.close()


class CandumpDriver(Driver):
    """Reads module frames from a CAN log file.

    Parameters
    ----------
    path : the log file.
    rate : replay pacing against the frames' timestamps (1.0 = as recorded);
        None reads as fast as possible.
    """

    scheme = "candump"
    pulls = True
    MAX_KEPT = 100

    def __init__(self, path: str | Path, *, rate: float | None = None,
                 on_record: RecordCallback | None = None, queue_size: int = 100_000):
        super().__init__(on_record=on_record, queue_size=queue_size)
        self.pacer: Pacer = Pacer(rate)  # checks `rate`
        self.path = Path(path)
        self.rate = rate
        self.decoder = CanDecoder()
        self.assembler = RecordAssembler()
        self.malformed: list[tuple[int, str]] = []
        self._frames: Iterator[can.Message] | None = None
        self._lines: _NumberedLines | None = None
        self._due: can.Message | None = None  # a frame read before its time (rate)

    @property
    def source(self) -> str:
        return f"candump:{self.path}"

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def summary(self) -> str:
        """The counters, and the first malformed line by number."""
        out = super().summary()
        if self.malformed:
            lineno, msg = self.malformed[0]
            out += f" (first: line {lineno}: {msg})"
        return out

    def _open(self) -> None:
        if not self.path.is_file():
            raise DeviceError(f"cannot open {self.source}: no such file")
        self._frames = self._read_frames()

    def _close(self) -> None:
        if self._lines is not None:
            self._lines.close()
            self._lines = None
        self._frames = None

    def _read_frames(self) -> Iterator[can.Message]:
        if self.path.suffix.lower() != ".log":
            try:
                with can.LogReader(self.path) as reader:
                    yield from reader
            except _PARSE_ERRORS as err:
                raise DeviceError(f"{self.source}: {err}") from err
            return
        try:
            handle = open(self.path, encoding="ascii", errors="replace")  # noqa: SIM115
        except OSError as err:
            raise DeviceError(f"cannot open {self.source}: {err.strerror}") from err
        self._lines = lines = _NumberedLines(handle)
        while True:
            reader = can.CanutilsLogReader(lines)  # type: ignore[arg-type]
            try:
                yield from reader
                return
            except _PARSE_ERRORS as err:  # the reader is dead; a new one goes on
                self.stats.malformed_lines += 1
                if len(self.malformed) < self.MAX_KEPT:
                    self.malformed.append((lines.lineno, f"{type(err).__name__}: {err}"[:200]))

    def _pull(self, timeout: float | None) -> None:
        frames = self._frames
        if frames is None:
            self._end()
            return
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            frame, self._due = self._due, None
            if frame is None:
                try:
                    frame = next(frames)
                except StopIteration:
                    self._end()
                    return
                except DeviceError as err:
                    self._fail(err)
                    self._end()
                    return
            if self.rate is not None and frame.timestamp is not None and not sleep_until(
                    self.pacer.due(frame.timestamp, time.monotonic()), deadline):
                self._due = frame  # the timeout comes first: read() says so
                return
            recs = [r for m in self.decoder.feed(frame)
                    for r in self.assembler.push(m, frame.timestamp)]
            if recs:
                self._deliver(recs)
                return
            if deadline is not None and time.monotonic() >= deadline:
                return

