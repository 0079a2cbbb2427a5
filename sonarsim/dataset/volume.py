"""The volume file: a complex voxel reconstruction (``recon ...``).

Why a reconstruction result lives in the simulator package: :mod:`sonarsim.dataset` is the
one home of every file format of the project (transients, sonar datasets, volumes), so that
readers such as ``sonarsim info`` and ``sonarsim plot`` understand every file without
importing :mod:`recon`, and the dependencies keep pointing one way (recon → sonarsim). The
voxel-centre convention (:func:`voxel_axes`) and the single-voxel rule
(:func:`voxel_spacing`) live here for the same reason; :mod:`recon.grid` delegates to them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from .attributes import check_attr_dict, write_attr_dict
from .checks import as_array, as_name
from .h5io import KIND_VOLUME, PathLike, atomic_write_h5, nbytes_of, write_header
from .reader import Reader, open_checked

# Fixed-schema root attributes of a volume file.
VOLUME_ATTRS = ("bounds", "method")


def voxel_axes(bounds, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x [nx], y [ny], z [nz]) voxel-centre coordinates (m) of a grid with ``bounds`` [3, 2]:
    ``linspace(lo, hi, n)`` per axis, endpoints included; a single voxel sits at lo."""
    return tuple(np.linspace(lo, hi, n) for (lo, hi), n in zip(np.asarray(bounds), shape))


SINGLE_VOXEL_RULES = ("nan", "zero", "min")


def voxel_spacing(bounds, shape: tuple[int, int, int], single: str = "nan") -> np.ndarray:
    """[3] spacing of voxel centres (m) of a grid with ``bounds`` [3, 2] (m) and ``shape``.

    The one home of the single-voxel rule. ``(hi − lo)/(n − 1)`` along an axis with n > 1;
    along an axis with a single voxel (centre at lo, hi ignored) the spacing is undefined
    and the caller says what it needs:

    - ``single='nan'``: NaN (reporting: there is no spacing);
    - ``single='zero'``: 0, so that ``lo + index·spacing`` is still the voxel centre
      (:class:`recon.grid.Grid`);
    - ``single='min'``: the smallest spacing of the other axes, a positive cell size for a
      flat volume (marching cubes, pixel extents); a grid of one voxel has none
      (``ValueError``).
    """
    if single not in SINGLE_VOXEL_RULES:
        raise ValueError(f"single: expected one of {SINGLE_VOXEL_RULES}, got {single!r}")
    b = np.asarray(bounds, dtype=np.float64).reshape(3, 2)
    n = np.asarray(shape, dtype=np.float64)
    multi = n > 1
    spacing = np.full(3, np.nan)
    spacing[multi] = (b[multi, 1] - b[multi, 0]) / (n[multi] - 1)
    if single == "zero":
        spacing[~multi] = 0.0
    elif single == "min":
        if not multi.any():
            raise ValueError("a grid of a single voxel has no voxel size")
        spacing[~multi] = spacing[multi].min()
    return spacing


@dataclass(eq=False)
class Volume:
    """A complex reconstruction on a regular grid.

    volume: complex64 [nx, ny, nz] (x, y, z order).
    bounds: float64 [3, 2] = [[x0, x1], [y0, y1], [z0, z1]] metres; voxel centres along
        each axis are linspace(lo, hi, n) (a single voxel sits at lo).
    method: the reconstruction ('backprojection', 'gd', ...); params: its settings.
    """

    volume: np.ndarray
    bounds: np.ndarray
    method: str
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        dims: dict = {}
        self.volume = as_array("volume", self.volume, ("nx", "ny", "nz"), np.complex64, dims,
                               kinds="fiuc")
        if 0 in self.volume.shape:
            raise InputError(f"volume has shape {self.volume.shape}, expected no empty axis")
        self.bounds = as_array("bounds", self.bounds, (3, 2), np.float64, dims)
        if (self.bounds[:, 1] < self.bounds[:, 0]).any():
            raise InputError(f"bounds {self.bounds.tolist()} has an upper bound below its lower")
        self.method = as_name("method", self.method)
        self.params = check_attr_dict("params", self.params, VOLUME_ATTRS)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.volume.shape)

    def voxel_centers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [nx], y [ny], z [nz]) voxel-centre coordinates, metres."""
        return voxel_axes(self.bounds, self.shape)

    def voxel_size(self) -> np.ndarray:
        """[3] spacing of voxel centres (m); NaN along an axis with a single voxel."""
        return voxel_spacing(self.bounds, self.shape)

    def magnitude(self, normalised: bool = True) -> np.ndarray:
        """|volume| float32 [nx, ny, nz], divided by its maximum if ``normalised`` (and > 0)."""
        mag = np.abs(self.volume)
        if normalised:
            peak = float(mag.max())
            if peak > 0:
                mag /= peak
        return mag

    def __repr__(self) -> str:
        return f"Volume(method={self.method!r}, shape={self.shape}, bounds={self.bounds.tolist()})"

    def write(self, path: PathLike) -> Path:
        """Write a volume file atomically; returns the path."""
        def fill(f: h5py.File) -> None:
            write_header(f, KIND_VOLUME)
            f.create_dataset("volume", data=self.volume)
            f.attrs["bounds"] = self.bounds
            f.attrs["method"] = self.method
            write_attr_dict(f, self.params)
        return atomic_write_h5(path, fill, size=nbytes_of(self.volume))

    @classmethod
    def read(cls, path: PathLike) -> "Volume":
        """Read and validate a volume file (FormatError on any problem)."""
        with open_checked(path, KIND_VOLUME) as (_, rd):
            return rd.construct(cls, cls._read_fields(rd))

    @staticmethod
    def _read_fields(rd: Reader, load: bool = True) -> dict:
        """Constructor arguments (``volume`` an open h5py.Dataset if not ``load``)."""
        volume = rd.dataset("volume", ("nx", "ny", "nz"), "c", dtype=np.complex64, load=load)
        # Checked here as well as in the constructor: inspect() never constructs.
        if 0 in volume.shape:
            rd.fail(f"dataset 'volume' has shape {volume.shape}, expected no empty axis")
        if "bounds" not in rd.f.attrs:
            rd.fail("missing attribute 'bounds'")
        bounds = np.asarray(rd.f.attrs["bounds"])
        if bounds.shape != (3, 2) or bounds.dtype.kind not in "fiu" \
                or not np.isfinite(bounds).all():
            rd.fail(f"attribute 'bounds' has shape {bounds.shape} dtype {bounds.dtype}, "
                    "expected finite (3, 2) float [[x0, x1], [y0, y1], [z0, z1]]")
        return {"volume": volume, "bounds": bounds.astype(np.float64),
                "method": rd.attr("", "method", "str"),
                "params": rd.attr_dict("", VOLUME_ATTRS)}
