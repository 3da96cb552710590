"""Scan CSV (FORMATS.md section 1): one row per ping of a transducer with known pose.

Columns in any order, header required, unknown columns ignored: ``t_s, x_m, y_m,
yaw_deg, tof_us`` and optional ``sensor``. An empty or ``nan`` ``tof_us`` means no
echo. A bad file raises :class:`LogFormatError` naming the line and column.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from sonarloc.errors import LogFormatError

REQUIRED = ("t_s", "x_m", "y_m", "yaw_deg", "tof_us")


@dataclass(frozen=True)
class ScanReadings:
    """Readings of one or more transducers, as parallel arrays of length n.

    ``yaw_rad`` is the transducer axis direction in the frame; ``tof_us`` is NaN where
    no echo came back; ``sensor`` the integer transducer id.
    """

    t_s: NDArray[np.float64]
    x_m: NDArray[np.float64]
    y_m: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    tof_us: NDArray[np.float64]
    sensor: NDArray[np.int64]

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name in ("x_m", "y_m", "yaw_rad", "tof_us", "sensor"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"`{name}` has length {len(getattr(self, name))}, expected {n}")

    def __len__(self) -> int:
        return len(self.t_s)

    FIELDS = (("t_s", np.float64), ("x_m", np.float64), ("y_m", np.float64),
              ("yaw_rad", np.float64), ("tof_us", np.float64), ("sensor", np.int64))
    """The arrays' names and dtypes, in order."""

    @classmethod
    def concat(cls, parts: Sequence[ScanReadings]) -> ScanReadings:
        """The readings of ``parts``, one after the other (new arrays)."""
        return cls(*[np.concatenate([getattr(p, f) for p in parts] + [np.empty(0, dtype=d)])
                     for f, d in cls.FIELDS])

    def timeouts_as_no_echo(self, max_tof_us: float) -> tuple[ScanReadings, int]:
        """These readings with every TOF at or above ``max_tof_us`` [us] made a no-echo
        reading (NaN), and how many were: for a module that reports its timeout (the
        end of its listening window) as a reading instead of as no echo."""
        late = self.tof_us >= max_tof_us  # NaN compares False: stays no echo
        n = int(np.count_nonzero(late))
        if n == 0:
            return self, 0
        return replace(self, tof_us=np.where(late, np.nan, self.tof_us)), n

    def select(self, mask: NDArray[np.bool_] | slice) -> ScanReadings:
        """The readings at ``mask`` (boolean array, index array or slice)."""
        return ScanReadings(self.t_s[mask], self.x_m[mask], self.y_m[mask],
                            self.yaw_rad[mask], self.tof_us[mask], self.sensor[mask])


class TimeoutWatch:
    """Watches a scan's readings, block by block, for a module's timeout reported as an
    echo: many readings at exactly the largest TOF of the scan. Echoes of a real
    reflector scatter by the module's jitter, so a value repeated exactly at the top of
    the range is the end of the listening window. Fitted, those readings make "walls"
    at that range (10.6 m for 62,000 us), some ``flat``, and their no-echo information
    (which bounds the arcs of real reflectors) is lost.

    >>> w = TimeoutWatch()
    >>> w.push(np.array([5000.0, 62000.0, np.nan, 62000.0, 9000.0] * 4))
    >>> w.suspect(echoes=16)
    (62000.0, 8)
    """

    MIN_COUNT = 5
    MIN_FRACTION = 0.05  # of the echoes

    def __init__(self) -> None:
        self.largest = -math.inf
        self.count = 0
        self.echoes = 0  # echoes watched

    def push(self, tof_us: NDArray[np.float64]) -> None:
        finite = tof_us[np.isfinite(tof_us) & (tof_us > 0.0)]  # echoes (not bad readings)
        if finite.size == 0:
            return
        self.echoes += finite.size
        top = float(finite.max())
        if top > self.largest:
            self.largest, self.count = top, 0
        if top == self.largest:
            self.count += int(np.count_nonzero(finite == top))

    def push_one(self, tof_us: float) -> None:
        """One reading (NaN: no echo), as :meth:`push` takes a block."""
        if not (math.isfinite(tof_us) and tof_us > 0.0):
            return
        self.echoes += 1
        if tof_us > self.largest:
            self.largest, self.count = tof_us, 0
        if tof_us == self.largest:
            self.count += 1

    def suspect(self, echoes: int | None = None) -> tuple[float, int] | None:
        """(the TOF [us], how many readings) when they look like timeouts, else None;
        ``echoes``: of how many (default: those watched)."""
        echoes = self.echoes if echoes is None else echoes
        if self.count >= max(self.MIN_COUNT, self.MIN_FRACTION * echoes):
            return self.largest, self.count
        return None

    def advice(self, echoes: int | None = None) -> str | None:
        """What to tell the user when the readings look like timeouts (``echoes``: as
        :meth:`suspect`), else None."""
        found = self.suspect(echoes)
        if found is None:
            return None
        tof, n = found
        echoes = self.echoes if echoes is None else echoes
        return (f"{n} of {echoes} echoes have exactly the largest TOF, {tof:g} us: a module's "
                f"timeout reported as an echo? If so, --max-tof {tof:g} takes them as no echo")


def _column(rows: list[list[str]], index: int, name: str, line_of: list[int],
            empty_is_nan: bool) -> NDArray[np.float64]:
    values = [row[index] if index < len(row) else "" for row in rows]
    if empty_is_nan:
        values = [v if v.strip() else "nan" for v in values]
    try:
        return np.array(values, dtype=float)
    except ValueError:
        pass
    for i, v in enumerate(values):  # slow path only to name the culprit
        try:
            float(v)
        except ValueError:
            raise LogFormatError(
                f"line {line_of[i]}: column `{name}` must be a number, got {v!r}"
            ) from None
    raise LogFormatError(f"column `{name}` could not be parsed")  # pragma: no cover


BLOCK_ROWS = 1 << 18
"""Lines of a scan CSV parsed at a time by :func:`iter_scan_csv` (and fitted at a time by
``sonarloc fit``). Measured (benchmarks/bench_fit_memory.py, a 1,000,000-line continuous
rotation, 43 MB): ``sonarloc fit`` peaks at 261 MB with blocks of this size against 604
MB with the whole file as one block, 122 MB
at 2**16 lines and 99 MB at 2**14, for 1.04x, 1.21x and 1.63x the CPU of one block
(each batch of lockstep fits has a fixed cost); files up to this size are one block."""


def read_scan_csv(source: str | Path | IO[str]) -> ScanReadings:
    """Read a scan CSV from a path or text stream.

    Poses must be finite and ``t_s`` non-decreasing; ``tof_us`` may be empty/NaN (no
    echo) or any number (non-finite values are kept for the fitter to reject). The
    blocks of :func:`iter_scan_csv`, joined.
    """
    blocks = list(iter_scan_csv(source))
    return blocks[0] if len(blocks) == 1 else ScanReadings.concat(blocks)


def iter_scan_csv(source: str | Path | IO[str], block_rows: int = BLOCK_ROWS
                  ) -> Iterator[ScanReadings]:
    """The readings of a scan CSV, ``block_rows`` lines at a time (memory bounded by a
    block, for files of any size; the checks of :func:`read_scan_csv`).

    The header is checked before the first block is yielded; a bad line raises
    :class:`LogFormatError` (naming it) when its block is parsed, after the blocks
    before it were yielded. ``t_s`` must not go backwards across blocks either.
    """
    if not (isinstance(block_rows, int) and block_rows >= 1):
        raise ValueError(f"`block_rows` must be a positive integer, got {block_rows!r}")
    if isinstance(source, (str, Path)):
        try:
            handle = open(source, newline="", encoding="utf-8", errors="replace")
        except OSError as err:
            raise LogFormatError(f"cannot open scan {source}: {err.strerror}") from err
        with handle:
            yield from iter_scan_csv(handle, block_rows)
        return
    reader = csv.reader(source)
    try:
        header = next(reader)
    except StopIteration:
        raise LogFormatError("line 1: empty file, expected a header row") from None
    except csv.Error as err:
        raise LogFormatError(f"line {reader.line_num}: {err}") from None
    if header:   # a byte-order mark (spreadsheets write one) is not part of the first name
        header[0] = header[0].removeprefix("\ufeff")
    names = [h.strip() for h in header]
    missing = [c for c in REQUIRED if c not in names]
    if missing:
        hint = next((f" (it is one field with {name} in it: the columns must be separated "
                     f"by commas)" for sep, name in ((";", "semicolons"), ("\t", "tabs"))
                     if len(names) == 1 and sep in names[0]), "")
        raise LogFormatError(f"line 1: header lacks column(s) {', '.join(missing)}{hint}")
    col = {name: names.index(name) for name in names if name in (*REQUIRED, "sensor")}
    first_line, t_before, any_block = 2, -math.inf, False
    while True:
        try:
            rows = list(itertools.islice(reader, block_rows))
        except csv.Error as err:   # a field over csv's size limit, say: a line, not a crash
            raise LogFormatError(f"line {reader.line_num}: {err}") from None
        if not rows:
            break
        block = _parse_block(rows, _row_lines(rows, first_line, reader.line_num), names, col,
                             t_before)
        first_line = reader.line_num + 1
        rows = []   # the text goes before the block is yielded (and fitted)
        if len(block):
            t_before = float(block.t_s[-1])
        if len(block) or not any_block:
            any_block = True
            yield block
    if not any_block:   # a header and nothing else: no readings
        yield _parse_block([], range(first_line, first_line), names, col, t_before)


def _row_lines(rows: list[list[str]], first_line: int, last_line: int) -> Sequence[int]:
    """The file's line number of each of ``rows``, read from lines ``first_line`` to
    ``last_line``: one line each, unless a quoted field spans lines (then counted from
    the line breaks the fields keep: an error names the line it is on, not the record)."""
    if last_line - first_line + 1 == len(rows):
        return range(first_line, last_line + 1)
    out, line = [], first_line
    for row in rows:
        out.append(line)
        line += 1 + sum(f.count("\n") + f.count("\r") - f.count("\r\n") for f in row)
    return out


def _parse_block(rows: list[list[str]], row_line: Sequence[int], names: list[str],
                 col: dict[str, int], t_before: float) -> ScanReadings:
    """The readings of ``rows`` (``row_line``: the line each is on; blank lines
    allowed); ``t_before``: the last ``t_s`` of the lines before."""
    line_of = [line for line, row in zip(row_line, rows, strict=True)
               if row and any(c.strip() for c in row)]
    rows = [row for row in rows if row and any(c.strip() for c in row)]
    for i, row in enumerate(rows):
        if len(row) < len(names):
            raise LogFormatError(f"line {line_of[i]}: {len(row)} fields, header has {len(names)}")
    arrays = {}
    for name in REQUIRED:
        arr = _column(rows, col[name], name, line_of, empty_is_nan=(name == "tof_us"))
        if name != "tof_us":
            bad = ~np.isfinite(arr)
            if bad.any():
                i = int(np.argmax(bad))
                raise LogFormatError(f"line {line_of[i]}: column `{name}` must be finite, "
                                     f"got {rows[i][col[name]]!r}")
        arrays[name] = arr
    if "sensor" in col:
        raw = [row[col["sensor"]].strip() or "0" for row in rows]
        try:
            sensor = np.array([int(v) for v in raw], dtype=np.int64)
        except (ValueError, OverflowError):   # (OverflowError: beyond 64 bits)
            i = _bad_sensor(raw)
            raise LogFormatError(f"line {line_of[i]}: column `sensor` must be a 64-bit "
                                 f"integer, got {raw[i]!r}") from None
    else:
        sensor = np.zeros(len(rows), dtype=np.int64)
    t = arrays["t_s"]
    back = np.flatnonzero(np.diff(np.concatenate([[t_before], t])) < 0)
    if back.size:
        i = int(back[0])
        before = t[i - 1] if i else t_before
        raise LogFormatError(f"line {line_of[i]}: `t_s` went backwards ({t[i]} after {before})")
    return ScanReadings(t, arrays["x_m"], arrays["y_m"], np.deg2rad(arrays["yaw_deg"]),
                        arrays["tof_us"], sensor)


def _bad_sensor(raw: list[str]) -> int:
    """Index of the first of ``raw`` that is not an integer of int64's range (which
    ``str.isdigit`` cannot tell: it passes "²", which ``int`` refuses)."""
    for i, v in enumerate(raw):
        try:
            if -(1 << 63) <= int(v) < (1 << 63):
                continue
        except ValueError:
            pass
        return i
    raise LogFormatError("column `sensor` could not be parsed")  # pragma: no cover


def write_scan_csv(target: str | Path | IO[str], scan: ScanReadings) -> None:
    """Write readings as a scan CSV (no echo = empty ``tof_us``)."""
    if isinstance(target, (str, Path)):
        with open(target, "w", newline="", encoding="utf-8") as handle:
            write_scan_csv(handle, scan)
        return
    target.write("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n")
    columns = zip(scan.t_s.tolist(), scan.x_m.tolist(), scan.y_m.tolist(),
                  np.rad2deg(scan.yaw_rad).tolist(), scan.tof_us.tolist(),
                  scan.sensor.tolist(), strict=True)
    for t, x, y, yaw, tof, sensor in columns:
        tof_text = "" if math.isnan(tof) else repr(tof)
        target.write(f"{t!r},{x!r},{y!r},{yaw!r},{tof_text},{sensor}\n")
