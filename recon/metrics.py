"""Geometric quality of a reconstructed volume against a ground-truth mesh.

Metrics (after the reference code's ``evaluate/`` scripts; choices documented in
docs/evaluation.md). Two protocols: :func:`evaluate` (exact, the default; a mesh:
:func:`evaluate_mesh`) and the reference's definitions (:mod:`recon.protocol_reference`).

* **Occupancy IoU** on a grid of ``cell`` (5 mm) cells over the volume's box
  ``[lo, hi]``: a cell of the prediction is occupied when a voxel centre with
  normalised magnitude > threshold falls in it (the reference's ``iou``). The GT cell is
  occupied when a voxel centre *inside the GT mesh* falls in it. The reference draws
  50 000 random volume samples of the mesh instead; a containment test at the volume's
  own voxel centres is deterministic (no seed, no empty interior cells: the reference's
  rejection sampling leaves ~28 % of the bunny's and ~40 % of the cube's cells empty), puts GT
  and prediction on the same point lattice (a perfect reconstruction scores exactly 1)
  and needs no rtree/embree. Containment is the majority vote of ray-crossing parity
  along x, y and z, which tolerates the small holes of the reference meshes (the bunny
  has 42 open edges).
* **Chamfer** between 20 000 seeded surface samples of the GT mesh and 20 000 of the
  reconstruction's marching-cubes surface: ``chamfer_sq`` = mean squared nearest
  distance GT->pred plus pred->GT (m², the reference's pytorch3d default) and
  ``chamfer_m`` = the mean of the two mean (unsquared) distances (m).
  ``chamfer_vox_sq`` / ``chamfer_vox_m`` use the occupied voxel centres instead of the
  mesh samples (the reference's ``cham``).
* **Normals**: each surface sample is paired with the nearest sample of the other surface;
  ``normal_consistency`` = mean ``|n_gt . n_pred|`` (1 = perfect) and ``normal_error_deg`` =
  mean ``arccos |n_gt . n_pred|`` (0° = perfect), both averaged over both directions
  (orientation-free: the reference meshes are not consistently oriented).
* A threshold **sweep** reports each metric at every threshold and its best value.

An empty reconstruction (nothing above the threshold) gives IoU 0 and ``None``
(JSON ``null``) for the distances, with ``empty = True``.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from sonarsim import identity
from sonarsim.errors import InputError

from . import export, groundtruth
from .containment import _axis_parity, inside_mesh_lattice  # noqa: F401 (re-exported)

IOU_CELL = 0.005
from .evaluation_options import N_SURFACE_SAMPLES  # noqa: E402 (re-exported)
DEFAULT_SWEEP = tuple(np.round(np.arange(0.05, 0.951, 0.05), 2))


# ------------------------------------------------------------------------ GT input

def load_gt_mesh(path: str | Path) -> trimesh.Trimesh:
    """Ground-truth mesh (metres) from a mesh file (as given), a sonarsim dataset ``.h5``
    holding ``gt/vertices`` + ``gt/faces`` (as placed), or a scene TOML / shipped scene name;
    checked by :func:`recon.groundtruth.load_ground_truth` (which also says which frame)."""
    return groundtruth.load_ground_truth(path).mesh


# ------------------------------------------------------------- GT point sets, made once

_GT_CACHE: "OrderedDict[tuple, object]" = OrderedDict()
GT_CACHE_SIZE = 16      # entries (a GT's lattice mask or sample set: a few MB each)


def cached_gt(kind: str, mesh: trimesh.Trimesh, args: tuple, compute):
    """``compute()`` for a GT mesh, remembered per (kind, mesh, args) in this process: the
    cells of one shape (every method, both protocols, every threshold) share the GT's
    containment lattice and sample sets instead of recomputing them (seconds each). The
    arrays returned are read-only. The mesh and ``args`` (which may hold arrays) are keyed by
    their content (:func:`sonarsim.identity.digest`)."""
    key = (kind, identity.digest(mesh, args))
    if key in _GT_CACHE:
        _GT_CACHE.move_to_end(key)
        return _GT_CACHE[key]
    value = compute()
    parts = value.values() if isinstance(value, dict) else \
        (value if isinstance(value, tuple) else (value,))
    for a in parts:
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    _GT_CACHE[key] = value
    while len(_GT_CACHE) > GT_CACHE_SIZE:
        _GT_CACHE.popitem(last=False)
    return value


class _LatticeValues:
    """A float array over a voxel lattice, NaN where not computed yet (kept in the GT cache
    and filled in place: a holder, so the cache does not make it read-only)."""

    def __init__(self, shape):
        self.values = np.full(shape, np.nan)


# --------------------------------------------------------------------------- IoU

@dataclass(frozen=True)
class CellGrid:
    """Cells of edge ``cell`` (m) covering the box ``[lo, hi]``; shape ceil((hi-lo)/cell)."""
    lo: np.ndarray
    hi: np.ndarray
    cell: float

    @property
    def shape(self) -> tuple[int, int, int]:
        n = np.ceil((self.hi - self.lo) / self.cell - 1e-9).astype(int)
        return tuple(int(v) for v in np.maximum(n, 1))

    def occupancy(self, points: np.ndarray) -> np.ndarray:
        """bool grid: cells containing at least one of ``points`` [K, 3] (outside: ignored).

        Points on the upper box face fall into the last cell.
        """
        occ = np.zeros(self.shape, dtype=bool)
        if len(points) == 0:
            return occ
        # Lattice points exactly on a cell face (e.g. voxel spacing = cell) must not
        # flip between cells by rounding: nudge by 1e-6 cell towards the upper cell.
        idx = np.floor((points - self.lo) / self.cell + 1e-6).astype(np.int64)
        shape = np.asarray(self.shape)
        on_top = np.isclose(points, self.hi, rtol=0, atol=1e-9)
        idx = np.where(on_top & (idx == shape), shape - 1, idx)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        i = idx[inside]
        occ[i[:, 0], i[:, 1], i[:, 2]] = True
        return occ


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∧ b| / |a ∨ b| of two bool grids; 1.0 when both are empty."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


# ----------------------------------------------------------------------- distances

def _nearest(tree_of_b, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) of each point of ``a`` to its nearest point of the tree's set."""
    return tree_of_b.query(a, workers=-1)


class PointSet:
    """Points [N, 3] (and optional unit normals [N, 3]) with their k-d tree built once, for
    comparing one set (a GT's surface samples) with many others (one per threshold)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray | None = None):
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.normals = normals
        self._tree = None

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def __len__(self) -> int:
        return len(self.points)


def _as_set(points, normals=None) -> PointSet:
    return points if isinstance(points, PointSet) else PointSet(points, normals)


def _chamfer_of(dab: np.ndarray, dba: np.ndarray) -> dict:
    """:func:`chamfer`'s values from the nearest-neighbour distances a→b and b→a (m)."""
    return {"sq": float(np.mean(dab ** 2) + np.mean(dba ** 2)),
            "m": float(0.5 * (dab.mean() + dba.mean())),
            "a_to_b_m": float(dab.mean()), "b_to_a_m": float(dba.mean())}


def surface_agreement(a, b, na=None, nb=None) -> tuple[dict, float | None, float | None]:
    """(:func:`chamfer` of ``a`` and ``b``, normal consistency, normal angular error in
    degrees) from one nearest-neighbour query each way: point sets [N, 3] / [M, 3] or
    :class:`PointSet` (whose tree is reused); normals [N, 3] / [M, 3] (or the sets' own)
    give the normal terms of :func:`normal_agreement`, else they are None."""
    a, b = _as_set(a, na), _as_set(b, nb)
    if len(a) == 0 or len(b) == 0:
        return {"sq": None, "m": None, "a_to_b_m": None, "b_to_a_m": None}, None, None
    dab, ia = _nearest(b.tree, a.points)
    dba, ib = _nearest(a.tree, b.points)
    cm = _chamfer_of(dab, dba)
    if a.normals is None or b.normals is None:
        return cm, None, None
    ab = np.clip(np.abs(np.sum(a.normals * b.normals[ia], axis=1)), 0.0, 1.0)
    ba = np.clip(np.abs(np.sum(b.normals * a.normals[ib], axis=1)), 0.0, 1.0)
    consistency = 0.5 * (ab.mean() + ba.mean())
    angle = 0.5 * (np.degrees(np.arccos(ab)).mean() + np.degrees(np.arccos(ba)).mean())
    return cm, float(consistency), float(angle)


def chamfer(a: np.ndarray, b: np.ndarray) -> dict:
    """Chamfer distances between point sets ``a`` [N, 3] and ``b`` [M, 3] (metres; either may
    be a :class:`PointSet`).

    ``sq``: mean squared NN distance a->b plus b->a (m²; reference definition);
    ``m``: (mean NN distance a->b + mean b->a) / 2 (m); ``a_to_b_m``, ``b_to_a_m``.
    ``None`` values when either set is empty.
    """
    return surface_agreement(a, b)[0]


def normal_agreement(pa: np.ndarray, na: np.ndarray, pb: np.ndarray, nb: np.ndarray
                     ) -> tuple[float | None, float | None]:
    """(consistency, angular error in degrees) of the normals ``na`` [N, 3], ``nb`` [M, 3] of
    two sample sets ``pa``, ``pb`` (unit normals; orientation-free).

    Each sample is paired with its nearest sample on the other surface; consistency is the
    mean ``|n_a . n_b|`` (1 = perfect), the angular error the mean ``arccos |n_a . n_b|``
    (0°..90°, 0 = perfect), each averaged over both directions. (None, None) if a set is empty.
    """
    _, consistency, angle = surface_agreement(pa, pb, na, nb)
    return consistency, angle


def normal_consistency(pa: np.ndarray, na: np.ndarray, pb: np.ndarray, nb: np.ndarray
                       ) -> float | None:
    """Mean ``|n_a . n_b|`` of nearest-neighbour pairs, averaged over both directions."""
    return normal_agreement(pa, na, pb, nb)[0]


def surface_samples(mesh: trimesh.Trimesh, count: int, seed: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform surface points [count, 3] and their face normals (seeded)."""
    if len(mesh.faces) == 0 or mesh.area <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(pts), np.asarray(mesh.face_normals[face])


def samples_in_box(mesh: trimesh.Trimesh, count: int, seed: int, box=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_samples`; with ``box`` [3, 2] (m), about ``count`` samples of the part of
    the surface inside the box (resampled densely enough, then truncated)."""
    pts, normals = surface_samples(mesh, count, seed)
    if box is None or len(pts) == 0:
        return pts, normals
    lo, hi = np.asarray(box, dtype=np.float64).T
    inside = np.all((pts >= lo - 1e-9) & (pts <= hi + 1e-9), axis=1)
    if inside.all() or not inside.any():
        return pts[inside], normals[inside]
    more = int(np.ceil(1.2 * count / inside.mean()))
    pts, normals = surface_samples(mesh, more, seed)
    inside = np.all((pts >= lo - 1e-9) & (pts <= hi + 1e-9), axis=1)
    return pts[inside][:count], normals[inside][:count]


# ---------------------------------------------------------------------- evaluation

class Evaluator:
    """Evaluate one volume against one GT mesh at any threshold.

    ``volume``: complex/real ``[nx, ny, nz]``; ``bounds`` [3, 2] (voxel-centre
    convention). GT samples and the GT occupancy are computed once.
    """

    def __init__(self, volume: np.ndarray, bounds, gt_mesh: trimesh.Trimesh, *,
                 normalization: str = "minmax", cell: float = IOU_CELL,
                 n_samples: int = N_SURFACE_SAMPLES, seed: int = 0, crop=None):
        if not cell > 0:
            raise InputError(f"IoU cell size must be positive, got {cell}")
        if int(n_samples) < 1:
            raise InputError(f"number of surface samples must be >= 1, got {n_samples}")
        self.crop = None if crop is None else np.asarray(crop, dtype=np.float64)
        if self.crop is not None:
            volume, bounds = export.crop_volume(volume, bounds, self.crop)
        self.magnitude = export.normalized_magnitude(volume, normalization)
        self.bounds = export.check_bounds(bounds, self.magnitude.shape)
        self.coords = export.voxel_axes(self.bounds, self.magnitude.shape)
        self.grid = CellGrid(self.bounds[:, 0], self.bounds[:, 1], float(cell))
        self.n_samples, self.seed = int(n_samples), int(seed)
        self.gt_mesh = gt_mesh
        inside = cached_gt("lattice", gt_mesh, tuple(self.coords),
                           lambda: inside_mesh_lattice(gt_mesh, self.coords))
        idx = np.nonzero(inside)
        self.gt_points = np.stack([self.coords[a][idx[a]] for a in range(3)], axis=1)
        self.gt_occupancy = self.grid.occupancy(self.gt_points)
        box = None if self.crop is None else self.bounds
        self.gt_surface, self.gt_normals = cached_gt(
            "samples", gt_mesh, (self.n_samples, self.seed, box),
            lambda: self._samples(gt_mesh, self.seed))
        self.gt_set = PointSet(self.gt_surface, self.gt_normals)   # its k-d tree: built once

    def _samples(self, mesh: trimesh.Trimesh, seed: int) -> tuple[np.ndarray, np.ndarray]:
        box = None if self.crop is None else self.bounds
        return samples_in_box(mesh, self.n_samples, seed, box)

    def at(self, threshold: float) -> dict:
        """All geometric metrics at one threshold (see module docstring)."""
        t = export.check_threshold(threshold)
        pts = export.occupied_points(self.magnitude, self.bounds, t)
        occ = self.grid.occupancy(pts)
        mesh = export.extract_surface(self.magnitude, self.bounds, t)
        # a different seed than the GT so the two sample sets are independent
        surf, normals = self._samples(mesh, self.seed + 1)
        cm, nc, angle = surface_agreement(self.gt_set, PointSet(surf, normals))
        cv = self._voxel_chamfer(t, pts)
        return {
            "threshold": t,
            "iou": iou(occ, self.gt_occupancy),
            "chamfer_sq": cm["sq"], "chamfer_m": cm["m"],
            "completeness_m": cm["a_to_b_m"], "accuracy_m": cm["b_to_a_m"],
            "chamfer_vox_sq": cv["sq"], "chamfer_vox_m": cv["m"],
            "normal_consistency": nc, "normal_error_deg": angle,
            "occupied_voxels": int(len(pts)), "occupied_cells": int(occ.sum()),
            "gt_cells": int(self.gt_occupancy.sum()),
            "mesh_faces": int(len(mesh.faces)),
            "empty": bool(len(pts) == 0),
        }

    def surface(self, threshold: float) -> trimesh.Trimesh:
        return export.extract_surface(self.magnitude, self.bounds, threshold)

    # The voxel Chamfer of a threshold sweep: the occupied voxels of every threshold above
    # ``lowest`` are subsets of those above ``lowest``, so their distances to the GT samples
    # are queried once, and each GT sample's nearest occupied voxel is the first of its
    # ``SWEEP_NEIGHBOURS`` nearest voxels above ``lowest`` whose magnitude exceeds the
    # threshold (a k-d tree of that threshold's voxels only where none of them does). The
    # numbers are those of chamfer(gt_surface, occupied_points(...)): the same point pairs.
    SWEEP_NEIGHBOURS = 32

    def prepare_sweep(self, lowest: float) -> None:
        """Make :meth:`at` of every threshold >= ``lowest`` reuse one set of voxel queries."""
        t = export.check_threshold(lowest)
        mask = self.magnitude > t
        pts = export.occupied_points(self.magnitude, self.bounds, t)
        self._sweep = None
        if len(pts) == 0 or len(self.gt_surface) == 0:
            return
        to_gt = self._distances_to_gt(mask)
        k = min(self.SWEEP_NEIGHBOURS, len(pts))
        dist, idx = cKDTree(pts).query(self.gt_surface, k=k, workers=-1)
        dist, idx = dist.reshape(len(self.gt_surface), k), idx.reshape(len(self.gt_surface), k)
        self._sweep = {"lowest": t, "mag": self.magnitude[mask], "pts": pts, "to_gt": to_gt,
                       "knn_dist": dist, "knn_mag": self.magnitude[mask][idx]}

    def _distances_to_gt(self, mask: np.ndarray) -> np.ndarray:
        """Distance (m) from each voxel centre of ``mask`` (C order) to the nearest GT
        surface sample; remembered per GT, sample set and lattice, so the volumes of other
        methods on the same grid query only the voxels not asked for before."""
        box = None if self.crop is None else self.bounds
        known = cached_gt("voxel distances", self.gt_mesh,
                          (self.n_samples, self.seed, box, tuple(self.coords)),
                          lambda: _LatticeValues(self.magnitude.shape))
        need = mask & np.isnan(known.values)
        if need.any():
            idx = np.nonzero(need)
            q = np.stack([self.coords[a][idx[a]] for a in range(3)], axis=1)
            known.values[need] = self.gt_set.tree.query(q, workers=-1)[0]
        return known.values[mask]

    def _voxel_chamfer(self, t: float, pts: np.ndarray) -> dict:
        sweep = getattr(self, "_sweep", None)
        if sweep is None or t < sweep["lowest"] or len(pts) == 0:
            return chamfer(self.gt_set, pts)
        keep = sweep["mag"] > t                          # the voxels of occupied_points(t)
        above = sweep["knn_mag"] > t
        first = above.argmax(axis=1)
        dab = sweep["knn_dist"][np.arange(len(first)), first]
        missing = ~above.any(axis=1)
        if missing.any():
            dab[missing], _ = cKDTree(sweep["pts"][keep]).query(self.gt_surface[missing],
                                                              workers=-1)
        return _chamfer_of(dab, sweep["to_gt"][keep])


# metric -> True when larger is better
SWEPT = {"iou": True, "chamfer_sq": False, "chamfer_m": False,
         "chamfer_vox_sq": False, "normal_consistency": True, "normal_error_deg": False}


def best_of(rows: list[dict]) -> dict:
    """``{metric: {'value', 'threshold'}}`` of the best row per metric in :data:`SWEPT`;
    ``None`` values where no row has the metric."""
    best = {}
    for key, larger in SWEPT.items():
        valid = [r for r in rows if r.get(key) is not None]
        if not valid:
            best[key] = {"value": None, "threshold": None}
            continue
        pick = (max if larger else min)(valid, key=lambda r: r[key])
        best[key] = {"value": pick[key], "threshold": pick["threshold"]}
    return best


def evaluate(volume: np.ndarray, bounds, gt_mesh: trimesh.Trimesh, *,
             threshold: float = export.DEFAULT_THRESHOLD,
             sweep: tuple[float, ...] | None = DEFAULT_SWEEP,
             normalization: str = "minmax", cell: float = IOU_CELL,
             n_samples: int = N_SURFACE_SAMPLES, seed: int = 0, crop=None) -> dict:
    """Metrics at ``threshold`` plus, with ``sweep``, each metric's best threshold.

    Returns a flat dict: the keys of :meth:`Evaluator.at` at ``threshold``, then
    ``best_<metric>`` and ``best_<metric>_threshold`` for the metrics in :data:`SWEPT`,
    and ``sweep`` (list of per-threshold rows).

    ``crop`` [3, 2] (m): evaluate only inside this box (e.g. z >= 5 mm to leave out the
    ground): voxels outside are dropped before normalising, and surface samples of both
    meshes outside the kept voxel centres' box (including the marching-cubes caps on the
    crop faces) are ignored.
    """
    ev = Evaluator(volume, bounds, gt_mesh, normalization=normalization, cell=cell,
                   n_samples=n_samples, seed=seed, crop=crop)
    main = ev.at(threshold)
    result = dict(main)
    result.update({"normalization": normalization, "iou_cell_m": float(cell),
                   "n_samples": int(n_samples), "seed": int(seed),
                   "evaluated_bounds": ev.bounds.tolist()})
    if sweep:
        thresholds = sorted(set(float(t) for t in sweep) | {main["threshold"]})
        ev.prepare_sweep(thresholds[0])
        rows = [main if abs(t - main["threshold"]) < 1e-12 else ev.at(t) for t in thresholds]
        for key, b in best_of(rows).items():
            result[f"best_{key}"] = b["value"]
            result[f"best_{key}_threshold"] = b["threshold"]
        result["sweep"] = rows
    return result


# ------------------------------------------------------------------- a mesh as prediction

def mesh_lattice(meshes, cell: float = IOU_CELL, crop=None) -> tuple[np.ndarray, list]:
    """(box [3, 2], lattice coordinates per axis) for evaluating meshes: the union of their
    bounding boxes snapped outwards to multiples of ``cell`` (intersected with ``crop``), and
    the centres of its half-cells, so that each IoU cell holds 2 × 2 × 2 lattice points."""
    los = [np.asarray(m.bounds[0]) for m in meshes if len(m.faces)]
    his = [np.asarray(m.bounds[1]) for m in meshes if len(m.faces)]
    lo = np.floor(np.min(los, axis=0) / cell - 1e-9) * cell
    hi = np.ceil(np.max(his, axis=0) / cell + 1e-9) * cell
    if crop is not None:
        c = np.asarray(crop, dtype=np.float64).reshape(3, 2)
        lo, hi = np.maximum(lo, c[:, 0]), np.minimum(hi, c[:, 1])
        if np.any(hi <= lo):
            raise InputError("--crop: the box does not overlap the meshes")
    coords = [lo[a] + (np.arange(max(1, int(round((hi[a] - lo[a]) / (cell / 2))))) + 0.5)
              * cell / 2 for a in range(3)]
    return np.stack([lo, hi], axis=1), coords


def evaluate_mesh(mesh: trimesh.Trimesh, gt_mesh: trimesh.Trimesh, *, cell: float = IOU_CELL,
                  n_samples: int = N_SURFACE_SAMPLES, seed: int = 0, crop=None) -> dict:
    """The exact protocol's metrics for a reconstructed *mesh* (world metres), e.g. the
    output of ``recon refine``: no threshold, nothing to sweep.

    * ``iou``: both meshes' containment at the half-cell centres of :func:`mesh_lattice`
      (their joint box), cells of ``cell``: the same definition as for a volume, on a lattice
      of our choosing (a mesh has none);
    * ``chamfer_*``, ``normal_*``: ``n_samples`` surface samples of each mesh (GT with
      ``seed``, the mesh with ``seed + 1``); with ``crop``, only the parts inside the box.
    """
    if int(n_samples) < 1:
        raise InputError(f"number of surface samples must be >= 1, got {n_samples}")
    empty = len(mesh.faces) == 0 or not mesh.area > 0
    box, coords = mesh_lattice([gt_mesh] if empty else [mesh, gt_mesh], cell, crop)
    grid = CellGrid(box[:, 0], box[:, 1], float(cell))

    def cells_inside(m):
        if len(m.faces) == 0:
            return grid.occupancy(np.zeros((0, 3)))
        idx = np.nonzero(inside_mesh_lattice(m, coords))
        return grid.occupancy(np.stack([coords[a][idx[a]] for a in range(3)], axis=1))

    pred_cells, gt_cells = cells_inside(mesh), cells_inside(gt_mesh)
    clip = None if crop is None else box
    gt_surf, gt_n = samples_in_box(gt_mesh, n_samples, seed, clip)
    surf, normals = samples_in_box(mesh, n_samples, seed + 1, clip)
    cm, nc, angle = surface_agreement(gt_surf, surf, gt_n, normals)
    return {"protocol": "exact", "threshold": None, "iou": iou(pred_cells, gt_cells),
            "chamfer_sq": cm["sq"], "chamfer_m": cm["m"],
            "completeness_m": cm["a_to_b_m"], "accuracy_m": cm["b_to_a_m"],
            "normal_consistency": nc, "normal_error_deg": angle,
            "occupied_cells": int(pred_cells.sum()), "gt_cells": int(gt_cells.sum()),
            "mesh_faces": int(len(mesh.faces)), "empty": bool(empty),
            "iou_cell_m": float(cell), "n_samples": int(n_samples), "seed": int(seed),
            "evaluated_bounds": box.tolist()}
