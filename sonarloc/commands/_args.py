"""Argument helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math
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
