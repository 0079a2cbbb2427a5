"""recon: reconstruction of coherent 3-D SAS scenes (backprojection, gradient descent, ...).

Builds on :mod:`sonarsim` (runtime, signals, file formats); never the reverse.
"""
# Dr.Jit is reached through sonarsim.runtime.mitsuba() (recon._jit), which locates libLLVM first.

__version__ = "0.1.0"
