"""Free-form HDF5 attributes (``meta``, ``params``): scalars and numeric arrays stored
natively, everything else as JSON text listed in the attribute ``json_keys``."""
from __future__ import annotations

import json
import os
from typing import Any, Mapping

import h5py
import numpy as np

from ..errors import InputError
from .h5io import HOUSEKEEPING


def check_attr_dict(name: str, values: Mapping | None, reserved: tuple) -> dict:
    """A copy of ``values`` after checking every key and value can be stored."""
    out = dict(values or {})
    for key, value in out.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise InputError(f"{name} key {key!r} must be a non-empty string without '/'")
        if key in reserved or key in HOUSEKEEPING:
            raise InputError(f"{name} key '{key}' is reserved by the file format")
        encode_attr(f"{name}['{key}']", value)
    return out


def encode_attr(name: str, value: Any) -> tuple[Any, bool]:
    """(value as stored, stored as JSON?)"""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (bool, int, float, str)):
        return value, False
    if isinstance(value, np.ndarray) and value.dtype.kind in "biufc" and value.size:
        return value, False
    try:
        return json.dumps(value, default=json_default), True
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} cannot be stored in an HDF5 attribute ({exc})") from None


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback for NumPy values and paths."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def write_attr_dict(obj: h5py.HLObject, values: Mapping) -> None:
    json_keys = []
    for key, value in values.items():
        stored, is_json = encode_attr(key, value)
        obj.attrs[key] = stored
        if is_json:
            json_keys.append(key)
    if json_keys:
        obj.attrs["json_keys"] = json_keys


def decode_scalar(value: Any) -> Any:
    """An attribute value as plain Python (bytes -> str, NumPy scalars -> Python)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray) and value.dtype.kind in "OSU":
        return [decode_scalar(v) for v in value.tolist()]
    return value
