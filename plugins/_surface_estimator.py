"""The surface estimator of the ``sonar_transient`` integrator (private helper module).

Bounce 1 as a stratified area quadrature over every surface (strata from
:mod:`._surface_samples`): one jittered point per stratum and half-estimate, shadow rays to
the TX and the RX, the facet's echo spread over quantiles of its path-length density.
Bounces >= 2 continue from the same points (:meth:`SurfaceEstimator._facet_paths`).
Depends on mitsuba, drjit and numpy only.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


class SurfaceEstimator:
    """Mixin of :class:`sonar_transient.SonarTransientIntegrator`: bounce 1 over the surfaces
    and the paths of bounces >= 2 that start at its points."""

    def _surface(self, scene, sink, ctx, roi):
        """Bounce 1 by stratified area quadrature: one jittered point per stratum and half."""
        lanes = self.surface_strata(scene, roi)[1]
        for mesh in lanes.meshes:
            rho = shape_albedo(mesh.shape)
            self._surface_lanes(scene, sink, ctx, len(mesh),
                                lambda k, u, m=mesh, r=rho: m.points(k, u, r), mesh.stable_id)
        for index, item in enumerate(lanes.parametric):
            rho = shape_albedo(item[1])
            self._surface_lanes(scene, sink, ctx, len(item[0]),
                                lambda k, u, it=item, r=rho: _parametric_points(it, k, u, r),
                                lambda k, i=index: k ^ mi.UInt32((0x7F4A7C15 * (i + 1)) & 0xFFFFFFFF))

    def _surface_lanes(self, scene, sink, ctx, n_strata, points, stable_id):
        """Launch the lanes (pose, half, stratum), in batches of < 2³¹ lanes."""
        per_batch = max(1, (2**31) // (2 * n_strata))
        for first in range(0, ctx["n_poses"], per_batch):
            count = min(per_batch, ctx["n_poses"] - first)
            self._surface_batch(scene, sink, ctx, n_strata, points, stable_id, first, count)
            sink.flush()

    def _surface_batch(self, scene, sink, ctx, n_strata, points, stable_id, first, count):
        UInt32, Float = mi.UInt32, mi.Float
        m = dr.opaque(UInt32, n_strata)
        lane = dr.arange(UInt32, count * 2 * n_strata)
        pair = lane // m                  # pose * 2 + half
        k = lane - pair * m               # stratum
        pose = (pair >> 1) + dr.opaque(UInt32, first)
        half = pair & 1
        key = mi.sample_tea_32(ctx["seed"], (pose + ctx["pose_offset"]) * 2 + half)[0]
        sid = stable_id(k)
        r1, r2 = mi.sample_tea_32(key, sid)
        u = mi.Point2f(Float(r1 >> 8) * (1.0 / 16777216.0), Float(r2 >> 8) * (1.0 / 16777216.0))
        p, n_geo, n_sh, rho, area, phase, corners = points(k, u)
        if not self.shading_normals:
            n_sh = n_geo
        p_tx = mi.Point3f(dr.gather(mi.Vector3f, ctx["tx"], pose))
        p_rx = mi.Point3f(dr.gather(mi.Vector3f, ctx["rx"], pose))
        b_tx = dr.normalize(dr.gather(mi.Vector3f, ctx["tx_dir"], pose))
        b_rx = dr.normalize(dr.gather(mi.Vector3f, ctx["rx_dir"], pose))
        to_tx, to_rx = p_tx - p, p_rx - p
        r_t, r_r = dr.norm(to_tx), dr.norm(to_rx)
        w_t, w_r = to_tx / r_t, to_rx / r_r
        length = r_t + r_r
        # Two-sided surfaces: orient the normals towards the TX's side.
        flip = dr.select(dr.dot(n_geo, w_t) < 0.0, -1.0, 1.0)
        n_geo, n_sh = n_geo * flip, n_sh * flip
        cos_i = dr.dot(n_geo, w_t)                      # geometric, as the TX-cone sampling
        cos_o = dr.maximum(dr.dot(n_sh, w_r), 0.0)
        active = (cos_i > 0.0) & (dr.dot(n_geo, w_r) > 0.0) & (cos_o > 0.0)
        ls = None
        if corners is None:
            lo_len = hi_len = length
        else:   # path lengths at the facet's corners: a ≤ c ≤ b
            ls = [dr.norm(p_tx - q) + dr.norm(p_rx - q) for q in corners]
            lo_len = dr.minimum(dr.minimum(ls[0], ls[1]), ls[2])
            hi_len = dr.maximum(dr.maximum(ls[0], ls[1]), ls[2])
        active &= (hi_len > ctx["start"] - ctx["margin"]) & (lo_len < ctx["end"] + ctx["margin"])
        ct, cr = -dr.dot(w_t, b_tx), -dr.dot(w_r, b_rx)
        weight = area * (1.0 if ctx["halves"] else 0.5)
        tx_beam, rx_beam = ctx["tx_beam"], ctx["rx_beam"]
        if self.amplitude == "intensity":
            g_t = tx_beam.gain(ct, ctx["tx_c"])
            value = (g_t * rx_beam.gain(cr, ctx["rx_c"])
                     * rho * dr.inv_pi * cos_i * cos_o / (r_t * r_t * r_r * r_r))
        else:   # the seed's Eq. (1): b_T b_R σ / (2π r_T r_R), σ = sqrt(ρ cosθ_i cosθ_o)
            g_t = tx_beam.amplitude(ct, ctx["tx_c"])
            value = (g_t * rx_beam.amplitude(cr, ctx["rx_c"])
                     * dr.sqrt(rho * cos_i * cos_o) * (0.5 * dr.inv_pi) / (r_t * r_r))
        value = value * weight
        active &= value != 0.0
        # Visibility: shadow rays from the point (offset along the oriented normal). The TX
        # ray also serves the paths of bounces >= 2 that start at this point.
        lit = (cos_i > 0.0) & (g_t != 0.0)
        lit = (active | lit) if self.max_bounces > 1 else active
        scale = dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
        origin = p + n_geo * ((1.0 + scale) * mi.math.RayEpsilon)
        for target in (p_tx, p_rx):
            ray = mi.Ray3f(origin, target - origin)
            ray.maxt = Float(1.0 - mi.math.ShadowEpsilon)
            if target is p_tx:
                lit &= ~scene.ray_test(ray, lit)
                active &= lit
            else:
                active &= ~scene.ray_test(ray, active)
        if self.max_bounces > 1:
            k = self.facet_paths
            for j in range(k):   # k continuations per point, the first direction stratified
                self._facet_paths(scene, sink, ctx, pose, half, p, n_geo, n_sh, rho, cos_i,
                                  r_t, g_t * (weight / k), phase, corners, lit,
                                  key ^ (0x632BE5AB * j & 0xFFFFFFFF), sid, p_tx, p_rx, b_rx,
                                  (j, k))
        slot = half if ctx["halves"] else UInt32(0)
        values = [value]
        if self.complex_output:
            values = [value * dr.cos(phase), value * dr.sin(phase)]
        if corners is None:           # analytic shapes: a point splat
            sink.add(values, length, pose, slot, 0, active)
            return
        # Flat facets: path length is linear over the facet to within s²/(2r); the
        # facet's area maps to the triangular density of L between its corners' lengths
        # a ≤ c ≤ b. Spread the value over m stratified quantiles of that density (one
        # random shift per lane), so the facet's echo is smooth in time, not a spike.
        m = self.path_samples
        shift = Float(mi.sample_tea_32(key, sid ^ 0x80000000)[0] >> 8) * (1.0 / 16777216.0)
        values = [v * (1.0 / m) for v in values]
        for li in self._quantiles(ls, shift, m):
            sink.add(values, li, pose, slot, 0, active)

    def _facet_paths(self, scene, sink, ctx, pose, half, p, n_geo, n_sh, albedo, cos_in, r_t,
                     tx_weight, phase, corners, active, key, sid, p_tx, p_rx, b_rx,
                     stratum=(0, 1)):
        """Bounces 2…B from the surface points: one path per lit stratum point x₁.

        x₁ carries the TX's transfer b_T cosθ_i dA / r_T² (intensity; a_T dA / r_T for
        pressure: the TX-cone tracer's weight with dω = cosθ_i dA / r_T²); the path goes on
        by cosine/guide sampling with next-event connections to the RX, as the tracer.
        For facets, the first two legs |TX − x₁| + |x₁ − x₂| are spread over the facet
        (triangular density between the corners' values) like bounce 1.
        """
        Float = mi.Float
        intensity = self.amplitude == "intensity"
        active = mi.Bool(active)          # a copy: the in-place &= below must not reach the caller
        rng = mi.PCG32(1, mi.sample_tea_64(key, sid), mi.sample_tea_64(sid, key ^ 0x5bd1e995))
        slot = half if ctx["halves"] else mi.UInt32(0)
        guide = self._guide(scene)
        throughput = tx_weight * (cos_in / (r_t * r_t) if intensity else 1.0 / r_t)
        prev_p, length, quantiles = p, Float(0.0), None
        n_geo_v, n_sh_v = n_geo, n_sh
        ray_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        m = self.path_samples
        for bounce in range(1, self.max_bounces):
            u_pick = rng.next_float32()
            u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
            if bounce == 1 and stratum[1] > 1:
                u2.x = (stratum[0] + u2.x) * (1.0 / stratum[1])
            d_new, inv_pdf = self._continuation(prev_p, n_sh_v, u_pick, u2, guide)
            cos_new = dr.dot(d_new, n_sh_v)
            active &= (dr.dot(d_new, n_geo_v) > 0.0) & (cos_new > 0.0)
            if intensity:
                throughput *= albedo * dr.inv_pi * cos_new * inv_pdf
            else:
                throughput *= dr.sqrt(albedo * cos_in * cos_new) * (0.5 * dr.inv_pi) * inv_pdf
            ray = self._continue_ray(prev_p, d_new)
            si = scene.ray_intersect(ray, ray_flags, dr.opaque(mi.Bool, False), active)
            active &= si.is_valid()
            seg = dr.norm(si.p - prev_p)
            if bounce == 1:
                if corners is not None:
                    lc = [dr.norm(p_tx - q) + dr.norm(q - si.p) for q in corners]
                    quantiles = self._quantiles(lc, rng.next_float32(), m)
                else:
                    quantiles = [r_t + seg]
            else:
                length += seg
            prev_p = si.p
            n_geo_v, n_sh_v, albedo = self._arrival(si, ray, active)
            if not intensity:
                cos_in = -dr.dot(n_geo_v, ray.d)
                active &= cos_in > 1e-6
                throughput = throughput * seg / cos_in
                if self.amplitude == "coherent":
                    phase = phase + self._voxel_phase(si.p, bounce, ctx)
            value, dist, w_rx, connect = self._connect_rx(
                scene, si, p_rx, b_rx, n_sh_v, n_geo_v, throughput, albedo, cos_in, active,
                intensity, ctx)
            values = [value * (1.0 / len(quantiles))]
            if self.complex_output:
                values = [values[0] * dr.cos(phase), values[0] * dr.sin(phase)]
            rest = length + dist
            offsets = [0.0] * len(quantiles)
            scales = [1.0] * len(quantiles)
            if self.vertex_spread > 0.0 and len(quantiles) > 1:
                # Spread x_k over a disk of radius vertex_spread in its tangent plane: the
                # semicircle density of L along the tangential gradient of the last two
                # legs, at stratified points paired with the quantiles by a permutation.
                grad = ray.d - w_rx
                grad = grad - dr.dot(grad, n_geo_v) * n_geo_v
                half_span = dr.norm(grad) * self.vertex_spread
                n_q = len(quantiles)
                shift = rng.next_float32()
                ts = [2.0 * ((i * 5) % n_q + shift) / n_q - 1.0 for i in range(n_q)]
                ws = [dr.safe_sqrt(1.0 - t * t) for t in ts]
                total = dr.maximum(sum(ws[1:], ws[0]), 1e-12)
                offsets = [t * half_span for t in ts]
                scales = [w * (n_q / total) for w in ws]
            for q, off, sc in zip(quantiles, offsets, scales):
                sink.add([v * sc for v in values], q + rest + off, pose, slot, bounce, connect)

    @staticmethod
    def _quantiles(ls, shift, m):
        """m stratified quantiles (i + shift)/m of the triangular density between the
        three corner values ``ls`` (a linear function's image of a uniform triangle)."""
        a = dr.minimum(dr.minimum(ls[0], ls[1]), ls[2])
        b = dr.maximum(dr.maximum(ls[0], ls[1]), ls[2])
        c = ls[0] + ls[1] + ls[2] - a - b
        span = dr.maximum(b - a, 1e-12)
        f_c = (c - a) / span
        out = []
        for i in range(m):
            q = (i + shift) * (1.0 / m)
            lo = a + _sqrt_pos(q * span * (c - a))
            hi = b - _sqrt_pos((1.0 - q) * span * (b - c))
            out.append(dr.select(q < f_c, lo, hi))
        return out


def _sqrt_pos(x):
    """sqrt(max(x, 1e-30)): safe_sqrt with a finite derivative where x reaches 0."""
    return dr.sqrt(dr.maximum(x, 1e-30))


def shape_albedo(shape):
    """The diffuse reflectance of ``shape``'s BSDF as a Dr.Jit Float of width 1 (textures:
    at uv = (0.5, 0.5)), differentiable with respect to the BSDF's parameters."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.uv = mi.Point2f(0.5, 0.5)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    value = shape.bsdf().eval_diffuse_reflectance(si, True)
    rho = mi.Float(value[0]) if dr.size_v(value) != 0 else mi.Float(value)
    if not dr.grad_enabled(rho):
        dr.make_opaque(rho)            # a value, not a literal: no recompilation per albedo
    return rho


class _MeshLanes:
    """The strata of one mesh (:class:`._surface_samples.MeshStrata`) as Dr.Jit arrays; the
    geometry of a stratum is computed per lane from the mesh's current vertex buffers, so
    it follows (and is differentiable with respect to) ``vertex_positions``."""

    def __init__(self, strata):
        self.shape = strata.shape
        self.n = len(strata)
        self.tri = mi.UInt32(strata.tri)
        self.beta1, self.beta2 = mi.Float(strata.beta1), mi.Float(strata.beta2)
        self.scale, self.inv_n2 = mi.Float(strata.scale), mi.Float(strata.inv_n2)
        self.sid = mi.UInt32(strata.sid)
        self.phase = None if strata.phase is None else mi.Float(strata.phase)

    def __len__(self) -> int:
        return self.n

    def stable_id(self, k):
        return dr.gather(mi.UInt32, self.sid, k)

    def points(self, k, u, rho):
        """(point, geometric normal, shading normal, albedo, area, phase, corners) of a
        uniform point ``u`` of stratum ``k`` (m, m²)."""
        shape = self.shape
        face = dr.gather(mi.UInt32, self.tri, k)
        faces = shape.faces_buffer()
        idx = [dr.gather(mi.UInt32, faces, face * 3 + j) for j in range(3)]
        vp = shape.vertex_positions_buffer()
        a, b, c = (dr.gather(mi.Point3f, vp, i) for i in idx)
        ea, eb = b - a, c - a
        beta1, beta2 = dr.gather(mi.Float, self.beta1, k), dr.gather(mi.Float, self.beta2, k)
        scale = dr.gather(mi.Float, self.scale, k)
        bary = mi.warp.square_to_uniform_triangle(u)
        w1, w2 = beta1 + scale * bary.x, beta2 + scale * bary.y     # parent barycentrics
        p = a + w1 * ea + w2 * eb
        cross = dr.cross(ea, eb)
        double_area = dr.norm(cross)
        n_geo = cross / double_area
        area = 0.5 * double_area * dr.gather(mi.Float, self.inv_n2, k)
        if shape.has_vertex_normals():
            vn = shape.vertex_normals_buffer()
            na, nb, nc = (dr.gather(mi.Vector3f, vn, i) for i in idx)
            n_sh = dr.normalize(na + w1 * (nb - na) + w2 * (nc - na))
        else:
            n_sh = n_geo
        phase = mi.Float(0.0) if self.phase is None else dr.gather(mi.Float, self.phase, k)
        p0 = a + beta1 * ea + beta2 * eb
        corners = (p0, p0 + scale * ea, p0 + scale * eb)
        return p, n_geo, n_sh, rho, area, phase, corners


class StrataLanes:
    """The surface quadrature of a scene as Dr.Jit arrays: :class:`_MeshLanes` per mesh
    and the cell grids of the analytic shapes."""

    def __init__(self, strata):
        self.meshes = [_MeshLanes(m) for m in strata.meshes]
        self.parametric = []
        for ps in strata.parametric:
            phase = ps.phase if ps.phase is not None else np.zeros(1, np.float32)
            self.parametric.append((range(len(ps)), ps.shape, dr.opaque(mi.UInt32, ps.n_v),
                                    dr.opaque(mi.Float, 1.0 / ps.n_u),
                                    dr.opaque(mi.Float, 1.0 / ps.n_v),
                                    dr.opaque(mi.Float, 1.0 / (ps.n_u * ps.n_v)),
                                    mi.Float(phase), ps.phase is not None))


def _parametric_points(item, k, u, rho):
    """A point of stratum k of an analytic shape: ``shape.sample_position`` of the cell."""
    _, shape, n_v, inv_nu, inv_nv, inv_cells, phases, has_phase = item
    iu = k // n_v
    iv = k - iu * n_v
    uv = mi.Point2f((mi.Float(iu) + u.x) * inv_nu, (mi.Float(iv) + u.y) * inv_nv)
    ps = shape.sample_position(0.0, uv)
    area = inv_cells / ps.pdf                 # cell measure / area density of the map
    phase = dr.gather(mi.Float, phases, k) if has_phase else mi.Float(0.0)
    return ps.p, ps.n, ps.n, rho, area, phase, None
