"""Inside/outside of a triangle mesh at lattice points or arbitrary points, by ray-crossing
parity along x, y and z with a majority vote (a hole in the surface corrupts at most one of
the three votes). Exact per triangle and vectorised; needs no rtree/embree.

Used by the evaluation's ground truth (:mod:`recon.metrics`, :mod:`recon.groundtruth`).
"""
from __future__ import annotations

import numpy as np
import trimesh


def _triangle_pairs(counts: np.ndarray, chunk: int = 2_000_000):
    """Yield (triangle index t, index within that triangle's candidates) per candidate pair,
    ``counts[i]`` candidates for triangle i, in groups of about ``chunk`` pairs (bounded
    memory)."""
    keep = np.nonzero(counts)[0]
    start = 0
    while start < len(keep):
        csum = np.cumsum(counts[keep[start:]])
        stop = start + max(1, int(np.searchsorted(csum, chunk, "right")))
        ids = keep[start:stop]
        start = stop
        cnt = counts[ids]
        yield np.repeat(ids, cnt), np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)


def _crossings(tri, pb, pc, t, qb, qc, axis: int):
    """Where the line through (qb, qc) along ``axis`` meets triangle t (projected corners
    ``pb``, ``pc`` [F, 3]): (hit mask, ``axis`` coordinate of each hit), by barycentric weights
    of the point in the projected triangle."""
    xb, xc = pb[t], pc[t]
    d = (xb[:, 1] - xb[:, 0]) * (xc[:, 2] - xc[:, 0]) - (xb[:, 2] - xb[:, 0]) * (xc[:, 1] - xc[:, 0])
    w1 = (qb - xb[:, 0]) * (xc[:, 2] - xc[:, 0]) - (xb[:, 2] - xb[:, 0]) * (qc - xc[:, 0])
    w2 = (xb[:, 1] - xb[:, 0]) * (qc - xc[:, 0]) - (qb - xb[:, 0]) * (xc[:, 1] - xc[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        w1, w2 = w1 / d, w2 / d
        w0 = 1.0 - w1 - w2
    hit = (np.abs(d) > 0) & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    za = tri[t[hit], :, axis]
    return hit, za[:, 0] * w0[hit] + za[:, 1] * w1[hit] + za[:, 2] * w2[hit]


def _axis_parity(tri: np.ndarray, coords: list[np.ndarray], axis: int) -> np.ndarray:
    """Inside-parity of every lattice point from rays parallel to ``axis``.

    ``tri`` [F, 3, 3] triangles; ``coords`` lattice coordinates per axis. Returns bool
    ``[nx, ny, nz]``: odd number of surface crossings below the point along ``axis``.
    """
    b, c = [a for a in range(3) if a != axis]
    bs, cs, As = coords[b], coords[c], coords[axis]
    # Rays exactly through an edge or vertex would be counted twice; an irrational
    # sub-nanometre offset of the rays avoids lattice-aligned mesh coordinates.
    eps = 1e-9 * np.array([np.sqrt(2.0), np.sqrt(3.0)])
    pb, pc = tri[:, :, b] - eps[0], tri[:, :, c] - eps[1]
    b0 = np.searchsorted(bs, pb.min(1), "left")
    b1 = np.searchsorted(bs, pb.max(1), "right")
    c0 = np.searchsorted(cs, pc.min(1), "left")
    c1 = np.searchsorted(cs, pc.max(1), "right")
    nb, nc = np.maximum(b1 - b0, 0), np.maximum(c1 - c0, 0)
    counts = nb * nc
    # uint8 crossing counts: wrap-around at 256 keeps the parity (256 is even)
    toggles = np.zeros((len(bs), len(cs), len(As) + 1), dtype=np.uint8)
    for t, local in _triangle_pairs(counts):
        ib = b0[t] + local // nc[t]
        ic = c0[t] + local % nc[t]
        hit, z = _crossings(tri, pb, pc, t, bs[ib], cs[ic], axis)
        k = np.searchsorted(As, z, "right")  # first lattice point beyond the crossing
        np.add.at(toggles, (ib[hit], ic[hit], k), 1)
    parity = (np.cumsum(toggles[:, :, :-1], axis=2, dtype=np.uint8) % 2).astype(bool)
    # parity is indexed (b, c, axis); move back to (x, y, z)
    return np.moveaxis(parity, 2, axis)


def inside_mesh_lattice(mesh: trimesh.Trimesh, coords: list[np.ndarray]) -> np.ndarray:
    """bool ``[nx, ny, nz]``: lattice points (``coords`` per axis, ascending) inside ``mesh``.

    Majority vote of the crossing parity along x, y and z, so a hole in the surface only
    corrupts one of the three votes.
    """
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    votes = sum(_axis_parity(tri, coords, a).astype(np.int8) for a in range(3))
    return votes >= 2


def inside_mesh_points(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """bool [K]: ``points`` [K, 3] inside ``mesh`` (majority vote of the ray-crossing parity
    along x, y and z, as :func:`inside_mesh_lattice`, for arbitrary points)."""
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    votes = sum(_points_axis_parity(tri, pts, a).astype(np.int8) for a in range(3))
    return votes >= 2


def _points_axis_parity(tri: np.ndarray, pts: np.ndarray, axis: int) -> np.ndarray:
    """bool [K]: odd number of surface crossings below each point along ``axis``."""
    b, c = [a for a in range(3) if a != axis]
    order = np.argsort(pts[:, b], kind="stable")
    bs = pts[order, b]
    pb, pc = tri[:, :, b], tri[:, :, c]
    i0 = np.searchsorted(bs, pb.min(1), "left")
    counts = np.searchsorted(bs, pb.max(1), "right") - i0
    crossings = np.zeros(len(pts), dtype=np.int64)
    for t, local in _triangle_pairs(counts):
        j = order[i0[t] + local]
        hit, z = _crossings(tri, pb, pc, t, pts[j, b], pts[j, c], axis)
        below = z < pts[j[hit], axis]
        np.add.at(crossings, j[hit][below], 1)
    return crossings % 2 == 1
