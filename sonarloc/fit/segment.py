"""Online segmentation: readings in, one segment per landmark pass out.

Readings arrive one at a time with the pose of the transducer that took them (any
fixed 2-D frame: ``odom`` for a robot, the scan frame for a pan). The segmenter
keeps only its *open* segments (plus a few recent no-echo readings per sensor) and
returns each segment as soon as its landmark has left the beam, so its memory is
bounded whatever the length of the stream.

Association of an echo with an open segment (the one that explains it best):

* **time**: at most ``max_gap_s`` after the segment's last echo;
* **direction**: the landmark of the segment lies, as seen from its last echo, on the
  arc of radius R_last within +-``beam_half_width_deg`` of that echo's beam axis; some
  point of that arc must also lie within +-``beam_half_width_deg`` of the new beam
  axis (this joins ring transducers seeing the same landmark and survives bearing
  wrap at +-180 deg, since only wrapped differences are used);
* **range**: the new range must match the distance from the new transducer position
  to one of those arc points within ``gate_us`` (jitter, threshold delay growth,
  ripple jumps). Motion of the transducer is accounted for by that distance. The arc
  is 7 points spaced ``beam_half_width_deg / 3`` apart, on purpose: the exact match
  over the continuous arc (tried twice, the second with ``max_travel_m``; docs/history/
  FITTING.md) joins more ring neighbours' echoes into one segment (fewer
  duplicate segments of a landmark) but the fit passes fewer of the merged segments
  (fewer ``OK`` landmarks, accuracy no better; docs/FITTING.md).

A reading that covers a segment's last seen landmark direction (within
``miss_half_width_deg``) without being associated with it is a *miss*; ``miss_limit``
consecutive misses, with the beam turned at least ``miss_angle_deg`` away from that
direction, close the segment (the landmark has left the beam or is hidden).
Isolated readings (spikes, cross-talk) open segments that never reach ``min_echoes``
and are dropped, counted in :class:`SegmenterStats`. Readings next to a segment (same
sensor, up to ``censor_window`` on each side) that show its landmark was *not*
detected are attached to it with a NaN TOF: no-echo readings, and echoes from farther
away (the module reports the first crossing, so a farther echo wins only if the
nearer landmark stayed below threshold). They bound the arc in the fit.

Readings known in advance go through :meth:`Segmenter.push_many` (and
:meth:`Segmenter.feed`): the same segments and counters as :meth:`Segmenter.push` one
reading at a time, with the arithmetic of a chunk in numpy and Python per reading only
where a decision is open.
"""

from __future__ import annotations

import math
from array import array
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import overload

import numpy as np
from numpy.typing import ArrayLike

from sonarloc.io.scancsv import ScanReadings
from sonarloc.physics.tof import ModuleParams

_TWO_PI = 2.0 * math.pi
_LIST_MAX = 4096    # push_many's columns as lists up to this many readings (_floats)
_SKIP_LAGS = 16     # push_many: pairs of a reading and its 16 previous tested in numpy
_SKIP_MIN = 256     # ... in chunks of at least this many readings
_NO_INDEX = -(1 << 62)   # _Open.k of a last echo outside the current chunk


def _wrap(a: float) -> float:
    return a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)


def _wrap_array(a: np.ndarray) -> np.ndarray:
    """:func:`_wrap` of an array, in the same float operations (the same bits)."""
    return a - _TWO_PI * np.floor((a + math.pi) / _TWO_PI)


@dataclass(frozen=True)
class SegmenterConfig:
    """Settings of :class:`Segmenter` (angles in degrees, times in seconds).

    Attributes
    ----------
    gate_us : TOF mismatch allowed for an echo of the same landmark, beyond what the
        transducer's motion explains (jitter, delay growth towards the arc edges,
        half-period ripple jumps).
    beam_half_width_deg : off-axis angle within which a landmark may echo.
    miss_half_width_deg : a reading whose axis points within this angle of a segment's
        last seen landmark, and does not echo from it, counts as a miss.
    miss_limit : consecutive misses that close a segment, once the beam points at least
        ``miss_angle_deg`` away from the landmark's last seen direction (so a strong
        reflector's null between main and side lobe does not split it); 4 x
        ``miss_limit`` misses close it anyway.
    max_gap_s : longest time without an echo inside one segment.
    min_echoes : segments with fewer echoes are dropped as spikes.
    max_readings : a segment is closed (and fitted) when it holds this many readings.
    censor_window : no-echo readings kept on each side of a segment.
    max_open : most segments open at once (the oldest is closed beyond).
    sweep_away_deg : a reading of one of a segment's transducers whose axis points more
        than this from the segment's last echo axis closes it (``"swept"``): a panning
        transducer has swept past the landmark, and its next pass is a new segment.
        The landmark lies within ``beam_half_width_deg`` of that axis, so twice that
        is safe. None (default): never; fixed transducers keep pointing where they
        did, and a landmark leaving one of them may enter its neighbour's beam.
    max_travel_m : an echo taken more than this far from where the segment's first
        echo was taken closes the segment (``"travel"``) and opens the next one: the
        odometry's error grows with the distance travelled, and within a longer pass
        the readings' relative poses are too far off for one fit. A pan (transducer
        standing still) never travels. 0 or inf: no limit.
    """

    gate_us: float = 40.0
    beam_half_width_deg: float = 25.0
    miss_half_width_deg: float = 10.0
    miss_limit: int = 4
    miss_angle_deg: float = 5.0
    max_gap_s: float = 2.0
    min_echoes: int = 3
    max_readings: int = 400
    censor_window: int = 8
    max_open: int = 64
    sweep_away_deg: float | None = None
    max_travel_m: float = 1.0

    def __post_init__(self) -> None:
        for name in ("gate_us", "beam_half_width_deg", "miss_half_width_deg", "max_gap_s",
                     "miss_angle_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        for name in ("miss_limit", "min_echoes", "max_readings", "max_open"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"`{name}` must be a positive integer, got {v!r}")
        if not (isinstance(self.censor_window, int) and self.censor_window >= 0):
            raise ValueError(f"`censor_window` must be a non-negative integer, "
                             f"got {self.censor_window!r}")
        if self.sweep_away_deg is not None and not (
                math.isfinite(self.sweep_away_deg) and self.sweep_away_deg > 0):
            raise ValueError(f"`sweep_away_deg` must be positive or None, "
                             f"got {self.sweep_away_deg!r}")
        if not self.max_travel_m >= 0.0:
            raise ValueError(f"`max_travel_m` must be non-negative (0 or inf: no limit), "
                             f"got {self.max_travel_m!r}")
        if self.max_readings < self.min_echoes:
            raise ValueError(f"`max_readings` ({self.max_readings}) must be at least "
                             f"`min_echoes` ({self.min_echoes})")


@dataclass(frozen=True)
class Segment:
    """The readings of one landmark pass, in arrival order.

    ``readings`` holds its echoes and the no-echo readings that bound it (NaN TOF);
    ``occluded`` says which ends of the arc a nearer echo hid.
    ``closed_by``: ``"misses"`` (left the beam or hidden), ``"gap"`` (time gap),
    ``"full"`` (``max_readings``), ``"crowded"`` (``max_open``), ``"swept"`` (a panning
    beam has moved on, ``sweep_away_deg``), ``"travel"`` (the next echo was taken more
    than ``max_travel_m`` from the first; it opened the next segment) or ``"flush"``
    (end of stream). ``seg_id``
    counts segments from 0 in the order they were opened.
    """

    readings: ScanReadings
    seg_id: int
    closed_by: str
    occluded: tuple[bool, bool] = (False, False)
    """Whether the (first, last) edge of the arc was hidden by a nearer echo: the
    reading of the same transducer just before the first echo / just after the last one
    pointed at the landmark but a nearer reflector answered, so the arc's end there
    says nothing about this landmark's strength."""

    @property
    def n_echo(self) -> int:
        return int(np.isfinite(self.readings.tof_us).sum())

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(t_s, x_m, y_m, yaw_rad, tof_us)``, the form :func:`pack_segments` takes."""
        r = self.readings
        return r.t_s, r.x_m, r.y_m, r.yaw_rad, r.tof_us


class SegmentBlock(Sequence[Segment]):
    """Segments stored end to end: one set of reading columns for all of them.

    ``readings`` holds every segment's readings in order, segment ``k``'s at
    ``bounds[k]:bounds[k + 1]``; ``seg_id``, ``closed_by`` and ``occluded`` are the
    segments' fields. Indexing gives segment ``k`` as a :class:`Segment` (its readings
    views into the block), built when asked for, so a scan's thousands of segments
    reach the fitter (:func:`sonarloc.fit.landmarks.fit_segments`) without an object
    each.
    """

    def __init__(self, readings: ScanReadings, bounds: Sequence[int], seg_id: list[int],
                 closed_by: list[str], occluded: list[tuple[bool, bool]]) -> None:
        n = len(seg_id)
        if not (len(bounds) == n + 1 and len(closed_by) == n and len(occluded) == n
                and bounds[0] == 0 and bounds[-1] == len(readings)):
            raise ValueError(f"`bounds` ({len(bounds)}), `closed_by` ({len(closed_by)}) "
                             f"and `occluded` ({len(occluded)}) do not fit {n} segments "
                             f"of {len(readings)} readings")
        self.readings = readings
        self.bounds = list(bounds)
        self.seg_id = seg_id
        self.closed_by = closed_by
        self.occluded = occluded

    @classmethod
    def of(cls, segments: Sequence[Segment]) -> SegmentBlock:
        """The block of ``segments`` (their readings copied end to end)."""
        bounds = np.cumsum([0] + [len(s.readings) for s in segments]).tolist()
        return cls(ScanReadings.concat([s.readings for s in segments]), bounds,
                   [s.seg_id for s in segments], [s.closed_by for s in segments],
                   [s.occluded for s in segments])

    @classmethod
    def join(cls, blocks: Sequence[SegmentBlock]) -> SegmentBlock:
        """One block of the segments of ``blocks``, in order."""
        bounds, base = [0], 0
        for b in blocks:
            bounds += [base + k for k in b.bounds[1:]]
            base += b.bounds[-1]
        return cls(ScanReadings.concat([b.readings for b in blocks]), bounds,
                   [k for b in blocks for k in b.seg_id],
                   [w for b in blocks for w in b.closed_by],
                   [o for b in blocks for o in b.occluded])

    def __len__(self) -> int:
        return len(self.seg_id)

    def __iter__(self) -> Iterator[Segment]:
        return (self[k] for k in range(len(self.seg_id)))

    @overload
    def __getitem__(self, k: int) -> Segment: ...

    @overload
    def __getitem__(self, k: slice) -> list[Segment]: ...

    def __getitem__(self, k: int | slice) -> Segment | list[Segment]:
        if isinstance(k, slice):
            return [self[j] for j in range(*k.indices(len(self)))]
        n = len(self.seg_id)
        if not -n <= k < n:
            raise IndexError(f"segment {k} of a block of {n}")
        k %= n
        return Segment(self.readings.select(slice(self.bounds[k], self.bounds[k + 1])),
                       self.seg_id[k], self.closed_by[k], self.occluded[k])


#: Largest TOF [us] and transducer coordinate [m] taken as data: beyond them a reading
#: is bad input (counted, ignored), not an echo 17 km away or a robot past the Moon.
#: Their squares and products stay far inside float64 (and float32 for the offsets the
#: fitter uses); a corrupt log's 1e300 us reading used to overflow the fit to NaN and
#: crash a table lookup on a moving ring's segment.
MAX_TOF_US = 1e8
MAX_COORD_M = 1e9


def usable(t: ArrayLike, x: ArrayLike, y: ArrayLike, yaw: ArrayLike, tof: ArrayLike
           ) -> np.ndarray:
    """Readings the segmenter and the fitter take: finite time and pose, coordinates
    within :data:`MAX_COORD_M`, TOF NaN (no echo) or in (0, :data:`MAX_TOF_US`]."""
    tof = np.asarray(tof, dtype=float)
    ok = (np.isfinite(t) & np.isfinite(yaw) & (np.abs(x) <= MAX_COORD_M)
          & (np.abs(y) <= MAX_COORD_M))
    return ok & (np.isnan(tof) | ((tof > 0.0) & (tof <= MAX_TOF_US)))


@dataclass
class SegmenterStats:
    """Counters of what the segmenter saw and dropped."""

    readings: int = 0
    echoes: int = 0
    no_echo: int = 0
    bad: int = 0            # non-finite or absurd pose or TOF (:func:`usable`)
    out_of_order: int = 0   # time went backwards
    spikes: int = 0         # echoes in segments dropped for having < min_echoes
    segments: int = 0       # segments returned


_Row = tuple[float, float, float, float, float, int] | int
"""A segment's reading: (t, x, y, yaw, tof, sensor), or in push_many an index into its
chunk (``~i``: reading i without its echo)."""


@dataclass(eq=False)   # identity: `in` / `remove` on the open list
class _Open:
    seg_id: int
    rows: list[_Row]
    n_echo: int
    last: tuple[float, float, float, float, float, int]  # last echo (t, x, y, yaw, R, sensor)
    misses: int = 0
    trailing: int = 0       # no-echo readings attached after the last echo
    sensors: set[int] = field(default_factory=set)
    # the landmark on the last echo's axis, and the arc's points (cached when needed),
    # as offsets from the last echo's transducer position (last[1], last[2]): a
    # reading's offset from them is (lx - x) + mid, the same in any frame (the
    # absolute point, x ~ 5e5 m in UTM, would round to 1e-10 m and move the knife-edge
    # tests of the miss angle; docs/FITTING.md "Numerics")
    mid: tuple[float, float] = (math.nan, math.nan)
    arc: list[tuple[float, float]] | None = None
    occluded_lead: bool = False     # the reading before the first echo: a nearer echo
    occluded_trail: bool = False    # the first reading after the last echo: a nearer echo
    first: tuple[float, float] = (math.nan, math.nan)   # where its first echo was taken
    k: int = _NO_INDEX      # push_many: the index of its last echo in the chunk


class _RecentIndex:
    """The readings of a chunk grouped by sensor: ``by_sensor[c]`` the indices of
    sensor ``c``'s readings in order, ``rank[i]`` the position of reading ``i`` there."""

    def __init__(self, sensor: np.ndarray) -> None:
        self.rank: Sequence[int]
        self.by_sensor: dict[int, Sequence[int]]
        # numpy forms: rank, and the k-th earlier reading of the same sensor of reading
        # i is ``order[place[i] - k]`` (None for one sensor: it is i - k)
        self.rank_np: np.ndarray
        self.order: np.ndarray | None = None
        self.place: np.ndarray | None = None
        if sensor[0] == sensor[-1] and not (sensor != sensor[0]).any():   # one sensor
            self.rank = range(len(sensor))
            self.by_sensor = {int(sensor[0]): self.rank}
            self.rank_np = np.arange(len(sensor))
            return
        order = np.argsort(sensor, kind="stable")
        starts = np.flatnonzero(np.r_[True, sensor[order][1:] != sensor[order][:-1]])
        ends = np.r_[starts[1:], len(order)]
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order)) - np.repeat(starts, ends - starts)
        self.rank = _ints(rank)
        self.rank_np, self.order = rank, order
        self.place = np.empty(len(order), dtype=np.int64)
        self.place[order] = np.arange(len(order))
        self.by_sensor = {
            int(sensor[order[a]]): _ints(order[a:b])
            for a, b in zip(starts.tolist(), ends.tolist(), strict=True)}


def _floats(a: np.ndarray) -> Sequence[float]:
    """The values of ``a`` (float64) as Python floats, indexed like a list: a list for a
    few readings (the fastest to index), an ``array.array`` for more: one block of
    memory that the garbage collector does not traverse (lists of a chunk's 65536
    floats cost milliseconds at each collection that sees them)."""
    if len(a) <= _LIST_MAX:
        return a.tolist()
    return array("d", np.ascontiguousarray(a, dtype=np.float64).tobytes())


def _ints(a: np.ndarray) -> Sequence[int]:
    """:func:`_floats` of integers (int64 values; bools as 0 / 1)."""
    if len(a) <= _LIST_MAX:
        return np.asarray(a, dtype=np.int64).tolist()
    return array("q", np.ascontiguousarray(a, dtype=np.int64).tobytes())


def _mids(yaw: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``mid`` of :class:`_Open` for echoes at (yaw, R) (offsets from their
    transducers): math's cos and sin, so the same bits as :meth:`Segmenter._step`."""
    a = (yaw + 0.0).tolist()
    return R * np.array(list(map(math.cos, a))), R * np.array(list(map(math.sin, a)))


class _Chunk:
    """The accepted readings of one :meth:`Segmenter.push_many` chunk: arrays (wrapped
    yaw, range R, inf without an echo) and the same as Python lists. A segment's
    ``rows`` hold indices into it while it is current (``~i``: reading i without its
    echo)."""

    def __init__(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                 tof: np.ndarray, sensor: np.ndarray, R: np.ndarray) -> None:
        self.m = len(t)
        self.t, self.x, self.y, self.yaw, self.R, self.sensor = t, x, y, yaw, R, sensor
        self.echo = R < np.inf
        self.cols = np.stack([t, x, y, yaw, tof])          # (5, m)
        self.tl, self.xl, self.yl, self.yawl, self.tofl, self.Rl = (
            _floats(a) for a in (t, x, y, yaw, tof, R))
        self.sl = _ints(sensor)
        self.at = 0      # the reading being handled
        self.closed: list[tuple[int, _Open, str]] = []    # (at, segment, closed_by)

    def row_of(self, r: int) -> tuple[float, float, float, float, float, int]:
        """The row tuple of index ``r`` (``~i``: reading i with a NaN TOF)."""
        i = r if r >= 0 else ~r
        return (self.tl[i], self.xl[i], self.yl[i], self.yawl[i],
                self.tofl[i] if r >= 0 else math.nan, self.sl[i])

    def block(self) -> SegmentBlock:
        """The segments closed in this chunk (``closed``), built together: their rows
        (indices, and tuples from before the chunk) taken from the chunk's columns in
        one go."""
        flat: list[int] = []
        extra: list[tuple[float, float, float, float, float, int]] = []
        ends: list[int] = [0]
        for _, s, _ in self.closed:
            rows = s.rows
            if type(rows[0]) is int:   # all indices (tuples from before come first)
                flat += rows               # type: ignore[arg-type]
            else:
                for r in rows:
                    if isinstance(r, int):
                        flat.append(r)
                    else:
                        flat.append(self.m + len(extra))
                        extra.append(r)
            ends.append(len(flat))
        i = np.fromiter(flat, dtype=np.int64, count=len(flat))
        bare = i < 0
        i[bare] = ~i[bare]
        cols, sensor = self.cols, self.sensor
        if extra:
            more = np.array([r[:5] for r in extra], dtype=float).T
            cols = np.concatenate([cols, more], axis=1)
            # the ids apart: through float64 an id beyond 2**53 would change (and one
            # near 2**63 overflow), splitting a segment's readings between two sensors
            sensor = np.concatenate([sensor, np.array([r[5] for r in extra], dtype=np.int64)])
        v = np.take(cols, i, axis=1)      # (a third of the time of cols[:, i])
        v[4, bare] = np.nan
        t, x, y, yaw, tof = v
        return SegmentBlock(ScanReadings(t, x, y, yaw, tof, np.take(sensor, i)), ends,
                            [s.seg_id for _, s, _ in self.closed],
                            [why for _, _, why in self.closed],
                            [(s.occluded_lead, s.occluded_trail) for _, s, _ in self.closed])


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
        self._max_gap = cfg.max_gap_s
        self._censor = cfg.censor_window
        self._max_readings = cfg.max_readings
        # squared, compared with the squared distance (inf: no limit)
        self._travel2 = cfg.max_travel_m ** 2 if cfg.max_travel_m > 0.0 else math.inf
        # set when a segment was just closed by travel: the echo that closed it opens the
        # next piece of the same pass (:meth:`_open_next`)
        self._cut = False
        self._half_count_us = 0.5 * self.module.count_period_us
        # at most the earliest last echo of the open segments (a lower bound kept
        # cheaply: last echoes only move forward): no gap can close one before
        # ``max_gap_s`` after it
        self._oldest_last = math.inf
        self._chunk: _Chunk | None = None      # push_many's current chunk
        # _step's settings in one tuple: tan of the miss test's width with a margin,
        # whether that cheap pre-test applies, the miss half-width, the gate [m], the beam
        # half-width and twice it
        self._consts = (self._tan_miss_wide, self._tan_miss_wide < math.inf, self._miss,
                        self._gate_m, self._beam, 2.0 * self._beam)

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

        ``tof_us`` NaN means no echo; inf, zero, negative or absurd TOFs and non-finite
        or absurd poses (:func:`usable`) are counted as bad and ignored, as are readings
        older than the previous one. A ``sensor`` id beyond int64 raises ``ValueError``
        (a bad argument, as in :class:`~sonarloc.io.scancsv.ScanReadings`).
        """
        sensor = int(sensor)
        if not -(1 << 63) <= sensor < (1 << 63):   # ScanReadings keeps ids as int64
            raise ValueError(f"`sensor` must be a 64-bit integer, got {sensor!r}")
        return self._push(float(t_s), float(x_m), float(y_m), float(yaw_rad), float(tof_us),
                          sensor)

    def _push(self, t: float, x: float, y: float, yaw: float, tof: float, sensor: int
              ) -> list[Segment]:
        """:meth:`push` of Python floats and an int: the checks and counters of one
        reading, then :meth:`_step`."""
        st = self.stats
        st.readings += 1
        if not (math.isfinite(t) and math.isfinite(yaw) and abs(x) <= MAX_COORD_M
                and abs(y) <= MAX_COORD_M) or tof <= 0.0 or tof > MAX_TOF_US:
            st.bad += 1   # as usable(): NaN passes both TOF tests (no echo)
            return []
        if t < self._last_t:
            st.out_of_order += 1
            return []
        self._last_t = t
        yaw = yaw - _TWO_PI * math.floor((yaw + math.pi) / _TWO_PI)
        if math.isnan(tof):
            st.no_echo += 1
            R = math.inf
        else:
            st.echoes += 1
            R = (tof - self._half_count_us) * self._m_per_us
        row = (t, x, y, yaw, tof, sensor)
        closed, best = self._step(row, R, row)
        if self._censor:
            self._remember(row, R)
        if best is None and R < math.inf:
            if self._cut:
                return closed + self._open_next(row, R, row)
            dq = self._recent.get(sensor)
            prev = [(r[0], r[3], r_range, (r[0], r[1], r[2], r[3], math.nan, r[5]))
                    for r, r_range in dq if r is not row] if dq else []
            closed += self._start(row, R, prev, row)
        return closed

    def push_many(self, t_s: ArrayLike, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                  tof_us: ArrayLike, sensor: ArrayLike | None = None,
                  chunk: int = 65536) -> list[tuple[int, Segment]]:
        """Add many readings at once: the same segments and counters as :meth:`push` of
        each in turn, faster.

        Parameters
        ----------
        t_s, x_m, y_m, yaw_rad, tof_us : (n,) readings in arrival order (as :meth:`push`).
        sensor : (n,) transducer ids (None: all 0).
        chunk : readings handled together at most (bounds the temporary arrays; the
            segmenter itself keeps only its open segments between chunks).

        Returns
        -------
        The segments closed, in order, each with the index (into the arrays) of the
        reading that closed it.

        The checks, counters, wrapped axes and ranges of all readings are computed in
        numpy; the per-reading decisions run through the same :meth:`_step` as
        :meth:`push`, except where the outcome is known in advance: readings without an
        echo while no segment is open change nothing, a run of echoes from the same
        spot each matching the previous one extends the only open segment (a panning
        transducer crossing a landmark) in one go, a run of no-echo readings while one
        segment is open takes a loop for that segment alone (its misses), a new
        segment's lead readings come from numpy tests of the chunk's candidate echoes,
        and the open segments whose last echo is one of a reading's 16 previous are
        passed over where numpy tests of the two readings show they surely neither
        match nor miss (a moving ring's transducers pointing elsewhere).
        """
        closed: list[tuple[int, Segment]] = []
        for at, block in self._push_blocks(t_s, x_m, y_m, yaw_rad, tof_us, sensor, chunk):
            closed += zip(at, block, strict=True)
        return closed

    def _push_blocks(self, t_s: ArrayLike, x_m: ArrayLike, y_m: ArrayLike,
                     yaw_rad: ArrayLike, tof_us: ArrayLike, sensor: ArrayLike | None,
                     chunk: int) -> list[tuple[list[int], SegmentBlock]]:
        """:meth:`push_many`, the segments each chunk closed in a block, with the indices
        of the readings that closed them."""
        cols = [np.asarray(a, dtype=float).ravel() for a in (t_s, x_m, y_m, yaw_rad, tof_us)]
        n = len(cols[0])
        sens = np.zeros(n, dtype=np.int64) if sensor is None else \
            np.asarray(sensor).astype(np.int64).ravel()
        for name, a in zip(("x_m", "y_m", "yaw_rad", "tof_us", "sensor"), [*cols[1:], sens],
                           strict=True):
            if len(a) != n:
                raise ValueError(f"`{name}` has length {len(a)}, expected {n}")
        if not (isinstance(chunk, int) and chunk >= 1):
            raise ValueError(f"`chunk` must be a positive integer, got {chunk!r}")
        out = []
        for lo in range(0, n, chunk):
            hi = min(lo + chunk, n)
            t, x, y, yaw, tof = (a[lo:hi] for a in cols)
            out.append(self._push_chunk(t, x, y, yaw, tof, sens[lo:hi], lo))
        return out

    def flush(self) -> list[Segment]:
        """Close every open segment (end of stream)."""
        closed: list[Segment] = []
        for s in list(self._open):
            closed += self._close(s, "flush")
        return closed

    def feed(self, scan: ScanReadings, chunk: int = 65536) -> Iterator[Segment]:
        """Push every reading of ``scan`` in order (:meth:`push_many`, ``chunk`` at a
        time), then flush; yields closed segments."""
        for lo in range(0, len(scan), chunk):
            part = slice(lo, lo + chunk)
            for _, s in self.push_many(scan.t_s[part], scan.x_m[part], scan.y_m[part],
                                       scan.yaw_rad[part], scan.tof_us[part],
                                       scan.sensor[part], chunk=chunk):
                yield s
        yield from self.flush()

    def feed_block(self, scan: ScanReadings, chunk: int = 65536) -> SegmentBlock:
        """:meth:`feed`, the segments in one :class:`SegmentBlock` (the same segments in
        the same order, without an object each)."""
        return SegmentBlock.join([*self._blocks(scan, chunk), SegmentBlock.of(self.flush())])

    def push_block(self, scan: ScanReadings, chunk: int = 65536) -> SegmentBlock:
        """:meth:`feed_block` without the flush: the segments these readings closed, in
        one block; the others stay open for the next readings."""
        return SegmentBlock.join(self._blocks(scan, chunk))

    def _blocks(self, scan: ScanReadings, chunk: int) -> list[SegmentBlock]:
        return [b for _, b in self._push_blocks(scan.t_s, scan.x_m, scan.y_m, scan.yaw_rad,
                                                scan.tof_us, scan.sensor, chunk)]

    # -- the per-reading decisions (shared by push and push_many) ----------------------

    def _step(self, row: tuple[float, float, float, float, float, int], R: float,
              ref: _Row, skip: int = 0) -> tuple[list[Segment], _Open | None]:
        """One accepted reading ``row`` = (t, x, y, yaw wrapped, tof, sensor), ``R`` its
        range (inf: no echo), against the open segments: closes, misses, censoring and
        the extension of the best matching segment. ``ref`` is what a segment's ``rows``
        get for it (the row, or push_many's index; ``~index``: the reading with no
        echo). Returns the segments closed and the
        segment extended (None: none; for an echo, the caller opens one, knowing the
        sensor's recent readings). ``skip`` (push_many): bit L set if this reading
        surely neither covers nor matches a segment whose last echo is the chunk's
        reading ``ref - L`` (:meth:`_skip_bits`); such segments are passed over.

        The loops over the open segments are written out inline (this runs once per
        reading, over every open segment): the match score and the miss test of
        :meth:`_off_axis` without calls, the gap test skipped while the oldest last
        echo cannot be ``max_gap_s`` old. Same segments as the plain form
        (tests/fit/segment_reference.py, compared in tests).
        """
        t, x, y, yaw, tof, sensor = row
        closed: list[Segment] = []
        opened = self._open
        # time gaps close segments first, then a panning beam that has moved on
        if t - self._oldest_last > self._max_gap:
            max_gap = self._max_gap
            for s in [s for s in opened if t - s.last[0] > max_gap]:
                closed += self._close(s, "gap")
            self._oldest_last = min((s.last[0] for s in opened), default=math.inf)
        if self._away < math.inf:
            for s in [s for s in opened if sensor in s.sensors
                      and self._off_axis(s, x, y, yaw) > self._away]:
                closed += self._close(s, "swept")
        cy, sy = math.cos(yaw), math.sin(yaw)
        wide, cheap, miss, gate, beam, two_beam = self._consts
        gone: list[_Open] = []
        if R < math.inf:
            atan2, floor, hypot, pi = math.atan2, math.floor, math.hypot, math.pi
            best, best_score = None, math.inf
            covered: list[tuple[_Open, float]] = []   # landmark within the miss width
            matched: list[_Open] = []    # segments this echo matches (finite score)
            for s in opened:
                if skip and skip >> (ref - s.k) & 1:   # type: ignore[operator]
                    continue
                # the miss test (applied below to all but the best match). Cheap test
                # first: a landmark well off the axis is neither missed nor censored (the
                # exact angle is only needed near the miss half-width)
                _, lx, ly, lyaw, lR, _ = s.last
                mx, my = s.mid
                ex, ey = lx - x, ly - y
                dx, dy = ex + mx, ey + my
                along = dx * cy + dy * sy
                if not (cheap and (along <= 0.0 or abs(dy * cy - dx * sy) > wide * along)):
                    a = atan2(dy, dx) - yaw
                    off = abs(a - _TWO_PI * floor((a + pi) / _TWO_PI))
                    if off <= miss:
                        covered.append((s, off))
                # the match score: normalised range mismatch with an arc point the new
                # beam covers (inf: no match); a pan's landmark stays at range lR
                if x == lx and y == ly:   # same spot (pan): the landmark stays at range lR
                    a = yaw - lyaw
                    if abs(a - _TWO_PI * floor((a + pi) / _TWO_PI)) > two_beam:
                        continue
                    d = abs(R - lR)
                    score = d / gate if d <= gate else math.inf
                else:
                    # (ex, ey) is -(x - lx, y - ly) exactly, and hypot takes abs values
                    d = hypot(ex, ey)
                    if abs(R - lR) > d + gate + 1e-9 * (1.0 + lR + R):
                        continue
                    # no arc point within the new beam: the arc spans +-beam about the
                    # last axis as seen from its transducer, and from here each point's
                    # direction differs by at most asin(d / lR) (the triangle's angle at
                    # the point, acute while d < lR)
                    a = lyaw - yaw
                    a = abs(a - _TWO_PI * floor((a + pi) / _TWO_PI))
                    if a > two_beam and d <= 0.99 * lR and \
                            a > two_beam + math.asin(d / lR) + 1e-9:
                        continue
                    arc = s.arc
                    if arc is None:
                        arc = s.arc = self._arc_points(s)
                    d_best = math.inf
                    for px, py in arc:
                        # the closest point within the gate that the new beam covers
                        # (range first: the cheaper test, and most points fail it)
                        dx, dy = ex + px, ey + py
                        d = abs(hypot(dx, dy) - R)
                        if d >= d_best or d > gate:
                            continue
                        a = atan2(dy, dx) - yaw
                        if abs(a - _TWO_PI * floor((a + pi) / _TWO_PI)) <= beam:
                            d_best = d
                    score = d_best / gate if d_best <= gate else math.inf
                if score < math.inf:
                    matched.append(s)
                    if score < best_score:
                        best, best_score = s, score
            for s, off in covered:
                if s is best:
                    continue
                # an echo this segment matches too (another matched better) may be its
                # own landmark's: it says neither that a nearer reflector answered nor
                # that a farther one won (its range grows as the transducer moves away)
                other = s not in matched
                last = s.last
                if (other and R < last[4] - gate and s.trailing == 0 and s.misses == 0
                        and sensor == last[5]):
                    s.occluded_trail = True   # a nearer reflector answered right after
                # a farther echo won: this landmark was not detected (censor)
                if (other and R > last[4] + gate and sensor in s.sensors
                        and s.trailing < self._censor):
                    s.rows.append(~ref if isinstance(ref, int)
                                  else (t, x, y, yaw, math.nan, sensor))
                    s.trailing += 1
                s.misses += 1
                if self._gone(s, off):
                    gone.append(s)
            for s in gone:
                closed += self._close(s, "misses")
            if best is None:
                return closed, None
            fx, fy = best.first
            if (x - fx) ** 2 + (y - fy) ** 2 > self._travel2:
                # too far from its first echo: the caller opens the next segment
                closed += self._close(best, "travel")
                self._cut = True
                return closed, None
            best.rows.append(ref)
            best.n_echo += 1
            best.last = (t, x, y, yaw, R, sensor)
            best.k = ref if isinstance(ref, int) else _NO_INDEX
            # (R cos(yaw + 0.0), R sin(yaw + 0.0)): yaw + 0.0 is yaw but for -0.0, whose
            # cosine is cos(0.0), and sine, -0.0, plus 0.0 is sin(0.0)
            best.mid = (R * cy, R * (sy + 0.0))
            best.arc = None
            best.misses = 0
            best.trailing = 0
            best.occluded_trail = False
            best.sensors.add(sensor)
            if len(best.rows) >= self._max_readings:
                closed += self._close(best, "full")
        else:
            best = None
            for s in opened:
                if skip and skip >> (ref - s.k) & 1:   # type: ignore[operator]
                    continue
                last = s.last
                mx, my = s.mid
                dx, dy = (last[1] - x) + mx, (last[2] - y) + my
                along = dx * cy + dy * sy
                if cheap and (along <= 0.0 or abs(dy * cy - dx * sy) > wide * along):
                    continue
                a = math.atan2(dy, dx) - yaw
                off = abs(a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI))
                if off <= miss:
                    if sensor in s.sensors and s.trailing < self._censor:
                        s.rows.append(ref)
                        s.trailing += 1
                    s.misses += 1
                    if self._gone(s, off):
                        gone.append(s)
            for s in gone:
                closed += self._close(s, "misses")
        return closed, best

    def _push_chunk(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                    tof: np.ndarray, sensor: np.ndarray, offset: int
                    ) -> tuple[list[int], SegmentBlock]:
        """:meth:`push_many` of one chunk (float64 / int64 arrays of one length)."""
        st = self.stats
        n = len(t)
        # the checks of :meth:`_push`, for all readings at once: bad values, then time
        # going backwards (behind the latest accepted time, as a running maximum)
        valid = usable(t, x, y, yaw, tof)
        latest = np.maximum.accumulate(np.concatenate(([self._last_t],
                                                       np.where(valid, t, -np.inf))))
        late = valid & (t < latest[:-1])
        keep = np.flatnonzero(valid & ~late)
        echo = ~np.isnan(tof[keep])
        st.readings += n
        st.bad += int(n - np.count_nonzero(valid))
        st.out_of_order += int(np.count_nonzero(late))
        st.echoes += int(np.count_nonzero(echo))
        st.no_echo += int(len(keep) - np.count_nonzero(echo))
        self._last_t = float(latest[-1])
        if not len(keep):
            return [], SegmentBlock.of([])
        tof = tof[keep]
        R = np.where(echo, (tof - self._half_count_us) * self._m_per_us, np.inf)
        ch = self._chunk = _Chunk(t[keep], x[keep], y[keep], _wrap_array(yaw[keep]), tof,
                                  sensor[keep], R)
        try:
            return self._chunk_loop(ch, keep + offset)
        finally:
            for s in self._open:    # the chunk's indices become rows of their own
                s.rows = [ch.row_of(r) if isinstance(r, int) else r for r in s.rows]
                s.k = _NO_INDEX
            self._chunk = None

    def _chunk_loop(self, ch: _Chunk, index: np.ndarray) -> tuple[list[int], SegmentBlock]:
        """The per-reading loop of :meth:`_push_chunk`: each reading through
        :meth:`_step`, skipping what changes nothing, extending chained runs and taking
        runs of misses of the only open segment through :meth:`_miss_run`."""
        m = ch.m
        chained = self._chain(ch)
        pos = np.arange(m)
        # the next echo at or after each reading, and the end of each chained run
        next_echo = _ints(np.minimum.accumulate(np.where(ch.echo, pos, m)[::-1])[::-1])
        run_end = _ints(np.minimum.accumulate(np.where(chained, m, pos)[::-1])[::-1])
        chain = _ints(chained)
        tl, xl, yl, yawl, tofl, sl, Rl = ch.tl, ch.xl, ch.yl, ch.yawl, ch.tofl, ch.sl, ch.Rl
        recent = _RecentIndex(ch.sensor) if self._censor else None
        # _start's lead rows and occluded_lead, worked out in advance for the echoes
        # that may open a segment (bits; -1: not worked out, _start's own loop does it)
        bits = self._lead_bits(ch, recent, ~chained) if recent is not None else None
        # pairs of readings that surely do nothing (None: no sweep test, which they skip)
        skips = self._skip_bits(ch) if self._away == math.inf else None
        max_gap = self._max_gap
        lags: dict[int, tuple[int, ...]] = {}
        one = recent is not None and recent.order is None
        want = self._censor - 1
        opened = self._open
        step = self._step
        max_readings = self._max_readings
        miss_run = self._miss_run
        i = 0
        while i < m:
            R = Rl[i]
            if not R < math.inf:
                if not opened:
                    i = next_echo[i]       # no echo and nothing open: nothing to do
                    continue
                if len(opened) == 1:       # misses of the only open segment
                    i = miss_run(ch, i, next_echo[i])
                    continue
                # no gap due and no sweep test: _step's miss loop here, over the segments
                # its skip bits do not pass over
                if skips is not None and not tl[i] - self._oldest_last > max_gap:
                    self._misses_of(ch, i, skips[i])
                    i += 1
                    continue
            row = (tl[i], xl[i], yl[i], yawl[i], tofl[i], sl[i])
            ch.at = i        # segments closed now go to ch.closed
            if opened:
                _, took = step(row, R, i, skips[i] if skips is not None else 0)
            else:
                # an echo with nothing open: _step would change nothing (no segment to
                # close, miss or extend), so it opens one; the earliest last echo is its
                took = None
                self._oldest_last = math.inf
            if took is None and R < math.inf:
                b = bits[i] if bits is not None else -1
                if self._cut:
                    self._open_next(row, R, i)
                elif b >= 0:
                    ks = lags.get(b)
                    if ks is None:   # the lags of its lead rows, oldest first
                        ks = lags[b] = tuple(k for k in range(want, 0, -1) if b >> k & 1)
                    if one:
                        lead: list[_Row] = [~i + k for k in ks]     # ~(i - k)
                    else:
                        assert recent is not None
                        mine, r = recent.by_sensor[sl[i]], recent.rank[i]
                        lead = [~mine[r - k] for k in ks]
                    self._open_new(row, R, lead, b & 1 == 1, i)
                else:
                    prev = self._recent_rows(ch, recent, i) if recent is not None else []
                    self._start(row, R, prev, i)
            i += 1
            # a run of echoes, each matching the one before from the same spot, extends
            # the only open segment (whose last echo is the reading just handled)
            if i < m and chain[i] and len(opened) == 1 and opened[0].rows[-1] == i - 1:
                s = opened[0]
                j = min(run_end[i], i + max_readings - 1 - len(s.rows))
                if j > i:
                    s.rows += range(i, j)
                    s.n_echo += j - i
                    k = j - 1
                    lx, ly, lyaw, lR = xl[k], yl[k], yawl[k], Rl[k]
                    s.last = (tl[k], lx, ly, lyaw, lR, sl[k])
                    s.k = k
                    s.mid = (lR * math.cos(lyaw + 0.0), lR * math.sin(lyaw + 0.0))
                    s.arc = None
                    s.misses = 0
                    s.trailing = 0
                    s.occluded_trail = False
                    i = j
        if recent is not None:
            self._remember_chunk(ch, recent)
        return [int(index[at]) for at, _, _ in ch.closed], ch.block()

    def _lead_bits(self, ch: _Chunk, recent: _RecentIndex, cand: np.ndarray
                   ) -> Sequence[int] | None:
        """What :meth:`_start` would find in its ``prev`` for each echo at ``cand`` ((m,)
        bool) whose sensor has ``censor_window - 1`` readings before it in the chunk:
        bit k (1 ...) set if its k-th earlier reading is a lead row, bit 0 if the one
        just before hid it (``occluded_lead``). -1 elsewhere. The tests of _start, in
        the same float operations, so exactly its outcome. None if no echo
        qualifies, or for a short chunk (its numpy calls cost more than they save)."""
        want = self._censor - 1
        if not 1 <= want <= 60 or ch.m < 1024:
            return None
        c = np.flatnonzero(cand & ch.echo & (recent.rank_np >= want))
        if not len(c):
            return None
        t, yaw, R = ch.t, ch.yaw, ch.R
        tc, yawc, Rc = t[c], yaw[c], R[c]
        farther, nearer = Rc + self._gate_m, Rc - self._gate_m
        max_gap, two_beam = self.config.max_gap_s, 2.0 * self._beam
        b = np.zeros(len(c), dtype=np.int64)
        for k in range(1, want + 1):
            j = c - k if recent.order is None or recent.place is None else \
                recent.order[recent.place[c] - k]
            near = (tc - t[j] <= max_gap) & (np.abs(_wrap_array(yaw[j] - yawc)) <= two_beam)
            b |= (near & (R[j] > farther)).astype(np.int64) << k
            if k == 1:
                b |= near & (R[j] < nearer)
        bits = np.full(ch.m, -1, dtype=np.int64)
        bits[c] = b
        return _ints(bits)

    def _skip_bits(self, ch: _Chunk) -> Sequence[int] | None:
        """For each reading ``i`` of the chunk, bit L (1 ... :data:`_SKIP_LAGS`) set if
        :meth:`_step` surely finds it neither covering nor matching a segment whose last
        echo is reading ``i - L``: the cheap miss test fails (the landmark is well off
        the new axis) and, for an echo, the range test of the match fails (the ranges
        differ by more than the transducers' distance and the gate). Both depend on the
        two readings alone; numpy's trigonometry may differ from math's in the last
        bits, so the tests keep a margin ``eps`` (far above those bits, far below the
        gate), which only passes a few more pairs on to the exact tests. None when the
        cheap miss test does not apply, or for a short chunk."""
        m = ch.m
        lags = min(_SKIP_LAGS, m - 1)
        wide = self._tan_miss_wide
        if lags < 1 or not wide < math.inf or m < _SKIP_MIN:
            return None
        x, y, yaw, R = ch.x, ch.y, ch.yaw, ch.R
        r_max = float(R[ch.echo].max()) if ch.echo.any() else 0.0
        eps = 1e-8 * (1.0 + 2.0 * r_max + float(max(np.abs(x).max(), np.abs(y).max())))
        e_miss = eps * (1.0 + wide)
        gate = self._gate_m + eps
        cy, sy = np.cos(yaw), np.sin(yaw)
        with np.errstate(invalid="ignore"):     # no echo: inf * 0 (never a last echo)
            px, py = x + R * cy, y + R * sy     # the landmark on the axis
        bits = np.zeros(m, dtype=np.int64)
        with np.errstate(invalid="ignore"):     # inf - inf: no echo on both sides
            for lag in range(1, lags + 1):
                i, k = slice(lag, m), slice(0, m - lag)
                xi, yi, ci, si = x[i], y[i], cy[i], sy[i]
                dx, dy = px[k] - xi, py[k] - yi
                skip = np.abs(dy * ci - dx * si) > wide * (dx * ci + dy * si) + e_miss
                skip &= np.abs(R[i] - R[k]) > np.hypot(x[k] - xi, y[k] - yi) + gate
                bits[lag:] |= skip.astype(np.int64) << lag
        return _ints(bits)

    def _misses_of(self, ch: _Chunk, i: int, skip: int) -> None:
        """:meth:`_step` of the chunk's no-echo reading ``i`` while several segments are
        open, no gap is due and there is no sweep test (``skip``: its skip bits): the
        same misses, censoring and closes, in the same float operations."""
        x, y, yaw, sensor = ch.xl[i], ch.yl[i], ch.yawl[i], ch.sl[i]
        cy = sy = 0.0
        turned = False      # cy, sy worked out
        wide, miss = self._tan_miss_wide, self._miss
        gone: list[_Open] = []
        for s in self._open:
            if skip >> (i - s.k) & 1:
                continue
            if not turned:
                cy, sy = math.cos(yaw), math.sin(yaw)
                turned = True
            last = s.last
            mx, my = s.mid
            dx, dy = (last[1] - x) + mx, (last[2] - y) + my
            along = dx * cy + dy * sy
            if along <= 0.0 or abs(dy * cy - dx * sy) > wide * along:
                continue
            a = math.atan2(dy, dx) - yaw
            off = abs(a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI))
            if off <= miss:
                if sensor in s.sensors and s.trailing < self._censor:
                    s.rows.append(i)
                    s.trailing += 1
                s.misses += 1
                if self._gone(s, off):
                    gone.append(s)
        if gone:
            ch.at = i
            for s in gone:
                self._close(s, "misses")

    def _miss_run(self, ch: _Chunk, i: int, e: int) -> int:
        """:meth:`_step` of the no-echo readings ``i`` to ``e - 1`` of the chunk while
        exactly one segment is open (a transducer turning or moving away from the
        landmark it last saw): the same closes, misses and censoring, for one segment,
        in the same float operations. Stops where the segment closes (the rest of the
        run then changes nothing). Returns the next reading to handle (``e``)."""
        s = self._open[0]
        tl, xl, yl, yawl, sl = ch.tl, ch.xl, ch.yl, ch.yawl, ch.sl
        last_t = s.last[0]
        mx, my = s.mid
        lx, ly = s.last[1], s.last[2]
        sensors, rows = s.sensors, s.rows
        max_gap, away, miss = self._max_gap, self._away, self._miss
        censor, lim, miss_angle = self._censor, self.config.miss_limit, self._miss_angle
        atan2, floor, pi = math.atan2, math.floor, math.pi
        # the segment's counters as locals, written back before a close and at the end
        oldest, trailing, misses = self._oldest_last, s.trailing, s.misses
        why = ""
        for j in range(i, e):
            t = tl[j]
            if t - oldest > max_gap:    # the gap test of _step
                if t - last_t > max_gap:
                    why = "gap"
                    break
                oldest = self._oldest_last = last_t
            yaw, sensor = yawl[j], sl[j]
            # the off-axis angle of _off_axis (the swept test) and of the miss test (whose
            # cheap pre-test only skips landmarks beyond the miss width: not needed here)
            a = atan2((ly - yl[j]) + my, (lx - xl[j]) + mx) - yaw
            off = abs(a - _TWO_PI * floor((a + pi) / _TWO_PI))
            if off > away and sensor in sensors:
                why = "swept"
                break
            if off <= miss:
                if sensor in sensors and trailing < censor:
                    rows.append(j)
                    trailing += 1
                misses += 1
                if (misses >= lim and off >= miss_angle) or misses >= 4 * lim:
                    why = "misses"
                    break
        s.trailing, s.misses = trailing, misses
        if why:
            ch.at = j
            self._close(s, why)
            if why == "gap":
                self._oldest_last = math.inf
        return e

    def _chain(self, ch: _Chunk) -> np.ndarray:
        """(m,) bool: reading i is an echo that :meth:`_step` surely adds to a segment
        whose last echo is reading i - 1, if no other segment is open: an echo of the same
        sensor from the same spot, within the gate and the time gap, the beam not swept
        away. The same-spot branch of the match, in the same float operations, so
        exactly its outcome."""
        t, x, y, yaw, R, sensor = ch.t, ch.x, ch.y, ch.yaw, ch.R, ch.sensor
        chain = np.zeros(ch.m, dtype=bool)
        if ch.m < 2:
            return chain
        a = yaw[1:] - yaw[:-1]
        with np.errstate(invalid="ignore"):     # inf - inf: no echo on either side
            dR = np.abs(R[1:] - R[:-1])
        c = ((R[1:] < np.inf) & (R[:-1] < np.inf) & (sensor[1:] == sensor[:-1])
             & (x[1:] == x[:-1]) & (y[1:] == y[:-1]) & ~(t[1:] - t[:-1] > self._max_gap)
             & ~(np.abs(_wrap_array(a)) > 2.0 * self._beam) & (dR <= self._gate_m))
        if self._away < math.inf and c.any():
            # the swept test: off-axis angle of the last echo's landmark (exact mid) with
            # numpy's arctan2, which may differ from math.atan2 in the last bits: a margin
            k = np.flatnonzero(c)
            mx, my = _mids(yaw[k], R[k])
            off = np.abs(_wrap_array(np.arctan2((y[k] - y[k + 1]) + my,
                                                (x[k] - x[k + 1]) + mx) - yaw[k + 1]))
            c[k[~(off <= self._away - 1e-9)]] = False
        chain[1:] = c
        return chain

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
               prev: Sequence[tuple[float, float, float, _Row]], ref: _Row) -> list[Segment]:
        """Open a segment with the echo ``row`` (range ``R``; ``ref`` the segment's row
        for it, as in :meth:`_step`). ``prev``: the earlier readings of its sensor,
        oldest first, as (t, yaw, range (inf: no echo), the segment's row for it without
        its echo); at most ``censor_window - 1`` of them (the sensor's recent readings
        with this one)."""
        t, _, _, yaw, _, _ = row
        lead: list[_Row] = []
        # earlier readings of this sensor that saw nothing here: no echo, or a farther
        # echo won (the first crossing would have been this landmark's); the cheap tests
        # first, :func:`_wrap` written out
        farther, max_gap, two_beam = R + self._gate_m, self._max_gap, 2.0 * self._beam
        for r_t, r_yaw, r_range, r_ref in prev:
            if r_range > farther and t - r_t <= max_gap:
                a = r_yaw - yaw
                if abs(a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)) <= two_beam:
                    lead.append(r_ref)
        # the reading of this sensor just before: a nearer echo there hid this landmark
        occluded = False
        if prev:
            r_t, r_yaw, r_range, _ = prev[-1]
            occluded = (t - r_t <= self.config.max_gap_s
                        and abs(_wrap(r_yaw - yaw)) <= 2.0 * self._beam
                        and r_range < R - self._gate_m)
        return self._open_new(row, R, lead, occluded, ref)

    def _open_next(self, row: tuple[float, float, float, float, float, int], R: float,
                   ref: _Row) -> list[Segment]:
        """Open the next piece of a pass that a segment closed by travel cut (``row`` the
        echo that closed it): without lead rows and not occluded.

        The piece starts where the one before ended, not where its landmark came into
        view: the sensor's earlier readings are that piece's echoes of the same landmark,
        farther (or nearer) by the distance driven between pings, not echoes of another
        reflector that won (or answered first). :meth:`_start`'s tests would attach them
        as no-echo readings (or mark the piece occluded): on bench_fit_quality's ten 30 s
        ring16 drives through maps/room.geojson, 90 of 427 `OK` points and 26 of 221
        walls (odometry poses) had such readings, up to seven on the beam's axis; read as
        "not detected there", they pushed kappa up (a rod fitted at 9 us instead of 3)
        and the range down (-6 mm), with the detection terms claiming SDs 2-3x too small
        (RMS of error/SD of those points 2.17 in range, 2.95 with the true poses)."""
        self._cut = False
        return self._open_new(row, R, [], False, ref)

    def _open_new(self, row: tuple[float, float, float, float, float, int], R: float,
                  lead: list[_Row], occluded: bool, ref: _Row) -> list[Segment]:
        """The rest of :meth:`_start`, given the lead rows (``lead``, appended to) and
        ``occluded_lead``: closes the oldest segment if ``max_open`` are open, opens
        this one."""
        t, x, y, yaw, _, sensor = row
        closed: list[Segment] = []
        if len(self._open) >= self.config.max_open:
            closed += self._close(min(self._open, key=lambda s: s.last[0]), "crowded")
        lead.append(ref)
        # its mid: the middle of :meth:`_arc_points` (the landmark on the echo's axis)
        s = _Open(self._next_id, lead, 1, (t, x, y, yaw, R, sensor), sensors={sensor},
                  mid=(R * math.cos(yaw + 0.0), R * math.sin(yaw + 0.0)),
                  occluded_lead=occluded, first=(x, y),
                  k=ref if isinstance(ref, int) else _NO_INDEX)
        self._next_id += 1
        self._open.append(s)
        self._oldest_last = min(self._oldest_last, t)
        return closed

    def _recent_rows(self, ch: _Chunk, recent: _RecentIndex, i: int
                     ) -> list[tuple[float, float, float, _Row]]:
        """The ``prev`` of :meth:`_start` for reading ``i`` of the chunk: the sensor's
        readings before it in the chunk, and before the chunk those
        :meth:`_remember` kept."""
        want = self._censor - 1
        sensor = ch.sl[i]
        mine = recent.by_sensor[sensor]
        r = recent.rank[i]
        tl, yawl, Rl = ch.tl, ch.yawl, ch.Rl
        out: list[tuple[float, float, float, _Row]] = [
            (tl[j], yawl[j], Rl[j], ~j) for j in mine[max(0, r - want):r]]
        if len(out) < want:
            dq = self._recent.get(sensor)
            if dq:
                old = [(row[0], row[3], r_range, (row[0], row[1], row[2], row[3], math.nan,
                                                  row[5]))
                       for row, r_range in list(dq)[max(0, len(dq) - (want - len(out))):]]
                out = old + out
        return out

    def _remember_chunk(self, ch: _Chunk, recent: _RecentIndex) -> None:
        """:meth:`_remember` of a chunk's last ``censor_window`` readings per sensor."""
        for sensor, mine in recent.by_sensor.items():
            dq = self._recent.get(sensor)
            if dq is None:
                dq = self._recent[sensor] = deque(maxlen=self._censor)
            dq.extend((ch.row_of(j), ch.Rl[j]) for j in mine[-self._censor:])

    def _close(self, s: _Open, why: str) -> list[Segment]:
        if s not in self._open:
            return []
        self._open.remove(s)
        if s.n_echo < self.config.min_echoes:
            self.stats.spikes += s.n_echo
            return []
        self.stats.segments += 1
        ch = self._chunk
        if ch is not None:   # push_many: built with the chunk's others at its end
            ch.closed.append((ch.at, s, why))
            return []
        cols = np.array(s.rows, dtype=float).T.copy()   # (6, n), one conversion
        # the ids from the rows, not through float64 (see _Chunk.block)
        # (outside a chunk the rows are tuples)
        sensor = np.fromiter((r[5] for r in s.rows), dtype=np.int64,  # type: ignore[index]
                             count=len(s.rows))
        readings = ScanReadings(cols[0], cols[1], cols[2], cols[3], cols[4], sensor)
        return [Segment(readings, s.seg_id, why, (s.occluded_lead, s.occluded_trail))]
