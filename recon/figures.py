"""Comparison figures of reconstructions against a ground truth (``recon compare``, the demo,
``examples/``).

:func:`comparison` draws one row per volume and a ground-truth row on top: the top view
(maximum-intensity projection along z), the side view (MIP along y), a render of the τ
surface and the headline metrics. The MIPs are |σ| normalised per volume (min–max) on one
fixed [0, 1] scale with one shared colour bar; the ground-truth row shows the GT mesh
voxelised on the first volume's lattice (its occupancy, the quantity the exact protocol's
IoU compares) with the same extents, so every column compares like with like. The best
value of each headline metric is starred.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sonarsim.errors import InputError

from . import export, metrics

# Headline metrics: (key, label, format, larger is better)
HEADLINE = (("iou", "IoU", ".3f", True), ("chamfer_m", "Chamfer (mm)", ".2f", False),
            ("normal_error_deg", "normal error (°)", ".1f", False))
VIEWS = ((2, "top view (MIP along z)"), (1, "side view (MIP along y)"))


def _as_volume(item):
    from sonarsim.dataset import Volume
    return Volume.read(item) if isinstance(item, (str, Path)) else item


def gt_occupancy(gt_mesh, bounds, shape) -> np.ndarray:
    """float [nx, ny, nz]: 1 where the voxel centre of the (bounds, shape) lattice lies
    inside ``gt_mesh``, else 0."""
    from .containment import inside_mesh_lattice
    return inside_mesh_lattice(gt_mesh, export.voxel_axes(bounds, shape)).astype(np.float32)


def mip_panel(ax, magnitude: np.ndarray, bounds, axis: int, title: str = "",
              ticks: bool = True):
    """Draw the maximum-intensity projection of ``magnitude`` [nx, ny, nz] (in [0, 1]) along
    ``axis`` on ``ax``, at the voxels' extents in metres (bounds [3, 2] of the voxel
    centres), on the fixed [0, 1] inferno scale every comparison figure shares. Returns the
    image (for a colour bar)."""
    u, v = export.mip_axes(axis)
    image = ax.imshow(export.mip(magnitude, axis), origin="lower", cmap="inferno", vmin=0,
                      vmax=1, interpolation="nearest",
                      extent=(*export.pixel_extent(bounds, magnitude.shape, u),
                              *export.pixel_extent(bounds, magnitude.shape, v)))
    if ticks:
        ax.set_xlabel(f"{'xyz'[u]} (m)")
        ax.set_ylabel(f"{'xyz'[v]} (m)")
    else:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=8 if not ticks else 9)
    return image


def render_panel(ax, mesh, cams, view: int, title: str = "") -> None:
    """Draw the shaded render of ``mesh`` from turntable view ``view`` of ``cams``
    (:class:`recon.views.Turntable`) on ``ax``, without axes."""
    from . import views
    shaded_panel(ax, views.render_views(mesh, cams, views=[view])["shaded"][0], title)


def shaded_panel(ax, shaded: np.ndarray, title: str = "") -> None:
    """Draw a shaded render (grey levels in [0, 1]) on ``ax``, without axes."""
    ax.imshow(shaded, cmap="gray", vmin=0, vmax=1)
    ax.axis("off")
    if title:
        ax.set_title(title, fontsize=9)


def _value(res: dict, key: str):
    v = res.get(key)
    if key == "chamfer_m" and v is not None:
        v = 1e3 * v
    return v if v is not None and np.isfinite(v) else None


def comparison(volumes, gt, *, labels=None, crop=None, threshold: float = export.DEFAULT_THRESHOLD,
               view: int = 1, normalize: str = "minmax", results: list[dict] | None = None):
    """A matplotlib Figure comparing ``volumes`` (Volume objects or .h5 paths) with ``gt``
    (a ``--gt`` spec or a trimesh).

    labels: row names (default each volume's method). crop: [x0, x1, y0, y1, z0, z1] m, shown
    and evaluated inside it. results: metrics per volume (``recon.metrics.evaluate`` or
    ``recon evaluate``'s dicts); computed here (exact protocol, no sweep) when None.
    view: which turntable view the renders show.
    """
    import matplotlib.pyplot as plt
    from . import views
    vols = [_as_volume(v) for v in volumes]
    if not vols:
        raise InputError("comparison: no volumes given")
    labels = list(labels) if labels is not None else [v.method for v in vols]
    if len(labels) != len(vols) or (results is not None and len(results) != len(vols)):
        raise InputError("comparison: labels and results must have one entry per volume")
    cams = views.Turntable()
    if not 0 <= view < cams.n_views:
        raise InputError(f"view must lie in 0..{cams.n_views - 1}, got {view}")
    threshold = export.check_threshold(threshold)
    gt_mesh = gt if hasattr(gt, "faces") else metrics.load_gt_mesh(gt)
    box = None if crop is None else np.reshape(np.asarray(crop, dtype=np.float64), (3, 2))
    rows = []
    for i, vol in enumerate(vols):
        volume, bounds = vol.volume, vol.bounds
        if box is not None:
            volume, bounds = export.crop_volume(volume, bounds, box)
        mag = export.normalized_magnitude(volume, normalize)
        res = results[i] if results is not None else metrics.evaluate(
            vol.volume, vol.bounds, gt_mesh, threshold=threshold, sweep=None, crop=box)
        render = views.render_views(export.extract_surface(mag, bounds, threshold), cams,
                                    views=[view])
        rows.append((labels[i], bounds, mag, res, render["shaded"][0]))
    best = {}
    for key, _, _, larger in HEADLINE:
        vals = [(_value(r[3], key), j) for j, r in enumerate(rows) if _value(r[3], key) is not None]
        if len(vals) > 1:        # every row that reaches the best value (ties) is starred
            top = (max if larger else min)(v for v, _ in vals)
            best[key] = {j for v, j in vals if v == top}

    gt_bounds, gt_mag = rows[0][1], gt_occupancy(gt_mesh, rows[0][1], rows[0][2].shape)
    all_rows = [("ground truth", gt_bounds, gt_mag, None,
                 views.render_views(gt_mesh, cams, views=[view])["shaded"][0])] + rows
    fig, axs = plt.subplots(len(all_rows), 3, figsize=(11.5, 3.0 * len(all_rows)), squeeze=False,
                            constrained_layout=True)
    image = None
    for r, (label, bounds, mag, res, shaded) in enumerate(all_rows):
        for c, (axis, name) in enumerate(VIEWS):
            image = mip_panel(axs[r, c], mag, bounds, axis,
                              f"{label} — {name}" if res is not None else
                              f"ground truth (occupancy) — {name}")
        ax = axs[r, 2]
        shaded_panel(ax, shaded)
        if res is None:
            ax.set_title("ground truth (render)", fontsize=9)
            continue
        parts = []
        for key, name, spec, _ in HEADLINE:
            val = _value(res, key)
            star = " ★" if r - 1 in best.get(key, ()) else ""
            parts.append(f"{name} {'n/a' if val is None else format(val, spec)}{star}")
        ax.set_title(f"{label}: surface @ τ = {threshold:g}\n" + ", ".join(parts), fontsize=9)
    fig.colorbar(image, ax=axs[:, :2].ravel().tolist(), shrink=0.6,
                 label="normalised |σ| (per volume, min–max); GT: occupancy")
    return fig


def save(fig, path: str | Path, dpi: int = 100) -> Path:
    """Write ``fig`` atomically (.png, .pdf or .svg) and close it."""
    import matplotlib.pyplot as plt
    from sonarsim.atomic import atomic_path
    path = Path(path)
    if path.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise InputError(f"{path}: the figure must be .png, .pdf or .svg")
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix.lower()[1:])
    finally:
        plt.close(fig)
    return path
