"""Dr.Jit array types of the selected variant (LLVM on the CPU, CUDA on a GPU)."""
from __future__ import annotations

import importlib
from types import ModuleType

import numpy as np

from sonarsim import runtime


def jit() -> ModuleType:
    """The ``drjit.<backend>.ad`` module matching the Mitsuba variant (e.g. ``drjit.llvm.ad``).

    Importing Mitsuba through :func:`sonarsim.runtime.mitsuba` first guarantees a working
    libLLVM; reconstruction itself needs Dr.Jit only.
    """
    runtime.mitsuba()
    variant = runtime.current_variant() or runtime.DEFAULT_VARIANT
    return importlib.import_module("drjit.cuda.ad" if variant.startswith("cuda") else "drjit.llvm.ad")


def aligned_upload(kind, values: np.ndarray, alignment: int = 64):
    """``values`` (any shape, flattened) as the Dr.Jit array type ``kind``, read from a host
    buffer whose start is aligned to ``alignment`` bytes.

    Dr.Jit's LLVM backend maps a NumPy buffer without copying it and writes the buffer's
    alignment into the kernel (vector loads ``align 32`` when the address allows it, ``align 1``
    otherwise), so the kernel's hash depends on where the allocator happened to put the array.
    A kernel that reads n freshly allocated NumPy arrays has up to 2ⁿ variants, and one that is
    rebuilt every iteration from new arrays compiles again nearly every time. An aligned buffer
    gives one variant."""
    flat = np.ascontiguousarray(values).ravel()
    raw = np.empty(flat.nbytes + alignment, dtype=np.uint8)
    start = -raw.ctypes.data % alignment
    host = raw[start:start + flat.nbytes].view(flat.dtype)
    host[:] = flat
    return kind(host)
