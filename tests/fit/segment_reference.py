"""The segmenter's per-reading logic as it was before its loop was written out inline
(session 3, sonarloc/fit/segment.py at 06e309f: ``_Open`` and ``Segmenter``, verbatim but
for the docstrings; its arc points and ``mid`` are offsets from the last
echo's transducer position, as the package's, for translation invariance), kept as the reference the fast form must match segment for segment
(tests/fit/test_fit_segment_equivalence.py). Its configuration, result and counter
types are the package's own. Not used by the package."""

# ruff: noqa
# mypy: ignore-errors


from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from sonarloc.fit.segment import Segment, SegmenterConfig, SegmenterStats, _wrap
from sonarloc.io.scancsv import ScanReadings
from sonarloc.physics.tof import ModuleParams

_TWO_PI = 2.0 * math.pi


@dataclass
class _Open:
    seg_id: int
    rows: list[tuple[float, float, float, float, float, int]]
    n_echo: int
    last: tuple[float, float, float, float, float, int]  # last echo (t, x, y, yaw, R, sensor)
    misses: int = 0
    trailing: int = 0       # no-echo readings attached after the last echo
    sensors: set[int] = field(default_factory=set)
    mid: tuple[float, float] = (math.nan, math.nan)   # landmark on the last echo's axis,
    # as arc: offsets from the last echo's transducer position (last[1], last[2])
    arc: list[tuple[float, float]] | None = None      # of ``last`` (cached when needed)
    occluded_lead: bool = False     # the reading before the first echo: a nearer echo
    occluded_trail: bool = False    # the first reading after the last echo: a nearer echo
    first: tuple[float, float] = (math.nan, math.nan)   # where its first echo was taken


class Segmenter:
    """Online segmenter (the only stateful object of ``sonarloc.fit``).

    Examples
    --------
    >>> seg = Segmenter()
    >>> closed = []
    >>> for i in range(40):                      # a pan over a pole at 0 deg, 1.5 m
    ...     yaw = np.deg2rad(-20 + i)
    ...     tof = 8746.0 + 0.67 * np.exp(yaw**2 / (2 * np.deg2rad(5.25)**2))
    ...     closed += seg.push(0.03 * i, 0.0, 0.0, yaw, tof if tof < 8758 else np.nan)
    >>> closed += seg.flush()
    >>> [s.n_echo for s in closed]
    [25]
    """

    def __init__(self, config: SegmenterConfig | None = None,
                 module: ModuleParams | None = None) -> None:
        self.config = config or SegmenterConfig()
        self.module = module or ModuleParams()
        self.stats = SegmenterStats()
        self._open: list[_Open] = []
        self._recent: dict[int, deque[tuple[tuple[float, float, float, float, float, int],
                                            float]]] = {}
        self._next_id = 0
        self._last_t = -math.inf
        cfg = self.config
        self._m_per_us = self.module.c_mps * 0.5e-6
        self._gate_m = cfg.gate_us * self._m_per_us
        self._beam = math.radians(cfg.beam_half_width_deg)
        self._miss = math.radians(cfg.miss_half_width_deg)
        # tan of the miss half-width plus a margin: beyond it, surely not within it
        wide = self._miss + math.radians(0.5)
        self._tan_miss_wide = math.tan(wide) if wide < math.radians(89.0) else math.inf
        self._miss_angle = math.radians(cfg.miss_angle_deg)
        self._arc = [self._beam * k / 3.0 for k in range(-3, 4)]
        self._away = math.inf if cfg.sweep_away_deg is None else \
            math.radians(cfg.sweep_away_deg)

    @property
    def open_segments(self) -> int:
        """Number of segments currently open (the segmenter's memory)."""
        return len(self._open)

    @property
    def open_since_s(self) -> float:
        """Earliest last-echo time of the open segments (inf if none): a segment closed
        later has its last echo (a fit's reference reading) at or after this time, or
        after the latest reading pushed."""
        return min((s.last[0] for s in self._open), default=math.inf)

    def push(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int = 0) -> list[Segment]:
        """Add one reading; returns the segments this reading closed (often none).

        ``tof_us`` NaN means no echo; inf, zero or negative TOFs and non-finite poses are
        counted as bad and ignored, as are readings older than the previous one.
        """
        return self._push(float(t_s), float(x_m), float(y_m), float(yaw_rad), float(tof_us),
                          int(sensor))

    def _push(self, t: float, x: float, y: float, yaw: float, tof: float, sensor: int
              ) -> list[Segment]:
        """:meth:`push` of Python floats and an int."""
        st = self.stats
        st.readings += 1
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)
                and math.isfinite(yaw)) or math.isinf(tof) or tof <= 0.0:
            st.bad += 1
            return []
        if t < self._last_t:
            st.out_of_order += 1
            return []
        self._last_t = t
        yaw = _wrap(yaw)
        closed: list[Segment] = []
        # time gaps close segments first, then a panning beam that has moved on
        for s in [s for s in self._open if t - s.last[0] > self.config.max_gap_s]:
            closed += self._close(s, "gap")
        if self._away < math.inf:
            for s in [s for s in self._open if sensor in s.sensors
                      and self._off_axis(s, x, y, yaw) > self._away]:
                closed += self._close(s, "swept")
        echo = not math.isnan(tof)
        row = (t, x, y, yaw, tof, sensor)
        if echo:
            st.echoes += 1
            R = (tof - 0.5 * self.module.count_period_us) * self._m_per_us
            best, best_score = None, math.inf
            for s in self._open:
                score = self._match(s, x, y, yaw, R)
                if score < best_score:
                    best, best_score = s, score
            miss, wide = self._miss, self._tan_miss_wide
            cy, sy = math.cos(yaw), math.sin(yaw)
            for s in list(self._open):
                if s is best:
                    continue
                # cheap test first: a landmark well off the axis is neither missed nor
                # censored (the exact angle is only needed near the miss half-width)
                dx, dy = (s.last[1] - x) + s.mid[0], (s.last[2] - y) + s.mid[1]
                along = dx * cy + dy * sy
                if wide < math.inf and (along <= 0.0 or abs(dy * cy - dx * sy) > wide * along):
                    continue
                off = self._off_axis(s, x, y, yaw)
                if off <= miss:
                    # an echo this segment matches too may be its own landmark's: neither
                    # a nearer reflector answering nor a farther one winning
                    other = self._match(s, x, y, yaw, R) == math.inf
                    if (other and R < s.last[4] - self._gate_m and s.trailing == 0
                            and s.misses == 0 and sensor == s.last[5]):
                        s.occluded_trail = True   # a nearer reflector answered right after
                    # a farther echo won: this landmark was not detected (censor)
                    if (other and R > s.last[4] + self._gate_m and sensor in s.sensors
                            and s.trailing < self.config.censor_window):
                        s.rows.append((t, x, y, yaw, math.nan, sensor))
                        s.trailing += 1
                    s.misses += 1
                    if self._gone(s, off):
                        closed += self._close(s, "misses")
            if self.config.censor_window:
                self._remember(row, R)
            # (session 13) an echo too far from the segment's first closes it and opens
            # the next
            cut = best is not None and self._travelled(best, x, y)
            if cut:
                assert best is not None
                closed += self._close(best, "travel")
                best = None
            if best is not None:
                best.rows.append(row)
                best.n_echo += 1
                best.last = (t, x, y, yaw, R, sensor)
                best.mid = self._mid_point(best)
                best.arc = None
                best.misses = 0
                best.trailing = 0
                best.occluded_trail = False
                best.sensors.add(sensor)
                if len(best.rows) >= self.config.max_readings:
                    closed += self._close(best, "full")
            else:
                closed += self._start(row, R, cut)
        else:
            st.no_echo += 1
            wide = self._tan_miss_wide
            cy, sy = math.cos(yaw), math.sin(yaw)
            for s in list(self._open):
                dx, dy = (s.last[1] - x) + s.mid[0], (s.last[2] - y) + s.mid[1]
                along = dx * cy + dy * sy
                if wide < math.inf and (along <= 0.0 or abs(dy * cy - dx * sy) > wide * along):
                    continue
                off = self._off_axis(s, x, y, yaw)
                if off <= self._miss:
                    if sensor in s.sensors and s.trailing < self.config.censor_window:
                        s.rows.append(row)
                        s.trailing += 1
                    s.misses += 1
                    if self._gone(s, off):
                        closed += self._close(s, "misses")
            if self.config.censor_window:
                self._remember(row, math.inf)
        return closed

    def flush(self) -> list[Segment]:
        """Close every open segment (end of stream)."""
        closed: list[Segment] = []
        for s in list(self._open):
            closed += self._close(s, "flush")
        return closed

    def feed(self, scan: ScanReadings) -> Iterator[Segment]:
        """Push every reading of ``scan`` in order, then flush; yields closed segments."""
        cols = (scan.t_s.tolist(), scan.x_m.tolist(), scan.y_m.tolist(),
                scan.yaw_rad.tolist(), scan.tof_us.tolist(), scan.sensor.tolist())
        push = self._push
        for t, x, y, yaw, tof, sensor in zip(*cols, strict=True):
            closed = push(t, x, y, yaw, tof, sensor)
            if closed:
                yield from closed
        yield from self.flush()

    # -- internals -------------------------------------------------------------------

    def _remember(self, row: tuple[float, float, float, float, float, int], R: float) -> None:
        sensor = row[5]
        dq = self._recent.get(sensor)
        if dq is None:
            dq = self._recent[sensor] = deque(maxlen=self.config.censor_window)
        dq.append((row, R))

    def _arc_points(self, s: _Open) -> list[tuple[float, float]]:
        _, _, _, lyaw, lR, _ = s.last
        return [(lR * math.cos(lyaw + a), lR * math.sin(lyaw + a)) for a in self._arc]

    @staticmethod
    def _mid_point(s: _Open) -> tuple[float, float]:
        """The middle of :meth:`_arc_points` (the landmark on the last echo's beam axis)."""
        _, _, _, lyaw, lR, _ = s.last
        return lR * math.cos(lyaw + 0.0), lR * math.sin(lyaw + 0.0)

    def _travelled(self, s: _Open, x: float, y: float) -> bool:
        """Whether (x, y) is more than ``max_travel_m`` from where ``s``'s first echo was
        taken (0 or inf: never)."""
        cap = self.config.max_travel_m
        if not 0.0 < cap < math.inf:
            return False
        return (x - s.first[0]) ** 2 + (y - s.first[1]) ** 2 > cap ** 2

    def _match(self, s: _Open, x: float, y: float, yaw: float, R: float) -> float:
        """Normalised range mismatch of an echo with segment ``s`` (inf: no match)."""
        _, lx, ly, lyaw, lR, _ = s.last
        gate = self._gate_m
        if x == lx and y == ly:   # same spot (pan): the landmark stays at range lR
            if abs(_wrap(yaw - lyaw)) > 2.0 * self._beam:
                return math.inf
            d = abs(R - lR)
            return d / gate if d <= gate else math.inf
        # every arc point lies lR from the last transducer position, so its distance
        # from this one is within lR ± that shift: no point can match a range outside
        shift = math.hypot(x - lx, y - ly)
        if abs(R - lR) > shift + gate + 1e-9 * (1.0 + lR + R):
            return math.inf
        best = math.inf
        beam = self._beam
        if s.arc is None:
            s.arc = self._arc_points(s)
        for px, py in s.arc:
            dx, dy = (lx - x) + px, (ly - y) + py
            a = math.atan2(dy, dx) - yaw
            if abs(a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)) > beam:
                continue
            d = abs(math.hypot(dx, dy) - R)
            if d < best:
                best = d
        return best / gate if best <= gate else math.inf

    def _off_axis(self, s: _Open, x: float, y: float, yaw: float) -> float:
        """Off-axis angle [rad] of ``s``'s last seen landmark for a reading at (x, y, yaw)."""
        px, py = s.mid   # the arc's middle point: the beam axis of the last echo
        a = math.atan2((s.last[2] - y) + py, (s.last[1] - x) + px) - yaw
        return abs(a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI))

    def _gone(self, s: _Open, off: float) -> bool:
        """The landmark has left the beam: enough misses, and the beam has moved on by
        ``miss_angle_deg`` (a strong reflector's null before its side lobe is bridged),
        or a great many misses (a beam standing still)."""
        lim = self.config.miss_limit
        return (s.misses >= lim and off >= self._miss_angle) or s.misses >= 4 * lim

    def _start(self, row: tuple[float, float, float, float, float, int], R: float,
               cut: bool = False) -> list[Segment]:
        """Open a segment with the echo ``row``; ``cut``: the next piece of a pass whose
        segment this echo closed by travel (no lead rows, not occluded: the sensor's
        earlier readings are that piece's own echoes)."""
        t, x, y, yaw, _, sensor = row
        closed: list[Segment] = []
        if len(self._open) >= self.config.max_open:
            closed += self._close(min(self._open, key=lambda s: s.last[0]), "crowded")
        lead: list[tuple[float, float, float, float, float, int]] = []
        dq = None if cut else self._recent.get(sensor)
        if dq:
            # earlier readings of this sensor that saw nothing here: no echo, or a
            # farther echo won (the first crossing would have been this landmark's)
            for r, r_range in dq:
                if (r is not row and t - r[0] <= self.config.max_gap_s
                        and abs(_wrap(r[3] - yaw)) <= 2.0 * self._beam
                        and r_range > R + self._gate_m):
                    lead.append((r[0], r[1], r[2], r[3], math.nan, r[5]))
        s = _Open(self._next_id, lead + [row], 1, (t, x, y, yaw, R, sensor), sensors={sensor},
                  first=(x, y))
        # the reading of this sensor just before: a nearer echo there hid this landmark
        prev = [(r, rr) for r, rr in dq if r is not row] if dq else []
        if prev:
            r, r_range = prev[-1]
            s.occluded_lead = (t - r[0] <= self.config.max_gap_s
                               and abs(_wrap(r[3] - yaw)) <= 2.0 * self._beam
                               and r_range < R - self._gate_m)
        s.mid = self._mid_point(s)
        self._next_id += 1
        self._open.append(s)
        return closed

    def _close(self, s: _Open, why: str) -> list[Segment]:
        if s not in self._open:
            return []
        self._open.remove(s)
        if s.n_echo < self.config.min_echoes:
            self.stats.spikes += s.n_echo
            return []
        cols = list(zip(*s.rows, strict=True))
        readings = ScanReadings(
            np.asarray(cols[0], dtype=float), np.asarray(cols[1], dtype=float),
            np.asarray(cols[2], dtype=float), np.asarray(cols[3], dtype=float),
            np.asarray(cols[4], dtype=float), np.asarray(cols[5], dtype=np.int64))
        self.stats.segments += 1
        return [Segment(readings, s.seg_id, why, (s.occluded_lead, s.occluded_trail))]
