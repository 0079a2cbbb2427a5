"""Validating HDF5 reader: every problem becomes a one-line :class:`FormatError` naming
the file and the field."""
from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Iterator, NoReturn

import h5py
import numpy as np

from ..errors import FormatError, InputError
from .attributes import decode_scalar
from .checks import shape_error
from .h5io import FORMAT_VERSION, HOUSEKEEPING, INCOMPLETE, KIND_NAMES, PathLike


class Reader:
    """Reads datasets/attributes of one open file, raising FormatError naming the file
    and field.  Named sizes (N, T, ...) are checked for consistency across datasets."""

    def __init__(self, f: h5py.File, label: str):
        self.f, self.label, self.dims = f, label, {}
        self.version = FORMAT_VERSION

    def fail(self, message: str) -> NoReturn:
        raise FormatError(f"{self.label}: {message}")

    def attrs_of(self, group: str) -> h5py.AttributeManager:
        """Attributes of ``group`` ('' = root)."""
        return self.f[group].attrs if group else self.f.attrs

    def dataset(self, name: str, pattern: tuple, kinds: str, *, dtype=None,
                optional: bool = False, load: bool = True, finite: bool = True):
        """The validated array (or the h5py.Dataset if ``load`` is False); None if
        ``optional`` and absent.  ``kinds``: allowed dtype kinds; ``dtype``: exact dtype."""
        try:
            obj = self.f.get(name)
        except (KeyError, OSError, RuntimeError) as exc:
            self.fail(f"cannot read '{name}' ({first_line(exc)})")
        if obj is None:
            if optional:
                return None
            self.fail(f"missing dataset '{name}'")
        if not isinstance(obj, h5py.Dataset):
            self.fail(f"'{name}' is a group, expected a dataset")
        if (dtype is not None and obj.dtype != np.dtype(dtype)) or obj.dtype.kind not in kinds:
            want = np.dtype(dtype).name if dtype is not None else _kinds_text(kinds)
            self.fail(f"dataset '{name}' has dtype {obj.dtype}, expected {want}")
        err = shape_error(obj.shape or (), pattern, self.dims, name)
        if err:
            self.fail(f"dataset '{name}' has shape {obj.shape}, expected {err}")
        if not load:
            return obj
        try:
            arr = obj[()]
        except (OSError, RuntimeError) as exc:
            self.fail(f"cannot read dataset '{name}', file truncated or corrupt "
                      f"({first_line(exc)})")
        if finite and arr.dtype.kind in "fc" and not np.isfinite(arr).all():
            self.fail(f"dataset '{name}' contains NaN or inf")
        return arr

    def attr(self, group: str, name: str, kind: str, *, optional: bool = False):
        """A scalar attribute of ``group`` ('' = root) as float/int/str/bool."""
        where = f"attribute '{name}'" + (f" of group '{group.rstrip('/')}'" if group else "")
        attrs = self.attrs_of(group)
        if name not in attrs:
            if optional:
                return None
            self.fail(f"missing {where}")
        value = decode_scalar(attrs[name])
        if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
            value = decode_scalar(value.reshape(-1)[0])
        ok = {"float": isinstance(value, (int, float)) and not isinstance(value, bool),
              "int": isinstance(value, int) and not isinstance(value, bool),
              "str": isinstance(value, str),
              "bool": isinstance(value, (bool, int))}[kind]
        if not ok:
            self.fail(f"{where} is {value!r}, expected {'a ' if kind != 'int' else 'an '}{kind}")
        if kind == "float":
            value = float(value)
            if not np.isfinite(value):
                self.fail(f"{where} is {value}, expected a finite number")
        return bool(value) if kind == "bool" else value

    def attr_dict(self, group: str, reserved: tuple) -> dict:
        """The free-form attributes of ``group`` (all but ``reserved`` and housekeeping)."""
        attrs = self.attrs_of(group)
        json_keys = set(decode_scalar(attrs["json_keys"])) if "json_keys" in attrs else set()
        out = {}
        for key in attrs:
            if key in reserved or key in HOUSEKEEPING:
                continue
            value = decode_scalar(attrs[key])
            if key in json_keys:
                try:
                    value = json.loads(value)
                except (TypeError, ValueError):
                    self.fail(f"attribute '{key}' is not valid JSON")
            out[key] = value
        return out

    def check_kind(self, expected: str | None, group: str = "",
                   allow_partial: bool = False) -> str:
        """The validated ``format`` of ``group`` ('' = root); also checks the version and,
        at the root, that the file is complete (unless ``allow_partial``)."""
        if "format" not in self.attrs_of(group):
            self.fail("not a sonarsim file (root attribute 'format' missing)" if not group
                      else f"attribute 'format' of group '{group}' missing")
        kind = self.attr(group, "format", "str")
        if kind not in KIND_NAMES:
            self.fail(f"attribute 'format' is '{kind}', not a sonarsim format "
                      f"({', '.join(KIND_NAMES)})")
        if expected is not None and kind != expected:
            self.fail(f"attribute 'format' is '{kind}', expected '{expected}' "
                      f"(this is a {KIND_NAMES[kind]} file, not a {KIND_NAMES[expected]} file)")
        version = self.attr(group, "format_version", "int")
        if not group:
            self.version = version
        if version > FORMAT_VERSION:
            self.fail(f"format_version {version} is newer than this sonarsim reads "
                      f"({FORMAT_VERSION}); upgrade sonarsim")
        if version < 1:
            self.fail(f"attribute 'format_version' is {version}, expected >= 1")
        if not group and not allow_partial and \
                self.attr(group, "complete", "bool", optional=True) is False:
            self.fail(INCOMPLETE)
        return kind

    def construct(self, cls, fields: dict):
        """``cls(**fields)``, its InputError turned into a FormatError naming the file."""
        try:
            return cls(**fields)
        except InputError as exc:
            raise FormatError(f"{self.label}: {exc}") from None


def _kinds_text(kinds: str) -> str:
    names = {"f": "float", "i": "int", "u": "unsigned int", "c": "complex", "b": "bool"}
    return " or ".join(names[k] for k in kinds)


def first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _check_file(path: PathLike) -> str:
    """``path`` as a label, after checking it exists and is an HDF5 file."""
    label = os.fspath(path)
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{label}: no such file")
    if p.is_dir():
        raise FormatError(f"{label}: is a directory, expected an HDF5 file")
    if p.stat().st_size == 0:
        raise FormatError(f"{label}: empty file (0 bytes), expected an HDF5 file")
    try:
        is_h5 = h5py.is_hdf5(p)
    except OSError as exc:
        raise FormatError(f"{label}: cannot read ({first_line(exc)})") from None
    if not is_h5:
        raise FormatError(f"{label}: not an HDF5 file")
    return label


@contextlib.contextmanager
def open_checked(path: PathLike, expected: str | None = None,
                 allow_partial: bool = False) -> Iterator[tuple[str, Reader]]:
    """Open ``path`` read-only, check format/version/completeness; yield (kind, reader)."""
    label = _check_file(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise FormatError(f"{label}: cannot open as HDF5, file truncated or corrupt "
                          f"({first_line(exc)})") from None
    with f:
        rd = Reader(f, label)
        try:
            kind = rd.check_kind(expected, allow_partial=allow_partial)
            yield kind, rd
        except (OSError, RuntimeError, KeyError) as exc:
            raise FormatError(f"{label}: cannot read, file truncated or corrupt "
                              f"({first_line(exc)})") from None
