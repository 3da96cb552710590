"""Pose CSV (FORMATS.md section 5): the estimate of ``base_link`` in ``map``, one row per odom.

Header ``t_s,x_m,y_m,yaw_deg,cov_xx,cov_xy,cov_xt,cov_yy,cov_yt,cov_tt`` (covariance in
m², m·rad, rad²; ``t`` = yaw). Columns may come in any order; unknown columns are
ignored. A bad file raises :class:`LogFormatError` naming the line and column.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from sonarloc.errors import LogFormatError

COLUMNS = ("t_s", "x_m", "y_m", "yaw_deg", "cov_xx", "cov_xy", "cov_xt", "cov_yy", "cov_yt",
           "cov_tt")


@dataclass(frozen=True)
class PoseTrack:
    """Poses of ``base_link`` in ``map`` with their covariance.

    ``t_s, x_m, y_m, yaw_rad``: (n,); ``cov``: (n, 3, 3) over (x [m], y [m], yaw [rad]).
    """

    t_s: NDArray[np.float64]
    x_m: NDArray[np.float64]
    y_m: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    cov: NDArray[np.float64]

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name in ("x_m", "y_m", "yaw_rad"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"`{name}` has length {len(getattr(self, name))}, expected {n}")
        if self.cov.shape != (n, 3, 3):
            raise ValueError(f"`cov` must have shape ({n}, 3, 3), got {self.cov.shape}")

    def __len__(self) -> int:
        return len(self.t_s)


def read_poses_csv(source: str | Path | IO[str]) -> PoseTrack:
    """Read a pose CSV (section 5) from a path or text stream.

    Every value must be a finite number; the covariance columns may be missing (then
    the covariance is NaN). Rows come as written, one per odom record: ``t_s`` may
    repeat or go back where the log's odometry did. Refused with
    :class:`LogFormatError` naming the line (and the file, given a path): a missing
    ``t_s``/``x_m``/``y_m``/``yaw_deg`` column, a scan CSV (section 1, told by its
    ``tof_us`` column: its poses are the transducers', not ``base_link``'s), a bad
    value, a header without rows. A byte-order mark is allowed.
    """
    if isinstance(source, (str, Path)):
        try:
            with open(source, encoding="utf-8", newline="") as handle:
                return read_poses_csv(handle)
        except OSError as err:
            raise LogFormatError(f"cannot open pose CSV {source}: {err.strerror}") from err
        except UnicodeDecodeError:
            raise LogFormatError(f"pose CSV {source} is not UTF-8 text") from None
        except LogFormatError as err:
            raise LogFormatError(f"pose CSV {source}: {err}") from None
    reader = csv.reader(source)
    try:
        rows = _parse_rows(reader)
    except csv.Error as err:  # a NUL byte, a field over csv's size limit: a line, not a crash
        raise LogFormatError(f"line {reader.line_num}: {err}") from None
    a = np.array(rows, dtype=float).reshape(-1, len(COLUMNS))
    cxx, cxy, cxt, cyy, cyt, ctt = (a[:, i] for i in range(4, 10))
    cov = np.stack([np.stack([cxx, cxy, cxt], -1), np.stack([cxy, cyy, cyt], -1),
                    np.stack([cxt, cyt, ctt], -1)], -2)
    return PoseTrack(a[:, 0], a[:, 1], a[:, 2], np.radians(a[:, 3]), cov)


def _parse_rows(reader: Iterator[list[str]]) -> list[list[float]]:
    """The rows of a pose CSV as :data:`COLUMNS` values (NaN for a missing column)."""
    header = next(reader, None)
    if header is None:
        raise LogFormatError("line 1: empty file (expected a header row)")
    if header:  # a byte-order mark (spreadsheets write one) is not part of the first name
        header[0] = header[0].removeprefix("\ufeff")
    names = [h.strip() for h in header]
    if "tof_us" in names:
        raise LogFormatError("line 1: this is a scan CSV (column `tof_us`: transducer poses, "
                             "FORMATS.md section 1), not a pose CSV of base_link (section 5, "
                             "as `sonarloc localize --out` writes)")
    for need in COLUMNS[:4]:
        if need not in names:
            raise LogFormatError(f"line 1: missing column `{need}` (have {', '.join(names)})")
    index = {name: names.index(name) for name in COLUMNS if name in names}
    rows: list[list[float]] = []
    for lineno, row in enumerate(reader, start=2):
        if not row or not any(cell.strip() for cell in row):
            continue
        values = []
        for name in COLUMNS:
            if name not in index:
                values.append(math.nan)
                continue
            cell = row[index[name]] if index[name] < len(row) else ""
            try:
                v = float(cell)
            except ValueError:
                raise LogFormatError(
                    f"line {lineno}: column `{name}` must be a number, got {cell!r}") from None
            if not math.isfinite(v):
                raise LogFormatError(f"line {lineno}: column `{name}` must be finite, got {cell!r}")
            values.append(v)
        rows.append(values)
    if not rows:
        raise LogFormatError("line 2: no pose rows after the header")
    return rows


def write_poses_csv(target: str | Path | IO[str], track: PoseTrack) -> None:
    """Write a pose CSV (section 5) to a path or text stream."""
    if isinstance(target, (str, Path)):
        with open(target, "w", encoding="utf-8", newline="") as handle:
            write_poses_csv(handle, track)
        return
    writer = csv.writer(target, lineterminator="\n")
    writer.writerow(COLUMNS)
    c = track.cov
    for i in range(len(track)):
        writer.writerow([repr(float(v)) for v in (
            track.t_s[i], track.x_m[i], track.y_m[i], math.degrees(track.yaw_rad[i]),
            c[i, 0, 0], c[i, 0, 1], c[i, 0, 2], c[i, 1, 1], c[i, 1, 2], c[i, 2, 2])])
