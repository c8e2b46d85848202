"""One 1e-9 relative comparison for the compiled core's parity tests (tests/test_core_*.py): the
core against its Python reference (issue 19: state and covariance to 1e-9 relative, events
identical).

``differences(a, b, path)`` walks two values (dataclass records, dicts, tuples/lists, numpy arrays,
numbers, strings) and lists (path, why) for every leaf that is not equal in this sense:

- a float: |a - b| <= RTOL max(|a|, |b|), or both NaN; an angle (a name ending in ``_rad``) against
  max(|a|, |b|, 1 rad): it is read off a unit quaternion or direction cosines, compared in their max
  norm, so a roll of 3e-7 rad at a level rest carries their ~1e-16 rad of rounding;
- a vector or a matrix that is not a covariance: max |a - b| <= RTOL max(max |a|, max |b|) (the
  max norm of the array: quaternions, biases, direction cosines);
- a covariance (a square 2-D array whose name is ``P``, starts with ``P_`` or holds ``cov``): per
  element |a_ij - b_ij| <= RTOL sqrt(|a_ii a_jj|), or both NaN (a failed fit's). The core's matrix
  products sum in another order than numpy's BLAS: an element that is 0 in exact arithmetic comes out
  ~1e-21 there, which no relative measure of the element itself can take;
- anything else (bools, ints, strings, None, types): identical (numpy scalars count as the Python
  ones: references hold some flags as numpy.bool_).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

RTOL = 1e-9


def _is_cov(path: str) -> bool:
    name = path.rsplit(".", 1)[-1].split("[", 1)[0]
    return name == "P" or name.startswith("P_") or "cov" in name


def differences(a, b, path: str = "", rtol: float = RTOL) -> list[tuple[str, str]]:
    """(path, why) of every leaf of ``a`` and ``b`` that differs (see the module docstring)."""
    bad: list[tuple[str, str]] = []
    _walk(a, b, path, rtol, bad)
    return bad


_SAME_WHEN_EQUAL = frozenset({float, int, str, bool, type(None)})
"""Leaf types that pass as soon as ``a == b`` with ``type(a) is type(b)`` (what ``_walk`` would
decide for them): checked before building a child's path, which is most of a walk's time (a
flight's solutions are ~10^6 leaves, nearly all equal)."""
_FIELDS: dict = {}


def _field_names(cls) -> tuple:
    names = _FIELDS.get(cls)
    if names is None:
        names = _FIELDS[cls] = tuple(f.name for f in dataclasses.fields(cls))
    return names


def _walk(a, b, path: str, rtol: float, bad: list) -> None:
    if isinstance(a, np.generic):
        a = a.item()
    if isinstance(b, np.generic):
        b = b.item()
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        if type(a) is not type(b):
            bad.append((path, f"{type(a).__name__} vs {type(b).__name__}"))
            return
        for name in _field_names(type(a)):
            x, y = getattr(a, name), getattr(b, name)
            if type(x) is type(y) and type(x) in _SAME_WHEN_EQUAL and x == y:
                continue
            _walk(x, y, f"{path}.{name}", rtol, bad)
    elif isinstance(a, dict):
        if not isinstance(b, dict) or set(a) != set(b):
            bad.append((path, f"keys {sorted(a) if isinstance(a, dict) else a!r} vs "
                              f"{sorted(b) if isinstance(b, dict) else b!r}"))
            return
        for k in a:
            x, y = a[k], b[k]
            if type(x) is type(y) and type(x) in _SAME_WHEN_EQUAL and x == y:
                continue
            _walk(x, y, f"{path}.{k}", rtol, bad)
    elif isinstance(a, (tuple, list)):
        if not isinstance(b, (tuple, list)) or len(a) != len(b):
            bad.append((path, f"{a!r} vs {b!r}"))
            return
        for i, (x, y) in enumerate(zip(a, b)):
            if type(x) is type(y) and type(x) in _SAME_WHEN_EQUAL and x == y:
                continue
            _walk(x, y, f"{path}[{i}]", rtol, bad)
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            bad.append((path, f"{a!r} vs {b!r}"))
            return
        if (a.dtype == b.dtype and a.dtype.kind in "biuf" and a.shape == b.shape and a.tobytes() == b.tobytes()
                and (a.dtype.kind != "f" or np.isfinite(a).all())):
            return   # the same finite numbers, bit for bit: within any tolerance below (a NaN or an inf is not)
        x, y = a.astype(float), b.astype(float)
        if x.shape != y.shape:
            bad.append((path, f"shape {x.shape} vs {y.shape}"))
        elif x.ndim == 2 and x.shape[0] == x.shape[1] and _is_cov(path):
            scale = np.sqrt(np.abs(np.outer(np.diag(x), np.diag(x))))
            over = np.where(np.isnan(x) & np.isnan(y), 0.0, np.abs(x - y) - rtol * scale)
            if not np.all(over <= 0.0):   # NaN fails too, unless both are (as a float)
                i, j = np.unravel_index(int(np.nanargmax(np.where(np.isnan(over), np.inf, over))), x.shape)
                bad.append((path, f"covariance [{i}, {j}] {x[i, j]!r} vs {y[i, j]!r}: off by "
                                  f"{abs(x[i, j] - y[i, j]):.3g} > {rtol:g} sqrt(P_ii P_jj) = {rtol * scale[i, j]:.3g}"))
        else:
            same_nan = np.isnan(x) & np.isnan(y)
            m = max(float(np.max(np.abs(np.where(same_nan, 0.0, x)), initial=0.0)),
                    float(np.max(np.abs(np.where(same_nan, 0.0, y)), initial=0.0)))
            ok = same_nan | (np.abs(x - y) <= rtol * m)
            if not np.all(ok):
                bad.append((path, f"{x!r} vs {y!r}"))
    elif (isinstance(a, float) or isinstance(b, float)) and all(
            isinstance(x, (float, int)) and not isinstance(x, bool) for x in (a, b)):
        scale = max(abs(a), abs(b), 1.0 if path.endswith("_rad") else 0.0)
        if not (a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= rtol * scale):
            bad.append((path, f"{a!r} vs {b!r}"))
    elif a != b or type(a) is not type(b):
        bad.append((path, f"{a!r} vs {b!r}"))
