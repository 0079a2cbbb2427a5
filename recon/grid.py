"""Voxel grids for reconstruction.

Convention (DESIGN §3): arrays are (nx, ny, nz) in x, y, z order; voxel centres along
each axis are ``linspace(lo, hi, n)`` with both endpoints included, and a single voxel
along an axis sits at ``lo``. Bounds are in metres, shape ``[3, 2]`` = [[x0,x1],[y0,y1],[z0,z1]].

Unlike the reference (meshgrid 'xy' indexing → (Y, X, Z) voxel order, reference code
``geometry.create_voxels``)
the flattened voxel list here is C-order over (nx, ny, nz): index = (ix*ny + iy)*nz + iz.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonarsim.errors import InputError

DEFAULT_VOXEL_SIZE = 0.0032   # metres; the reference's simulated-scene pitch (reference code geometry.py)
MAX_VOXELS_PER_AXIS = 1e12    # a voxel size that gives more is a typo, refused before any arithmetic


def _check_bounds(bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape == (6,):
        b = b.reshape(3, 2)
    if b.shape != (3, 2):
        raise InputError(f"grid bounds: expected [3, 2] (x0 x1 y0 y1 z0 z1), got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise InputError("grid bounds: contain NaN or infinity")
    if np.any(b[:, 1] < b[:, 0]):
        raise InputError(f"grid bounds: each upper bound must be >= its lower bound, got {b.tolist()}")
    return b


def _check_shape(shape) -> tuple[int, int, int]:
    try:
        s = tuple(int(n) for n in shape)
        ok = len(s) == 3 and all(float(a) == n for a, n in zip(shape, s))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"grid shape: expected three integers (nx, ny, nz), got {shape!r}")
    if min(s) < 1:
        raise InputError(f"grid shape: every axis needs at least 1 voxel, got {s}")
    return s


@dataclass(frozen=True, init=False)
class Grid:
    """A regular grid of voxel centres.

    bounds: float64 [3, 2] metres (voxel-centre convention); shape: (nx, ny, nz).
    An axis with n > 1 needs hi > lo; an axis with n == 1 sits at lo (hi is ignored).
    2-D grids are grids with nz == 1.
    """

    bounds: np.ndarray
    shape: tuple[int, int, int]

    def __init__(self, bounds, shape):
        b = _check_bounds(bounds)
        s = _check_shape(shape)
        for axis, (n, (lo, hi)) in enumerate(zip(s, b)):
            if n > 1 and not hi > lo:
                raise InputError(f"grid bounds: axis {'xyz'[axis]} has {n} voxels but an empty "
                                 f"extent [{lo}, {hi}]")
        b.setflags(write=False)
        object.__setattr__(self, "bounds", b)
        object.__setattr__(self, "shape", s)

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y, z (metres), each ``[n_axis]``."""
        from sonarsim.dataset.volume import voxel_axes
        return voxel_axes(self.bounds, self.shape)

    @property
    def spacing(self) -> np.ndarray:
        """Voxel pitch per axis [3] (metres); 0 along an axis with one voxel
        (:func:`sonarsim.dataset.volume.voxel_spacing`, rule ``'zero'``)."""
        from sonarsim.dataset.volume import voxel_spacing
        return voxel_spacing(self.bounds, self.shape, single="zero")

    def points(self) -> np.ndarray:
        """Voxel centres ``[nx*ny*nz, 3]`` float64, C-order over (nx, ny, nz) (x-major)."""
        x, y, z = self.axes()
        g = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1)
        return g.reshape(-1, 3)

    def points_range(self, start: int, stop: int) -> np.ndarray:
        """Voxel centres ``[stop-start, 3]`` float64 of flat indices start..stop-1 (C-order),
        without building the whole grid."""
        idx = np.unravel_index(np.arange(start, min(stop, self.size)), self.shape)
        return self.bounds[:, 0] + np.stack(idx, axis=1) * self.spacing

    def index_of(self, point) -> tuple[int, int, int]:
        """Indices (ix, iy, iz) of the voxel whose centre is nearest to ``point`` [3]."""
        p = np.asarray(point, dtype=np.float64)
        sp = self.spacing
        idx = np.where(sp > 0, np.rint((p - self.bounds[:, 0]) / np.where(sp > 0, sp, 1)), 0)
        return tuple(int(np.clip(i, 0, n - 1)) for i, n in zip(idx, self.shape))

    def position_of(self, index) -> np.ndarray:
        """Centre [3] (metres) of the voxel with indices (ix, iy, iz)."""
        return self.bounds[:, 0] + np.asarray(index, dtype=np.float64) * self.spacing

    @classmethod
    def from_box(cls, box, shape) -> "Grid":
        """Grid over a ``sonarsim.geometry.SceneBox`` (lo/hi corners)."""
        return cls(np.stack([np.asarray(box.lo, float), np.asarray(box.hi, float)], axis=1), shape)

    @classmethod
    def from_voxel_size(cls, bounds, voxel_size: float = DEFAULT_VOXEL_SIZE) -> "Grid":
        """Grid over ``bounds`` [3, 2] with voxels ``voxel_size`` metres apart: along each axis
        ``round((hi - lo) / voxel_size) + 1`` voxel centres from lo to hi (the pitch is adjusted
        so that both bounds are centres). InputError for a size that is not positive and finite
        or that gives more than 10^12 voxels along an axis."""
        b = _check_bounds(bounds)
        try:
            size = float(voxel_size)
        except (TypeError, ValueError):
            raise InputError(f"voxel size must be a number (m), got {voxel_size!r}") from None
        if not (np.isfinite(size) and size > 0):
            raise InputError(f"--voxel-size: must be a positive finite number, got {voxel_size}")
        counts = [(hi - lo) / size for lo, hi in b]
        if not all(np.isfinite(n) and n < MAX_VOXELS_PER_AXIS for n in counts):
            raise InputError(f"--voxel-size {size:g} gives more than 10^12 voxels along an axis")
        return cls(b, tuple(int(round(n)) + 1 for n in counts))

    @classmethod
    def from_dataset(cls, dataset, shape, bounds=None) -> "Grid":
        """Grid over ``bounds`` if given, else the dataset's scene box, else the rig's SIM_BOX."""
        if bounds is not None:
            return cls(bounds, shape)
        return cls.from_box(scene_box_of(dataset), shape)

    def __eq__(self, other):
        return (isinstance(other, Grid) and self.shape == other.shape
                and np.array_equal(self.bounds, other.bounds))

    def __hash__(self):
        return hash((self.shape, self.bounds.tobytes()))

    def __repr__(self):
        return f"Grid(bounds={self.bounds.tolist()}, shape={self.shape})"


def box_bounds(box) -> np.ndarray:
    """The [3, 2] bounds (metres) of a ``sonarsim.geometry.SceneBox``."""
    return np.stack([np.asarray(box.lo, float), np.asarray(box.hi, float)], axis=1)


def grid_from_options(default_bounds, bounds=None, shape=None,
                      voxel_size: float = DEFAULT_VOXEL_SIZE) -> Grid:
    """The grid of the ``--bounds`` / ``--shape`` / ``--voxel-size`` rule, used by the
    command line and ``sonarsim batch`` alike: ``bounds`` if given, else ``default_bounds``
    (the dataset's or scene's box); ``shape`` if given, else :meth:`Grid.from_voxel_size`."""
    b = _check_bounds(default_bounds if bounds is None else bounds)
    if shape is not None:
        return Grid(b, shape)
    return Grid.from_voxel_size(b, voxel_size)


def scene_box_of(dataset):
    """The scene box a dataset declares in ``meta['box']``, else ``sonarsim.geometry.SIM_BOX``
    (see :func:`sonarsim.dataset.declared_scene_box`)."""
    from sonarsim import geometry
    from sonarsim.dataset import declared_scene_box
    return declared_scene_box(dataset, geometry.SIM_BOX)