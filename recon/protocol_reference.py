"""The reference's evaluation protocol (``recon evaluate --protocol reference``): its
definitions, *and* its quirks, so that our numbers can sit beside the paper's Table 2.

Reed et al. 2023, reference code ``evaluate/point_cloud_utils.py`` and
``evaluate/main_mesh_recon_and_3d_space_loss.py`` (docs/evaluation.md, "Protocols"):

* **GT volume points**: ``trimesh.sample.volume_mesh(mesh, 50 000)``: uniform tries in the
  mesh's bounding box, those inside kept (:func:`volume_samples`).
* **IoU grid** (:func:`voxelize`): Open3D's ``create_from_point_cloud_within_bounds`` with
  5 mm cells from (−0.2, −0.2, 0), then copied into a NumPy array of
  ``int((hi − lo)/0.005)`` = **80 × 80 × 60** cells. Open3D does not drop points outside the
  bounds; the copy clamps indices above the grid to its last cell and lets NumPy wrap negative
  ones, so points just below z = 0 (the reference cube reaches z = −4.5 mm) land in the *top*
  layers of cells. Reproduced.
* **Prediction points**: the voxel centres whose min–max-normalised magnitude exceeds τ
  (the reference's ``iou``, the paper's choice); the mesh's surface samples give ``mesh_iou``.
* **Surface** (:func:`reference_mesh`): binarise at τ, pad by one voxel, PyMCubes' constrained
  smoothing, marching cubes at level 0; vertices mapped with ``lo + p/n·(hi − lo)`` where p is
  the index in the *padded* array (the padding is not removed and the division is by n, not
  n − 1): the mesh sits up to one voxel (3.2 mm) towards +x, +y, +z. Reproduced
  (``mapping='reference'``); ``mapping='centre'`` maps by the voxel-centre convention.
* **Chamfer**: pytorch3d's default (squared, mean each way, summed) between 20 000 GT surface
  samples and 20 000 samples of the surface (``mesh_cham``, the paper's choice).
* **Threshold sweep**: τ = 0.10, 0.11, …, 0.49 (the reference's ``np.arange(.1, .5, .01)``),
  each metric's best value reported as its "optimal value".

A reconstructed **mesh** (``recon refine`` output, any PLY/OBJ in world metres) is evaluated by
the same definitions (:func:`evaluate_reference_mesh`): its prediction points are the
centres of the reference's 125 × 125 × 94 voxel grid that lie inside it, its surface is itself.
"""
from __future__ import annotations

import numpy as np
import trimesh

from sonarsim.errors import InputError

from . import export
from .containment import inside_mesh_lattice, inside_mesh_points
from .evaluation_options import MAPPINGS, N_VOLUME_SAMPLES  # noqa: F401
from .metrics import (N_SURFACE_SAMPLES, PointSet, cached_gt, iou, surface_agreement,
                      surface_samples)

BOX = np.array([[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]])      # the simulated scene box (m)
GRID_SHAPE = (125, 125, 94)                                  # its voxel grid (3.2 mm)
IOU_UNIT = 0.005                                             # IoU cell (m)
IOU_CELLS = tuple(int((hi - lo) / IOU_UNIT) for lo, hi in BOX)   # (80, 80, 60), as the reference
SWEEP = tuple(float(t) for t in np.round(np.arange(0.10, 0.50, 0.01), 2))
# Chamfer sweep: a surface per threshold costs a constrained smoothing each, so the Chamfer's
# best τ is searched on this coarser subset of SWEEP (the IoU's on all of it).
CHAMFER_SWEEP = tuple(float(t) for t in np.round(np.arange(0.10, 0.50, 0.05), 2))


def volume_samples(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """The reference's GT volume samples (``trimesh.sample.volume_mesh``): ``count`` uniform
    points in the mesh's bounding box (seeded), of which those inside the mesh are returned
    ([≈ count·V/V_box, 3]). Containment by :func:`recon.containment.inside_mesh_points`
    (trimesh's own needs rtree and is very slow on the open bunny mesh)."""
    lo, hi = np.asarray(mesh.bounds[0], float), np.asarray(mesh.bounds[1], float)
    pts = lo + np.random.default_rng(seed).random((int(count), 3)) * (hi - lo)
    return pts[inside_mesh_points(mesh, pts)]


def voxelize(points: np.ndarray) -> np.ndarray:
    """bool ``IOU_CELLS`` occupancy of ``points`` [K, 3] as the reference computes it.

    Cell index ``floor((p − lo)/0.005)`` per axis; indices ≥ N go to the last cell, indices in
    [−N, 0) wrap to N + index (NumPy negative indexing); points further below the box would
    crash the reference and are dropped here.
    """
    occ = np.zeros(IOU_CELLS, dtype=bool)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return occ
    n = np.asarray(IOU_CELLS)
    idx = np.floor((pts - BOX[:, 0]) / IOU_UNIT).astype(np.int64)
    idx = np.minimum(idx, n - 1)
    keep = np.all(idx >= -n, axis=1)
    idx = np.where(idx < 0, idx + n, idx)[keep]
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return occ


def reference_mesh(magnitude: np.ndarray, bounds, threshold: float,
                   mapping: str = "reference") -> trimesh.Trimesh:
    """The reference's ``mesh_smooth``: binarise ``magnitude > threshold``, pad by one voxel,
    PyMCubes' constrained smoothing (:func:`recon.smoothing.smooth_constrained`, the same
    result, faster), marching cubes at level 0.

    ``mapping='reference'``: vertex = ``lo + p/n·(hi − lo)`` with p the index in the padded
    array (the reference's ``normalize_vertices``); ``'centre'``: ``lo + (p − 1)·Δ``, Δ = (hi −
    lo)/(n − 1) (the voxel-centre convention). An empty binary volume gives an empty mesh.
    """
    import mcubes

    from .smoothing import smooth_constrained
    if mapping not in MAPPINGS:
        raise InputError(f"mapping: choose one of {MAPPINGS}, got {mapping!r}")
    t = export.check_threshold(threshold)
    binary = np.asarray(magnitude) > t
    if not binary.any():
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    smooth = smooth_constrained(np.pad(binary, 1))
    verts, faces = mcubes.marching_cubes(smooth, 0.0)
    verts = np.asarray(verts, dtype=np.float64)
    b = np.asarray(bounds, dtype=np.float64)
    if mapping == "reference":
        n = np.asarray(binary.shape, dtype=np.float64)
        world = b[:, 0] + verts / n * (b[:, 1] - b[:, 0])
    else:
        world = b[:, 0] + (verts - 1.0) * export.voxel_spacing(b, binary.shape)
    return trimesh.Trimesh(world, np.asarray(faces, dtype=np.int64), process=False)


def grid_points_inside(mesh: trimesh.Trimesh) -> np.ndarray:
    """Centres [K, 3] of the reference's voxel grid (:data:`GRID_SHAPE` over :data:`BOX`)
    inside ``mesh``: a mesh's analogue of the voxels above τ."""
    coords = [np.linspace(lo, hi, n) for (lo, hi), n in zip(BOX, GRID_SHAPE)]
    if len(mesh.faces) == 0:
        return np.zeros((0, 3))
    idx = np.nonzero(inside_mesh_lattice(mesh, coords))
    return np.stack([coords[a][idx[a]] for a in range(3)], axis=1)


class _GroundTruth:
    """The reference's GT point sets of one mesh: volume samples and their cells, surface
    samples and normals."""

    def __init__(self, gt_mesh: trimesh.Trimesh, seed: int, n_volume: int, n_surface: int):
        self.volume = cached_gt("volume samples", gt_mesh, (n_volume, seed),
                                lambda: volume_samples(gt_mesh, n_volume, seed))
        self.cells = voxelize(self.volume)
        self.surface, self.normals = cached_gt("samples", gt_mesh, (n_surface, seed, None),
                                               lambda: surface_samples(gt_mesh, n_surface, seed))
        self.surface_set = PointSet(self.surface, self.normals)    # k-d tree built once
        self.seed, self.n_surface = seed, n_surface

    def surface_scores(self, mesh: trimesh.Trimesh) -> dict:
        """Chamfer, normal agreement and ``mesh_iou`` of a reconstructed surface."""
        surf, normals = surface_samples(mesh, self.n_surface, self.seed + 1)
        cm, nc, angle = surface_agreement(self.surface_set, PointSet(surf, normals))
        return {"chamfer_sq": cm["sq"], "chamfer_m": cm["m"],
                "completeness_m": cm["a_to_b_m"], "accuracy_m": cm["b_to_a_m"],
                "normal_consistency": nc, "normal_error_deg": angle,
                "mesh_iou": iou(voxelize(surf), self.cells) if len(surf) else 0.0,
                "mesh_faces": int(len(mesh.faces))}

    def describe(self, n_volume: int) -> dict:
        return {"gt_volume_samples": int(len(self.volume)), "gt_cells": int(self.cells.sum()),
                "n_volume": int(n_volume), "n_samples": int(self.n_surface),
                "seed": int(self.seed), "iou_cell_m": IOU_UNIT, "iou_cells": list(IOU_CELLS),
                "iou_bounds": BOX.tolist()}


def evaluate_reference(volume: np.ndarray, bounds, gt_mesh: trimesh.Trimesh, *,
                       threshold: float = export.DEFAULT_THRESHOLD, seed: int = 0,
                       n_volume: int = N_VOLUME_SAMPLES, n_surface: int = N_SURFACE_SAMPLES,
                       sweep: tuple[float, ...] | None = SWEEP,
                       chamfer_sweep: tuple[float, ...] | None = CHAMFER_SWEEP, crop=None,
                       mapping: str = "reference") -> tuple[dict, trimesh.Trimesh]:
    """Geometric metrics of a volume by the reference's definitions (module docstring).

    ``iou`` (voxels above τ), ``mesh_iou``, ``chamfer_sq`` / ``chamfer_m`` (of
    :func:`reference_mesh`), ``normal_error_deg`` (mean angle between nearest surface samples'
    normals, orientation-free) at ``threshold``. With ``sweep``: ``best_iou`` /
    ``best_iou_threshold`` over it; with ``chamfer_sweep``: ``best_chamfer_sq`` /
    ``best_chamfer_sq_threshold`` (and the normal error there) over that subset.
    ``crop`` [3, 2]: drop voxels outside before normalising (the reference evaluates the whole
    box). Returns (metrics, the ``mesh_smooth`` at τ for the image metrics).
    """
    t = export.check_threshold(threshold)
    if crop is not None:
        volume, bounds = export.crop_volume(volume, bounds, np.asarray(crop, dtype=np.float64))
    mag = export.normalized_magnitude(volume)
    bounds = export.check_bounds(bounds, mag.shape)
    gt = _GroundTruth(gt_mesh, seed, n_volume, n_surface)

    def voxel_iou(tau: float) -> float:
        return iou(voxelize(export.occupied_points(mag, bounds, tau)), gt.cells)

    mesh = reference_mesh(mag, bounds, t, mapping)
    pts = export.occupied_points(mag, bounds, t)
    result = {"protocol": "reference", "threshold": t, "iou": voxel_iou(t),
              **gt.surface_scores(mesh), "occupied_voxels": int(len(pts)),
              "empty": bool(len(pts) == 0), "normalization": "minmax", "mapping": mapping,
              **gt.describe(n_volume), "evaluated_bounds": np.asarray(bounds).tolist()}
    rows = {}
    if sweep:
        for s in sorted(set(float(s) for s in sweep) | {t}):
            rows[s] = {"threshold": s, "iou": voxel_iou(s)}
        best = max(rows.values(), key=lambda r: r["iou"])
        result.update({"best_iou": best["iou"], "best_iou_threshold": best["threshold"]})
    if chamfer_sweep:
        for s in sorted(set(float(s) for s in chamfer_sweep) | {t}):
            scores = ({k: result[k] for k in ("chamfer_sq", "normal_error_deg")} if s == t else
                      gt.surface_scores(reference_mesh(mag, bounds, s, mapping)))
            rows.setdefault(s, {"threshold": s, "iou": voxel_iou(s)}).update(
                chamfer_sq=scores["chamfer_sq"], normal_error_deg=scores["normal_error_deg"])
        valid = [r for r in rows.values() if r.get("chamfer_sq") is not None]
        if valid:
            best = min(valid, key=lambda r: r["chamfer_sq"])
            result.update({"best_chamfer_sq": best["chamfer_sq"],
                           "best_chamfer_sq_threshold": best["threshold"],
                           "best_chamfer_sq_normal_error_deg": best["normal_error_deg"]})
    if rows:
        result["sweep"] = [rows[s] for s in sorted(rows)]
    return result, mesh


def evaluate_reference_mesh(mesh: trimesh.Trimesh, gt_mesh: trimesh.Trimesh, *, seed: int = 0,
                            n_volume: int = N_VOLUME_SAMPLES,
                            n_surface: int = N_SURFACE_SAMPLES) -> dict:
    """The reference's metrics for a reconstructed *mesh* (world metres): ``iou`` from the
    centres of the reference's voxel grid inside it (:func:`grid_points_inside`), ``mesh_iou``,
    Chamfer and normal error from its surface samples (module docstring)."""
    gt = _GroundTruth(gt_mesh, seed, n_volume, n_surface)
    pts = grid_points_inside(mesh)
    return {"protocol": "reference", "threshold": None,
            "iou": iou(voxelize(pts), gt.cells), **gt.surface_scores(mesh),
            "occupied_voxels": int(len(pts)), "empty": bool(len(mesh.faces) == 0),
            **gt.describe(n_volume), "evaluated_bounds": BOX.tolist()}
