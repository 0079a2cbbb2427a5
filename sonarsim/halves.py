"""Sampling densities and the seeds of two independent half-estimates.

Every simulated pose is rendered as two independent half-estimates in one launch
(``sonarsim.render.iter_render(..., halves=True)``: paths of even and odd index, the
surface estimator's two jittered points per stratum); their mean is the dataset's
transients and their half difference a sample of its Monte-Carlo error
(:mod:`sonarsim.fidelity`).

The sampling density is a :class:`Sampling`: TX-cone paths per pose (bounces >= 2 from the
TX, and bounce 1 with the 'cone' estimator) and, for the surface (area) estimator of
bounce 1, the size of its strata (``surface_spacing``, m; the density is 1/spacing²).
:func:`half_seed` derives independent seeds (the density pilot uses them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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


def default_surface_spacing(integrator) -> float | None:
    """The integrator's surface strata size (m), or None if bounce 1 is not a surface integral."""
    if getattr(integrator, "bounce1", "cone") != "surface":
        return None
    value = getattr(integrator, SURFACE_PROP, None)
    return None if value is None else float(value)
