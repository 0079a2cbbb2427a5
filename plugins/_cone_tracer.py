"""The TX-cone path tracer of the ``sonar_transient`` integrator (private helper module).

Paths leave the TX in directions drawn from its beam; at every vertex a shadow ray connects
to the RX (next-event estimation) and the path goes on by cosine/guide sampling. Bounce 1
with ``bounce1='cone'``, bounces >= 2 otherwise only when traced from the TX. Launches of
at most :data:`_TRACE_BATCH` lanes, each pose's paths sorted by the Morton cell of their
first TX sample so that neighbouring lanes trace coherent rays
(docs/transient_rendering.md, "Performance design"). Depends on mitsuba and drjit only.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

# Lanes per launch (its lane order takes about 8 bytes per lane), the fewest paths per pose
# for which sorting them by TX direction pays, and the paths per direction cell of that
# sort (see ConeTracer._coherent_order).
_TRACE_BATCH = 2**24
_ORDER_MIN_PATHS = 64
_ORDER_PER_CELL = 16.0


class ConeTracer:
    """Mixin of :class:`sonar_transient.SonarTransientIntegrator`: the TX-cone paths."""

    def _trace(self, scene, sink, ctx, paths_per_pose, ray_stats=None):
        """The TX-cone paths of every pose, in launches of at most _TRACE_BATCH lanes:
        whole poses, or (beyond _TRACE_BATCH paths per pose) part of one pose's paths."""
        n_poses, P = ctx["n_poses"], paths_per_pose
        if P <= _TRACE_BATCH:
            per = max(1, _TRACE_BATCH // P)
            batches = [(p0, min(per, n_poses - p0), 0, P) for p0 in range(0, n_poses, per)]
        else:
            batches = [(p0, 1, a, min(_TRACE_BATCH, P - a))
                       for p0 in range(n_poses) for a in range(0, P, _TRACE_BATCH)]
        for pose0, n_batch_poses, path0, n_paths in batches:
            batch = {"pose0": dr.opaque(mi.UInt32, pose0), "path0": dr.opaque(mi.UInt32, path0),
                     "n_paths": dr.opaque(mi.UInt32, n_paths)}
            order = self._coherent_order(ctx, batch, n_batch_poses, n_paths, P)
            self._trace_lanes(scene, sink, ctx, paths_per_pose, batch, n_batch_poses * n_paths,
                              order, ray_stats)
            sink.flush()

    @staticmethod
    def _path_rng(ctx, pose, path):
        """The PCG32 stream of path ``path`` of pose ``pose`` (index in this call), seeded
        by a hash of (seed, global pose index, path): independent of chunking and order."""
        stream_key = mi.sample_tea_32(ctx["seed"], pose + ctx["pose_offset"])[0]
        return mi.PCG32(1, mi.sample_tea_64(stream_key, path), mi.sample_tea_64(path, stream_key))

    @staticmethod
    def _direction_cell(ctx, batch, index, level):
        """(pose, path, Morton cell of the first TX sample square at ``level``) of lane
        ``index`` of a batch: the cell's 4^level squares tile [0, 1)² (the beam warps
        map nearby points of the square to nearby directions)."""
        UInt32 = mi.UInt32
        pose = batch["pose0"] + index // batch["n_paths"]
        path = batch["path0"] + index % batch["n_paths"]
        rng = ConeTracer._path_rng(ctx, pose, path)
        rng.next_float32()                                   # u_pick
        side = mi.Float(UInt32(1) << level)
        x = dr.minimum(UInt32(rng.next_float32() * side), (UInt32(1) << level) - 1)
        y = dr.minimum(UInt32(rng.next_float32() * side), (UInt32(1) << level) - 1)
        return pose, path, _interleave(x) | (_interleave(y) << 1)

    def _coherent_order(self, ctx, batch, n_batch_poses, n_paths, P):
        """The order in which a batch's lanes are traced: UInt32 [n_batch_poses·n_paths],
        lane i traces path order[i] (index into the batch, pose-major), or None (the
        identity) for fewer than _ORDER_MIN_PATHS paths per pose.

        Each path keeps its own random numbers (they depend on pose and path index
        only), so results are the same in any order; the order only decides which paths
        share a SIMD packet. Each pose's paths (of this batch) are sorted by the Morton
        cell of their first TX sample (4^L cells, about 16 paths per cell, L <= 8),
        stably (by index within a cell): neighbouring lanes then leave the TX in nearby
        directions, hit nearby points and send nearby shadow rays, so Embree's 16-ray
        packets stay coherent (docs/transient_rendering.md, "Performance design"). The
        sort is Dr.Jit's per-block stable counting sort (``drjit.detail.block_mkperm``,
        on which ``drjit.argsort`` is built; deterministic, a few ns per lane); with a
        Dr.Jit that lacks it, lanes stay in index order.
        """
        mkperm = getattr(getattr(dr, "detail", None), "block_mkperm", None)
        if P < _ORDER_MIN_PATHS or mkperm is None:
            return None
        level = max(0, min(8, int(math.log(n_paths / _ORDER_PER_CELL, 4.0))))
        index = dr.arange(mi.UInt32, n_batch_poses * n_paths)
        cell = self._direction_cell(ctx, batch, index, dr.opaque(mi.UInt32, level))[2]
        dr.eval(cell)
        order = mkperm(cell, n_paths, 4 ** level)     # blocks: the poses of the batch
        dr.eval(order)
        return order

    def _trace_lanes(self, scene, sink, ctx, paths_per_pose, batch, n_lanes, order,
                     ray_stats=None):
        """Trace the ``n_lanes`` paths of one batch, lane i taking batch path ``order[i]``
        (pose-major index into the batch; None: lane i takes path i)."""
        UInt32, Float = mi.UInt32, mi.Float
        index = dr.arange(UInt32, n_lanes)
        if order is not None:
            index = dr.gather(UInt32, order, index)
        pose = batch["pose0"] + index // batch["n_paths"]
        path = batch["path0"] + index % batch["n_paths"]
        rng = self._path_rng(ctx, pose, path)
        # Half h = paths of parity h; weights make the full estimate the mean of the halves.
        half = path & 1
        n0, n1 = (paths_per_pose + 1) // 2, paths_per_pose // 2
        if ctx["halves"]:
            w0, w1 = 1.0 / n0, 1.0 / n1
        elif paths_per_pose == 1:
            w0 = w1 = 1.0
        else:
            w0, w1 = 0.5 / n0, 0.5 / n1
        weight = dr.select(half == 0, dr.opaque(Float, w0), dr.opaque(Float, w1))
        slot = half if ctx["halves"] else UInt32(0)

        p_tx = mi.Point3f(dr.gather(mi.Vector3f, ctx["tx"], pose))
        p_rx = mi.Point3f(dr.gather(mi.Vector3f, ctx["rx"], pose))
        b_tx = dr.normalize(dr.gather(mi.Vector3f, ctx["tx_dir"], pose))
        b_rx = dr.normalize(dr.gather(mi.Vector3f, ctx["rx_dir"], pose))
        intensity = self.amplitude == "intensity"
        guide = self._guide(scene) if self.max_bounces > 1 else None

        # Bounce 0: leave the TX in a direction drawn from its beam.
        u_pick = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        tx_beam = ctx["tx_beam"]
        d_local, inv_pdf = tx_beam.sample(u_pick, u2, ctx["tx_c"])
        beam = (tx_beam.gain if intensity else tx_beam.amplitude)(d_local.z, ctx["tx_c"])
        ray = mi.Ray3f(p_tx, mi.Frame3f(b_tx).to_world(d_local))
        # intensity: b_T/pdf; pressure: a_T/pdf, completed by r/cosθ_i at the vertex
        throughput = beam * inv_pdf * weight
        length = Float(0.0)
        phase = Float(0.0)
        prev_p = p_tx
        active = dr.full(mi.Bool, True, n_lanes)

        # Position, normals, UV (for textured albedo); no partial derivatives.
        ray_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        for bounce in range(self.max_bounces):    # unrolled: faster than a loop for few bounces
            if ray_stats is not None:
                ray_stats["intersect"] = ray_stats.get("intersect", 0) + int(dr.count(active)[0])
            si = scene.ray_intersect(ray, ray_flags, dr.opaque(mi.Bool, False), active)
            active &= si.is_valid()
            # Length between the vertices themselves (the ray starts a little past
            # the previous vertex, see below).
            seg = dr.norm(si.p - prev_p)
            length += seg
            prev_p = si.p
            n_geo, n_shade, albedo = self._arrival(si, ray, active)
            cos_in = None                                  # used by the pressure models only
            if not intensity:
                cos_in = -dr.dot(n_geo, ray.d)
                active &= cos_in > 1e-6
                throughput = throughput * seg / cos_in          # dA = r²/cosθ_i dω (÷ r: Eq. (1))
                if self.amplitude == "coherent":
                    phase += self._voxel_phase(si.p, bounce, ctx)

            if bounce > 0 or self.bounce1 == "cone":
                # Next-event connection to the point receiver.
                value, dist, w_rx, connect = self._connect_rx(
                    scene, si, p_rx, b_rx, n_shade, n_geo, throughput, albedo, cos_in, active,
                    intensity, ctx, ray_stats)
                values = [value]
                if self.complex_output:
                    values = [value * dr.cos(phase), value * dr.sin(phase)]
                if bounce == 0 or self.vertex_spread <= 0.0:
                    sink.add(values, length + dist, pose, slot, bounce, connect)
                else:
                    # Spread over a disk of radius ρ_s around the vertex in its tangent
                    # plane: L varies along the tangential gradient g of the last two
                    # legs; a uniform disk maps to the semicircle density of L over
                    # [−ρ_s|g|, ρ_s|g|], taken at m stratified points with weights.
                    grad = ray.d - w_rx                    # ∂(|x−x_prev| + |x−rx|)/∂x
                    grad = grad - dr.dot(grad, n_geo) * n_geo
                    half_span = dr.norm(grad) * self.vertex_spread
                    m = self.path_samples
                    shift = rng.next_float32()
                    ts = [(2.0 * (i + shift) / m) - 1.0 for i in range(m)]
                    ws = [dr.safe_sqrt(1.0 - t * t) for t in ts]
                    norm = 1.0 / dr.maximum(sum(ws[1:], ws[0]), 1e-12)
                    for t, wt in zip(ts, ws):
                        sink.add([v * wt * norm for v in values], length + dist + t * half_span,
                                 pose, slot, bounce, connect)

            if bounce + 1 < self.max_bounces:
                u_pick = rng.next_float32()
                u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
                d_new, inv_pdf = self._continuation(si.p, n_shade, u_pick, u2, guide)
                cos_new = dr.dot(d_new, n_shade)
                active &= (dr.dot(d_new, n_geo) > 0.0) & (cos_new > 0.0)
                if intensity:                              # (ρ/π · cosθ_o) / pdf
                    throughput *= albedo * dr.inv_pi * cos_new * inv_pdf
                else:   # σ/(2π) / pdf with σ = sqrt(ρ cosθ_i cosθ_o)
                    throughput *= dr.sqrt(albedo * cos_in * cos_new) * (0.5 * dr.inv_pi) * inv_pdf
                ray = self._continue_ray(si.p, d_new)


def _interleave(x):
    """The bits of UInt32 ``x`` < 2^16 spread to the even bit positions (Morton code)."""
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    return (x | (x << 1)) & 0x55555555


