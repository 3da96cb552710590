"""Landmarks from the fit output JSON (FORMATS.md section 2) back into :class:`Landmark`.

``sonarloc fit SCAN.csv --json`` prints ``{"landmarks": [...]}``; plots and reports read
that file. Angles are degrees in the JSON and radians in :class:`Landmark`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from sonarloc.errors import LogFormatError
from sonarloc.fit.result import FitStatus, Landmark


def _num(obj: dict[str, Any], name: str, where: str) -> float:
    v = obj.get(name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise LogFormatError(f"{where}: field `{name}` must be a finite number, got {v!r}")
    return float(v)


def landmark_from_dict(obj: dict[str, Any], where: str = "landmark") -> Landmark:
    """One landmark object of FORMATS.md section 2 (``where`` names it in errors)."""
    kind = obj.get("kind")
    if kind == "point":
        params = [_num(obj, "x_m", where), _num(obj, "y_m", where)]
    elif kind == "line":
        params = [_num(obj, "rho_m", where), math.radians(_num(obj, "alpha_deg", where))]
    else:
        raise LogFormatError(f"{where}: `kind` must be 'point' or 'line', got {kind!r}")
    params.append(_num(obj, "kappa_us", where))
    cov = np.asarray(obj.get("cov", np.full((3, 3), np.nan)), dtype=float)
    if cov.shape != (3, 3):
        raise LogFormatError(f"{where}: `cov` must be 3x3, got shape {cov.shape}")
    status = obj.get("status", "ok")
    try:
        st = FitStatus(status)
    except ValueError:
        st = FitStatus.OK if status in (None, True) else FitStatus.UNRESOLVED
    n = obj.get("n_readings", 0)
    return Landmark(kind=kind, params=np.array(params), cov=cov,
                    range_m=_num(obj, "range_m", where),
                    bearing_rad=math.radians(_num(obj, "bearing_deg", where)),
                    n_readings=int(n) if isinstance(n, int) else 0,
                    ref_t_s=float(obj.get("ref_t_s", math.nan) or math.nan),
                    ref_pose=(math.nan, math.nan, math.nan), status=st,
                    reason=str(obj.get("reason", "")), tier=str(obj.get("tier", "gauss")))


def read_fit_json(path: str | Path) -> list[Landmark]:
    """The landmarks of a ``sonarloc fit --json`` output file."""
    try:
        obj = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as err:
        raise LogFormatError(f"cannot open fit JSON {path}: {err.strerror}") from err
    except json.JSONDecodeError as err:
        raise LogFormatError(f"fit JSON {path}: line {err.lineno}: {err.msg}") from err
    items = obj.get("landmarks") if isinstance(obj, dict) else None
    if not isinstance(items, list):
        raise LogFormatError(f"fit JSON {path}: expected an object with a `landmarks` list")
    return [landmark_from_dict(x, f"{path}: landmarks[{i}]") for i, x in enumerate(items)
            if isinstance(x, dict)]
