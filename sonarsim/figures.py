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
