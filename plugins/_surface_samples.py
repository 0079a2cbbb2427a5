"""Stratified surface quadrature for the ``sonar_transient`` bounce-1 surface estimator.

Not a plugin (private module): builds, once per scene and spacing, the strata of an area
quadrature over every shape of a Mitsuba scene, in NumPy.

* **Triangle meshes.** Triangle (a, b, c) with longest edge E is cut into n² congruent
  sub-triangles, n = ⌈E / spacing⌉ (n(n+1)/2 "up" and n(n−1)/2 "down" ones, each of area
  A/n²). Only the *topology* is stored here, per mesh: for each stratum the face index, the
  parent barycentrics (β1, β2) of its corner and the signed scale ±1/n of its edges. The
  geometry (corner P0 = a + β1·(b − a) + β2·(c − a), edges ±(b − a)/n and ±(c − a)/n, normals,
  area A/n²) is computed per lane in Dr.Jit from the mesh's vertex buffers
  (:mod:`._surface_estimator`), so it is differentiable with respect to the vertex positions.
* **Other shapes** (Mitsuba's analytic ``rectangle``, ``sphere``, ``disk``, ...): a grid of
  n_u × n_v cells of the unit square that ``shape.sample_position`` maps onto the surface;
  n_u, n_v = ⌈length of the mapped mid-line / spacing⌉. A sample's area weight is
  (1/(n_u n_v)) / pdf, with the pdf that ``sample_position`` reports, so the quadrature is
  exact in expectation for any mapping.

Coherent mode: a scatterer cell (size ``speckle_spacing``) carries one random phase. The
quadrature strata are nested inside the cells (the fine grid is a k-fold refinement of the
cell grid, k = ⌈speckle_spacing / spacing⌉), so a stratum never straddles two phases.
Cell phases are drawn from ``numpy.random.default_rng([speckle_seed, shape index])``,
independently of the sampling seed.

Depends on numpy and mitsuba (the scene's buffers) only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class MeshStrata:
    """The strata of one triangle mesh: arrays [M] (topology; positions are the mesh's)."""
    shape: object              # the Mitsuba mesh
    tri: np.ndarray            # uint32: face index
    beta1: np.ndarray          # float32: parent barycentric of the stratum corner along b − a
    beta2: np.ndarray          # float32: ... along c − a
    scale: np.ndarray          # float32: ±1/n (down sub-triangles negative)
    inv_n2: np.ndarray         # float32: 1/n² (the stratum's share of the face area)
    sid: np.ndarray            # uint32: stable stratum id (seeds its random numbers)
    phase: np.ndarray | None   # radians [M] (coherent mode) or None

    def __len__(self) -> int:
        return len(self.tri)


@dataclass
class ParametricStrata:
    """A grid of n_u × n_v cells of the unit square of ``shape.sample_position``."""
    shape: object
    n_u: int
    n_v: int
    rho: float
    phase: np.ndarray | None   # radians [n_u * n_v], index iu * n_v + iv

    def __len__(self) -> int:
        return self.n_u * self.n_v


@dataclass
class SurfaceStrata:
    meshes: list               # MeshStrata per mesh with strata
    parametric: list
    spacing: float
    speckle_spacing: float | None
    roi: np.ndarray | None = None    # [2, 3] box (m) the triangle strata were clipped to

    @property
    def count(self) -> int:
        return sum(len(m) for m in self.meshes) + sum(len(p) for p in self.parametric)


def _grid(n: int, i0: int = 0, i1: int | None = None, j0: int = 0, j1: int | None = None):
    """Sub-triangles (i, j, down) of an n-fold subdivision with i0 <= i < i1, j0 <= j < j1."""
    i1 = n if i1 is None else i1
    j1 = n if j1 is None else j1
    i, j = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1), indexing="ij")
    up = (i + j) <= n - 1
    down = (i + j) <= n - 2
    return (np.concatenate([i[up], i[down]]), np.concatenate([j[up], j[down]]),
            np.concatenate([np.zeros(up.sum(), bool), np.ones(down.sum(), bool)]))


_CLIP_ABOVE = 32     # triangles subdivided finer than this are clipped to the ROI


def _clip_range(a, eb, ec, n: int, roi) -> tuple[int, int, int, int]:
    """(i0, i1, j0, j1): the sub-triangle index ranges that can meet the box ``roi`` [2, 3]."""
    corners = np.array([[roi[x][0], roi[y][1], roi[z][2]] for x in (0, 1) for y in (0, 1)
                        for z in (0, 1)], np.float64)
    basis = np.stack([eb, ec], axis=1)                     # [3, 2]
    beta = np.linalg.lstsq(basis, (corners - a).T, rcond=None)[0]   # [2, 8]
    lo, hi = beta.min(axis=1) * n, beta.max(axis=1) * n
    i0, j0 = (max(0, int(math.floor(v)) - 1) for v in lo)
    i1, j1 = (min(n, int(math.ceil(v)) + 1) for v in hi)
    return i0, max(i0, i1), j0, max(j0, j1)


def _albedo(mi, shape) -> float:
    """The diffuse reflectance of the shape's BSDF (textures: evaluated once, at uv = 0)."""
    bsdf = shape.bsdf()
    if bsdf is None:
        return 0.0
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(0.5, 0.5)
    value = bsdf.eval_diffuse_reflectance(si, True)
    return float(np.asarray(value[0] if hasattr(value, "__len__") else value).ravel()[0])


def _cell_phases(rng, n_cells: int) -> np.ndarray:
    return (2 * np.pi * rng.random(n_cells)).astype(np.float32)


def mesh_strata(mi, shape, spacing: float, speckle_spacing: float | None,
                rng, roi=None, id_offset: int = 0) -> MeshStrata:
    """The strata of the triangle mesh ``shape`` (spacing in m; see the module doc)."""
    v = np.asarray(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    f = np.asarray(shape.faces_buffer(), np.int64).reshape(-1, 3)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    keep = double_area > 0
    face_index = np.flatnonzero(keep)
    f, a, b, c = f[keep], a[keep], b[keep], c[keep]
    edge = np.maximum(np.maximum(np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1)),
                      np.linalg.norm(a - c, axis=1))
    if speckle_spacing is not None:
        n_cell = np.maximum(1, np.ceil(edge / speckle_spacing - 1e-9)).astype(np.int64)
        k = max(1, math.ceil(speckle_spacing / spacing - 1e-9))
        n_sub = n_cell * k
        cell_offset = np.concatenate([[0], np.cumsum(2 * n_cell ** 2)])
        phases = _cell_phases(rng, int(cell_offset[-1]))
    else:
        n_sub = np.maximum(1, np.ceil(edge / spacing - 1e-9)).astype(np.int64)
    out = {key: [] for key in ("tri", "i", "j", "down")}

    def add(tris, grid):
        i, j, down = grid
        out["tri"].append(np.repeat(tris, len(i)))
        out["i"].append(np.tile(i, len(tris)))
        out["j"].append(np.tile(j, len(tris)))
        out["down"].append(np.tile(down, len(tris)))

    for n in np.unique(n_sub):          # group triangles by subdivision level
        tris = np.nonzero(n_sub == n)[0]
        if roi is None or n <= _CLIP_ABOVE:
            add(tris, _grid(int(n)))
        else:                            # large triangles (ground planes): only near the ROI
            for t in tris:
                add(np.array([t]), _grid(int(n), *_clip_range(a[t], b[t] - a[t], c[t] - a[t],
                                                               int(n), roi)))
    tri, i, j, down = (np.concatenate(out[key]) for key in ("tri", "i", "j", "down"))
    # stable id: position in the unclipped enumeration of all shapes (mod 2^32)
    tri_offset = np.concatenate([[0], np.cumsum(2 * n_sub ** 2)])
    sid = (id_offset + tri_offset[tri] + (i * n_sub[tri] + j) * 2 + down) % 2**32
    n = n_sub[tri].astype(np.float64)
    sgn = np.where(down, -1.0, 1.0)
    # parent barycentrics (β1 along b − a, β2 along c − a) of the stratum corner
    beta1 = (i + down) / n
    beta2 = (j + down) / n
    phase = None
    if speckle_spacing is not None:
        nc_ = n_cell[tri]
        # centroid barycentrics of the stratum -> the scatterer cell that contains it
        cb1 = beta1 + sgn / (3 * n)
        cb2 = beta2 + sgn / (3 * n)
        ci, cj = np.floor(cb1 * nc_), np.floor(cb2 * nc_)
        cdown = (cb1 * nc_ - ci) + (cb2 * nc_ - cj) > 1.0
        local = (ci * nc_ + cj) * 2 + cdown          # 2·nc² slots per triangle
        phase = phases[cell_offset[tri] + local.astype(np.int64)]
    f32 = lambda x: np.ascontiguousarray(x, np.float32)
    return MeshStrata(shape, np.ascontiguousarray(face_index[tri], np.uint32), f32(beta1),
                      f32(beta2), f32(sgn / n), f32(1.0 / n ** 2), sid.astype(np.uint32), phase)


def _mid_line_length(mi, shape, axis: int, n: int = 65) -> float:
    t = np.linspace(0.0, 1.0, n)
    uv = np.stack([t, np.full(n, 0.5)] if axis == 0 else [np.full(n, 0.5), t])
    ps = shape.sample_position(0.0, mi.Point2f(mi.Float(uv[0]), mi.Float(uv[1])))
    p = np.stack([np.asarray(ps.p.x), np.asarray(ps.p.y), np.asarray(ps.p.z)], axis=1)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def parametric_strata(mi, shape, spacing: float, rho: float, speckle_spacing: float | None,
                      rng) -> ParametricStrata:
    lu, lv = _mid_line_length(mi, shape, 0), _mid_line_length(mi, shape, 1)
    if speckle_spacing is not None:
        k = max(1, math.ceil(speckle_spacing / spacing - 1e-9))
        cu = max(1, math.ceil(lu / speckle_spacing - 1e-9))
        cv = max(1, math.ceil(lv / speckle_spacing - 1e-9))
        n_u, n_v = cu * k, cv * k
        cell = _cell_phases(rng, cu * cv)
        iu, iv = np.meshgrid(np.arange(n_u) // k, np.arange(n_v) // k, indexing="ij")
        phase = cell[(iu * cv + iv).ravel()]
    else:
        n_u = max(1, math.ceil(lu / spacing - 1e-9))
        n_v = max(1, math.ceil(lv / spacing - 1e-9))
        phase = None
    return ParametricStrata(shape, n_u, n_v, rho, phase)


def build(mi, scene, spacing: float, speckle_spacing: float | None = None,
          speckle_seed: int = 0, roi=None) -> SurfaceStrata:
    """Strata of every shape of ``scene`` (spacing and speckle_spacing in metres).

    ``roi``: a box [[x0, y0, z0], [x1, y1, z1]] (m); finely subdivided triangles keep only
    the strata near it (a stratum's id and random numbers do not depend on the clipping).
    """
    meshes, parametric = [], []
    for index, shape in enumerate(scene.shapes()):
        rho = _albedo(mi, shape)
        if rho <= 0:
            continue
        rng = np.random.default_rng([int(speckle_seed), index])
        if shape.is_mesh():
            strata = mesh_strata(mi, shape, spacing, speckle_spacing, rng, roi,
                                 index * 0x9E3779B9)
            if len(strata):
                meshes.append(strata)
        else:
            parametric.append(parametric_strata(mi, shape, spacing, rho, speckle_spacing, rng))
    return SurfaceStrata(meshes, parametric, float(spacing), speckle_spacing,
                         None if roi is None else np.asarray(roi, np.float64))
