"""Figure and image helpers shared by the quick-look plots (:mod:`sonarsim.plot`,
:mod:`sonarsim.plot_transients`): atomic PNG/EXR writers, dB scaling, ping pooling."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import InputError

FIGURE_DPI = 120
MAX_PNG_ROWS = 2000     # PNG echo images max-pool consecutive pings down to this many rows


def write_exr(path: str | Path, channels: dict[str, np.ndarray], comments: str = "") -> Path:
    """Write float32 image channels (each [H, W]) to an OpenEXR file, atomically."""
    import OpenEXR

    path = Path(path)
    arrays = {name: np.ascontiguousarray(a, dtype=np.float32) for name, a in channels.items()}
    shapes = {a.shape for a in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise InputError(f"{path}: EXR channels must be 2-D and of one shape, got {shapes}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if comments:
        header["comments"] = comments
    with atomic_path(path) as tmp, OpenEXR.File(header, arrays) as f:
        f.write(str(tmp))
    return path


def save_figure(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=FIGURE_DPI, format="png")
    return path


def to_db(magnitude: np.ndarray, dynamic_range_db: float, *, power: bool = False,
          reference: float | None = None) -> np.ndarray:
    """20·log10(magnitude / reference) clipped to [−dynamic_range_db, 0] (float32).

    ``power=True`` for energies/intensities: 10·log10 instead. ``reference`` defaults to
    the maximum of ``magnitude``.
    """
    mag = np.asarray(magnitude, dtype=np.float32)
    factor = 10.0 if power else 20.0
    peak = reference if reference is not None else (float(mag.max()) if mag.size else 0.0)
    if not peak > 0:
        return np.full(mag.shape, -dynamic_range_db, dtype=np.float32)
    floor = peak * 10.0 ** (-dynamic_range_db / factor)
    db = factor * np.log10(np.maximum(mag, floor) / peak)
    return np.minimum(db, 0.0).astype(np.float32)


def ping_group(n_pings: int, max_rows: int = MAX_PNG_ROWS) -> int:
    """Consecutive pings per PNG row so that at most ``max_rows`` rows remain (>= 1)."""
    return max(1, -(-n_pings // max(1, min(n_pings, max_rows))))


def max_pool_rows(rows: np.ndarray, group: int) -> np.ndarray:
    """Maximum over groups of ``group`` consecutive rows: [N, ...] -> [ceil(N/group), ...].

    The last group may be shorter. Works on strided views without copying them.
    """
    full = len(rows) // group * group
    parts = [rows[:full].reshape(-1, group, *rows.shape[1:]).max(axis=1)]
    if full < len(rows):
        parts.append(rows[full:].max(axis=0, keepdims=True))
    return np.concatenate(parts)


def voxel_extent(bounds, shape, axis: int) -> tuple[float, float]:
    """Outer edges (m) of the voxels along ``axis``: voxel centres span ``bounds[axis]``
    (lo, hi), so the image covers lo - d/2 .. hi + d/2 with d = (hi - lo) / (n - 1); a
    single voxel takes the smallest spacing of the other axes
    (:func:`sonarsim.dataset.volume.voxel_spacing`, rule ``'min'``), a grid of one voxel 1 m."""
    from .dataset.volume import voxel_spacing
    b = np.asarray(bounds, dtype=np.float64).reshape(3, 2)
    d = voxel_spacing(b, shape, single="min")[axis] if (np.asarray(shape) > 1).any() else 1.0
    return float(b[axis, 0] - d / 2), float(b[axis, 1] + d / 2)


def mip_comparison(columns: list[tuple[str, np.ndarray, np.ndarray]], path: Path, *,
                   colorbar_label: str = "|σ| / max |σ| (per volume)",
                   suptitle: str = "") -> Path:
    """A comparison figure: one column per volume, top view (maximum-intensity projection
    along z) above side view (MIP along y), one colour scale [0, 1] and one colour bar.

    ``columns``: ``(title, magnitude [nx, ny, nz] in [0, 1], bounds [3, 2] of the voxel
    centres in m)`` each; the title may hold several lines (e.g. the scores). Views are
    drawn with equal metre scales on both axes so shapes are not squashed.
    """
    from matplotlib.figure import Figure

    views = ((2, "top view (MIP along z)"), (1, "side view (MIP along y)"))
    fig = Figure(figsize=(3.3 * len(columns) + 1.2, 7.0), layout="constrained")
    axs = fig.subplots(2, len(columns), squeeze=False)
    image = None
    for col, (title, magnitude, bounds) in enumerate(columns):
        mag = np.asarray(magnitude, dtype=np.float32)
        for row, (axis, view) in enumerate(views):
            u, v = [a for a in range(3) if a != axis]
            ax = axs[row, col]
            image = ax.imshow(mag.max(axis=axis).T, origin="lower", cmap="inferno", vmin=0,
                              vmax=1, interpolation="nearest", aspect="equal",
                              extent=(*voxel_extent(bounds, mag.shape, u),
                                      *voxel_extent(bounds, mag.shape, v)))
            ax.set_xlabel(f"{'xyz'[u]} (m)")
            ax.set_ylabel(f"{'xyz'[v]} (m)")
            ax.set_title(f"{title}\n{view}" if row == 0 else view, fontsize=9)
    fig.colorbar(image, ax=axs, label=colorbar_label, shrink=0.8)
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    return save_figure(fig, Path(path))
