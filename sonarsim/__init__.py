"""sonarsim: coherent 3-D synthetic aperture sonar simulation (AirSAS-style).

Importing this package has no side effects: Dr.Jit's libLLVM is located and Mitsuba's
variant selected on first use of the runtime (:func:`sonarsim.runtime.mitsuba`).
"""
__version__ = "0.1.0"
