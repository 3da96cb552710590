"""Sonar rigs: a panning transducer and a ring of fixed transducers, and JSON rig files.

A rig says where its transducers sit on the robot (mount poses in ``base_link``,
:class:`~sonarloc.io.logfile.SensorMount`) and when each one fires:

* :class:`PanRig` -- one transducer on a pan unit stepping through an angle schedule
  ``START:STOP:STEP`` (degrees, STOP included), ``repeat`` pings per angle, one ping
  every ``ping_period_s``; the schedule starts again after the last angle.
* :class:`RingRig` -- fixed transducers (``ring16``: 16 on a 0.2 m circle, 22.5 deg
  apart) fired in groups of non-adjacent sensors, one group per time slot of
  ``slot_s`` (30 ms = echoes up to about 5 m, the ``range_gate_m``).

Rig files are JSON (docs/RIGS.md); a bad file raises ValueError naming the field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarloc.io.logfile import SensorMount

Firing = tuple[float, tuple[tuple[int, float | None], ...]]
"""One firing event: (time from the start [s], ((sensor id, pan_deg or None), ...))."""


def parse_pan_schedule(text: str) -> tuple[float, float, float]:
    """Parse ``START:STOP:STEP`` (degrees) into three floats.

    Raises
    ------
    ValueError
        naming the value if it is not three finite numbers with a non-zero step that
        goes from START towards STOP.
    """
    parts = str(text).split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        start, stop, step = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"pan schedule must be START:STOP:STEP in degrees, got {text!r}") \
            from None
    check_pan(start, stop, step, name=f"pan schedule {text!r}")
    return start, stop, step


def check_pan(start: float, stop: float, step: float, name: str = "pan") -> None:
    """Raise ValueError unless (start, stop, step) is a usable angle schedule."""
    if not all(math.isfinite(v) for v in (start, stop, step)):
        raise ValueError(f"{name}: angles must be finite")
    if step == 0 or (stop - start) * step < 0:
        raise ValueError(f"{name}: step {step:g} does not go from {start:g} to {stop:g}")
    if abs(start) > 360 or abs(stop) > 360:
        raise ValueError(f"{name}: angles must be within [-360, 360] deg")
    if abs(stop - start) / abs(step) > 1e6:
        raise ValueError(f"{name}: more than a million angles")


def pan_angles_deg(start: float, stop: float, step: float) -> NDArray[np.float64]:
    """The angles of a pan schedule, STOP included when it falls on the grid (to 1e-9)."""
    check_pan(start, stop, step)
    n = int(math.floor((stop - start) / step + 1e-9)) + 1
    return np.round(start + step * np.arange(n), 9)


@dataclass(frozen=True)
class PanRig:
    """A transducer on a pan unit.

    Attributes
    ----------
    sensor : mount pose of the pan unit (its zero direction) in ``base_link``.
    pan_deg : (start, stop, step) of the angle schedule, degrees relative to the mount.
    repeat : pings per angle.
    ping_period_s : time between pings (the module needs ~0.1 s for full range).
    range_gate_m : echoes beyond this are not reported (None = module's maximum).
    """

    sensor: SensorMount = SensorMount(0, 0.0, 0.0, 0.0)
    pan_deg: tuple[float, float, float] = (-40.0, 40.0, 0.3)
    repeat: int = 1
    ping_period_s: float = 0.1
    range_gate_m: float | None = None
    kind: str = field(default="pan", init=False)

    def __post_init__(self) -> None:
        check_pan(*self.pan_deg, name="`pan_deg`")
        _check_int("repeat", self.repeat, 1)
        _check_positive("ping_period_s", self.ping_period_s)
        if self.range_gate_m is not None:
            _check_positive("range_gate_m", self.range_gate_m)

    @property
    def sensors(self) -> tuple[SensorMount, ...]:
        return (self.sensor,)

    @property
    def angles_deg(self) -> NDArray[np.float64]:
        return pan_angles_deg(*self.pan_deg)

    @property
    def sweep_s(self) -> float:
        """Duration of one pass through the schedule."""
        return float(len(self.angles_deg) * self.repeat * self.ping_period_s)

    def firings(self) -> Iterator[Firing]:
        """Endless firing schedule: one ping per period, ``repeat`` per angle, cycling."""
        angles = self.angles_deg.tolist()
        j = 0
        while True:
            a = angles[(j // self.repeat) % len(angles)]
            yield (round(j * self.ping_period_s, 9), ((self.sensor.id, a),))
            j += 1


@dataclass(frozen=True)
class RingRig:
    """Fixed transducers fired in groups, one group per time slot.

    Attributes
    ----------
    sensors : mount poses in ``base_link``.
    groups : sensor ids fired together in each slot, cycled in order.
    slot_s : time per slot.
    range_gate_m : echoes beyond this are not reported (default: what a slot allows,
        c * slot / 2 with c = 343 m/s, at most the module's maximum).
    """

    sensors: tuple[SensorMount, ...]
    groups: tuple[tuple[int, ...], ...]
    slot_s: float = 0.03
    range_gate_m: float | None = None
    kind: str = field(default="ring", init=False)

    def __post_init__(self) -> None:
        if not self.sensors:
            raise ValueError("`sensors` must not be empty")
        ids = [s.id for s in self.sensors]
        if len(set(ids)) != len(ids):
            raise ValueError(f"`sensors` ids must be unique, got {ids}")
        _check_positive("slot_s", self.slot_s)
        if not self.groups:
            raise ValueError("`groups` must not be empty")
        for g, group in enumerate(self.groups):
            if not group:
                raise ValueError(f"`groups[{g}]` is empty")
            for sid in group:
                if sid not in ids:
                    raise ValueError(f"`groups[{g}]` names unknown sensor id {sid!r}")
        if self.range_gate_m is not None:
            _check_positive("range_gate_m", self.range_gate_m)

    @property
    def cycle_s(self) -> float:
        """Time to fire every group once."""
        return self.slot_s * len(self.groups)

    def firings(self) -> Iterator[Firing]:
        """Endless firing schedule: group ``j % len(groups)`` at ``j * slot_s``."""
        j = 0
        while True:
            group = self.groups[j % len(self.groups)]
            yield (round(j * self.slot_s, 9), tuple((sid, None) for sid in group))
            j += 1


Rig = PanRig | RingRig


def ring_rig(n: int = 16, radius_m: float = 0.2, slot_s: float = 0.03,
             n_groups: int | None = None, range_gate_m: float | None = None) -> RingRig:
    """A ring of ``n`` outward-looking transducers evenly spaced on a circle.

    Sensor i sits at angle 360*i/n deg (id i, yaw the same). Groups fire sensors
    ``n_groups`` apart (default 4 groups for 16 sensors: 90 deg between sensors of a
    group), so no two neighbours fire together.
    """
    _check_int("n", n, 1)
    _check_positive("radius_m", radius_m)
    g = n_groups if n_groups is not None else max(1, min(4, n))
    _check_int("n_groups", g, 1)
    if g > n:
        raise ValueError(f"`n_groups` must be at most n={n}, got {g}")
    mounts = []
    for i in range(n):
        a = 360.0 * i / n
        mounts.append(SensorMount(i, round(radius_m * math.cos(math.radians(a)), 9),
                                  round(radius_m * math.sin(math.radians(a)), 9), a))
    groups = tuple(tuple(range(j, n, g)) for j in range(g))
    return RingRig(tuple(mounts), groups, slot_s, range_gate_m)


def ring16() -> RingRig:
    """The default ring: 16 transducers, 0.2 m radius, 4 groups, 30 ms slots."""
    return ring_rig(16, 0.2, 0.03)


def slot_range_m(slot_s: float, c_mps: float = 343.0) -> float:
    """Range whose echo returns within one slot, c * slot / 2."""
    return c_mps * slot_s / 2.0


# --------------------------------------------------------------------------- JSON


def _check_positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not (math.isfinite(value) and value > 0):
        raise ValueError(f"`{name}` must be a positive number, got {value!r}")


def _check_int(name: str, value: int, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}, got {value!r}")


def _mount_json(m: SensorMount) -> dict[str, Any]:
    return {"id": m.id, "x_m": m.x_m, "y_m": m.y_m, "yaw_deg": m.yaw_deg}


def rig_to_json(rig: Rig) -> dict[str, Any]:
    """The JSON object of a rig (docs/RIGS.md)."""
    obj: dict[str, Any]
    if isinstance(rig, PanRig):
        start, stop, step = rig.pan_deg
        obj = {"kind": "pan", "sensors": [_mount_json(rig.sensor)],
               "pan": {"start_deg": start, "stop_deg": stop, "step_deg": step},
               "repeat": rig.repeat, "ping_period_s": rig.ping_period_s}
    else:
        obj = {"kind": "ring", "sensors": [_mount_json(m) for m in rig.sensors],
               "groups": [list(g) for g in rig.groups], "slot_s": rig.slot_s}
    if rig.range_gate_m is not None:
        obj["range_gate_m"] = rig.range_gate_m
    return obj


def _field(obj: dict[str, Any], name: str, default: Any = None, required: bool = False) -> Any:
    if name not in obj:
        if required:
            raise ValueError(f"rig field `{name}` is missing")
        return default
    return obj[name]


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"rig field `{name}` must be a finite number, got {value!r}")
    return float(value)


def _mounts(value: Any) -> tuple[SensorMount, ...]:
    if not isinstance(value, list) or not value:
        raise ValueError(f"rig field `sensors` must be a non-empty list, got {value!r:.60}")
    out = []
    for i, s in enumerate(value):
        name = f"sensors[{i}]"
        if not isinstance(s, dict):
            raise ValueError(f"rig field `{name}` must be an object, got {s!r:.60}")
        sid = s.get("id", i)
        if isinstance(sid, bool) or not isinstance(sid, int):
            raise ValueError(f"rig field `{name}.id` must be an integer, got {sid!r}")
        out.append(SensorMount(sid, _number(s.get("x_m", 0.0), f"{name}.x_m"),
                               _number(s.get("y_m", 0.0), f"{name}.y_m"),
                               _number(s.get("yaw_deg", 0.0), f"{name}.yaw_deg")))
    return tuple(out)


def rig_from_json(obj: Any) -> Rig:
    """A rig from its JSON object; ValueError naming the field on bad input."""
    if not isinstance(obj, dict):
        raise ValueError(f"a rig file must hold a JSON object, got {type(obj).__name__}")
    kind = _field(obj, "kind", required=True)
    gate = _field(obj, "range_gate_m")
    gate_m = None if gate is None else _number(gate, "range_gate_m")
    try:
        if kind == "pan":
            mounts = _mounts(_field(obj, "sensors", required=True))
            if len(mounts) != 1:
                raise ValueError(f"rig field `sensors` of a pan rig must hold exactly one "
                                 f"sensor, got {len(mounts)}")
            pan = _field(obj, "pan", {"start_deg": -40.0, "stop_deg": 40.0, "step_deg": 0.3})
            if isinstance(pan, str):
                sched = parse_pan_schedule(pan)
            elif isinstance(pan, dict):
                sched = (_number(pan.get("start_deg"), "pan.start_deg"),
                         _number(pan.get("stop_deg"), "pan.stop_deg"),
                         _number(pan.get("step_deg"), "pan.step_deg"))
            else:
                raise ValueError(f"rig field `pan` must be an object or 'START:STOP:STEP', "
                                 f"got {pan!r:.60}")
            repeat = _field(obj, "repeat", 1)
            period = _number(_field(obj, "ping_period_s", 0.1), "ping_period_s")
            return PanRig(mounts[0], sched, repeat, period, gate_m)
        if kind == "ring":
            mounts = _mounts(_field(obj, "sensors", required=True))
            groups_raw = _field(obj, "groups", None)
            if groups_raw is None:
                groups = tuple((m.id,) for m in mounts)
            else:
                if not isinstance(groups_raw, list) or not all(
                        isinstance(g, list) and all(isinstance(s, int) and not isinstance(s, bool)
                                                    for s in g) for g in groups_raw):
                    raise ValueError(f"rig field `groups` must be a list of lists of sensor "
                                     f"ids, got {groups_raw!r:.60}")
                groups = tuple(tuple(g) for g in groups_raw)
            slot = _number(_field(obj, "slot_s", 0.03), "slot_s")
            return RingRig(mounts, groups, slot, gate_m)
    except ValueError as err:
        msg = str(err)
        if msg.startswith("`"):
            msg = "rig field " + msg
        raise ValueError(msg) from None
    raise ValueError(f"rig field `kind` must be 'pan' or 'ring', got {kind!r}")


def load_rig(path: str | Path) -> Rig:
    """Read a JSON rig file (docs/RIGS.md); ValueError naming the file and field."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ValueError(f"cannot open rig file {path}: {err.strerror}") from err
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"rig file {path}: not JSON (line {err.lineno}: {err.msg})") from err
    try:
        return rig_from_json(obj)
    except ValueError as err:
        raise ValueError(f"rig file {path}: {err}") from None


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write a rig as JSON."""
    Path(path).write_text(json.dumps(rig_to_json(rig), indent=1) + "\n", encoding="utf-8")


def rig_by_name(name: str, pan: Sequence[float] | None = None, repeat: int | None = None) -> Rig:
    """``ring16``, ``pan`` or a path to a rig JSON file; ``pan``/``repeat`` adjust a pan rig.

    Raises
    ------
    ValueError
        naming the value for an unknown name, or a pan option on a ring rig.
    """
    rig: Rig
    if name == "ring16":
        rig = ring16()
    elif name == "pan":
        rig = PanRig()
    elif name.endswith(".json") or Path(name).is_file():
        rig = load_rig(name)
    else:
        raise ValueError(f"`--rig` must be ring16, pan or a rig .json file, got {name!r}")
    if pan is not None or repeat is not None:
        if not isinstance(rig, PanRig):
            raise ValueError(f"--pan/--repeat need a pan rig, but rig {name!r} is a ring")
        start, stop, step = pan if pan is not None else rig.pan_deg
        rig = PanRig(rig.sensor, (start, stop, step),
                     repeat if repeat is not None else rig.repeat, rig.ping_period_s,
                     rig.range_gate_m)
    return rig
