"""Evaluating a reconstruction file — a volume (``.h5``) or a mesh (PLY/OBJ/..., world metres)
— against a ground truth: every metric of ``recon evaluate``, under the exact protocol or the
reference's (docs/evaluation.md), plus its text and JSON forms.

Used by ``recon evaluate``, ``recon compare``, the batch reconstruction step and
``benchmarks/table2.py``.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError, SonarsimError

from . import export, groundtruth, metrics, protocol_reference, views

from .evaluation_options import PROTOCOLS  # noqa: E402 (re-exported)


def is_mesh_file(path) -> bool:
    """True for a mesh file (by suffix): evaluated as a surface, not as a volume."""
    return Path(path).suffix.lower() in groundtruth.MESH_SUFFIXES


def _as_ground_truth(gt) -> groundtruth.GroundTruth:
    """A :class:`GroundTruth` from a GroundTruth, a mesh (described as given by the caller)
    or a ``--gt`` spec."""
    if isinstance(gt, groundtruth.GroundTruth):
        return gt
    if hasattr(gt, "faces"):
        mesh, warnings = groundtruth.check_mesh(gt, "ground truth")
        return groundtruth.GroundTruth(mesh, "(mesh given by the caller)", "mesh",
                                       "as given by the caller", warnings)
    return groundtruth.load_ground_truth(gt)


def gt_shape_name(gt: groundtruth.GroundTruth) -> str | None:
    """The GT's shape name (which of the reference's cameras render it): a dataset's scene
    name (meta ``scene``), else the stem of the ``--gt`` file or scene name."""
    if gt.kind == "dataset":
        from sonarsim.dataset import inspect
        try:
            with inspect(gt.source) as (_, fields_):
                return (fields_.get("meta") or {}).get("scene")
        except (SonarsimError, OSError):
            return None
    return Path(str(gt.source)).stem


def evaluate_file(path: Path, gt, *, threshold: float = export.DEFAULT_THRESHOLD,
                  normalize: str = "minmax", sweep: bool = True, images: bool = True,
                  samples: int = metrics.N_SURFACE_SAMPLES, seed: int = 0, crop=None,
                  protocol: str = "exact",
                  volume_samples: int = protocol_reference.N_VOLUME_SAMPLES,
                  view_resolution: int | None = None, mapping: str = "reference",
                  reference_views: str = "paper") -> dict:
    """All metrics of one reconstruction file against ``gt`` (a ``--gt`` spec, a
    :class:`recon.groundtruth.GroundTruth` or a trimesh).

    A volume: :func:`recon.metrics.evaluate` (exact) or
    :func:`recon.protocol_reference.evaluate_reference`; a mesh file:
    :func:`recon.metrics.evaluate_mesh` or :func:`recon.protocol_reference.evaluate_reference_mesh`
    (no threshold, no sweep). ``crop``: six numbers x0 x1 y0 y1 z0 z1 (m) or None. Image
    metrics render the (cropped) reconstruction against the whole GT mesh;
    ``view_resolution`` overrides the protocol's image size (pixels, e.g. for quick runs).
    ``mapping``: the reference protocol's vertex mapping (``protocol_reference.MAPPINGS``).
    ``reference_views``: the reference protocol's cameras (:func:`recon.views.reference_views`:
    'paper', its camera table for the GT's shape name, or 'released', the 60-rad views).

    The result names the ground truth (``gt``: source, kind, frame, bounds) and carries
    ``warnings`` (one line each) about it: a mesh file scored as given while the volume's
    dataset placed its object elsewhere, a GT outside the evaluated box, a flat or open GT.
    """
    export.check_threshold(threshold)
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol: choose one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    for name, n in (("--samples", samples), ("--volume-samples", volume_samples)):
        if int(n) < 1:
            raise InputError(f"{name}: must be >= 1, got {n}")
    gt = _as_ground_truth(gt)
    box = None if crop is None else np.asarray(crop, dtype=np.float64).reshape(3, 2)
    if box is not None and not (np.all(np.isfinite(box)) and np.all(box[:, 1] >= box[:, 0])):
        raise InputError(f"--crop: expected x0 x1 y0 y1 z0 z1 (m, finite, each low <= high), "
                         f"got {box.ravel().tolist()}")
    if protocol == "reference":
        cams, reference = views.reference_views(gt_shape_name(gt), reference_views), True
        if normalize != "minmax":
            raise InputError("--protocol reference normalises min-max (as the reference); "
                             "drop --normalize")
    else:
        cams, reference = views.Turntable(), False
    if view_resolution:
        cams = replace(cams, resolution=int(view_resolution))
    warnings = list(gt.warnings)
    if is_mesh_file(path):
        mesh = groundtruth.load_reconstruction_mesh(path)
        if protocol == "reference":
            result = protocol_reference.evaluate_reference_mesh(
                mesh, gt.mesh, seed=seed, n_volume=volume_samples, n_surface=samples)
        else:
            result = metrics.evaluate_mesh(mesh, gt.mesh, n_samples=samples, seed=seed, crop=box)
        result = {"volume": str(path), "method": "mesh", "kind": "mesh",
                  "normalization": None, **result}
        warnings += groundtruth.outside_box_warnings(gt, result["evaluated_bounds"])
    else:
        from sonarsim.dataset import Volume
        vol = Volume.read(path)
        warnings += groundtruth.placement_warnings(gt, vol.params.get("dataset"))
        if protocol == "reference":
            result, mesh = protocol_reference.evaluate_reference(
                vol.volume, vol.bounds, gt.mesh, threshold=threshold, seed=seed,
                n_volume=volume_samples, n_surface=samples,
                sweep=protocol_reference.SWEEP if sweep else None,
                chamfer_sweep=protocol_reference.CHAMFER_SWEEP if sweep else None,
                crop=box, mapping=mapping)
        else:
            result = metrics.evaluate(vol.volume, vol.bounds, gt.mesh, threshold=threshold,
                                      sweep=metrics.DEFAULT_SWEEP if sweep else None,
                                      normalization=normalize, n_samples=samples, seed=seed,
                                      crop=box)
            result["protocol"] = "exact"
            mesh = None
        result = {"volume": str(path), "method": vol.method, "kind": "volume", **result}
        warnings += groundtruth.outside_box_warnings(gt, result["evaluated_bounds"])
        if images and mesh is None:
            volume, bounds = vol.volume, vol.bounds
            if box is not None:
                volume, bounds = export.crop_volume(volume, bounds, box)
            mesh = export.mesh_from_volume(volume, bounds, threshold, normalize)
    if images:
        result.update(views.image_metrics(gt.mesh, mesh, cams, reference=reference))
        result["views"] = {"n_views": cams.n_views, "resolution": cams.resolution,
                           "yfov_rad": cams.yfov, "distance_m": cams.distance,
                           "elevation_m": cams.elevation, "look_height_m": cams.look_height}
        if reference:
            result["views"]["set"] = reference_views
    result["gt"] = gt.describe()
    result["warnings"] = warnings
    return result


def json_safe(value):
    """Replace non-finite floats by None (JSON has no inf/NaN): a PSNR of identical images
    (inf) and an undefined distance both become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [json_safe(v) for v in value]
    return value


def fmt_value(value, unit: str = "") -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        if math.isinf(value):
            return "inf"
        return f"{value:.4g}{unit}"
    return f"{value}{unit}"


ROWS = [("iou", "IoU (5 mm cells)", ""), ("mesh_iou", "IoU of the mesh samples", ""),
        ("chamfer_sq", "Chamfer, squared (ref.)", " m²"),
        ("chamfer_m", "Chamfer, mean L2", " m"), ("accuracy_m", "  pred -> GT", " m"),
        ("completeness_m", "  GT -> pred", " m"),
        ("chamfer_vox_sq", "Chamfer vs voxels, sq.", " m²"),
        ("normal_consistency", "normal consistency", ""),
        ("normal_error_deg", "normal error", "°"),
        ("psnr_depth", "PSNR depth", " dB"), ("ssim_depth", "SSIM depth", ""),
        ("psnr_shaded", "PSNR shaded", " dB"), ("ssim_shaded", "SSIM shaded", "")]


def format_table(result: dict) -> list[str]:
    if result.get("kind") == "mesh":
        head = (f"{result['volume']} (mesh), {result['protocol']} protocol")
    else:
        head = (f"{result['volume']} ({result['method']}), {result['protocol']} protocol, "
                f"threshold {result['threshold']:g}, normalisation {result['normalization']}")
    lines = [head]
    gt = result.get("gt")
    if gt:
        lines.append(f"  ground truth: {gt['source']} ({gt['kind']}: {gt['frame']})")
    if result["empty"]:
        lines.append("  reconstruction is empty" + ("" if result.get("kind") == "mesh" else
                                                    " at this threshold: no voxel above it"))
    for key, label, unit in ROWS:
        if key not in result:
            continue
        line = f"  {label:<26} {fmt_value(result[key], unit):>14}"
        if f"best_{key}" in result:
            line += (f"   best {fmt_value(result[f'best_{key}'], unit)}"
                     f" @ {fmt_value(result[f'best_{key}_threshold'])}")
        lines.append(line)
    return lines
