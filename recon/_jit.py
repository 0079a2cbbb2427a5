"""Dr.Jit array types of the selected variant (LLVM on the CPU, CUDA on a GPU)."""
from __future__ import annotations

import importlib
from types import ModuleType

from sonarsim import runtime


def jit() -> ModuleType:
    """The ``drjit.<backend>.ad`` module matching the Mitsuba variant (e.g. ``drjit.llvm.ad``).

    Importing Mitsuba through :func:`sonarsim.runtime.mitsuba` first guarantees a working
    libLLVM; reconstruction itself needs Dr.Jit only.
    """
    runtime.mitsuba()
    variant = runtime.current_variant() or runtime.DEFAULT_VARIANT
    return importlib.import_module("drjit.cuda.ad" if variant.startswith("cuda") else "drjit.llvm.ad")
