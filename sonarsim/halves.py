"""Two independent half-estimates of the transients of a chunk of poses.

:class:`HalfRenderer` renders every pose twice with independent random numbers, each an
unbiased estimate with half of the samples, and returns their mean (the dataset's
transients) and their half difference (a sample of the Monte-Carlo error of the mean,
:mod:`sonarsim.fidelity`). If the integrator can return both halves from one launch
(``render_transients(..., halves=True)`` -> [2, N, B, T]) that is used; otherwise the two
halves are two launches with half of the paths each and seeds derived from the run's
seed by :func:`half_seed` (independent for every seed and half).

The sampling density is a :class:`Sampling`: TX-cone paths per pose (bounces >= 2, and
bounce 1 with the 'cone' estimator) and, for the surface (area) estimator of bounce 1,
the size of its strata (``surface_spacing``, m; the density is 1/spacing²). Integrator options that change the
physics or the estimator (bounce-1 estimator, amplitude model, speckle seed) are an
:class:`Estimator`, passed to :func:`sonarsim.render.make_integrator`.
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .errors import InputError
from .render import AMPLITUDES, BOUNCE1_ESTIMATORS, PathWindow
from .render import make_integrator as render_integrator

SURFACE_PROP = "surface_spacing"      # integrator property: strata size of the surface estimator
_MIX = 0x9E3779B9


def half_seed(seed: int, half: int) -> int:
    """The 32-bit integrator seed of half ``half`` (0 or 1) of run seed ``seed``.

    A bijective mix of 2·seed + half (mod 2³²): distinct for every (seed, half) pair with
    seed < 2³¹, so no half of one seed reuses the random numbers of another seed's half.
    """
    x = (2 * int(seed) + int(half)) & 0xFFFFFFFF
    x = (x * _MIX) & 0xFFFFFFFF            # odd multiplier: bijective mod 2^32
    x ^= x >> 16
    x = (x * 0x85EBCA6B) & 0xFFFFFFFF
    x ^= x >> 13
    return x


@dataclass(frozen=True)
class Sampling:
    """Sampling density: ``paths_per_pose`` TX-cone paths (both halves together) and the
    surface estimator's strata size ``surface_spacing`` in m (None: no surface estimator)."""
    paths_per_pose: int
    surface_spacing: float | None = None

    def scaled(self, factor: float, max_paths: int, min_spacing: float = 0.0) -> "Sampling":
        """Every density times ``factor`` (paths × factor, spacing / √factor); paths rounded
        up to an even count, at most ``max_paths``; spacing at least ``min_spacing``."""
        paths = min(int(max_paths), max(2, math.ceil(self.paths_per_pose * factor)))
        paths += paths % 2
        spacing = None
        if self.surface_spacing is not None:
            spacing = max(float(min_spacing), self.surface_spacing / math.sqrt(factor))
        return Sampling(paths, spacing)

    def describe(self) -> str:
        """The density that drives the estimate: the surface strata with the surface
        estimator (its samples also start bounces >= 2, so no TX-cone paths are traced),
        else the TX-cone paths per pose."""
        if self.surface_spacing is not None:
            return f"surface spacing {self.surface_spacing * 1e3:.3g} mm"
        return f"{self.paths_per_pose} paths/pose"


@dataclass(frozen=True)
class Estimator:
    """Integrator options: bounce-1 estimator (None: the integrator's default), amplitude
    model and the speckle phases' seed (coherent only)."""
    bounce1: str | None = None
    amplitude: str = "intensity"
    speckle_seed: int = 0

    def validate(self) -> None:
        if self.amplitude not in AMPLITUDES:
            raise InputError(f"amplitude must be one of {', '.join(AMPLITUDES)}, "
                             f"got {self.amplitude!r}")
        if self.bounce1 is not None and self.bounce1 not in BOUNCE1_ESTIMATORS:
            raise InputError(f"bounce-1 estimator must be one of {', '.join(BOUNCE1_ESTIMATORS)}, "
                             f"got {self.bounce1!r}")
        if isinstance(self.speckle_seed, bool) or not 0 <= int(self.speckle_seed) < 2**32:
            raise InputError(f"speckle seed must be in [0, 2^32), got {self.speckle_seed}")

    @property
    def complex(self) -> bool:
        """Whether the histograms may be complex (phase-carrying)."""
        return self.amplitude == "coherent"



def make_integrator(bounces: int, beams: Mapping | None, estimator: Estimator,
                    sampling: Sampling | None = None):
    """A ``sonar_transient`` integrator with these beams, estimator and surface spacing
    (:func:`sonarsim.render.make_integrator`)."""
    spacing = None if sampling is None else sampling.surface_spacing
    return render_integrator(bounces, beams, bounce1=estimator.bounce1,
                             amplitude=estimator.amplitude, surface_spacing=spacing,
                             speckle_seed=int(estimator.speckle_seed))


def default_surface_spacing(integrator) -> float | None:
    """The integrator's surface strata size (m), or None if bounce 1 is not a surface integral."""
    if getattr(integrator, "bounce1", "cone") != "surface":
        return None
    value = getattr(integrator, SURFACE_PROP, None)
    return None if value is None else float(value)


class HalfRenderer:
    """Render (mean, half difference) histograms of poses with a fixed integrator setup."""

    def __init__(self, scene, bounces: int, beams: Mapping | None, estimator: Estimator,
                 sampling: Sampling, window: PathWindow, seed: int):
        self.scene, self.window, self.seed = scene, window, int(seed)
        self.sampling = sampling
        self.integrator = make_integrator(bounces, beams, estimator, sampling)
        params = inspect.signature(self.integrator.render_transients).parameters
        self.native_halves = "halves" in params
        self.paths_per_half = max(1, sampling.paths_per_pose // 2)

    def render(self, poses, sl: slice) -> tuple[np.ndarray, np.ndarray]:
        """(mean, (a − b)/2) [n, B, T] for poses[sl] (global indices: chunk-independent)."""
        w = self.window
        args = (self.scene, poses.tx[sl], poses.rx[sl], poses.tx_boresight[sl],
                poses.rx_boresight[sl], w.path_start, w.bin_width, w.n_bins)
        if self.native_halves:
            both = self.integrator.render_transients(
                *args, self.sampling.paths_per_pose, self.seed, pose_offset=sl.start,
                halves=True)
            a, b = both[0], both[1]
        else:
            a, b = (self.integrator.render_transients(
                *args, self.paths_per_half, half_seed(self.seed, h), pose_offset=sl.start)
                for h in (0, 1))
        mean = (a + b) * 0.5
        diff = (a - b) * 0.5
        return mean.astype(np.result_type(a, np.float32)), diff.astype(np.result_type(a, np.float32))


