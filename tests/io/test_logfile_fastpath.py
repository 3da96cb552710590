"""The log reader's fast paths (one-call JSON decode of a line, well-formed tof / odom /
truth records without the field-by-field checks) change nothing a reader can see: the
same records, the same malformed lines with the same messages and line numbers, the same
counts of unknown records and time-going-backwards reports, strict or not.

The reference is the reader as it was (``json.loads`` per line, every record through the
checking path), written out here.
"""

from __future__ import annotations

import io
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from io_strategies import odom_records, tof_records

from sonarloc.errors import LogFormatError
from sonarloc.io import logfile
from sonarloc.io.logfile import (
    LogStats,
    LogWriter,
    TofRun,
    TruthRecord,
    iter_log,
    iter_log_runs,
    record_from_dict,
)


def reference_iter(text: str, stats: LogStats, strict: bool = False) -> list:
    """The session-3 ``iter_log`` loop over a text."""
    out = []
    last_t = -math.inf
    for lineno, line in enumerate(io.StringIO(text), start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            if not isinstance(obj, dict):
                raise ValueError("not a JSON object")
            rec = logfile._record_checked(obj, obj.get("type"))
        except ValueError as err:
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
            if strict:
                raise LogFormatError(f"line {lineno}: time went backwards "
                                     f"({rec.t_s} after {last_t})")
            stats.time_backwards_count += 1
            if len(stats.time_backwards) < stats.MAX_KEPT:
                stats.time_backwards.append((lineno, last_t, rec.t_s))
        last_t = max(last_t, rec.t_s)
        stats.records += 1
        out.append(rec)
    return out


def _runs_expanded(text: str, stats: LogStats, strict: bool = False,
                   seen: list | None = None) -> list:
    """iter_log_runs' items with every run as its records (``seen``: the records
    received before an error)."""
    out = [] if seen is None else seen
    for item in iter_log_runs(io.StringIO(text), stats, strict):
        if isinstance(item, TofRun):
            assert 0 < len(item) <= logfile._RUN_MAX
            out += item.records()
        else:
            out.append(item)
    return out


def _same(text: str) -> None:
    want_stats = LogStats()
    want = reference_iter(text, want_stats)
    for reader in (lambda s: list(iter_log(io.StringIO(text), s)),
                   lambda s: _runs_expanded(text, s)):
        got_stats = LogStats()
        got = reader(got_stats)
        assert repr(got) == repr(want)           # repr: NaN fields compare too
        assert vars(got_stats) == vars(want_stats)
    errs, before = [], []
    for fn in (lambda: list(iter_log(io.StringIO(text), strict=True)),
               lambda: _runs_expanded(text, LogStats(), True, before),
               lambda: reference_iter(text, LogStats(), strict=True)):
        try:
            fn()
            errs.append(None)
        except LogFormatError as err:
            errs.append(str(err))
    assert errs[0] == errs[1] == errs[2]
    if errs[2] is not None:   # the records before the bad line all came out first
        line = int(errs[2].split(":")[0].split()[1])
        assert repr(before) == repr(reference_iter(
            "".join(io.StringIO(text).readlines()[:line - 1]), LogStats()))


_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5), st.booleans(),
    st.none(), st.text(max_size=3), st.just([1.0]), st.just({"a": 1}))
_FIELDS = ("type", "t_s", "x_m", "y_m", "yaw_deg", "tof_us", "sensor", "pan_deg", "reset")


@st.composite
def _lines(draw) -> str:
    """Log lines: records as the writer writes them, records with odd field values,
    and damaged text."""
    kind = draw(st.integers(0, 3))
    if kind == 0:
        rec = draw(st.one_of(tof_records(), odom_records(),
                             odom_records().map(lambda r: TruthRecord(r.t_s, r.x_m, r.y_m,
                                                                      r.yaw_deg))))
        buf = io.StringIO()
        LogWriter(buf).write(rec)
        return buf.getvalue()
    if kind == 1:
        obj = {"type": draw(st.sampled_from(["tof", "odom", "truth", "imu", "init", 3]))}
        for name in draw(st.lists(st.sampled_from(_FIELDS[1:]), max_size=7, unique=True)):
            obj[name] = draw(_VALUES)
        return json.dumps(obj) + "\n"
    base = json.dumps({"type": "odom", "t_s": 1.0, "x_m": 0.0, "y_m": 0.0, "yaw_deg": 0.0})
    damage = draw(st.sampled_from([
        lambda s: " " + s, lambda s: s + " x", lambda s: s + s, lambda s: s[:-3],
        lambda s: "\ufeff" + s, lambda s: s + "\x0b", lambda s: s + "\u00a0",
        lambda s: s + "\r", lambda s: s + " \t", lambda s: "[1, 2]", lambda s: "NaN",
        lambda s: "", lambda s: "   ", lambda s: s.replace("1.0", "1e999"),
        lambda s: s.replace("1.0", "NaN"), lambda s: s.replace("0.0", "-Infinity"),
        lambda s: s.replace(":", "", 1), lambda s: "{}", lambda s: s + "{}",
    ]))
    if draw(st.booleans()):   # the canonical tof form (iter_log_runs' regular expression)
        base = draw(st.sampled_from([
            '{"type":"tof","t_s":1.5,"sensor":3,"tof_us":9000.0}',
            '{"type":"tof","t_s":0.5,"sensor":-0,"tof_us":null,"pan_deg":-12.5}',
            '{"type":"tof","t_s":2,"sensor":12345678901234567890,"tof_us":1}',
            '{"type":"tof","t_s":1e-3,"sensor":0,"tof_us":null,"pan_deg":null}']))
        damage = draw(st.sampled_from([
            lambda s: s, lambda s: s.replace("1.5", "1e999"), lambda s: s.replace("0.5", "-0.5"),
            lambda s: s.replace("9000.0", "9e999"), lambda s: s.replace("12.5", "1E400"),
            lambda s: s.replace("3", "03"), lambda s: s.replace("3", "true"),
            lambda s: s.replace("0,", "0.0,"), lambda s: s.replace('"tof_us"', '"tof"'),
            lambda s: s[:-1] + ',"x":1}', lambda s: s.replace("}", "}}")]))
    return damage(base) + draw(st.sampled_from(["\n", "\r\n", ""]))


@settings(max_examples=300, deadline=None)
@given(st.lists(_lines(), max_size=25))
def test_reader_sees_what_the_reference_sees(lines):
    # a line without its newline joins the next one, as in a real file
    _same("".join(lines))


def test_runs_are_bounded_and_split_by_other_records():
    buf = io.StringIO()
    w = LogWriter(buf)
    n = logfile._RUN_MAX + 10
    for i in range(n):
        w.write(logfile.TofRecord(0.001 * i, i % 16, None if i % 3 else 5000.0 + i))
    w.write(logfile.OdomRecord(n * 0.001, 0.0, 0.0, 0.0))
    w.write(logfile.TofRecord(n * 0.001, 2, 7000.0, 15.0))
    stats = LogStats()
    items = list(iter_log_runs(io.StringIO(buf.getvalue()), stats))
    assert [type(i).__name__ for i in items] == ["TofRun", "TofRun", "OdomRecord", "TofRun"]
    assert [len(i) for i in items if isinstance(i, TofRun)] == [logfile._RUN_MAX, 10, 1]
    assert items[-1].records() == [logfile.TofRecord(n * 0.001, 2, 7000.0, 15.0)]
    assert stats.records == n + 2


def test_strict_errors_come_after_the_records_before_them():
    tof = '{"type":"tof","t_s":%s,"sensor":1,"tof_us":null}\n'
    odom = '{"type":"odom","t_s":%s,"x_m":0.0,"y_m":0.0,"yaw_deg":0.0}\n'
    for text in [tof % 1.0 + tof % 2.0 + tof % 1.5,            # backwards inside a run
                 tof % 1.0 + tof % 2.0 + odom % 1.5,           # after a run
                 tof % 1.0 + tof % 2.0 + "{x\n",                # malformed after a run
                 odom % 1.0 + tof % 2.0 + tof % 1e999]:         # not finite
        _same(text)


def test_record_from_dict_fast_path_equals_checked_path():
    for obj in [{"type": "tof", "t_s": 1.0, "sensor": 2, "tof_us": 9000.5},
                {"type": "tof", "t_s": 1.0, "sensor": 2, "tof_us": None},
                {"type": "tof", "t_s": 1.0, "tof_us": 12.0},
                {"type": "odom", "t_s": 0.5, "x_m": -1.0, "y_m": 2.0, "yaw_deg": 370.0},
                {"type": "truth", "t_s": 0.5, "x_m": -1.0, "y_m": 2.0, "yaw_deg": -0.0}]:
        assert record_from_dict(obj) == logfile._record_checked(obj, obj["type"])
    for obj in [{"type": "tof", "t_s": 1.0, "sensor": True, "tof_us": 9.0},
                {"type": "tof", "t_s": math.inf, "sensor": 1, "tof_us": 9.0},
                {"type": "odom", "t_s": 0.5, "x_m": math.nan, "y_m": 2.0, "yaw_deg": 1.0}]:
        with pytest.raises(ValueError) as fast:
            record_from_dict(obj)
        with pytest.raises(ValueError) as checked:
            logfile._record_checked(obj, obj["type"])
        assert str(fast.value) == str(checked.value)
