"""Beam patterns of the ``sonar_transient`` integrator (private helper module).

A :class:`Beam` gives the intensity gain ``b(θ)`` and the pressure gain ``a(θ)`` (both 1 on
the axis) of a direction at angle θ from the boresight, and samples TX directions:
'cone' (1 inside a cone of full width ``beamwidth``, 0 outside), 'isotropic' (1 everywhere),
'piston' (a baffled circular piston, |2 J1(ka sinθ)/(ka sinθ)|², with ``beamwidth`` its
half-power width). Depends on mitsuba and drjit only.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

BEAM_KINDS = ("cone", "isotropic", "piston")
# Piston pattern: |2 J1(x)/x|² = 1/2 at x = 1.6163 (half-power), first null at x = 3.8317.
_PISTON_HALF_POWER_X = 1.616339948
_PISTON_FIRST_NULL_X = 3.831705970
_PISTON_MAIN_LOBE_FRACTION = 0.9   # share of TX samples drawn inside the main lobe


def piston_ka(beamwidth_deg: float) -> float:
    """Piston ``k·a`` (wavenumber × radius) whose full half-power beamwidth is ``beamwidth_deg``."""
    return _PISTON_HALF_POWER_X / math.sin(math.radians(beamwidth_deg) / 2.0)


def _bessel_j1_over_x(x):
    """J1(x)/x for x >= 0 (Abramowitz & Stegun 9.4.4 and 9.4.6, |error| < 1e-7)."""
    y = (x * (1.0 / 3.0)) ** 2
    small = 0.5 + y * (-0.56249985 + y * (0.21093573 + y * (-0.03954289 + y * (
        0.00443319 + y * (-0.00031761 + y * 0.00001109)))))
    xs = dr.maximum(x, 3.0)
    z = 3.0 / xs
    f1 = 0.79788456 + z * (0.00000156 + z * (0.01659667 + z * (0.00017105 + z * (
        -0.00249511 + z * (0.00113653 + z * -0.00020033)))))
    t1 = xs - 2.35619449 + z * (0.12499612 + z * (0.00005650 + z * (-0.00637879 + z * (
        0.00074348 + z * (0.00079824 + z * -0.00029166)))))
    large = f1 * dr.cos(t1) / (xs * dr.sqrt(xs))
    return dr.select(x <= 3.0, small, large)


class Beam:
    """A beam pattern: intensity gain ``b(θ)`` and pressure gain ``a(θ)`` (both 1 on the
    axis) and, for the TX, direction sampling.

    Per-call constants are made opaque when the kernel is built (:meth:`opaque`), so the
    beamwidth never forces a recompilation.
    """

    def __init__(self, kind: str, beamwidth_deg: float, role: str):
        if kind not in BEAM_KINDS:
            raise ValueError(f"sonar_transient: {role}_beam must be one of {BEAM_KINDS}, "
                             f"got {kind!r}")
        if kind != "isotropic" and not (0.0 < beamwidth_deg < 180.0):
            raise ValueError(f"sonar_transient: {role}_beamwidth must be in (0, 180) degrees, "
                             f"got {beamwidth_deg}")
        self.kind = kind
        self.beamwidth_deg = float(beamwidth_deg)
        half = math.radians(self.beamwidth_deg) / 2.0
        if kind == "cone":
            self.cos_cut = math.cos(half)        # cone edge
            self.ka = 0.0
        elif kind == "piston":
            self.ka = piston_ka(self.beamwidth_deg)
            s = _PISTON_FIRST_NULL_X / self.ka
            self.cos_cut = math.sqrt(1.0 - s * s) if s < 1.0 else 0.0   # main-lobe edge
        else:
            self.cos_cut = -1.0
            self.ka = 0.0

    def describe(self) -> str:
        return "isotropic" if self.kind == "isotropic" else f"{self.kind} {self.beamwidth_deg:g}°"

    def opaque(self) -> dict:
        return {"cos_cut": dr.opaque(mi.Float, self.cos_cut), "ka": dr.opaque(mi.Float, self.ka)}

    def amplitude(self, cos_theta, c):
        """Pressure gain for a direction at angle θ from the boresight (``cos_theta``):
        1/0 for the cone, 1 for isotropic, the signed 2·J1(ka sinθ)/(ka sinθ) in front of
        a baffled piston (its square is :meth:`gain`)."""
        if self.kind == "isotropic":
            return dr.full(mi.Float, 1.0, dr.width(cos_theta))
        if self.kind == "cone":
            return dr.select(cos_theta >= c["cos_cut"], 1.0, 0.0)
        sin_theta = dr.safe_sqrt(1.0 - cos_theta * cos_theta)
        return dr.select(cos_theta > 0.0, 2.0 * _bessel_j1_over_x(c["ka"] * sin_theta), 0.0)

    def gain(self, cos_theta, c):
        """Intensity gain for a direction at angle θ from the boresight (``cos_theta``)."""
        if self.kind == "piston":   # |2 J1(ka sinθ)/(ka sinθ)|² in front, nothing behind
            a = self.amplitude(cos_theta, c)
            return a * a
        return self.amplitude(cos_theta, c)

    def sample(self, u_pick, u2, c):
        """Local direction (z = boresight) and 1/pdf (sr) for uniform numbers."""
        if self.kind == "isotropic":
            return mi.warp.square_to_uniform_sphere(u2), dr.full(mi.Float, 4.0 * math.pi,
                                                                  dr.width(u_pick))
        cone_solid_angle = 2.0 * math.pi * (1.0 - c["cos_cut"])
        if self.kind == "cone":
            return mi.warp.square_to_uniform_cone(u2, c["cos_cut"]), cone_solid_angle
        # Piston: mixture of the main-lobe cone (fraction q) and the front hemisphere,
        # which keeps side lobes (unbiased) while spending most samples in the main lobe.
        q = _PISTON_MAIN_LOBE_FRACTION
        in_lobe = u_pick < q
        d_cone = mi.warp.square_to_uniform_cone(u2, c["cos_cut"])
        d_hemi = mi.warp.square_to_uniform_hemisphere(u2)
        d = dr.select(in_lobe, d_cone, d_hemi)
        pdf = (1.0 - q) / (2.0 * math.pi) + dr.select(d.z >= c["cos_cut"],
                                                       q / cone_solid_angle, 0.0)
        return d, 1.0 / pdf

