"""Log JSONL (FORMATS.md section 4): typed records, a writer and a forgiving reader.

One JSON object per line, non-decreasing ``t_s``; ``type`` says which record.
The reader never stops a long run silently: malformed lines are skipped and named
by line number in :class:`LogStats`, unknown record types are counted, and time
going backwards is reported. ``strict=True`` raises :class:`LogFormatError` instead.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, ClassVar, TypeGuard

from sonarloc.errors import LogFormatError
from sonarloc.physics.sound import check_air_speed_of_sound


@dataclass(frozen=True)
class SensorMount:
    """A transducer's mount pose in ``base_link`` (metres, degrees CCW)."""

    id: int
    x_m: float
    y_m: float
    yaw_deg: float


@dataclass(frozen=True)
class RigRecord:
    sensors: tuple[SensorMount, ...]
    speed_of_sound_mps: float = 343.0
    t_s: float = 0.0
    type: ClassVar[str] = "rig"


#: The SDs of an exact prior (an init record's 0, as a simulation writes its truth): a
#: Gaussian needs a positive variance
EXACT_PRIOR_SD_M = 1e-6
EXACT_PRIOR_SD_RAD = 1e-6


@dataclass(frozen=True)
class InitRecord:
    """The prior pose of ``base_link`` in ``map`` and its SDs (0: exact)."""

    t_s: float
    x_m: float
    y_m: float
    yaw_deg: float
    sd_xy_m: float
    sd_yaw_deg: float
    type: ClassVar[str] = "init"

    def prior_sds(self) -> tuple[float, float]:
        """(position SD [m], yaw SD [rad]) of the prior, an exact one's (0) raised to
        :data:`EXACT_PRIOR_SD_M` / :data:`EXACT_PRIOR_SD_RAD`."""
        return (max(self.sd_xy_m, EXACT_PRIOR_SD_M),
                max(math.radians(self.sd_yaw_deg), EXACT_PRIOR_SD_RAD))


@dataclass(frozen=True)
class OdomRecord:
    """Wheel-odometry pose of ``base_link`` in ``odom`` (integrated, drifting).

    ``reset``: this pose starts a new odometry frame (the base controller restarted and
    its odometry began again, e.g. at (0, 0, 0)): it is not differenced against the
    pose before it. Written only when true (``"reset": true``); absent means false.
    """

    t_s: float
    x_m: float
    y_m: float
    yaw_deg: float
    reset: bool = False
    type: ClassVar[str] = "odom"


@dataclass(frozen=True)
class TofRecord:
    """One ping: ``tof_us`` is None when no echo came back."""

    t_s: float
    sensor: int
    tof_us: float | None
    pan_deg: float | None = None
    type: ClassVar[str] = "tof"


@dataclass(frozen=True)
class TruthRecord:
    """True pose of ``base_link`` in ``map`` (simulator only; localization never reads it)."""

    t_s: float
    x_m: float
    y_m: float
    yaw_deg: float
    type: ClassVar[str] = "truth"


Record = RigRecord | InitRecord | OdomRecord | TofRecord | TruthRecord

_DECODER = json.JSONDecoder()   # json.loads' settings


def record_to_dict(rec: Record) -> dict[str, Any]:
    """The JSON object of a record, with ``type`` first and optional fields omitted when None."""
    if isinstance(rec, RigRecord):
        return {"type": "rig", "t_s": rec.t_s,
                "sensors": [{"id": s.id, "x_m": s.x_m, "y_m": s.y_m, "yaw_deg": s.yaw_deg}
                            for s in rec.sensors],
                "speed_of_sound_mps": rec.speed_of_sound_mps}
    out: dict[str, Any] = {"type": rec.type}
    for name in rec.__dataclass_fields__:
        if name == "type":
            continue
        value = getattr(rec, name)
        if (value is None and name == "pan_deg") or (name == "reset" and not value):
            continue
        out[name] = value
    return out


def _num(obj: dict[str, Any], name: str, default: float | None = None) -> float:
    if name not in obj:
        if default is not None:
            return default
        raise ValueError(f"missing field `{name}`")
    value = obj[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"field `{name}` must be a finite number, got {value!r}")
    return float(value)


def _sd(obj: dict[str, Any], name: str) -> float:
    """A standard deviation field: a non-negative number (0: exact, as a simulation's
    truth) whose square is finite (a variance of 1e600 would overflow the prior's
    covariance)."""
    v = _num(obj, name)
    if not (v >= 0.0 and math.isfinite(v * v)):
        raise ValueError(f"init record: field `{name}` must be a non-negative standard "
                         f"deviation, got {v!r}")
    return v


def _finite(v: object) -> TypeGuard[float]:
    """``v`` is a finite float (not an int, bool or anything else)."""
    return type(v) is float and v - v == 0.0


def record_from_dict(obj: dict[str, Any]) -> Record | None:
    """Parse one JSON object; None for an unknown ``type``; ValueError names a bad field."""
    kind = obj.get("type")
    # the common well-formed records first (floats where floats belong); anything else
    # takes the checking path below, which names what is wrong
    if kind == "tof":
        t, tof, sensor = obj.get("t_s"), obj.get("tof_us"), obj.get("sensor", 0)
        if _finite(t) and (tof is None or _finite(tof)) and type(sensor) is int and \
                obj.get("pan_deg") is None:
            return TofRecord(t, sensor, tof, None)
    elif kind == "odom" or kind == "truth":
        t, x, y, yaw = obj.get("t_s"), obj.get("x_m"), obj.get("y_m"), obj.get("yaw_deg")
        if _finite(t) and _finite(x) and _finite(y) and _finite(yaw) and \
                (kind == "truth" or "reset" not in obj):
            return OdomRecord(t, x, y, yaw) if kind == "odom" else TruthRecord(t, x, y, yaw)
    return _record_checked(obj, kind)


def _record_checked(obj: dict[str, Any], kind: object) -> Record | None:
    """:func:`record_from_dict` field by field (every record; names what is wrong)."""
    if kind == "tof":
        tof = obj.get("tof_us")
        if tof is not None:
            tof = _num(obj, "tof_us")
        sensor = obj.get("sensor", 0)
        if isinstance(sensor, bool) or not isinstance(sensor, int):
            raise ValueError(f"field `sensor` must be an integer, got {sensor!r}")
        pan = _num(obj, "pan_deg") if obj.get("pan_deg") is not None else None
        return TofRecord(_num(obj, "t_s"), sensor, tof, pan)
    if kind in ("odom", "truth"):
        pose = {n: _num(obj, n) for n in ("t_s", "x_m", "y_m", "yaw_deg")}
        if kind == "truth":
            return TruthRecord(**pose)
        reset = obj.get("reset", False)
        if not isinstance(reset, bool):
            raise ValueError(f"field `reset` must be true or false, got {reset!r}")
        return OdomRecord(**pose, reset=reset)
    if kind == "init":
        try:
            pose = {n: _num(obj, n) for n in ("t_s", "x_m", "y_m", "yaw_deg")}
        except ValueError as err:  # named as an init record's (a missing prior is fatal)
            raise ValueError(f"init record: {err}") from None
        return InitRecord(**pose, sd_xy_m=_sd(obj, "sd_xy_m"), sd_yaw_deg=_sd(obj, "sd_yaw_deg"))
    if kind == "rig":
        sensors = obj.get("sensors")
        if not isinstance(sensors, list) or not sensors:
            raise ValueError("field `sensors` must be a non-empty list")
        mounts = []
        for i, s in enumerate(sensors):
            if not isinstance(s, dict) or isinstance(s.get("id"), bool) \
                    or not isinstance(s.get("id"), int):
                raise ValueError(f"sensors[{i}] needs an integer `id`")
            try:
                mounts.append(SensorMount(s["id"], _num(s, "x_m"), _num(s, "y_m"),
                                          _num(s, "yaw_deg")))
            except ValueError as err:
                raise ValueError(f"sensors[{i}]: {err}") from None
        if len({m.id for m in mounts}) != len(mounts):
            raise ValueError("sensor ids must be unique")
        # (3 m/s, a typo or another unit, left every reading unmatched by the map)
        c = check_air_speed_of_sound(_num(obj, "speed_of_sound_mps", 343.0),
                                     "`speed_of_sound_mps`")
        return RigRecord(tuple(mounts), c, _num(obj, "t_s", 0.0))
    return None


@dataclass
class LogStats:
    """What a reader met besides good records."""

    records: int = 0
    unknown: Counter[str] = field(default_factory=Counter)
    malformed: list[tuple[int, str]] = field(default_factory=list)
    time_backwards: list[tuple[int, float, float]] = field(default_factory=list)

    MAX_KEPT = 1000  # malformed/backwards lines kept verbatim; the rest only counted
    malformed_count: int = 0
    time_backwards_count: int = 0

    def summary(self) -> str:
        parts = [f"{self.records} records"]
        if self.unknown:
            parts.append(f"{sum(self.unknown.values())} of unknown type "
                         f"({', '.join(f'{k}: {v}' for k, v in sorted(self.unknown.items()))})")
        if self.malformed_count:
            first = self.malformed[0]
            parts.append(f"{self.malformed_count} malformed (first: line {first[0]}: {first[1]})")
        if self.time_backwards_count:
            ln, prev, now = self.time_backwards[0]
            parts.append(f"time went backwards {self.time_backwards_count} times "
                         f"(first: line {ln}, {now} after {prev})")
        return "; ".join(parts)


#: The canonical form of the common records (as :class:`LogWriter` writes them), read by
#: a regular expression instead of the JSON decoder: numbers in JSON's grammar (the same
#: ``float`` / ``int`` json gives them), sensor ids of at most 18 digits. Any other
#: line, and any such line with a value the record refuses (e.g. ``1e999``), takes the
#: general path (the same records, the same messages).
_NUM = r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?"
_TOF_LINE = re.compile(
    r'\{"type":"tof","t_s":(' + _NUM + r'),"sensor":(-?(?:0|[1-9][0-9]{0,17})),'
    r'"tof_us":(?:(' + _NUM + r')|null)(?:,"pan_deg":(' + _NUM + r'))?\}\n?')
_POSE_LINE = re.compile(
    r'\{"type":"(odom|truth)","t_s":(' + _NUM + r'),"x_m":(' + _NUM + r'),"y_m":('
    + _NUM + r'),"yaw_deg":(' + _NUM + r')\}\n?')
#: Most tof records in one :class:`TofRun`.
_RUN_MAX = 4096


@dataclass(frozen=True)
class TofRun:
    """Consecutive ``tof`` records of a log as columns (:func:`iter_log_runs`).

    ``t_s`` [s], ``sensor``, ``tof_us`` [us] (NaN: no echo; a record's None) and
    ``pan_deg`` (None where the record has none), one entry per record, in log order.
    """

    t_s: list[float]
    sensor: list[int]
    tof_us: list[float]
    pan_deg: list[float | None]

    def __len__(self) -> int:
        return len(self.t_s)

    def records(self) -> list[TofRecord]:
        """The :class:`TofRecord` s of the run, in order."""
        return [TofRecord(t, s, None if v != v else v, p) for t, s, v, p in
                zip(self.t_s, self.sensor, self.tof_us, self.pan_deg, strict=True)]


def iter_log(
    source: str | Path | IO[str], stats: LogStats | None = None, strict: bool = False
) -> Iterator[Record]:
    """Yield the records of a log file (path or open text stream), one at a time.

    Memory stays flat whatever the length of the log. Problems go to ``stats``
    (or raise :class:`LogFormatError` naming the line when ``strict``).
    """
    for item in iter_log_runs(source, stats, strict):
        if type(item) is TofRun:
            yield from item.records()
        else:
            yield item  # type: ignore[misc]


def iter_log_runs(
    source: str | Path | IO[str], stats: LogStats | None = None, strict: bool = False
) -> Iterator[Record | TofRun]:
    """:func:`iter_log` with each run of consecutive ``tof`` records (at most 4096)
    yielded as one :class:`TofRun` (columns, no record objects): the same records in
    the same order, the same ``stats`` and errors (a run is yielded before the error of
    the line after it). For readers of whole logs (the batch replay).
    """
    stats = stats if stats is not None else LogStats()
    if isinstance(source, (str, Path)):
        try:
            handle: IO[str] = open(source, encoding="utf-8", errors="replace")  # noqa: SIM115
        except OSError as err:
            raise LogFormatError(f"cannot open log {source}: {err.strerror}") from err
        close = True
    else:
        handle, close = source, False
    last_t = -math.inf
    raw_decode = _DECODER.raw_decode
    tof_line, pose_line = _TOF_LINE.fullmatch, _POSE_LINE.fullmatch
    nan = math.nan
    run_t: list[float] = []
    run_s: list[int] = []
    run_v: list[float] = []
    run_p: list[float | None] = []
    try:
        for lineno, line in enumerate(handle, start=1):
            rec: Record | None = None
            m = tof_line(line)
            if m is not None:
                ts, ss, vs, ps = m.groups()
                t = float(ts)
                v = nan if vs is None else float(vs)
                p = None if ps is None else float(ps)
                # finite (a huge exponent reads as inf: the general path names it)
                if t - t == 0.0 and (vs is None or v - v == 0.0) and \
                        (p is None or p - p == 0.0):
                    if t < last_t:
                        if strict and run_t:
                            stats.records += len(run_t)
                            yield TofRun(run_t, run_s, run_v, run_p)
                            run_t, run_s, run_v, run_p = [], [], [], []
                        _backwards(stats, strict, lineno, last_t, t)
                    else:
                        last_t = t
                    run_t.append(t)
                    run_s.append(int(ss))
                    run_v.append(v)
                    run_p.append(p)
                    if len(run_t) >= _RUN_MAX:
                        stats.records += len(run_t)
                        yield TofRun(run_t, run_s, run_v, run_p)
                        run_t, run_s, run_v, run_p = [], [], [], []
                    continue
            else:
                m = pose_line(line)
                if m is not None:
                    kind, ts, xs, ys, yaws = m.groups()
                    t, x, y, yaw = float(ts), float(xs), float(ys), float(yaws)
                    if t - t == 0.0 and x - x == 0.0 and y - y == 0.0 and yaw - yaw == 0.0:
                        rec = OdomRecord(t, x, y, yaw) if kind == "odom" else \
                            TruthRecord(t, x, y, yaw)
            if run_t:
                stats.records += len(run_t)
                yield TofRun(run_t, run_s, run_v, run_p)
                run_t, run_s, run_v, run_p = [], [], [], []
            if rec is None:
                if not line.strip():
                    continue
                try:
                    try:  # one object from the line's start to its end: json.loads
                        obj, end = raw_decode(line)   # without its wrapper (same object)
                        if end != len(line) and line[end:] != "\n":
                            obj = json.loads(line)
                    except ValueError:
                        obj = json.loads(line)  # the same object, or json's own message
                    if not isinstance(obj, dict):
                        raise ValueError("not a JSON object")
                    rec = record_from_dict(obj)
                # json.JSONDecodeError is a ValueError; a line nested too deeply for
                # json's recursion (a RecursionError) is as malformed
                except (ValueError, RecursionError) as err:
                    msg = str(err).splitlines()[0][:200]
                    if strict:
                        raise LogFormatError(f"line {lineno}: {msg}") from err
                    stats.malformed_count += 1
                    if len(stats.malformed) < stats.MAX_KEPT:
                        stats.malformed.append((lineno, msg))
                    continue
                if rec is None:
                    stats.unknown[str(obj.get("type"))[:40]] += 1
                    continue
            if rec.t_s < last_t:
                _backwards(stats, strict, lineno, last_t, rec.t_s)
            else:
                last_t = rec.t_s
            stats.records += 1
            yield rec
        if run_t:
            stats.records += len(run_t)
            yield TofRun(run_t, run_s, run_v, run_p)
    finally:
        if close:
            handle.close()


def _backwards(stats: LogStats, strict: bool, lineno: int, last_t: float, t: float) -> None:
    """Report a record at ``t`` after one at ``last_t`` (raise when ``strict``)."""
    if strict:
        raise LogFormatError(f"line {lineno}: time went backwards ({t} after {last_t})")
    stats.time_backwards_count += 1
    if len(stats.time_backwards) < stats.MAX_KEPT:
        stats.time_backwards.append((lineno, last_t, t))


class LogWriter:
    """Write records as JSONL to a path or text stream (use as a context manager).

    A file is written in whole lines only: when the disk fills (or a file size limit is
    reached) the lines written so far stay, the partial one is cut off, and the
    ``OSError`` names the file, so a log cut short is still valid up to its last line.
    """

    BUFFER = 1 << 16  # bytes collected before a write to the file

    def __init__(self, target: str | Path | IO[str]):
        self._raw: IO[bytes] | None = None
        self._handle: IO[str] | None = None
        if isinstance(target, (str, Path)):
            self.path = str(target)
            self._raw = open(target, "wb", buffering=0)  # noqa: SIM115
        else:
            self.path = str(getattr(target, "name", "<stream>"))
            self._handle = target
        self._lines: list[str] = []
        self._pending = 0  # characters in _lines
        self._written = 0  # bytes of whole lines in the file
        self._failed: OSError | None = None

    def write(self, rec: Record) -> None:
        line = json.dumps(record_to_dict(rec), separators=(",", ":")) + "\n"
        if self._handle is not None:
            self._handle.write(line)
            return
        self._lines.append(line)
        self._pending += len(line)
        if self._pending >= self.BUFFER:
            self.flush()

    def write_all(self, recs: Iterable[Record]) -> None:
        for rec in recs:
            self.write(rec)

    def flush(self) -> None:
        if self._handle is not None:
            self._handle.flush()
            return
        if self._failed is not None:
            raise self._failed
        if not self._lines or self._raw is None:
            return
        data = "".join(self._lines).encode("utf-8")
        self._lines, self._pending = [], 0
        view, done = memoryview(data), 0
        try:
            while done < len(data):
                done += self._raw.write(view[done:]) or 0
        except OSError as err:
            kept = data.rfind(b"\n", 0, done) + 1  # whole lines only
            try:
                self._raw.truncate(self._written + kept)
            except OSError:
                pass
            self._written += kept
            self._failed = OSError(err.errno, f"cannot write {self.path}: {err.strerror} "
                                              f"(the log is whole up to there)")
            raise self._failed from err
        self._written += len(data)

    def close(self) -> None:
        if self._raw is None:
            if self._handle is not None:
                self._handle.flush()
            return
        try:
            if self._failed is None:
                self.flush()
        finally:
            self._raw.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
