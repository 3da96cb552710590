"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math
import os
import re

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
