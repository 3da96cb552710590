"""Odometry that restarts or jumps, joined into one continuous odometry frame.

A wheel odometry integrates from wherever its base controller started. When the
controller reboots, its odometry begins again (usually at (0, 0, 0)); a glitch can make
the pose jump. Differenced against the pose before it, such a record is taken as
motion: metres and radians in a tenth of a second. An odom record flagged ``reset``
(FORMATS.md section 4, extension) says so; an increment implying more than a speed or
yaw-rate limit is taken as one too (a *jump*).

:class:`OdomJoiner` keeps the poses of one continuous frame (the *joined* odometry):
across a reset or jump the increment is not applied; the joined pose stays where it
was, and the new odometry frame is placed there (:attr:`OdomJoiner.frame`, the pose of
the raw odometry frame in the joined one). Everything downstream (the Localizer's
history, the segmenter's transducer poses, the map builder's dead reckoning) works in
the joined frame and sees no motion across the reset; the robot's true motion between
the two records is unknown, and the Localizer grows its belief's covariance by
``LocalizerConfig.odom_reset_sd_m`` / ``odom_reset_sd_deg`` to cover it. Readings
taken between the two records have no pose and are skipped
(``skipped["tof_across_odom_reset"]``).
"""

from __future__ import annotations

import math
from typing import Literal

from sonarloc import se2

#: Shortest time [s] a jump test divides by: two records at nearly the same time do not
#: make a millimetre a jump.
JUMP_MIN_DT_S = 0.02

Frame = tuple[float, float, float]
Pose = tuple[float, float, float]
Restart = Literal["reset", "jump"]


def check_odom_reset_settings(max_speed_mps: float, max_yaw_rate_rad_s: float,
                              reset_sd_m: float | None = None,
                              reset_sd_deg: float | None = None) -> None:
    """Raise ``ValueError`` naming a bad setting: the limits must be positive
    (``math.inf``: no jump detection), the SDs finite and non-negative."""
    for name, v in (("odom_max_speed_mps", max_speed_mps),
                    ("odom_max_yaw_rate_rad_s", max_yaw_rate_rad_s)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ValueError(f"`{name}` must be positive (math.inf: no jump detection), "
                             f"got {v!r}")
    for name, sd in (("odom_reset_sd_m", reset_sd_m), ("odom_reset_sd_deg", reset_sd_deg)):
        if sd is None:
            continue
        if isinstance(sd, bool) or not isinstance(sd, (int, float)) or \
                not (math.isfinite(sd) and sd >= 0):
            raise ValueError(f"`{name}` must be finite and non-negative, got {sd!r}")


class OdomJoiner:
    """Joins odometry across resets and jumps (see the module docstring).

    Parameters
    ----------
    max_speed_mps : an increment between consecutive records implying a faster motion
        (distance over the time between them, at least :data:`JUMP_MIN_DT_S`) is a jump.
    max_yaw_rate_rad_s : the same for the turn [rad/s]. ``math.inf``: never.

    Use :meth:`restart` to classify a record, :meth:`join` to place it (and to move to a
    new frame at a reset or jump); records going back in time are the caller's to drop.
    """

    __slots__ = ("max_speed_mps", "max_yaw_rate_rad_s", "frame", "_last_t", "_last_raw",
                 "_last_joined")

    def __init__(self, max_speed_mps: float = 5.0, max_yaw_rate_rad_s: float = 10.0) -> None:
        check_odom_reset_settings(max_speed_mps, max_yaw_rate_rad_s)
        self.max_speed_mps = float(max_speed_mps)
        self.max_yaw_rate_rad_s = float(max_yaw_rate_rad_s)
        #: pose of the current raw odometry frame in the joined frame; None: the same
        self.frame: Frame | None = None
        self._last_t = math.nan
        self._last_raw: Pose | None = None
        self._last_joined: Pose | None = None

    def forget(self) -> None:
        """The next record starts the odometry afresh (a new prior): it is neither a
        reset nor a jump, and the frame is kept."""
        self._last_raw = self._last_joined = None
        self._last_t = math.nan

    def restart(self, t_s: float, raw: Pose, reset: bool = False) -> Restart | None:
        """Whether the raw pose ``raw`` (x_m, y_m, yaw_rad in ``odom``) at ``t_s`` starts
        a new frame: ``"reset"`` (flagged), ``"jump"`` (its increment from the last
        record implies more than the limits) or None. The first record never does."""
        last = self._last_raw
        if last is None:
            return None
        if reset:
            return "reset"
        dt = max(t_s - self._last_t, JUMP_MIN_DT_S)
        dx, dy = raw[0] - last[0], raw[1] - last[1]
        dyaw = abs((raw[2] - last[2] + math.pi) % (2.0 * math.pi) - math.pi)
        if math.hypot(dx, dy) > self.max_speed_mps * dt or \
                dyaw > self.max_yaw_rate_rad_s * dt:
            return "jump"
        return None

    def peek(self, raw: Pose) -> Pose:
        """The joined pose of ``raw`` in the current frame (nothing changes)."""
        if self.frame is None:
            return (float(raw[0]), float(raw[1]), float(raw[2]))
        j = se2.compose_floats(self.frame, raw)
        return (j[0], j[1], j[2])

    def join(self, t_s: float, raw: Pose, restart: Restart | None = None) -> Pose:
        """The joined pose of raw pose ``raw`` at ``t_s``, :meth:`restart`'s verdict
        ``restart`` applied: at a reset or jump the joined pose is the last one, and the
        new raw frame is placed there."""
        if restart is not None and self._last_joined is not None:
            joined = self._last_joined
            f = se2.compose_floats(joined, se2.between_floats(raw, (0.0, 0.0, 0.0)))
            self.frame = (f[0], f[1], f[2])
        else:
            joined = self.peek(raw)
        self._last_t = t_s
        self._last_raw = (float(raw[0]), float(raw[1]), float(raw[2]))
        self._last_joined = joined
        return joined


def raw_pose(joined: Pose, frame: Frame | None) -> Pose:
    """The raw odometry pose of joined pose ``joined`` in raw frame ``frame`` (None:
    the joined frame itself)."""
    if frame is None:
        return joined
    r = se2.between_floats(frame, joined)
    return (r[0], r[1], r[2])
