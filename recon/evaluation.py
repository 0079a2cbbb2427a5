"""Evaluating a volume file against a ground-truth mesh: every metric of ``recon evaluate``,
under the exact protocol or the reference's (docs/evaluation.md), plus its text and JSON forms.

Used by ``recon evaluate``, ``recon compare``, the batch reconstruction step and
``benchmarks/table2.py``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sonarsim.dataset import Volume

from . import export, metrics

PROTOCOLS = ("exact", "reference")


def evaluate_file(path: Path, gt_mesh, *, threshold: float, normalize: str = "minmax",
                  sweep: bool = True, images: bool = True, samples: int =
                  metrics.N_SURFACE_SAMPLES, seed: int = 0, crop=None,
                  protocol: str = "exact", volume_samples: int = metrics.N_VOLUME_SAMPLES,
                  view_resolution: int | None = None) -> dict:
    """All metrics of one volume file (see :func:`recon.metrics.evaluate`, or
    :func:`recon.metrics.evaluate_reference` with ``protocol='reference'``).

    ``crop``: six numbers x0 x1 y0 y1 z0 z1 (m) or None. Image metrics render the
    (cropped) reconstruction against the whole GT mesh; ``view_resolution`` overrides the
    protocol's image size (pixels, e.g. for quick runs).
    """
    from dataclasses import replace

    from sonarsim.errors import InputError
    from . import views
    export.check_threshold(threshold)
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol: choose one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    for name, n in (("--samples", samples), ("--volume-samples", volume_samples)):
        if int(n) < 1:
            raise InputError(f"{name}: must be >= 1, got {n}")
    vol = Volume.read(path)
    box = None if crop is None else np.asarray(crop, dtype=np.float64).reshape(3, 2)
    if protocol == "reference":
        if normalize != "minmax":
            raise InputError("--protocol reference normalises min-max (as the reference); "
                             "drop --normalize")
        result, mesh = metrics.evaluate_reference(
            vol.volume, vol.bounds, gt_mesh, threshold=threshold, seed=seed,
            n_volume=volume_samples, n_surface=samples,
            sweep=metrics.DEFAULT_SWEEP if sweep else None, crop=box)
        result = {"volume": str(path), "method": vol.method, **result}
        if images:
            cams = views.REFERENCE_VIEWS
            if view_resolution:
                cams = replace(cams, resolution=int(view_resolution))
            result.update(views.image_metrics(gt_mesh, mesh, cams, gaussian_ssim=True))
        return result
    result = metrics.evaluate(vol.volume, vol.bounds, gt_mesh, threshold=threshold,
                              sweep=metrics.DEFAULT_SWEEP if sweep else None,
                              normalization=normalize, n_samples=samples, seed=seed, crop=box)
    result = {"volume": str(path), "method": vol.method, "protocol": "exact", **result}
    if images:
        volume, bounds = vol.volume, vol.bounds
        if box is not None:
            volume, bounds = export.crop_volume(volume, bounds, box)
        mesh = export.mesh_from_volume(volume, bounds, threshold, normalize)
        cams = views.Turntable()
        if view_resolution:
            cams = replace(cams, resolution=int(view_resolution))
        result.update(views.image_metrics(gt_mesh, mesh, cams))
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
        ("psnr_depth", "PSNR depth", " dB"), ("ssim_depth", "SSIM depth", ""),
        ("psnr_shaded", "PSNR shaded", " dB"), ("ssim_shaded", "SSIM shaded", "")]


def format_table(result: dict) -> list[str]:
    lines = [f"{result['volume']} ({result['method']}), {result['protocol']} protocol, "
             f"threshold {result['threshold']:g}, normalisation {result['normalization']}"]
    if result["empty"]:
        lines.append("  reconstruction is empty at this threshold: no voxel above it")
    for key, label, unit in ROWS:
        if key not in result:
            continue
        line = f"  {label:<26} {fmt_value(result[key], unit):>14}"
        if f"best_{key}" in result:
            line += (f"   best {fmt_value(result[f'best_{key}'], unit)}"
                     f" @ {fmt_value(result[f'best_{key}_threshold'])}")
        lines.append(line)
    return lines
