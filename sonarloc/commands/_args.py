"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
from collections.abc import Iterable
from typing import Any, TypeVar

_Config = TypeVar("_Config")

# Values such as "-40:40:0.3" or "-1.5,2,90" start with "-": let argparse take them as
# values, not options (it only knows plain negative numbers).
_NEGATIVE_VALUE = re.compile(r"^-\d+$|^-\d*\.\d+$|^-[\d.]+([,:][-+\d.eE]*)+$")


def accept_negative_values(parser: argparse.ArgumentParser) -> None:
    """Let ``parser`` take values like ``-40:40:0.3`` or ``-1,2,90`` as option values."""
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = _NEGATIVE_VALUE


def parse_pose(text: str, option: str = "--at") -> tuple[float, float, float]:
    """``X,Y,YAW_DEG`` -> three finite floats; ValueError naming the option and value."""
    parts = str(text).split(",")
    try:
        if len(parts) != 3:
            raise ValueError
        x, y, yaw = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"{option} must be X,Y,YAW_DEG (three numbers), got {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise ValueError(f"{option} must be finite numbers, got {text!r}")
    return x, y, yaw


def refuse_overwrite(outputs: dict[str, str | None], inputs: dict[str, str | None]) -> None:
    """ValueError naming both options when a file to write (``outputs``: option -> path)
    is one of the files read (``inputs``), or two outputs are the same file: opening it
    for writing would destroy what is still to be read (``localize LOG --out LOG`` left
    a recording of 1740 lines empty), or one output would overwrite the other. Paths
    that are None (an option not given) are left out, and so are inputs that are not
    files (a rig or map given by name, a device)."""
    outs = [(name, path) for name, path in outputs.items() if path]
    for i, (name, path) in enumerate(outs):
        for other, src in inputs.items():
            if src and os.path.isfile(src) and os.path.exists(path) \
                    and os.path.samefile(path, src):
                raise ValueError(f"{name} {path} is the input {other}: it would be overwritten")
        for other, earlier in outs[:i]:
            if os.path.realpath(path) == os.path.realpath(earlier):
                raise ValueError(f"{name} {path} is also {other}: one would overwrite the "
                                 "other")


def add_reading_limit_options(parser: argparse.ArgumentParser, like: str) -> None:
    """``--max-tof``, ``--odom-max-speed`` and ``--odom-max-yaw-rate``: how a log's
    timeouts and odometry jumps are read (``localize`` and ``map build`` alike; ``like``
    names the other command in the help)."""
    parser.add_argument("--max-tof", type=float, metavar="US", default=None,
                        help="readings at or above this TOF [us] are a module's timeout, "
                             f"taken as no echo and counted (as `sonarloc {like} --max-tof`)")
    parser.add_argument("--odom-max-speed", type=float, metavar="MPS", default=None,
                        help="an odometry increment implying more speed is a jump, taken as "
                             "a restart of the odometry (default 5 m/s; inf: never)")
    parser.add_argument("--odom-max-yaw-rate", type=float, metavar="DEG_S", default=None,
                        help="the same for turning (default 573 deg/s = 10 rad/s; inf: never)")


def reading_limit_options(args: argparse.Namespace) -> list[tuple[str, str, Any]]:
    """(option, config field, value) of :func:`add_reading_limit_options`' options, the
    yaw rate in rad/s (fields of both ``LocalizerConfig`` and ``BuildConfig``)."""
    yaw_rate = args.odom_max_yaw_rate
    if yaw_rate is not None:
        if not yaw_rate > 0:  # named in the user's unit, before the config's rad/s check
            raise ValueError(f"--odom-max-yaw-rate must be positive (deg/s; inf: never), "
                             f"got {yaw_rate}")
        yaw_rate = math.radians(yaw_rate)
    return [("--max-tof", "max_tof_us", args.max_tof),
            ("--odom-max-speed", "odom_max_speed_mps", args.odom_max_speed),
            ("--odom-max-yaw-rate", "odom_max_yaw_rate_rad_s", yaw_rate)]


def replace_options(config: _Config, options: Iterable[tuple[str, str, Any]]) -> _Config:
    """``config`` (a dataclass) with each (option, field, value) whose value is not None
    set; a value its check refuses is a ValueError naming the option."""
    for option, name, value in options:
        if value is None:
            continue
        try:
            config = dataclasses.replace(config, **{name: value})  # type: ignore[type-var]
        except ValueError as exc:  # the config's own check, named by the option
            raise ValueError(f"{option}: {exc}") from None
    return config
