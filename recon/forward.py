"""Differentiable ellipsoidal forward model on Dr.Jit (reference code
``inr_reconstruction/sampling.py``, ``forward_model.py``; Reed et al. 2023 supplemental Eq. 10–12).

For a ping with transmitter tx and receiver rx and a round-trip path length r, the points
that return an echo at r lie on the ellipsoid {x : |x − tx| + |x − rx| = r} (foci tx, rx).
A fixed cone of rays leaves tx around the TX boresight; ray j meets the ellipsoid once, at

    t = (r² − |e|²) / (2 (r + d_j·e)),   e = tx − rx,   x = tx + t·d_j

(the positive root of the reference's quadratic, which is linear here because the ray
starts at a focus). The estimated complex sample is the coherent sum over rays

    ŝ(r) = Σ_j σ(x_j) · L_j · T_j                                           (Eq. 12)

with σ the complex scene (trilinear from complex voxels, or any differentiable callable),
L_j = max(0, ⟨n(x_j), −d_j⟩) a Lambertian factor with n = −∇|σ|/‖∇|σ|‖ (for voxels the
exact gradient of the trilinear interpolant, as the reference's autograd normals; for other
callables central finite differences) and T_j a transmittance. Like the reference: no
solid-angle weights or 1/r² spreading, the beam only limits the cone, phase comes from
complex σ (so voxels must be finer than about a quarter wavelength of round-trip path).

Deliberate differences from the reference (documented quirks, docs/reconstruction.md):
- ray directions are unit vectors, spread uniformly in solid angle over the cone (a
  Fibonacci spiral on the spherical cap) instead of a square grid on a plane with
  unnormalised directions;
- the transmittance integrates |σ| over the *along-ray* step between consecutive samples
  of the same ray, T_k = exp(−2·s_occ·Σ_{i<k} |σ_i|·Δt_i) (factor 2 = the return path, as the
  reference's ``factor2``), not over the differences of the selected radii;
- trilinear lookups are zero outside the grid (the reference clamps to the border voxel,
  which smears the boundary to infinity), so the occlusion-free model is exactly linear.

The linear, occlusion-free, non-Lambertian form is the operator :class:`EllipsoidOperator`
(voxels → samples); its adjoint scatters each sample back along its ellipsoid, i.e. an
ellipsoidal backprojection (the suite checks ⟨Ax, y⟩ = ⟨x, Aᴴy⟩ and that Dr.Jit's AD gradient
equals 2Aᴴ(Ax − t)).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from sonarsim.dataset.volume import voxel_spacing
from sonarsim.errors import InputError

from ._jit import jit
from .grid import Grid

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


# ---------------------------------------------------------------------------------------
# Generic linear operators

class LinearOperator:
    """A linear map between complex NumPy arrays (sigpy-like).

    Subclasses set ``ishape``/``oshape`` and implement ``_forward``/``_adjoint``.
    ``op.H`` is the adjoint operator.
    """

    ishape: tuple
    oshape: tuple

    def forward(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x)
        if x.shape != tuple(self.ishape):
            raise InputError(f"{type(self).__name__}.forward: expected shape {self.ishape}, got {x.shape}")
        return self._forward(x)

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        y = np.asarray(y)
        if y.shape != tuple(self.oshape):
            raise InputError(f"{type(self).__name__}.adjoint: expected shape {self.oshape}, got {y.shape}")
        return self._adjoint(y)

    __call__ = forward

    @property
    def H(self) -> "LinearOperator":
        return _Adjoint(self)

    def _forward(self, x):
        raise NotImplementedError

    def _adjoint(self, y):
        raise NotImplementedError


class _Adjoint(LinearOperator):
    def __init__(self, op: LinearOperator):
        self.op, self.ishape, self.oshape = op, op.oshape, op.ishape

    def _forward(self, x):
        return self.op._adjoint(x)

    def _adjoint(self, y):
        return self.op._forward(y)

    @property
    def H(self):
        return self.op


# ---------------------------------------------------------------------------------------
# Rays and ellipsoid samples

def cone_directions(n_rays: int, beamwidth_deg: float) -> np.ndarray:
    """``n_rays`` unit directions [J, 3] spread uniformly in solid angle over a cone of full
    angle ``beamwidth_deg`` around +z (deterministic Fibonacci spiral on the cap)."""
    if int(n_rays) < 1:
        raise InputError(f"n_rays: must be >= 1, got {n_rays}")
    if not 0 < beamwidth_deg <= 360:
        raise InputError(f"beamwidth: full cone angle must be in (0, 360] degrees, got {beamwidth_deg}")
    i = np.arange(int(n_rays)) + 0.5
    cos_min = math.cos(math.radians(beamwidth_deg) / 2)
    cos_t = 1.0 - (1.0 - cos_min) * i / n_rays
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    phi = GOLDEN_ANGLE * i
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)


def boresight_frames(boresight) -> np.ndarray:
    """Orthonormal frames [P, 3, 3] whose third column is the unit boresight [P, 3]:
    a local direction d maps to the world as ``frames[p] @ d``."""
    b = np.asarray(boresight, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    helper = np.where(np.abs(b[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(helper, b)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(b, e1)
    return np.stack([e1, e2, b], axis=2)


@dataclass
class PingGeometry:
    """Per-ping inputs of the forward model (NumPy, float64, metres).

    tx, rx, boresight: [P, 3]; ranges: [P, K] round-trip path lengths, ascending per ping;
    bin_width: [P] round-trip path length of one waveform sample (c_p/fs), or None.
    """

    tx: np.ndarray
    rx: np.ndarray
    boresight: np.ndarray
    ranges: np.ndarray
    bin_width: np.ndarray | None = None

    @property
    def n_pings(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def n_bins(self) -> int:
        return int(self.ranges.shape[1])


class EllipsoidSamples:
    """Sample points of P pings × J rays × K ranges in Dr.Jit (lane = (p·J + j)·K + k).

    ``points`` Array3f, ``dirs`` Array3f (world ray directions), ``t`` Float (distance from
    tx), ``valid`` Bool (r > |tx − rx| and t > 0), ``out_index`` UInt32 = p·K + k.
    The per-ping values are gathered from arrays, so new pings/ranges reuse compiled kernels.
    ``frames`` [P, 3, 3] (local cone → world) defaults to :func:`boresight_frames`.
    """

    def __init__(self, geometry: PingGeometry, directions: np.ndarray,
                 frames: np.ndarray | None = None):
        import drjit as dr
        m = jit()
        P, K, J = geometry.n_pings, geometry.n_bins, len(directions)
        self.shape = (P, J, K)
        self.m = m
        if frames is None:
            frames = boresight_frames(geometry.boresight)
        frames = np.asarray(frames, dtype=np.float64).reshape(P, 9)
        lane = dr.arange(m.UInt32, P * J * K)
        k = lane % K
        pj = lane // K
        j = pj % J
        p = pj // J
        tx = dr.gather(m.Array3f, m.Float(np.asarray(geometry.tx, np.float32).ravel()), p)
        rx = dr.gather(m.Array3f, m.Float(np.asarray(geometry.rx, np.float32).ravel()), p)
        fr = m.Float(frames.astype(np.float32).ravel())
        cols = [m.Array3f(*(dr.gather(m.Float, fr, p * 9 + 3 * row + c) for row in range(3)))
                for c in range(3)]
        dl = dr.gather(m.Array3f, m.Float(np.asarray(directions, np.float32).ravel()), j)
        d = cols[0] * dl[0] + cols[1] * dl[1] + cols[2] * dl[2]
        r = dr.gather(m.Float, m.Float(np.asarray(geometry.ranges, np.float32).ravel()), p * K + k)
        e = tx - rx
        e2 = dr.squared_norm(e)
        denom = 2.0 * (r + dr.dot(d, e))
        t = (r * r - e2) / dr.select(denom > 0, denom, 1.0)
        self.valid = (r * r > e2) & (denom > 0) & (t > 0)
        self.t = dr.select(self.valid, t, 0.0)
        self.points = tx + d * self.t
        self.dirs = d
        self.out_index = p * K + k
        self.n_out = P * K
        self._origin, self._r, self._e2, self._de = tx, r, e2, dr.dot(d, e)
        self._midpoint = 0.5 * (tx + rx)
        self._bin_width = None
        if geometry.bin_width is not None:
            self._bin_width = dr.gather(m.Float, m.Float(np.asarray(geometry.bin_width,
                                                                    np.float32)), p)
        dr.eval(self.points, self.dirs, self.t, self.valid, self.out_index)

    def points_at(self, fraction: float):
        """The points of the same rays on the ellipsoids of path length r + fraction · bin
        width (e.g. ±0.5: the front and back of each sample's range bin), Array3f; where that
        ellipsoid does not meet the ray, the sample's own point."""
        import drjit as dr
        if self._bin_width is None:
            raise ValueError("points_at: the geometry has no bin_width")
        r = self._r + fraction * self._bin_width
        denom = 2.0 * (r + self._de)
        t = (r * r - self._e2) / dr.select(denom > 0, denom, 1.0)
        ok = self.valid & (r * r > self._e2) & (denom > 0) & (t > 0)
        return self._origin + self.dirs * dr.select(ok, t, self.t)

    def look_directions(self):
        """Unit vectors (Array3f, one per lane) from each sample point toward the midpoint of
        its ping's TX and RX: the direction in which the echo the sample stands for leaves the
        point (monostatic back-scatter for a co-located TX/RX; :mod:`recon.scattering`).
        Where the point is the midpoint itself (an invalid lane): +z."""
        import drjit as dr
        v = self._midpoint - self.points
        n = dr.norm(v)
        ok = n > 0
        inv = dr.select(ok, 1.0 / dr.select(ok, n, 1.0), 0.0)
        return self.m.Array3f(v[0] * inv, v[1] * inv, dr.select(ok, v[2] * inv, 1.0))

    def ray_steps(self):
        """Along-ray distance Δt to the next sample of the same ray (last sample: the
        previous step; single sample: 0), as a Float per lane."""
        import drjit as dr
        m = self.m
        P, J, K = self.shape
        if K == 1:
            return dr.zeros(m.Float, P * J * K)
        lane = dr.arange(m.UInt32, P * J * K)
        last = (lane % K) == K - 1
        nxt = dr.gather(m.Float, self.t, dr.select(last, lane - 1, lane + 1))
        return dr.select(last, self.t - nxt, nxt - self.t)


# ---------------------------------------------------------------------------------------
# Scenes

class VoxelField:
    """Trilinear interpolation of complex voxels on a :class:`Grid` (zero outside the grid).

    Along an axis with one voxel the interpolation tent uses the smallest spacing of the
    other axes (:func:`sonarsim.dataset.volume.voxel_spacing`, rule ``'min'``).

    Voxel arrays re, im are flat [nx*ny*nz] (x, y, z order). Kernels read them through a
    *packed* buffer (:meth:`pack`): per z-pair slot the four float32 (Re, Im) of voxels z and
    z + 1 of one (x, y) column, so that one 16-byte packet gather fetches both z corners of
    a cell and one packet scatter-add returns their adjoints. On the 2-core CPU the 4 packet
    scatters of a cell cost about a fifth of 16 scalar ones (measured, docs/reconstruction.md).
    """

    def __init__(self, grid: Grid):
        self.grid = grid
        # sonarsim's single-voxel rule 'min': a 2-D grid is a slab one (smallest) voxel thick
        self.h = voxel_spacing(grid.bounds, grid.shape, single="min") if max(grid.shape) > 1 \
            else np.full(3, 0.01)
        self.lo = grid.bounds[:, 0]
        self.m = jit()
        nx, ny, nz = grid.shape
        self.n_slots = nx * ny * (nz + 1)
        # How the adjoint's scatter-add accumulates into the packed buffer: 'Expand' (a private
        # copy per CPU thread, no atomics) is 2-4x faster than atomics here; keep it while the
        # copies stay below 2^26 floats (256 MB) over all threads. The GPU uses atomics.
        import drjit as dr
        threads = max(int(dr.thread_count()), 1)
        small = 4 * self.n_slots * threads <= (1 << 26)
        self.reduce_mode = "Expand" if small and self.m.__name__.startswith("drjit.llvm") \
            else "Auto"

    def corners(self, points):
        """The 8 (flat index UInt32, weight Float, inside Bool) of trilinear interpolation."""
        import drjit as dr
        m = self.m
        nx, ny, nz = self.grid.shape
        g = [(points[a] - float(self.lo[a])) * float(1.0 / self.h[a]) for a in range(3)]
        i0 = [m.Int32(dr.floor(ga)) for ga in g]
        f = [ga - m.Float(ia) for ga, ia in zip(g, i0)]
        out = []
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    ix, iy, iz = i0[0] + cx, i0[1] + cy, i0[2] + cz
                    inside = ((ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
                              & (iz >= 0) & (iz < nz))
                    w = ((f[0] if cx else 1.0 - f[0]) * (f[1] if cy else 1.0 - f[1])
                         * (f[2] if cz else 1.0 - f[2]))
                    idx = m.UInt32(dr.select(inside, (ix * ny + iy) * nz + iz, 0))
                    out.append((idx, w, inside))
        return out

    # packed z-pairs --------------------------------------------------------------------
    def pack(self, re, im):
        """Packed buffer (flat Float [4·nx·ny·(nz+1)]) of voxel arrays re, im: slot
        s = (ix·ny + iy)·(nz + 1) + iz + 1, for iz = −1 … nz − 1, holds
        (Re v[iz], Im v[iz], Re v[iz+1], Im v[iz+1]), with v = 0 outside the grid."""
        import drjit as dr
        m = self.m
        nz = self.grid.shape[2]
        s = dr.arange(m.UInt32, self.n_slots)
        row, j = s // (nz + 1), s % (nz + 1)
        lo_ok, hi_ok = j > 0, j < nz
        i_lo = row * nz + dr.select(lo_ok, j - 1, 0)
        i_hi = row * nz + dr.select(hi_ok, j, 0)
        vals = [dr.gather(m.Float, re, i_lo, lo_ok), dr.gather(m.Float, im, i_lo, lo_ok),
                dr.gather(m.Float, re, i_hi, hi_ok), dr.gather(m.Float, im, i_hi, hi_ok)]
        buf = dr.zeros(m.Float, 4 * self.n_slots)
        dr.scatter(buf, m.Array4f(*vals), s)
        dr.eval(buf)
        return buf

    def unpack(self, buf):
        """Adjoint of :meth:`pack`: voxel arrays (re, im) [nx*ny*nz], each voxel the sum of its
        two entries in the packed buffer ``buf``."""
        import drjit as dr
        m = self.m
        nz = self.grid.shape[2]
        v = dr.arange(m.UInt32, self.grid.size)
        row, z = v // nz, v % nz
        first = dr.gather(m.Array4f, buf, row * (nz + 1) + z + 1)    # voxel z as lower node
        second = dr.gather(m.Array4f, buf, row * (nz + 1) + z)       # voxel z as upper node
        re, im = first[0] + second[2], first[1] + second[3]
        dr.eval(re, im)
        return re, im

    def _cells(self, points, with_gradient: bool):
        """Per (x, y) corner column of each lane's cell: (slot UInt32, active Bool, weights of
        the lower and upper z node, and with ``with_gradient`` their ∂/∂x, ∂/∂y, ∂/∂z per metre)."""
        import drjit as dr
        m = self.m
        nx, ny, nz = self.grid.shape
        g = [(points[a] - float(self.lo[a])) * float(1.0 / self.h[a]) for a in range(3)]
        fl = [dr.floor(ga) for ga in g]
        f = [ga - fa for ga, fa in zip(g, fl)]
        i0 = [m.Int32(fa) for fa in fl]
        z_ok = (i0[2] >= -1) & (i0[2] < nz)
        inv = [float(1.0 / ha) for ha in self.h]
        out = []
        for cx in (0, 1):
            ix = i0[0] + cx
            wx = f[0] if cx else 1.0 - f[0]
            for cy in (0, 1):
                iy = i0[1] + cy
                wy = f[1] if cy else 1.0 - f[1]
                ok = z_ok & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
                slot = m.UInt32(dr.select(ok, (ix * ny + iy) * (nz + 1) + i0[2] + 1, 0))
                wxy = wx * wy
                w = (wxy * (1.0 - f[2]), wxy * f[2])
                dw = None
                if with_gradient:
                    sx = inv[0] if cx else -inv[0]
                    sy = inv[1] if cy else -inv[1]
                    dx, dy, dz = sx * wy, sy * wx, wxy * inv[2]
                    # ∂w/∂(x, y, z) of the lower and the upper z node
                    dw = ((dx * (1.0 - f[2]), dy * (1.0 - f[2]), -dz),
                          (dx * f[2], dy * f[2], dz))
                out.append((slot, ok, w, dw))
        return out

    def _gather(self, buf, points, active, with_gradient: bool):
        """Interpolation from a packed buffer (no AD): [re, im] or [re, im, ∂x re, ∂y re,
        ∂z re, ∂x im, ∂y im, ∂z im] (Float per lane; derivatives per metre)."""
        import drjit as dr
        m = self.m
        n = dr.width(points)
        out = [dr.zeros(m.Float, n) for _ in range(8 if with_gradient else 2)]
        for slot, ok, w, dw in self._cells(points, with_gradient):
            v = dr.gather(m.Array4f, buf, slot, ok & active)
            out[0] += w[0] * v[0] + w[1] * v[2]
            out[1] += w[0] * v[1] + w[1] * v[3]
            if with_gradient:
                for a in range(3):
                    out[2 + a] += dw[0][a] * v[0] + dw[1][a] * v[2]
                    out[5 + a] += dw[0][a] * v[1] + dw[1][a] * v[3]
        return out

    def _scatter(self, points, active, cot):
        """Adjoint of :meth:`_gather`: the packed buffer receiving the per-lane cotangents
        ``cot`` (same layout as :meth:`_gather`'s output), 4 packet scatter-adds per lane, each
        CPU thread into its own copy while the buffer is small (:attr:`reduce_mode`)."""
        import drjit as dr
        m = self.m
        mode = getattr(dr.ReduceMode, self.reduce_mode)
        with_gradient = len(cot) == 8
        acc = dr.zeros(m.Float, 4 * self.n_slots)
        for slot, ok, w, dw in self._cells(points, with_gradient):
            c = [w[0] * cot[0], w[0] * cot[1], w[1] * cot[0], w[1] * cot[1]]
            if with_gradient:
                for a in range(3):
                    c[0] = dr.fma(dw[0][a], cot[2 + a], c[0])
                    c[1] = dr.fma(dw[0][a], cot[5 + a], c[1])
                    c[2] = dr.fma(dw[1][a], cot[2 + a], c[2])
                    c[3] = dr.fma(dw[1][a], cot[5 + a], c[3])
            dr.scatter_reduce(dr.ReduceOp.Add, acc, m.Array4f(*c), slot, ok & active, mode=mode)
        return acc

    def _interpolate(self, re, im, points, active, with_gradient: bool, buf=None):
        """:meth:`_gather` as one differentiable operation in re, im (not in the points),
        whose adjoint is :meth:`_scatter` then :meth:`unpack`: the backward pass reads no
        voxel values (automatic differentiation of the gathers would re-gather the voxels
        for every downstream nonlinearity). ``buf``: ``pack(re, im)`` if already made."""
        import drjit as dr
        points = dr.detach(points)
        if buf is None:
            buf = self.pack(dr.detach(re), dr.detach(im))
        if not (dr.grad_enabled(re) or dr.grad_enabled(im)):
            return self._gather(buf, points, active, with_gradient)
        return list(dr.custom(_trilinear_op(), self, buf, re, im, points, active,
                              with_gradient))

    def sample(self, re, im, points, active=True, buf=None):
        """Complex values (re, im) Float at ``points`` Array3f from voxel arrays re, im [nx*ny*nz]
        (differentiable with Dr.Jit AD in re, im)."""
        out = self._interpolate(re, im, points, active, False, buf)
        return out[0], out[1]

    def splat(self, points, val_re, val_im, active=True):
        """Explicit adjoint of :meth:`sample`: voxel arrays (re, im) with the values scattered."""
        import drjit as dr
        return self.unpack(self._scatter(dr.detach(points), active, [val_re, val_im]))

    def sample_with_gradient(self, re, im, points, active=True, buf=None):
        """(re, im, ∇re, ∇im) at ``points``: the trilinear interpolant and its exact spatial
        gradient (Array3f, per metre) from the same 4 packet gathers; differentiable in re, im."""
        out = self._interpolate(re, im, points, active, True, buf)
        m = self.m
        return out[0], out[1], m.Array3f(*out[2:5]), m.Array3f(*out[5:8])

    def field(self, re, im) -> "BoundVoxels":
        """A callable points → (re, im) bound to the voxel arrays ``re``, ``im``."""
        return BoundVoxels(self, re, im)


@functools.cache
def _trilinear_op():
    """The ``drjit.CustomOp`` of :meth:`VoxelField._interpolate` (a class made on first use:
    drjit is imported lazily)."""
    import drjit as dr

    class TrilinearOp(dr.CustomOp):
        """Trilinear interpolation (and its spatial gradient) of voxel arrays re, im at fixed
        points; the adjoint scatters into the packed layout and unpacks."""

        def eval(self, vf, buf, re, im, points, active, with_gradient):
            self.vf, self.points, self.active = vf, points, active
            out = vf._gather(buf, points, active, with_gradient)
            dr.eval(*out)
            return tuple(out)

        def forward(self):
            buf = self.vf.pack(self.grad_in("re"), self.grad_in("im"))
            out = self.vf._gather(buf, self.points, self.active, len(self.grad_out()) == 8)
            self.set_grad_out(tuple(out))

        def backward(self):
            acc = self.vf._scatter(self.points, self.active, list(self.grad_out()))
            g_re, g_im = self.vf.unpack(acc)
            self.set_grad_in("re", g_re)
            self.set_grad_in("im", g_im)

        def name(self):
            return "trilinear"

    return TrilinearOp


class BoundVoxels:
    """Voxel arrays bound to their :class:`VoxelField`: ``self(points)`` → (re, im), and
    ``gradient_of_magnitude(points)`` → (re, im, ∇|σ|) for exact Lambertian normals. The
    packed buffer is made once per binding and shared by every lookup."""

    def __init__(self, vf: VoxelField, re, im):
        self.vf, self.re, self.im = vf, re, im
        self._buf = None

    @property
    def buf(self):
        import drjit as dr
        if self._buf is None:
            self._buf = self.vf.pack(dr.detach(self.re), dr.detach(self.im))
        return self._buf

    def __call__(self, points):
        return self.vf.sample(self.re, self.im, points, buf=self.buf)

    def gradient_of_magnitude(self, points):
        re, im, g_re, g_im = self.vf.sample_with_gradient(self.re, self.im, points, buf=self.buf)
        mag = _magnitude(re, im)
        return re, im, (g_re * re + g_im * im) / mag


def _magnitude(re, im):
    import drjit as dr
    return dr.sqrt(re * re + im * im + 1e-20)


def lambertian(field: Callable, points, dirs, eps: float, grad=None):
    """max(0, ⟨n, −d⟩) with n = −∇|σ|/‖∇|σ|‖.

    ∇|σ| is ``grad`` if given (e.g. the exact gradient of the trilinear interpolant, see
    :class:`BoundVoxels`), else central differences of step ``eps`` (m) of ``field``. Where
    the gradient vanishes the factor goes to 0, like the reference's clamped normalisation
    followed by NaN → 0.
    """
    import drjit as dr
    m = jit()
    if grad is None:
        comps = []
        for a in range(3):
            off = [0.0, 0.0, 0.0]
            off[a] = eps
            step = m.Array3f(*off)
            plus = _magnitude(*field(points + step))
            minus = _magnitude(*field(points - step))
            comps.append((plus - minus) * (0.5 / eps))
        grad = m.Array3f(*comps)
    norm = dr.sqrt(dr.squared_norm(grad) + 1e-30)
    # n = -g/|g|; incidence factor <n, -d> = <g, d>/|g|
    return dr.maximum(0.0, dr.dot(grad, dirs) / norm)


def render(field: Callable, samples: EllipsoidSamples, *, lambertian_eps: float | None = None,
           occlusion_scale: float = 0.0, occlusion_factor: float = 2.0, with_sigma: bool = False):
    """Estimated complex samples (re, im) Float [P·K] (index p·K + k) of the scene ``field``.

    field: callable Array3f → (re, im), differentiable (a :class:`BoundVoxels` gives exact
    normals from the trilinear gradient); a *directional* field (``field.directional``, e.g.
    :class:`recon.scattering.BoundShNetwork`) is evaluated by ``field.scatter_toward(points,
    look directions, with_gradient)`` → (σ_re, σ_im, density_re, density_im, ∇|density|): σ
    seen from each sample's look direction (:meth:`EllipsoidSamples.look_directions`) is
    summed, the density sets the transmittance and the Lambertian normals. lambertian_eps: finite-difference step (m) of the
    Lambertian normals of other callables; None = no Lambertian factor. occlusion_scale: s_occ
    (per metre per unit |σ|), 0 = no occlusion. With ``with_sigma`` also returns the sampled
    (re, im) at every lane (for regularisers).
    """
    import drjit as dr
    m = samples.m
    P, J, K = samples.shape
    grad = None
    d_re = d_im = None
    if getattr(field, "directional", False):
        # σ(x, ω) toward the array scatters; the density (transmittance, normals) is the
        # field's direction-independent part (recon.scattering)
        s_re, s_im, d_re, d_im, grad = field.scatter_toward(
            samples.points, samples.look_directions(), with_gradient=lambertian_eps is not None)
    elif lambertian_eps is not None and hasattr(field, "gradient_of_magnitude"):
        s_re, s_im, grad = field.gradient_of_magnitude(samples.points)
    else:
        s_re, s_im = field(samples.points)
    isotropic = d_re is s_re and d_im is s_im       # e.g. sh:0: one variable, one graph
    s_re = dr.select(samples.valid, s_re, 0.0)
    s_im = dr.select(samples.valid, s_im, 0.0)
    if d_re is not None:
        d_re, d_im = (s_re, s_im) if isotropic else (dr.select(samples.valid, d_re, 0.0),
                                                     dr.select(samples.valid, d_im, 0.0))
    w = m.Float(1.0)
    if lambertian_eps is not None:
        w = lambertian(field, samples.points, samples.dirs, float(lambertian_eps), grad)
    dens = None
    if occlusion_scale > 0:
        dens = (_magnitude(s_re, s_im) if d_re is None else _magnitude(d_re, d_im)) \
            * samples.ray_steps()
    # One kernel for what is read several times below (σ, its Lambertian factor and the
    # along-ray density): left lazy, each reduction (the cumulative sum, the two sums over
    # rays, the priors) would re-gather the voxels or re-run the network's last step.
    dr.eval(s_re, s_im, w, dens)
    if occlusion_scale > 0:
        tens = m.TensorXf(dens, shape=(P * J, K))
        inclusive = dr.cumsum(tens, axis=1).array
        w = w * dr.exp(-float(occlusion_scale * occlusion_factor) * (inclusive - dens))
    y_re, y_im = _sum_over_rays(m, s_re * w, s_im * w, samples)
    if with_sigma:
        return y_re, y_im, s_re, s_im
    return y_re, y_im


def render_occupancy(field, samples: EllipsoidSamples, *, occlusion: bool = True):
    """Estimated complex samples (re, im) Float [P·K] of an occupancy scene, and the
    scattering a·w at every lane: (y_re, y_im, s_re, s_im).

    field: ``occupancy_and_amplitude(points)`` → (o ∈ [0, 1], Re a, Im a). Along each ray
    (samples k of the drawn bins, in order of path length) the weight is that of volume
    rendering with occupancies (UNISURF, Oechsle et al. 2021):

        w_k = o_k · T_k,   T_k = Π_{i<k} (1 − o_i)       (T = 1 without ``occlusion``)

    so the first occupied sample along a ray scatters with amplitude a and everything behind
    it — the inside of a solid, surfaces it hides — does not. ŝ = Σ_j a·w over the rays.
    """
    import drjit as dr
    m = samples.m
    P, J, K = samples.shape
    o, a_re, a_im = field.occupancy_and_amplitude(samples.points)
    o = dr.select(samples.valid, o, 0.0)
    w = o
    if occlusion:
        log_t = dr.log(dr.maximum(1.0 - o, 1e-6))
        dr.eval(o, a_re, a_im, log_t)
        inclusive = dr.cumsum(m.TensorXf(log_t, shape=(P * J, K)), axis=1).array
        w = o * dr.exp(inclusive - log_t)
    s_re, s_im = a_re * w, a_im * w
    dr.eval(s_re, s_im)
    if hasattr(field, "cache"):
        field.cache = {"occupancy": o}
    y_re, y_im = _sum_over_rays(m, s_re, s_im, samples)
    return y_re, y_im, s_re, s_im


def _sum_over_rays(m, re, im, samples):
    """Σ_j over the rays of per-lane values re, im → Float [P·K] (index p·K + k).

    A scatter-add into the P·K outputs, each thread into its own copy (``Expand``: no
    atomics; the outputs are few): one kernel for both parts, and its adjoint is a gather.
    On one thread the additions run in lane order, i.e. over j = 0…J−1 per output, the
    same order as a sum along the ray axis of a (P, J, K) tensor. (A single packet scatter
    of (re, im) is a little faster but aborts drjit 1.5's AD when the sums are gathered
    again, as the pulse-autocorrelation model does.)"""
    import drjit as dr
    mode = dr.ReduceMode.Expand if m.__name__.startswith("drjit.llvm") else dr.ReduceMode.Auto
    out = []
    for v in (re, im):
        acc = dr.zeros(m.Float, samples.n_out)
        dr.scatter_reduce(dr.ReduceOp.Add, acc, v, samples.out_index, mode=mode)
        out.append(acc)
    dr.eval(*out)
    return out[0], out[1]


# ---------------------------------------------------------------------------------------
# The linear operator

class EllipsoidOperator(LinearOperator):
    """The occlusion-free, non-Lambertian ellipsoidal model A: complex voxels [nx, ny, nz]
    → complex samples [P, K] (y[p, k] = Σ_j σ(x_pjk), trilinear σ). Aᴴ is its explicit adjoint
    (ellipsoidal backprojection by scatter-add)."""

    def __init__(self, grid: Grid, geometry: PingGeometry, n_rays: int = 1000,
                 beamwidth_deg: float = 30.0, directions: np.ndarray | None = None):
        self.grid = grid
        self.geometry = geometry
        self.directions = cone_directions(n_rays, beamwidth_deg) if directions is None else directions
        self.samples = EllipsoidSamples(geometry, self.directions)
        self.field = VoxelField(grid)
        self.ishape = tuple(grid.shape)
        self.oshape = (geometry.n_pings, geometry.n_bins)

    def forward_jit(self, re, im):
        """A on Dr.Jit voxel arrays (re, im) [nx*ny*nz] → (re, im) [P·K]; differentiable."""
        return render(self.field.field(re, im), self.samples)

    def adjoint_jit(self, y_re, y_im):
        """Aᴴ on Dr.Jit sample arrays [P·K] → voxel arrays (re, im) [nx*ny*nz]."""
        import drjit as dr
        m = self.field.m
        s = self.samples
        v_re = dr.gather(m.Float, y_re, s.out_index)
        v_im = dr.gather(m.Float, y_im, s.out_index)
        return self.field.splat(s.points, v_re, v_im, s.valid)

    def _forward(self, x):
        m = self.field.m
        x = np.asarray(x, dtype=np.complex64).ravel()
        y_re, y_im = self.forward_jit(m.Float(x.real.copy()), m.Float(x.imag.copy()))
        return (np.asarray(y_re) + 1j * np.asarray(y_im)).reshape(self.oshape)

    def _adjoint(self, y):
        m = self.field.m
        y = np.asarray(y, dtype=np.complex64).ravel()
        x_re, x_im = self.adjoint_jit(m.Float(y.real.copy()), m.Float(y.imag.copy()))
        return (np.asarray(x_re) + 1j * np.asarray(x_im)).reshape(self.ishape)


def ping_geometry(dataset, pings, bins, sound_speeds=None) -> PingGeometry:
    """:class:`PingGeometry` of dataset pings [P] at waveform sample indices ``bins`` [P, K]
    (round-trip path r = c_p·(start_sample + k)/fs)."""
    pings = np.asarray(pings)
    bins = np.asarray(bins)
    c = (np.full(len(pings), float(dataset.sound_speed)) if sound_speeds is None
         else np.asarray(sound_speeds)[pings])
    ranges = c[:, None] * (dataset.start_sample + bins) / float(dataset.fs)
    return PingGeometry(tx=np.asarray(dataset.tx)[pings], rx=np.asarray(dataset.rx)[pings],
                        boresight=np.asarray(dataset.boresight)[pings], ranges=ranges,
                        bin_width=c / float(dataset.fs))
