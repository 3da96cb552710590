"""Reflector kinds and their reflecting strength kappa = tau/A0 [us].

Smaller kappa means a stronger echo (a shorter threshold delay). The paper's values
at 1.5 m (Kuc 2003): 1 m plane 0.15 us, 8.9 cm pole 0.67 us, 8 mm rod 2.68 us.

* ``plane``/``wall``: a specular plane; echoes only from the normal-incidence point.
* ``corner``: a concave right-angle corner returns the wave by two reflections, like
  a plane mirror facing the sonar: as strong as a plane (Kuc 2003, Sec. III).
* ``edge``: a convex edge diffracts weakly and is detectable only nearer than
  ``EDGE_MAX_RANGE_M`` (0.5 m, Kuc 1990): modelled as a rod-strength reflector with
  that hard range limit.
* ``pole``/``rod``/``point``: vertical cylinders (the ``point`` kind without a radius
  is a generic small landmark as strong as the paper's pole).

Cylinder strength against radius (:func:`cylinder_kappa_us`). A convex cylinder of
radius a, extending above and below the beam, reflects specularly; its curvature
spreads the echo horizontally. By geometric acoustics (reflected wavefront radii r
vertically and r a/(a + 2r) horizontally at the surface, then spreading back over r)
its echo amplitude relative to a plane at the same range r is sqrt(a / (a + r)),
so kappa_cyl = kappa_inf * sqrt((a + r)/a). That rule alone gives the pole/rod
strength ratio as 3.31 (10.4 dB); the paper measured 4 (12 dB): the 8 mm rod
(ka = 3.6 at 49.4 kHz) is already leaving the geometric regime, where a cylinder
much thinner than the wavelength scatters as (ka)^(3/2) relative to geometric
(2-D Rayleigh scattering). We join both limits with

    f(ka) = sqrt((ka)^3 / ((ka)^3 + c^3)),   kappa_cyl = kappa_inf sqrt((a + r)/a) / f(ka)

and fix the two constants (kappa_inf = 0.114 us, c = 2.83) so that the rule gives
exactly the paper's pole (a = 4.45 cm, 0.67 us) and rod (a = 4 mm, 2.68 us) at 1.5 m.
The crossover c means a = 3.1 mm: thinner rods fade fast (radius 2 mm: 6.8 us).
kappa_inf is not the plane's 0.15 us: the paper's 1 m plane came out 2.4 dB weaker
than this infinite-radius limit; planes keep the measured value.

Range: the module's time-variable gain keeps a plane's on-axis amplitude constant
over range; a cylinder's relative amplitude falls as sqrt(a/(a + r)), so its kappa
grows as sqrt((a + r)/(a + r_ref)) (:func:`kappa_at_range_us`).
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.physics.tof import ModuleParams

REFERENCE_RANGE_M = 1.5
"""Range at which the paper measured its kappa values (and default kappas apply)."""

PLANE_KAPPA_US = 0.15
POLE_KAPPA_US = 0.67
ROD_KAPPA_US = 2.68
POLE_RADIUS_M = 0.0445
"""The paper's pole: 8.9 cm diameter."""
ROD_RADIUS_M = 0.004
"""The paper's rod: 8 mm diameter."""

EDGE_MAX_RANGE_M = 0.5
"""Edges produce detectable echoes only nearer than this (Kuc 1990)."""


class ReflectorKind(enum.StrEnum):
    """Kinds of reflector a map may hold (FORMATS.md section 3)."""

    PLANE = "plane"
    WALL = "wall"
    POLE = "pole"
    ROD = "rod"
    CORNER = "corner"
    EDGE = "edge"
    POINT = "point"

    @classmethod
    def parse(cls, name: str | ReflectorKind) -> ReflectorKind:
        """Kind from its name (case-insensitive); ValueError naming a bad one."""
        if isinstance(name, ReflectorKind):
            return name
        try:
            return cls(str(name).strip().lower())
        except ValueError:
            kinds = ", ".join(k.value for k in cls)
            raise ValueError(f"`kind` must be one of {kinds}; got {name!r}") from None

    @property
    def is_cylinder(self) -> bool:
        """Pole, rod and point: vertical cylinders (radius may be 0)."""
        return self in (ReflectorKind.POLE, ReflectorKind.ROD, ReflectorKind.POINT)

    @property
    def is_planar(self) -> bool:
        """Plane and wall: specular segments."""
        return self in (ReflectorKind.PLANE, ReflectorKind.WALL)


_DEFAULT_KAPPA_US = {
    ReflectorKind.PLANE: PLANE_KAPPA_US,
    ReflectorKind.WALL: PLANE_KAPPA_US,
    ReflectorKind.CORNER: PLANE_KAPPA_US,
    ReflectorKind.POLE: POLE_KAPPA_US,
    ReflectorKind.POINT: POLE_KAPPA_US,
    ReflectorKind.ROD: ROD_KAPPA_US,
    ReflectorKind.EDGE: ROD_KAPPA_US,
}

_DEFAULT_RADIUS_M = {ReflectorKind.POLE: POLE_RADIUS_M, ReflectorKind.ROD: ROD_RADIUS_M}


def _wavenumber(params: ModuleParams) -> float:
    return 2.0 * math.pi * params.carrier_hz / params.c_mps


def _roll_off(ka: NDArray[np.float64], c: float) -> NDArray[np.float64]:
    """f(ka) = sqrt((ka)^3 / ((ka)^3 + c^3)): 1 for thick cylinders, (ka/c)^1.5 for thin."""
    x3 = ka ** 3
    return np.sqrt(x3 / (x3 + c ** 3))


@functools.lru_cache(maxsize=8)
def cylinder_rule_constants(params: ModuleParams = ModuleParams()) -> tuple[float, float]:
    """(kappa_inf [us], c) of the cylinder rule, fitted to the paper's pole and rod.

    ``c`` in closed form: with ``P, R`` the cubes of ``ka`` of the pole and the rod,
    ``G`` their geometric strength ratio ``sqrt((a_rod + r)/a_rod) / sqrt((a_pole + r)
    /a_pole)`` and ``Q`` the paper's ratio 2.68/0.67, the squared rule
    ``G^2 P (R + c^3) / (R (P + c^3)) = Q^2`` is linear in ``c^3``:
    ``c^3 = P R (Q^2 - G^2) / (G^2 P - Q^2 R)``, positive for every module: Q^2 = 16
    exceeds G^2 = 10.8, and ``P / R`` (the radius ratio cubed, 1.4e3) exceeds
    ``Q^2 / G^2``.
    """
    k = _wavenumber(params)
    r = REFERENCE_RANGE_M

    def geo(a: float) -> float:
        return math.sqrt((a + r) / a)

    p3, r3 = (k * POLE_RADIUS_M) ** 3, (k * ROD_RADIUS_M) ** 3
    g2 = (geo(ROD_RADIUS_M) / geo(POLE_RADIUS_M)) ** 2
    q2 = (ROD_KAPPA_US / POLE_KAPPA_US) ** 2
    c = (p3 * r3 * (q2 - g2) / (g2 * p3 - q2 * r3)) ** (1.0 / 3.0)
    f_pole = float(_roll_off(np.array(k * POLE_RADIUS_M), c))
    return POLE_KAPPA_US * f_pole / geo(POLE_RADIUS_M), c


def _check_nonneg(name: str, value: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=float)
    bad = ~(np.isfinite(arr) & (arr >= 0))
    if bad.any():
        raise ValueError(f"`{name}` must be non-negative and finite, got "
                         f"{float(arr.reshape(-1)[int(np.argmax(bad.reshape(-1)))])!r}")
    return arr


def _check_pos(name: str, value: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=float)
    bad = ~(np.isfinite(arr) & (arr > 0))
    if bad.any():
        raise ValueError(f"`{name}` must be positive and finite, got "
                         f"{float(arr.reshape(-1)[int(np.argmax(bad.reshape(-1)))])!r}")
    return arr


def cylinder_kappa_us(
    radius_m: ArrayLike, range_m: ArrayLike = REFERENCE_RANGE_M,
    params: ModuleParams = ModuleParams(),
) -> NDArray[np.float64]:
    """Reflecting strength of a vertical cylinder of radius ``radius_m`` at ``range_m``.

    kappa = kappa_inf sqrt((a + r)/a) / f(ka) (see the module docstring): the paper's
    0.67 us for the 8.9 cm pole and 2.68 us for the 8 mm rod at 1.5 m.

    Parameters
    ----------
    radius_m : (...,) cylinder radius a [m], > 0.
    range_m : (...,) range r from the transducer to the cylinder's surface [m], > 0.

    Returns
    -------
    (...,) kappa [us], broadcast shape of the inputs.

    Examples
    --------
    >>> round(float(cylinder_kappa_us(0.0445)), 3), round(float(cylinder_kappa_us(0.004)), 3)
    (0.67, 2.68)
    """
    a = _check_pos("radius_m", radius_m)
    r = _check_pos("range_m", range_m)
    kappa_inf, c = cylinder_rule_constants(params)
    return kappa_inf * np.sqrt((a + r) / a) / _roll_off(_wavenumber(params) * a, c)


def default_kappa_us(kind: str | ReflectorKind, radius_m: float = 0.0,
                     params: ModuleParams = ModuleParams()) -> float:
    """Default reflecting strength [us] at the reference range 1.5 m.

    Cylinders (pole, rod, point) with ``radius_m > 0`` follow
    :func:`cylinder_kappa_us`; without a radius they take the paper's value for their
    kind (pole and point 0.67 us, rod 2.68 us). Planes, walls and corners 0.15 us;
    edges 2.68 us (and only within ``EDGE_MAX_RANGE_M``).
    """
    k = ReflectorKind.parse(kind)
    radius = float(_check_nonneg("radius_m", radius_m))
    if k.is_cylinder and radius > 0:
        return float(cylinder_kappa_us(radius, REFERENCE_RANGE_M, params))
    return _DEFAULT_KAPPA_US[k]


def kappa_at_range_us(
    kappa_us: ArrayLike, kind: str | ReflectorKind, range_m: ArrayLike,
    radius_m: ArrayLike = 0.0,
) -> NDArray[np.float64]:
    """Strength at ``range_m`` of a reflector whose strength at 1.5 m is ``kappa_us``.

    Planes, walls, corners and edges keep their kappa (the module's gain compensates a
    plane's spreading); cylinders grow as sqrt((a + r)/(a + 1.5 m)), with a the radius
    (the kind's default radius for a pole or rod given without one, 0 for a point).

    Parameters
    ----------
    kappa_us : (...,) strength at the reference range [us].
    range_m : (...,) range to the reflecting surface [m].
    radius_m : (...,) cylinder radius [m] (ignored for other kinds).
    """
    k = ReflectorKind.parse(kind)
    kap = _check_pos("kappa_us", kappa_us)
    r = _check_pos("range_m", range_m)
    a = _check_nonneg("radius_m", radius_m)
    if not k.is_cylinder:
        return np.broadcast_to(kap, np.broadcast_shapes(kap.shape, r.shape)).astype(float)
    a = np.where(a > 0, a, _DEFAULT_RADIUS_M.get(k, 0.0))
    return kap * np.sqrt((a + r) / (a + REFERENCE_RANGE_M))


def max_range_m(kind: str | ReflectorKind) -> float:
    """Largest range at which a reflector of this kind echoes (inf except for edges)."""
    return EDGE_MAX_RANGE_M if ReflectorKind.parse(kind) is ReflectorKind.EDGE else math.inf


@dataclass(frozen=True)
class Reflector:
    """A reflector's kind, strength at 1.5 m [us], radius [m] and range limit [m]."""

    kind: ReflectorKind
    kappa_us: float
    radius_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", ReflectorKind.parse(self.kind))
        _check_pos("kappa_us", self.kappa_us)
        _check_nonneg("radius_m", self.radius_m)
        if self.radius_m > 0 and not self.kind.is_cylinder:
            raise ValueError(
                f"`radius_m` applies to pole, rod and point reflectors only; got "
                f"{self.radius_m!r} for a {self.kind.value}"
            )

    @property
    def max_range_m(self) -> float:
        return max_range_m(self.kind)

    def kappa_at_range_us(self, range_m: ArrayLike) -> NDArray[np.float64]:
        """Strength at ``range_m`` (see :func:`kappa_at_range_us`)."""
        return kappa_at_range_us(self.kappa_us, self.kind, range_m, self.radius_m)


def make_reflector(kind: str | ReflectorKind, radius_m: float | None = None,
                   kappa_us: float | None = None,
                   params: ModuleParams = ModuleParams()) -> Reflector:
    """A :class:`Reflector` with defaults filled in.

    ``kappa_us`` given wins; otherwise :func:`default_kappa_us` from the kind and
    radius. ``radius_m`` defaults to 0 (for a pole or rod given without a radius, the
    default kappa is the paper's value for that kind).
    """
    radius = 0.0 if radius_m is None else float(_check_nonneg("radius_m", radius_m))
    kap = default_kappa_us(kind, radius, params) if kappa_us is None else kappa_us
    return Reflector(ReflectorKind.parse(kind), float(_check_pos("kappa_us", kap)), radius)
