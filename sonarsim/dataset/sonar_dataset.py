"""The sonar dataset file: time-domain waveforms plus geometry (``simulate``, importers)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from .attributes import check_attr_dict, write_attr_dict
from .checks import as_array, as_float, as_int, as_name, as_unit_rows, ping_index
from .h5io import (KIND_DATASET, KIND_TRANSIENTS, PathLike, atomic_write_h5, nbytes_of,
                   ping_layout, write_header)
from .reader import Reader, open_checked
from .transients import Transients

# Fixed-schema root attributes of a dataset file.
DATASET_ATTRS = ("fs", "sound_speed", "source", "start_sample", "snr_db", "seed",
                 "waveform_kind")

# What ``waveforms`` holds (root attribute ``waveform_kind``; absent = 'real'):
# 'real': float32 received waveforms (the pulse still in them);
# 'deconvolved_analytic': complex64 analytic signals of pulse-deconvolved reflectivity
# (``recon deconvolve``), already pulse-compressed: solvers use them as they are.
WAVEFORM_KINDS = {"real": (np.float32, "fiu"), "deconvolved_analytic": (np.complex64, "c")}


@dataclass(eq=False)
class SonarDataset:
    """Time-domain sonar measurements with their geometry.

    waveforms: float32 [N, T]; sample k of ping i is at time (start_sample + k) / fs
        after transmission (group delay removed). complex64 when ``waveform_kind`` is
        'deconvolved_analytic' (see WAVEFORM_KINDS).
    tx, rx: float64 [N, 3] positions (m); boresight: float64 [N, 3] unit transmitter
        boresight (also the receiver's unless rx_boresight [N, 3] is given).
    pulse: float64 [L], the transmitted pulse sampled at fs.
    fs (Hz), sound_speed (m/s), source ('simulated', 'airsas', ...).
    temperatures: float64 [N] air temperature per ping (deg C) or None.
    gt_vertices float64 [V, 3] (m) / gt_faces int64 [F, 3]: ground-truth mesh or None.
    snr_db: SNR of the added noise (dB, see signals.add_noise) or None (no noise added).
    seed: random seed of the simulation or None.  transients: the rendered transients or None.
    meta: free-form settings (scene name, pulse name, scene box ``box``, ...).
    """

    waveforms: np.ndarray
    tx: np.ndarray
    rx: np.ndarray
    boresight: np.ndarray
    pulse: np.ndarray
    fs: float
    sound_speed: float
    source: str
    start_sample: int = 0
    temperatures: np.ndarray | None = None
    gt_vertices: np.ndarray | None = None
    gt_faces: np.ndarray | None = None
    snr_db: float | None = None
    seed: int | None = None
    transients: Transients | None = None
    meta: dict = field(default_factory=dict)
    rx_boresight: np.ndarray | None = None
    waveform_kind: str = "real"

    def __post_init__(self):
        dims: dict = {}
        if self.waveform_kind not in WAVEFORM_KINDS:
            raise InputError(f"waveform_kind must be one of {', '.join(WAVEFORM_KINDS)}, "
                             f"got {self.waveform_kind!r}")
        dtype, kinds = WAVEFORM_KINDS[self.waveform_kind]
        self.waveforms = as_array("waveforms", self.waveforms, ("N", "T"), dtype, dims,
                                  kinds=kinds)
        if self.waveforms.shape[1] < 1:
            raise InputError("waveforms has no samples (shape "
                             f"{self.waveforms.shape}), expected at least one")
        self._validate_header(dims)

    def _validate_header(self, dims: dict) -> None:
        """Validate every field but ``waveforms`` (N taken from ``dims`` if present)."""
        self.tx = as_array("tx", self.tx, ("N", 3), np.float64, dims)
        if len(self.tx) < 1:
            raise InputError("the dataset has no pings (0 rows); a sonar dataset needs at least "
                             "one ping")
        self.rx = as_array("rx", self.rx, ("N", 3), np.float64, dims)
        self.boresight = as_unit_rows("boresight", self.boresight, dims)
        if self.rx_boresight is not None:
            self.rx_boresight = as_unit_rows("rx_boresight", self.rx_boresight, dims)
        self.pulse = as_array("pulse", self.pulse, ("L",), np.float64, dims)
        if self.pulse.size == 0:
            raise InputError("pulse is empty")
        self.fs = as_float("fs", self.fs, positive=True)
        self.sound_speed = as_float("sound_speed", self.sound_speed, positive=True)
        self.source = as_name("source", self.source)
        self.start_sample = as_int("start_sample", self.start_sample)
        if self.temperatures is not None:
            self.temperatures = as_array("temperatures", self.temperatures, ("N",),
                                         np.float64, dims)
        self._validate_gt_mesh(dims)
        if self.snr_db is not None:
            self.snr_db = as_float("snr_db", self.snr_db)
        if self.seed is not None:
            self.seed = as_int("seed", self.seed, minimum=0)
        if self.transients is not None:
            self._check_transients_match(dims["N"][0])
        self.meta = check_attr_dict("meta", self.meta, DATASET_ATTRS)

    def _validate_gt_mesh(self, dims: dict) -> None:
        if (self.gt_vertices is None) != (self.gt_faces is None):
            raise InputError("gt_vertices and gt_faces must be given together")
        if self.gt_vertices is None:
            return
        self.gt_vertices = as_array("gt_vertices", self.gt_vertices, ("V", 3),
                                    np.float64, dims)
        self.gt_faces = as_array("gt_faces", self.gt_faces, ("F", 3), np.int64, dims,
                                 kinds="iu")
        if self.gt_faces.size and (self.gt_faces.min() < 0 or
                                   self.gt_faces.max() >= len(self.gt_vertices)):
            raise InputError(f"gt_faces index out of range 0..{len(self.gt_vertices) - 1}")

    def _check_transients_match(self, n_pings: int) -> None:
        if not isinstance(self.transients, Transients):
            raise InputError("transients must be a Transients object or None")
        if self.transients.n_pings != n_pings:
            raise InputError(f"transients has {self.transients.n_pings} pings, "
                             f"the dataset {n_pings}")
        for name in ("tx", "rx"):
            if not np.allclose(getattr(self.transients, name), getattr(self, name),
                               rtol=0, atol=1e-9):
                raise InputError(f"transients.{name} differs from the dataset's {name} "
                                 "(transients must be rendered at the dataset's poses)")

    # ---- derived quantities
    @property
    def n_pings(self) -> int:
        return self.waveforms.shape[0]

    @property
    def n_samples(self) -> int:
        return self.waveforms.shape[1]

    @property
    def receiver_boresight(self) -> np.ndarray:
        """[N, 3] receiver boresight (the transmitter's unless rx_boresight is set)."""
        return self.boresight if self.rx_boresight is None else self.rx_boresight

    def sample_times(self) -> np.ndarray:
        """Time of each waveform sample after transmission, float64 [T], seconds."""
        return (self.start_sample + np.arange(self.n_samples)) / self.fs

    def sample_path_lengths(self) -> np.ndarray:
        """Round-trip path length of each sample, float64 [T], metres."""
        return self.sample_times() * self.sound_speed

    def select(self, indices) -> "SonarDataset":
        """The pings ``indices`` (index array, boolean mask or slice) as a new dataset."""
        indices = ping_index(indices)
        pick = (lambda a: None if a is None else a[indices])
        return SonarDataset(
            waveforms=self.waveforms[indices], tx=self.tx[indices], rx=self.rx[indices],
            boresight=self.boresight[indices], pulse=self.pulse, fs=self.fs,
            sound_speed=self.sound_speed, source=self.source, start_sample=self.start_sample,
            temperatures=pick(self.temperatures), gt_vertices=self.gt_vertices,
            gt_faces=self.gt_faces, snr_db=self.snr_db, seed=self.seed,
            transients=None if self.transients is None else self.transients.select(indices),
            meta=dict(self.meta), rx_boresight=pick(self.rx_boresight),
            waveform_kind=self.waveform_kind)

    def __repr__(self) -> str:
        return (f"SonarDataset(source={self.source!r}, N={self.n_pings}, T={self.n_samples}, "
                f"fs={self.fs:g} Hz, c={self.sound_speed:g} m/s, "
                f"transients={'yes' if self.transients is not None else 'no'})")

    # ---- files
    def write(self, path: PathLike) -> Path:
        """Write a dataset file atomically; returns the path."""
        def fill(f: h5py.File) -> None:
            self._write_header_fields(f)
            f.create_dataset("waveforms", data=self.waveforms,
                             **ping_layout(self.waveforms.shape, self.waveforms.dtype))
            if self.transients is not None:
                self.transients._write_group(f.create_group("transients"))
        return atomic_write_h5(path, fill, size=self.nbytes())

    def nbytes(self) -> int:
        """Bytes of the arrays a file of this dataset holds (uncompressed)."""
        t = self.transients
        return nbytes_of(self.waveforms, self.tx, self.rx, self.boresight, self.rx_boresight,
                         self.pulse, self.temperatures, self.gt_vertices, self.gt_faces,
                         None if t is None else t.transients)

    def _write_header_fields(self, f: h5py.Group) -> None:
        """Everything but ``waveforms`` and ``transients`` (shared with the stream writer)."""
        write_header(f, KIND_DATASET)
        f.create_dataset("pings/tx", data=self.tx)
        f.create_dataset("pings/rx", data=self.rx)
        f.create_dataset("pings/boresight", data=self.boresight)
        if self.rx_boresight is not None:
            f.create_dataset("pings/rx_boresight", data=self.rx_boresight)
        if self.temperatures is not None:
            f.create_dataset("pings/temperature", data=self.temperatures)
        f.create_dataset("pulse", data=self.pulse)
        if self.gt_vertices is not None:
            f.create_dataset("gt/vertices", data=self.gt_vertices)
            f.create_dataset("gt/faces", data=self.gt_faces)
        for name in DATASET_ATTRS:
            if getattr(self, name) is not None:
                f.attrs[name] = getattr(self, name)
        write_attr_dict(f, self.meta)

    @classmethod
    def read(cls, path: PathLike, *, transients: bool = True) -> "SonarDataset":
        """Read and validate a dataset file; ``transients=False`` skips loading them."""
        with open_checked(path, KIND_DATASET) as (_, rd):
            return cls._from_reader(rd, transients=transients)

    @classmethod
    def _from_reader(cls, rd: Reader, transients: bool = True) -> "SonarDataset":
        fields_ = cls._read_fields(rd)
        if fields_["transients"] is not None:
            fields_["transients"] = (rd.construct(Transients, fields_["transients"])
                                     if transients else None)
        return rd.construct(cls, fields_)

    @staticmethod
    def _read_fields(rd: Reader, load: bool = True) -> dict:
        """Constructor arguments; ``transients`` is a fields dict (or None), not an object."""
        ds = rd.dataset
        kind = rd.attr("", "waveform_kind", "str", optional=True) or "real"
        if kind not in WAVEFORM_KINDS:
            rd.fail(f"attribute 'waveform_kind' is {kind!r}, expected one of "
                    f"{', '.join(WAVEFORM_KINDS)}")
        fields_ = {
            "waveforms": ds("waveforms", ("N", "T"), WAVEFORM_KINDS[kind][1],
                            dtype=WAVEFORM_KINDS[kind][0], load=load),
            "tx": ds("pings/tx", ("N", 3), "f"),
            "rx": ds("pings/rx", ("N", 3), "f"),
            "boresight": ds("pings/boresight", ("N", 3), "f"),
            "rx_boresight": ds("pings/rx_boresight", ("N", 3), "f", optional=True),
            "temperatures": ds("pings/temperature", ("N",), "f", optional=True),
            "pulse": ds("pulse", ("L",), "f"),
            "gt_vertices": ds("gt/vertices", ("V", 3), "f", optional=True),
            "gt_faces": ds("gt/faces", ("F", 3), "iu", optional=True),
            "fs": rd.attr("", "fs", "float"),
            "sound_speed": rd.attr("", "sound_speed", "float"),
            "source": rd.attr("", "source", "str"),
            "start_sample": rd.attr("", "start_sample", "int", optional=True) or 0,
            "snr_db": rd.attr("", "snr_db", "float", optional=True),
            "seed": rd.attr("", "seed", "int", optional=True),
            "meta": rd.attr_dict("", DATASET_ATTRS),
            "transients": None,
            "waveform_kind": kind,
        }
        if (fields_["gt_vertices"] is None) != (fields_["gt_faces"] is None):
            rd.fail("dataset 'gt/vertices' and 'gt/faces' must both be present or both absent")
        if "transients" in rd.f:
            if not isinstance(rd.f["transients"], h5py.Group):
                rd.fail("'transients' is a dataset, expected a group")
            rd.check_kind(KIND_TRANSIENTS, "transients")
            fields_["transients"] = Transients._read_fields(rd, load, "transients/")
        return fields_


def declared_scene_box(dataset, default):
    """The scene box a dataset declares in ``meta['box']``, else ``default`` (a SceneBox).

    ``meta['box']`` = [[x0, x1], [y0, y1], [z0, z1]] metres (the layout of
    :class:`~sonarsim.dataset.Volume` bounds), as ``simulate``, ``import-airsas`` and
    ``import-pik`` write it. Works on anything with a ``meta`` dict.
    """
    from ..geometry import SceneBox
    meta = getattr(dataset, "meta", None) or {}
    if "box" not in meta:
        if "box_lo" in meta or "box_hi" in meta:
            raise InputError("dataset meta 'box_lo'/'box_hi' is not read: store the scene box as "
                             "meta 'box' = [[x0, x1], [y0, y1], [z0, z1]] (m)")
        return default
    try:
        a = np.asarray(meta["box"], dtype=np.float64)
    except (TypeError, ValueError):
        a = np.empty(0)
    if a.shape != (3, 2) or not np.all(np.isfinite(a)) or not np.all(a[:, 1] > a[:, 0]):
        raise InputError(f"dataset meta 'box': expected [[x0, x1], [y0, y1], [z0, z1]] (m) with "
                         f"x0 < x1 etc., got {meta['box']!r}")
    return SceneBox(a[:, 0], a[:, 1])
