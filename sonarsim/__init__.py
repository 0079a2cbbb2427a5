"""sonarsim: coherent 3-D synthetic aperture sonar simulation (AirSAS-style).

Importing this package only locates a working libLLVM for Dr.Jit's CPU backend
(see :mod:`sonarsim.runtime`); Mitsuba and Dr.Jit are loaded when first needed.
"""
from . import runtime as _runtime

__version__ = "0.1.0"

_runtime.configure_llvm()
