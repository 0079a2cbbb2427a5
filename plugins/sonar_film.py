"""Mitsuba film ``sonar_film``: the time axis of a ``sonar`` sensor's histograms.

A histogram of ``temporal_bins`` bins over round-trip path length: bin j covers
[``start_opl`` + j·``bin_width_opl``, ``start_opl`` + (j+1)·``bin_width_opl``) metres and
stands for its centre (the integrator splats each contribution linearly between the two
bins whose centres enclose its path length). The names and units are mitransient's
``transient_hdr_film`` ones (optical path length in metres, not time): a sonar with sound
speed c, sample rate fs and K bins per sample has ``bin_width_opl`` = c/(fs·K), and
``start_opl`` = c·t₀ for a window that starts t₀ seconds after transmission.

``start_opl`` and ``bin_width_opl`` are differentiable parameters (``mi.traverse``): set them
from a grad-enabled sound speed and ``mi.render``'s gradients reach it
(docs/differentiable.md). The film holds the last rendered histograms
(:meth:`SonarFilm.develop`); the spatial size that Mitsuba's ``Film`` base class keeps is
unused. Depends on mitsuba and drjit only.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

PLUGIN_NAME = "sonar_film"
VARIANT = mi.variant()   # the variant this module's class was built for


def _window_value(value, name: str) -> float:
    """A scalar window setting as a finite Python float (ValueError otherwise)."""
    try:
        number = float(dr.detach(value)[0]) if dr.is_array_v(value) else float(value)
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"sonar_film: {name} must be one number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"sonar_film: {name} must be finite, got {number}")
    return number


class SonarFilm(mi.Film):
    """Histogram axis of a ``sonar`` sensor.

    Properties: ``temporal_bins`` (int >= 1, default 1000), ``start_opl`` (m of round-trip
    path, default 0), ``bin_width_opl`` (m, > 0, default 8.6e-4: 344.973 m/s over 100 kHz
    × 20 bins per sample, the reference's defaults).
    """

    def __init__(self, props):
        super().__init__(props)
        self.temporal_bins = int(props.get("temporal_bins", 1000))
        self.start_opl = mi.Float(float(props.get("start_opl", 0.0)))
        self.bin_width_opl = mi.Float(float(props.get("bin_width_opl", 344.973 / 2e6)))
        self.histogram = None
        self._check()

    def _check(self) -> None:
        if not 1 <= self.temporal_bins < 2**31:
            raise ValueError(f"sonar_film: temporal_bins must be >= 1, got {self.temporal_bins}")
        _window_value(self.start_opl, "start_opl")
        if not _window_value(self.bin_width_opl, "bin_width_opl") > 0:
            raise ValueError(f"sonar_film: bin_width_opl must be > 0, got {self.bin_width_opl}")
        for value in (self.start_opl, self.bin_width_opl):
            if dr.width(value) != 1:
                raise ValueError("sonar_film: start_opl and bin_width_opl are single numbers")

    def window(self):
        """(start_opl, bin_width_opl, temporal_bins): Dr.Jit Floats of width 1 (m; they
        carry gradients where enabled) and an int."""
        for value in (self.start_opl, self.bin_width_opl):
            if not dr.grad_enabled(value):
                dr.make_opaque(value)
        return self.start_opl, self.bin_width_opl, self.temporal_bins

    def traverse(self, callback):
        callback.put("start_opl", self.start_opl, mi.ParamFlags.Differentiable)
        callback.put("bin_width_opl", self.bin_width_opl, mi.ParamFlags.Differentiable)
        callback.put("temporal_bins", self.temporal_bins, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        # Updated in place (the arrays mi.traverse holds, where gradients accumulate).
        self.temporal_bins = int(self.temporal_bins)
        self._check()

    def prepare(self, aovs):
        return 1

    def clear(self):
        self.histogram = None

    def develop(self, raw: bool = False):
        """The histograms of the last render (TensorXf, see ``sonar_transient.render``)."""
        if self.histogram is None:
            raise RuntimeError("sonar_film: nothing rendered yet (call mi.render)")
        return self.histogram

    def to_string(self):
        return (f"SonarFilm[temporal_bins={self.temporal_bins}, "
                f"start_opl={_window_value(self.start_opl, 'start_opl')}, "
                f"bin_width_opl={_window_value(self.bin_width_opl, 'bin_width_opl')}]")


mi.register_film(PLUGIN_NAME, lambda props: SonarFilm(props))
