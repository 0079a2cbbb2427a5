"""Per-vertex steps of the ``sonar_transient`` paths (private helper module): arrival at a
vertex (two-sided normals, albedo), the next-event connection to the receiver, the
continuation direction (cosine / guide-sphere mixture), the speckle phase of a vertex, the
continued ray and the tent splat into the histograms. Depends on mitsuba and drjit
(numpy for the scene's bounding boxes) only.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np


class PathVertices:
    """Mixin of :class:`sonar_transient.SonarTransientIntegrator`: the steps at a path vertex."""

    def _arrival(self, si, ray, active):
        """(geometric normal, shading normal, albedo) at the vertex a ray arrives at; the
        surfaces are two-sided, so both normals face the side the ray comes from."""
        flip = dr.select(dr.dot(si.n, ray.d) > 0.0, -1.0, 1.0)
        n_shade = (si.sh_frame.n if self.shading_normals else si.n) * flip
        return si.n * flip, n_shade, si.bsdf().eval_diffuse_reflectance(si, active)[0]

    def _connect_rx(self, scene, si, p_rx, b_rx, n_shade, n_geo, throughput, albedo, cos_in,
                    active, intensity: bool, ctx, ray_stats=None):
        """Next-event connection of vertex ``si`` to the point receiver: (value, |x − rx|,
        unit direction to the receiver, connected mask). Intensity: throughput·ρ/π·cosθ_o·b_R/r²; pressure/coherent:
        throughput·√(ρ cosθ_i cosθ_o)/(2π)·a_R/r (supplemental Eq. (1)). Shadow ray included."""
        to_rx = p_rx - si.p
        dist2 = dr.squared_norm(to_rx)
        dist = dr.sqrt(dist2)
        w_rx = to_rx / dist
        cos_out = dr.maximum(dr.dot(n_shade, w_rx), 0.0)
        c_rx = -dr.dot(w_rx, b_rx)
        if intensity:
            value = (throughput * albedo * dr.inv_pi * cos_out
                     * ctx["rx_beam"].gain(c_rx, ctx["rx_c"]) / dist2)
        else:
            value = (throughput * dr.sqrt(albedo * cos_in * cos_out) * (0.5 * dr.inv_pi)
                     * ctx["rx_beam"].amplitude(c_rx, ctx["rx_c"]) / dist)
        connect = active & (dr.dot(n_geo, w_rx) > 0.0) & (value != 0.0)
        if ray_stats is not None:
            ray_stats["shadow"] = ray_stats.get("shadow", 0) + int(dr.count(connect)[0])
        connect &= ~scene.ray_test(si.spawn_ray_to(p_rx), connect)
        return value, dist, w_rx, connect

    def _guide(self, scene):
        """Bounding sphere (centre, radius) of the scene's non-flat shapes, or None."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for shape in scene.shapes():
            bb = shape.bbox()
            a, b = np.array(bb.min, np.float64), np.array(bb.max, np.float64)
            if np.all(b - a > 1e-6):
                lo, hi = np.minimum(lo, a), np.maximum(hi, b)
        if not np.all(np.isfinite(lo)) or self.guide_fraction <= 0.0:
            return None
        centre = (lo + hi) / 2.0
        return {"centre": mi.Point3f(*(dr.opaque(mi.Float, float(v)) for v in centre)),
                "radius2": dr.opaque(mi.Float, float(np.sum((hi - lo) ** 2) / 4.0)),
                "q": dr.opaque(mi.Float, self.guide_fraction)}

    @staticmethod
    def _continuation(p, n, u_pick, u2, guide):
        """A continuation direction and 1/pdf (sr): cosine-weighted about ``n``, or (one-sample
        MIS, probability q) uniform in the cone towards the guide sphere when ``p`` is
        outside it; pdf = q·[in cone]/Ω + (1 − q)·cos⁺/π, unbiased for any q."""
        frame = mi.Frame3f(n)
        d_cos = frame.to_world(mi.warp.square_to_cosine_hemisphere(u2))
        if guide is None:
            return d_cos, dr.pi / dr.maximum(dr.dot(d_cos, n), 1e-12)
        to_c = guide["centre"] - p
        dist2 = dr.squared_norm(to_c)
        outside = dist2 > guide["radius2"] * 1.0001
        cos_max = dr.safe_sqrt(1.0 - guide["radius2"] / dr.maximum(dist2, 1e-30))
        axis = to_c * dr.rsqrt(dr.maximum(dist2, 1e-30))
        d_cone = mi.Frame3f(axis).to_world(mi.warp.square_to_uniform_cone(u2, cos_max))
        q = dr.select(outside, guide["q"], 0.0)
        d = dr.select(u_pick < q, d_cone, d_cos)
        solid = 2.0 * dr.pi * dr.maximum(1.0 - cos_max, 1e-12)
        in_cone = outside & (dr.dot(d, axis) >= cos_max)
        pdf = dr.select(in_cone, q / solid, 0.0) + (1.0 - q) * dr.maximum(dr.dot(d, n), 0.0) * dr.inv_pi
        return d, dr.select(pdf > 0.0, 1.0 / pdf, 0.0)

    @staticmethod
    def _voxel_phase(p, bounce, ctx):
        """Phase (rad) of the world-space speckle cell (cube of side speckle_spacing) at p,
        for the vertices of paths with ≥ 2 bounces (a stream independent of bounce 1's)."""
        q = mi.Vector3i(dr.floor(p * ctx["inv_speckle"]))
        h = mi.sample_tea_32(mi.UInt32(q.x), mi.UInt32(q.y) ^ (ctx["speckle_key"] * 2 + 1))[0]
        h = mi.sample_tea_32(h, mi.UInt32(q.z) ^ 0x9E3779B9)[0]
        return mi.Float(h >> 8) * (2.0 * math.pi / 16777216.0)

    @staticmethod
    def _continue_ray(p, d):
        """The ray leaving vertex ``p`` in direction ``d``, started ε = (1 + max|p|)·9e-5 m
        along ``d`` itself to avoid re-hitting the surface at p.

        ``si.spawn_ray`` offsets the origin along the *normal* instead; the traced ray
        then misses the sampled line near grazing directions, which lengthens paths
        systematically (inside a hollow sphere of radius 1 cm, mean bounce-2 length
        +4.6e-5 m from si.t, +1.1e-4 m from vertex distances; now 0 within 5e-6 m).
        Along ``d`` the ray is the sampled line; only geometry within ε of p is skipped.
        """
        scale = dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
        eps = (1.0 + scale) * mi.math.RayEpsilon
        return mi.Ray3f(p + eps * d, d)


def _tent(length, pose, slot, bounce, ctx):
    """The two bins (j0, j0 + 1) whose centres enclose ``length`` and their weights, as flat
    indices into a [slots, N, B, T] buffer: [(index, weight, in-window mask), ...]."""
    u = (length - ctx["start"]) * ctx["inv_width"] - 0.5   # in bin-centre units
    u = dr.clip(u, -2.0, mi.Float(ctx["n_bins"]) + 1.0)   # keep the int cast defined
    j0f = dr.floor(dr.detach(u))
    frac = u - j0f
    j0 = mi.Int32(j0f)
    base = slot * ctx["half_stride"] + pose * ctx["pose_stride"] + bounce * ctx["n_bins_u"]
    return [(base + mi.UInt32(j), w, (j >= 0) & (j < ctx["n_bins"]))
            for j, w in ((j0, 1.0 - frac), (j0 + 1, frac))]


class HistogramSink:
    """Where contributions go in a forward render: a tent splat into the histogram buffers
    ``hists`` (one per part: the real one, and the imaginary one for complex output)."""

    def __init__(self, hists, ctx):
        self.hists, self.ctx = hists, ctx

    def add(self, values, length, pose, slot, bounce, active):
        """Splat ``values`` (one per buffer) at path length ``length`` (m) into the bins of
        (slot, pose, bounce); lanes where ``active`` is False add nothing."""
        for index, weight, inside in _tent(length, pose, slot, bounce, self.ctx):
            ok = active & inside
            for hist, value in zip(self.hists, values):
                dr.scatter_reduce(dr.ReduceOp.Add, hist, type(hist)(value * weight), index, ok,
                                  mode=self.ctx["reduce_mode"])

    def flush(self):
        """End of a launch (nothing to do: the buffers are evaluated by the caller)."""


class AdjointSink:
    """Where contributions go in a reverse-mode replay (path replay): each one is weighted
    by the adjoint histogram ``grads`` (one per part, laid out as the histograms) at its
    tent bins, and :meth:`flush` back-propagates the sum of a launch's lanes. The launch's
    derivative graph lives only until that flush, whatever the path depth."""

    def __init__(self, grads, ctx):
        self.grads, self.ctx = grads, ctx
        self.total = None

    def add(self, values, length, pose, slot, bounce, active):
        for index, weight, inside in _tent(length, pose, slot, bounce, self.ctx):
            ok = active & inside
            for grad, value in zip(self.grads, values):
                adjoint = dr.gather(mi.Float, grad, index, ok)
                term = dr.select(ok, value * (weight * adjoint), 0.0)
                self.total = term if self.total is None else self.total + term

    def flush(self):
        """Back-propagate ⟨adjoint, contributions⟩ of the launch into the scene parameters."""
        total, self.total = self.total, None
        if total is None or not dr.grad_enabled(total):
            return
        dr.set_grad(total, 1.0)
        dr.enqueue(dr.ADMode.Backward, total)
        dr.traverse(dr.ADMode.Backward)
        dr.eval()
