"""Value checks shared by the file objects' constructors and readers.

Array shapes are patterns: ints are fixed sizes, strings are named sizes ("N", "T", ...)
that must agree across all arrays checked with the same ``dims`` dict.  Failures raise
:class:`InputError` with one line naming the field.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InputError


def shape_text(pattern: tuple) -> str:
    return "(" + ", ".join(str(p) for p in pattern) + (",)" if len(pattern) == 1 else ")")


def shape_error(shape: tuple, pattern: tuple, dims: dict, source: str) -> str | None:
    """Why ``shape`` does not fit ``pattern`` (ints fixed, strings named sizes kept in
    ``dims`` across arrays), or None.  Records newly seen named sizes in ``dims``."""
    expected = shape_text(pattern)
    if len(shape) != len(pattern):
        return expected
    seen = {}
    for size, want in zip(shape, pattern):
        if isinstance(want, int):
            if size != want:
                return expected
        elif want in dims and dims[want][0] != size:
            value, origin = dims[want]
            return f"{expected} with {want} = {value} (from '{origin}')"
        elif want in seen and seen[want] != size:
            return expected
        else:
            seen[want] = size
    for name, size in seen.items():
        dims.setdefault(name, (size, source))
    return None


def as_array(name: str, value: Any, pattern: tuple, dtype, dims: dict, *,
             kinds: str = "fiu", finite: bool = True) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype`` with shape ``pattern``."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array ({exc})") from None
    if arr.dtype.kind not in kinds:
        want = ("complex" if kinds == "c" else
                "complex or real" if "c" in kinds else "real")
        raise InputError(f"{name} has dtype {arr.dtype}, expected {want} numbers")
    err = shape_error(arr.shape, pattern, dims, name)
    if err:
        raise InputError(f"{name} has shape {arr.shape}, expected {err}")
    arr = np.ascontiguousarray(arr, dtype=dtype)
    if finite and arr.dtype.kind in "fc" and not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or inf")
    return arr


def as_float(name: str, value: Any, *, positive: bool = False) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(out) or (positive and out <= 0):
        raise InputError(f"{name} must be {'positive and ' if positive else ''}finite, got {out}")
    return out


def as_int(name: str, value: Any, *, minimum: int | None = None) -> int:
    """An integer (or an integral float); bools are refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        if not (isinstance(value, (float, np.floating)) and float(value).is_integer()):
            raise InputError(f"{name} must be an integer, got {value!r}")
    out = int(value)
    if minimum is not None and out < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {out}")
    return out


def as_unit_rows(name: str, value: Any, dims: dict) -> np.ndarray:
    """float64 [N, 3] directions normalised to unit length."""
    vec = as_array(name, value, ("N", 3), np.float64, dims)
    norm = np.linalg.norm(vec, axis=1, keepdims=True)
    if (norm <= 0).any():
        raise InputError(f"{name} has a zero-length direction in row {int(np.argmin(norm))}")
    # Rows already unit length are kept bit for bit, so reading back is exact.
    return np.where(np.abs(norm - 1.0) > 1e-12, vec / norm, vec)


def as_name(name: str, value: Any) -> str:
    """A non-empty string (``source``, ``method``)."""
    if not isinstance(value, str) or not value:
        raise InputError(f"{name} must be a non-empty string, got {value!r}")
    return value


def ping_index(indices: Any) -> Any:
    """``indices`` usable to pick pings while keeping the ping axis (int -> [int])."""
    return [indices] if isinstance(indices, (int, np.integer)) else indices
