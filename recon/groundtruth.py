"""The ground-truth mesh of an evaluation: where it comes from, in which frame, and whether
it can be trusted.

``recon evaluate --gt`` accepts three kinds of ground truth, and they are *not* the same mesh:

* a **dataset** ``.h5`` (``gt/vertices``, ``gt/faces``): the mesh exactly as the simulator
  placed it in the world (the scene's ``fit``, ``scale``, ``rotate``, ``translate`` applied);
* a **scene** TOML or shipped scene name: the same placement, recomputed from the scene file;
* a **mesh file** (OBJ/PLY/STL/OFF/GLB): the file's coordinates *as they are*, in metres. A
  scene that placed the mesh with a transform (``fit = true``) put it elsewhere: scoring a
  reconstruction against the raw file then measures the transform, not the reconstruction.

:func:`load_ground_truth` returns the mesh with a one-line description of its source and
frame; :func:`placement_warnings` compares a mesh-file GT with the mesh of the dataset a
volume came from (``params['dataset']``) and says loudly when they differ. Meshes that no
metric can use are refused (:class:`FormatError`: no triangles, non-finite vertices, every
triangle degenerate); meshes that make the volume metrics meaningless are warned about
(flat or enclosing no volume: the IoU is 0 by construction; widely open: inside/outside is a
guess).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from sonarsim.errors import FormatError

from .containment import inside_mesh_lattice

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
# A mesh-file GT whose bounding box differs from the dataset's placed mesh by more than this
# (m, per corner coordinate) is reported as not matching it.
PLACEMENT_TOLERANCE_M = 1e-3
# Boundary edges above this fraction of all edges: the mesh is "widely open" (warned).
OPEN_EDGE_FRACTION = 0.01


@dataclass
class GroundTruth:
    """A checked GT mesh (metres), ``source`` (the ``--gt`` argument), ``kind`` ('dataset',
    'scene' or 'mesh file'), ``frame`` (one line: which placement), ``warnings`` (one line
    each: what makes some metric unreliable)."""
    mesh: trimesh.Trimesh
    source: str
    kind: str
    frame: str
    warnings: list[str] = field(default_factory=list)

    def describe(self) -> dict:
        """JSON-ready description, for the evaluation's output."""
        lo, hi = self.mesh.bounds
        return {"source": self.source, "kind": self.kind, "frame": self.frame,
                "bounds": np.stack([lo, hi], axis=1).round(6).tolist(),
                "faces": int(len(self.mesh.faces)), "watertight": bool(self.mesh.is_watertight),
                "warnings": list(self.warnings)}


def dataset_gt_mesh(path: str | Path) -> trimesh.Trimesh | None:
    """The placed GT mesh stored in a dataset file (``gt/``), or None if it has none.

    Reads only the small arrays (the waveforms and transients stay on disk)."""
    from sonarsim.dataset import inspect
    from sonarsim.dataset.h5io import KIND_DATASET, KIND_NAMES
    with inspect(path) as (kind, fields_):
        verts, faces = fields_.get("gt_vertices"), fields_.get("gt_faces")
        if kind != KIND_DATASET:
            raise FormatError(f"{path}: a {KIND_NAMES.get(kind, kind)} file, not a sonar "
                              "dataset: it holds no ground-truth mesh")
    if verts is None or faces is None:
        return None
    return trimesh.Trimesh(np.asarray(verts, float), np.asarray(faces, np.int64), process=False)


def load_ground_truth(spec: str | Path) -> GroundTruth:
    """Load and check the GT named by ``spec``: a mesh file, a dataset ``.h5`` or a scene
    TOML / shipped scene name (see the module docstring)."""
    p = Path(spec)
    suffix = p.suffix.lower()
    if suffix in MESH_SUFFIXES:
        mesh = _read_mesh_file(p, "ground-truth mesh file")
        kind, frame = "mesh file", "the file's own coordinates, as given (no scene transform)"
    elif suffix in (".h5", ".hdf5"):
        mesh = dataset_gt_mesh(p)
        if mesh is None:
            raise FormatError(f"{p}: no ground-truth mesh (gt/vertices, gt/faces) in this file")
        kind, frame = "dataset", "as the simulator placed it (scene transform applied)"
    else:
        from sonarsim.scene import load_scene
        mesh = load_scene(str(spec)).gt_mesh()
        kind, frame = "scene", "as the scene places it (scene transform applied)"
    if not isinstance(mesh, trimesh.Trimesh):
        raise FormatError(f"{p}: ground-truth mesh has no triangles")
    mesh, warnings = check_mesh(mesh, str(spec))
    return GroundTruth(mesh, str(spec), kind, frame, warnings)


def check_mesh(mesh: trimesh.Trimesh, name: str) -> tuple[trimesh.Trimesh, list[str]]:
    """(cleaned copy of ``mesh``, warnings). Refuses (FormatError, one line) a mesh without
    triangles, with non-finite vertices or with only degenerate triangles; warns when it
    encloses no volume or is widely open."""
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        raise FormatError(f"{name}: ground-truth mesh has no triangles")
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        raise FormatError(f"{name}: ground-truth mesh has {int(bad.sum())} vertex/vertices with NaN "
                          "or infinite coordinates")
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.merge_vertices()
    if not mesh.area > 0:
        raise FormatError(f"{name}: every triangle of the ground-truth mesh is degenerate "
                          "(zero area)")
    warnings = []
    if _encloses_no_volume(mesh):
        warnings.append(f"{name}: the ground-truth mesh encloses no volume (flat or a single "
                        "sheet): its IoU is 0 by construction; only the surface metrics "
                        "(Chamfer, normals) mean something")
    else:
        _, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
        open_edges = int(np.sum(counts == 1))
        if open_edges > OPEN_EDGE_FRACTION * len(counts):
            warnings.append(f"{name}: the ground-truth mesh is open ({open_edges} of "
                            f"{len(counts)} edges on a boundary): inside/outside, and so the "
                            "IoU, is a majority vote of rays along x, y and z and may be off")
    return mesh, warnings


def _encloses_no_volume(mesh: trimesh.Trimesh, n: int = 24) -> bool:
    """True when no point of an ``n``³ lattice over the mesh's bounding box is inside it
    (flat meshes, single sheets, a lone triangle), as the IoU's containment test sees it."""
    lo, hi = mesh.bounds
    if np.min(hi - lo) <= 1e-9 * max(float(np.max(hi - lo)), 1e-30):
        return True
    coords = [np.linspace(a, b, n + 2)[1:-1] for a, b in zip(lo, hi)]
    return not inside_mesh_lattice(mesh, coords).any()


def placement_warnings(gt: GroundTruth, dataset_path: str | None) -> list[str]:
    """Warnings when a mesh-file GT is not where the dataset ``dataset_path`` (the one the
    reconstruction came from, if known and readable) placed its object."""
    if gt.kind != "mesh file" or not dataset_path or not Path(dataset_path).is_file():
        return []
    try:
        placed = dataset_gt_mesh(dataset_path)
    except Exception:                   # an unreadable record is not the evaluation's problem
        return []
    if placed is None:
        return []
    a, b = np.asarray(gt.mesh.bounds), np.asarray(placed.bounds)
    if np.abs(a - b).max() <= PLACEMENT_TOLERANCE_M:
        return []
    fmt = lambda bb: "[" + ", ".join(f"{lo:.3f}..{hi:.3f}" for lo, hi in bb.T) + "]"  # noqa: E731
    return [f"--gt {gt.source} is scored as given (bounds {fmt(a)} m), but the dataset "
            f"{dataset_path} this reconstruction came from placed its object at {fmt(b)} m "
            f"(scene transform): use --gt {dataset_path} to score against the placed mesh"]


def outside_box_warnings(gt: GroundTruth, bounds) -> list[str]:
    """A warning when most of the GT mesh lies outside the evaluated box ``bounds`` [3, 2]."""
    b = np.asarray(bounds, dtype=np.float64)
    lo, hi = gt.mesh.bounds
    inter = np.clip(np.minimum(hi, b[:, 1]) - np.maximum(lo, b[:, 0]), 0, None)
    ext = np.maximum(hi - lo, 1e-12)
    frac = float(np.prod(np.minimum(inter / ext, 1.0)))
    if frac >= 0.5:
        return []
    return [f"--gt {gt.source}: only {100 * frac:.0f} % of the ground-truth mesh's bounding "
            "box lies inside the evaluated box: is it in the reconstruction's frame?"]


def _read_mesh_file(p: Path, what: str):
    """trimesh's reading of mesh file ``p`` as given (no processing), refused in one line
    (FormatError naming ``what``) when missing or unreadable."""
    if not p.is_file():
        raise FormatError(f"{p}: {what} not found")
    try:
        return trimesh.load(p, force="mesh", process=False)
    except Exception as exc:
        raise FormatError(f"{p}: cannot read mesh ({exc})") from None


def load_reconstruction_mesh(path: str | Path) -> trimesh.Trimesh:
    """A reconstructed surface from a mesh file (world metres, as given), for evaluation:
    refused in one line when unreadable, without triangles or with non-finite vertices."""
    p = Path(path)
    mesh = _read_mesh_file(p, "mesh file")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise FormatError(f"{p}: the reconstructed mesh has no triangles")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        raise FormatError(f"{p}: the reconstructed mesh has {int(bad.sum())} vertices with NaN "
                          "or infinite coordinates")
    mesh = trimesh.Trimesh(verts, np.asarray(mesh.faces), process=False)
    mesh.merge_vertices()
    return mesh
