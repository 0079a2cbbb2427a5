"""recon: reconstruction of coherent 3-D SAS scenes (backprojection, gradient descent, ...).

Builds on :mod:`sonarsim` (runtime, signals, file formats); never the reverse.
"""
import sonarsim as _sonarsim  # noqa: F401  (locates libLLVM before drjit is imported)

__version__ = "0.1.0"
