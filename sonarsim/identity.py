"""Identity of a request: one digest of the values that determine an output.

Every "is this the same run?" question of the project (a finished ``simulate`` output, a
batch job and its reconstruction steps, a solver checkpoint's dataset, a stale scratch file)
is answered by comparing :func:`digest` values, so that two runs agree on what "the same
inputs" means:

* NumPy arrays count by dtype, shape and bytes; NumPy scalars as Python numbers;
* numbers by value: ``20`` and ``20.0`` are the same setting (a TOML ``snr_db = 20`` and the
  CLI's ``--snr-db 20`` name one run); ``True``/``False`` are not numbers here;
* strings, ``None``, paths (by their text), lists and tuples (in order), dicts (by sorted key),
  dataclasses (type name and fields), meshes (anything with ``vertices`` and ``faces``);
* callables count as "a callable" (loggers and callbacks never change an output);
* anything else by ``repr``, which must not hold a memory address (:class:`TypeError` if it
  does, rather than a digest that differs on every run).

Each value is fed with a type tag and its length, so ``["ab"]`` and ``["a", "b"]`` differ.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import re

import numpy as np

DIGEST_CHARS = 24          # hex characters kept (96 bits): ample for telling runs apart
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+>")


class _Feeder:
    """Feeds values into a SHA-256 hash with type tags (see the module docstring)."""

    def __init__(self):
        self.h = hashlib.sha256()

    def tag(self, kind: bytes, payload: bytes = b"") -> None:
        self.h.update(kind + str(len(payload)).encode() + b":" + payload)

    def feed(self, v) -> None:
        if v is None:
            self.tag(b"N")
        elif isinstance(v, (bool, np.bool_)):
            self.tag(b"B", b"1" if v else b"0")
        elif isinstance(v, (int, float, np.integer, np.floating)):
            self.tag(b"n", _number_text(v).encode())
        elif isinstance(v, str):
            self.tag(b"s", v.encode("utf-8", "surrogatepass"))
        elif isinstance(v, os.PathLike):
            self.tag(b"s", os.fspath(v).encode("utf-8", "surrogatepass"))
        elif isinstance(v, bytes):
            self.tag(b"y", v)
        elif isinstance(v, np.ndarray):
            self.tag(b"a", f"{v.dtype.str}{v.shape}".encode())
            self.h.update(np.ascontiguousarray(v).tobytes())
        elif dataclasses.is_dataclass(v) and not isinstance(v, type):
            fields = dataclasses.fields(v)
            self.tag(b"D", f"{type(v).__name__}:{len(fields)}".encode())
            for f in fields:
                self.tag(b"k", f.name.encode())
                self.feed(getattr(v, f.name))
        elif isinstance(v, dict):
            self.tag(b"d", str(len(v)).encode())
            for k in sorted(v, key=str):
                self.feed(str(k))
                self.feed(v[k])
        elif isinstance(v, (list, tuple)):
            self.tag(b"l", str(len(v)).encode())
            for item in v:
                self.feed(item)
        elif hasattr(v, "vertices") and hasattr(v, "faces"):       # a mesh
            self.tag(b"m")
            self.feed(np.asarray(v.vertices))
            self.feed(np.asarray(v.faces))
        elif callable(v):
            self.tag(b"c")
        else:
            text = repr(v)
            if _ADDRESS.search(text):
                raise TypeError(f"identity.digest: {type(v).__name__} has no stable value "
                                f"({text[:60]}); pass its contents instead")
            self.tag(b"r", text.encode())


def _number_text(v) -> str:
    """One text per numerical value: integral floats as integers, others by ``repr``."""
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    f = float(v)
    if math.isfinite(f) and f.is_integer():
        return str(int(f))
    return repr(f)


def digest(*values, length: int = DIGEST_CHARS) -> str:
    """Hex digest (``length`` characters) of ``values`` (see the module docstring)."""
    feeder = _Feeder()
    feeder.tag(b"T", str(len(values)).encode())
    for value in values:
        feeder.feed(value)
    return feeder.h.hexdigest()[:length]


def dataset_digest(dataset, length: int = DIGEST_CHARS) -> str:
    """Digest of what a sonar dataset holds for a reconstruction: waveforms, poses,
    boresights, pulse, sampling (fs, sound speed, first sample), the per-ping temperatures
    if any and the waveform kind (real or deconvolved). ``dataset``: a :class:`sonarsim.dataset.SonarDataset`."""
    parts = [np.asarray(getattr(dataset, name)) for name in ("waveforms", "tx", "rx", "pulse")]
    extra = {name: getattr(dataset, name, None)
             for name in ("boresight", "rx_boresight", "temperatures")}
    return digest(*parts, {k: (None if v is None else np.asarray(v)) for k, v in extra.items()},
                  float(dataset.fs), float(dataset.sound_speed), int(dataset.start_sample),
                  str(getattr(dataset, "waveform_kind", "real")), length=length)
