"""The transients file: path-length histograms from ``sonarsim render``."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from .attributes import check_attr_dict, write_attr_dict
from .checks import as_array, as_float, as_int, ping_index
from .h5io import (KIND_TRANSIENTS, PathLike, atomic_write_h5, nbytes_of, ping_layout,
                   write_header)
from .reader import Reader, open_checked

# Fixed-schema root attributes of a transients file (or group).
TRANSIENT_ATTRS = ("path_start", "path_bin_width", "sound_speed", "fs", "oversample")


@dataclass(eq=False)
class Transients:
    """Path-length histograms of received energy, one per ping and bounce.

    transients: float32 [N, B, T]; ``[i, b, j]`` is the energy of ping i, bounce b+1,
        in path-length bin j = round-trip path in [path_start + j*w, path_start + (j+1)*w),
        w = ``path_bin_width`` (metres), nominally sound_speed / (fs * oversample).
    path_start, path_bin_width: metres of round-trip path.  sound_speed: m/s.
    fs: sample rate (Hz) the bins subdivide; oversample: bins per sample period.
    tx, rx: float64 [N, 3] transmitter/receiver positions (metres, world frame).
    meta: free-form settings (scene, paths_per_pose, seed, beams, ...).
    """

    transients: np.ndarray
    path_start: float
    path_bin_width: float
    sound_speed: float
    fs: float
    oversample: int
    tx: np.ndarray
    rx: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        dims: dict = {}
        self.transients = as_array("transients", self.transients, ("N", "B", "T"),
                                   np.float32, dims)
        if self.transients.shape[1] < 1 or self.transients.shape[2] < 1:
            raise InputError(f"transients has shape {self.transients.shape}, "
                             "expected at least one bounce and one bin")
        self.tx = as_array("tx", self.tx, ("N", 3), np.float64, dims)
        self.rx = as_array("rx", self.rx, ("N", 3), np.float64, dims)
        self._validate_scalars()

    def _validate_scalars(self):
        self.path_start = as_float("path_start", self.path_start)
        self.path_bin_width = as_float("path_bin_width", self.path_bin_width, positive=True)
        self.sound_speed = as_float("sound_speed", self.sound_speed, positive=True)
        self.fs = as_float("fs", self.fs, positive=True)
        self.oversample = as_int("oversample", self.oversample, minimum=1)
        nominal = self.sound_speed / (self.fs * self.oversample)
        if abs(self.path_bin_width - nominal) > 1e-3 * nominal:
            raise InputError(f"path_bin_width {self.path_bin_width:.6g} m does not match "
                             f"sound_speed / (fs * oversample) = {nominal:.6g} m")
        self.meta = check_attr_dict("meta", self.meta, TRANSIENT_ATTRS)

    # ---- derived quantities
    @property
    def n_pings(self) -> int:
        return self.transients.shape[0]

    @property
    def n_bounces(self) -> int:
        return self.transients.shape[1]

    @property
    def n_bins(self) -> int:
        return self.transients.shape[2]

    @property
    def path_end(self) -> float:
        """Upper edge of the last bin (metres of round-trip path)."""
        return self.path_start + self.n_bins * self.path_bin_width

    def path_lengths(self) -> np.ndarray:
        """Bin centres, float64 [T], metres of round-trip path."""
        return self.path_start + (np.arange(self.n_bins) + 0.5) * self.path_bin_width

    def times(self) -> np.ndarray:
        """Bin centres as times after transmission, float64 [T], seconds."""
        return self.path_lengths() / self.sound_speed

    def select(self, indices) -> "Transients":
        """The pings ``indices`` (index array, boolean mask or slice) as a new object."""
        indices = ping_index(indices)
        return Transients(self.transients[indices], self.path_start, self.path_bin_width,
                          self.sound_speed, self.fs, self.oversample, self.tx[indices],
                          self.rx[indices], dict(self.meta))

    def __repr__(self) -> str:
        return (f"Transients(N={self.n_pings}, B={self.n_bounces}, T={self.n_bins}, "
                f"path {self.path_start:.4g}..{self.path_end:.4g} m, fs={self.fs:g} Hz)")

    # ---- files
    def write(self, path: PathLike) -> Path:
        """Write a transients file atomically; returns the path."""
        return atomic_write_h5(path, self._write_group,
                               size=nbytes_of(self.transients, self.tx, self.rx))

    def _write_group(self, g: h5py.Group, data: bool = True) -> None:
        """Fill ``g`` (a file root or the ``transients`` group of a dataset file);
        ``data=False`` leaves the big ``transients`` array to the caller."""
        write_header(g, KIND_TRANSIENTS)
        if data:
            g.create_dataset("transients", data=self.transients,
                             **ping_layout(self.transients.shape, np.float32))
        g.create_dataset("pings/tx", data=self.tx)
        g.create_dataset("pings/rx", data=self.rx)
        for name in TRANSIENT_ATTRS:
            g.attrs[name] = getattr(self, name)
        write_attr_dict(g, self.meta)

    @classmethod
    def read(cls, path: PathLike) -> "Transients":
        """Read and validate a transients file (FormatError on any problem)."""
        with open_checked(path, KIND_TRANSIENTS) as (_, rd):
            return rd.construct(cls, cls._read_fields(rd))

    @staticmethod
    def _read_fields(rd: Reader, load: bool = True, prefix: str = "") -> dict:
        """Constructor arguments read from the file root or the group ``prefix``."""
        group = prefix.rstrip("/")
        # The transients' T (bins) is not the waveforms' T: share only the ping count N.
        outer = rd.dims
        rd.dims = {k: v for k, v in outer.items() if k == "N"}
        fields_ = {"transients": rd.dataset(prefix + "transients", ("N", "B", "T"), "f",
                                            dtype=np.float32, load=load),
                   "tx": rd.dataset(prefix + "pings/tx", ("N", 3), "f"),
                   "rx": rd.dataset(prefix + "pings/rx", ("N", 3), "f")}
        for name in TRANSIENT_ATTRS:
            fields_[name] = rd.attr(group, name, "int" if name == "oversample" else "float")
        fields_["meta"] = rd.attr_dict(group, TRANSIENT_ATTRS)
        rd.dims = outer | {"N": rd.dims["N"]}
        return fields_
