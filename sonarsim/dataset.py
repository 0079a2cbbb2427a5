"""sonarsim's three HDF5 files as typed objects: transients, sonar datasets, volumes.

* :class:`Transients` -- path-length histograms from ``sonarsim render``;
* :class:`SonarDataset` -- time-domain sonar waveforms plus geometry (``simulate``, importers);
* :class:`Volume` -- a complex voxel reconstruction (``recon ...``).

Each has ``.write(path)`` (atomic: a temporary file in the same directory, then
``os.replace``) and a validating classmethod ``.read(path)``; :func:`read_any` reads
whichever kind a file holds.  :class:`DatasetStreamWriter` writes a dataset ping
chunk by ping chunk into ``<path>.partial`` and can resume after an interruption.
Constructors raise :class:`InputError` for bad arrays or values; readers raise
:class:`FormatError` with one line naming the file and the offending field.
The full schema is in ``docs/formats.md``.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import h5py
import numpy as np

from .errors import FormatError, InputError

__all__ = ["FORMAT_VERSION", "KIND_TRANSIENTS", "KIND_DATASET", "KIND_VOLUME", "Transients",
           "SonarDataset", "Volume", "read_any", "file_kind", "inspect", "atomic_write_h5",
           "DatasetStreamWriter", "TransientsLayout"]

FORMAT_VERSION = 1
KIND_TRANSIENTS = "sonarsim.transients"
KIND_DATASET = "sonarsim.dataset"
KIND_VOLUME = "sonarsim.volume"
KIND_NAMES = {KIND_TRANSIENTS: "transients", KIND_DATASET: "sonar dataset",
              KIND_VOLUME: "volume"}
# Root attributes every file carries; never part of ``meta``/``params``.
_HOUSEKEEPING = ("format", "format_version", "complete", "json_keys")
PARTIAL_SUFFIX = ".partial"

PathLike = str | os.PathLike


# --------------------------------------------------------------------------------------
# Shapes, arrays and scalar checks (shared by constructors and readers)

def _shape_text(pattern: tuple) -> str:
    return "(" + ", ".join(str(p) for p in pattern) + (",)" if len(pattern) == 1 else ")")


def _shape_error(shape: tuple, pattern: tuple, dims: dict, source: str) -> str | None:
    """Why ``shape`` does not fit ``pattern`` (ints fixed, strings named sizes kept in
    ``dims`` across arrays), or None.  Records newly seen named sizes in ``dims``."""
    expected = _shape_text(pattern)
    if len(shape) != len(pattern):
        return expected
    seen = {}
    for size, want in zip(shape, pattern):
        if isinstance(want, int):
            if size != want:
                return expected
        elif want in dims and dims[want][0] != size:
            value, origin = dims[want]
            return f"{expected} with {want} = {value} (from '{origin}')"
        elif want in seen and seen[want] != size:
            return expected
        else:
            seen[want] = size
    for name, size in seen.items():
        dims.setdefault(name, (size, source))
    return None


def _array(name: str, value: Any, pattern: tuple, dtype, dims: dict, *,
           kinds: str = "fiu", finite: bool = True) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype`` with shape ``pattern`` (InputError)."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array ({exc})") from None
    if arr.dtype.kind not in kinds:
        raise InputError(f"{name} has dtype {arr.dtype}, expected "
                         f"{'complex or real' if 'c' in kinds else 'real'} numbers")
    err = _shape_error(arr.shape, pattern, dims, name)
    if err:
        raise InputError(f"{name} has shape {arr.shape}, expected {err}")
    arr = np.ascontiguousarray(arr, dtype=dtype)
    if finite and arr.dtype.kind in "fc" and not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or inf")
    return arr


def _float(name: str, value: Any, *, positive: bool = False) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(out) or (positive and out <= 0):
        raise InputError(f"{name} must be {'positive and ' if positive else ''}finite, got {out}")
    return out


def _int(name: str, value: Any, *, minimum: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        if not (isinstance(value, (float, np.floating)) and float(value).is_integer()):
            raise InputError(f"{name} must be an integer, got {value!r}")
    out = int(value)
    if minimum is not None and out < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {out}")
    return out


def _unit_rows(name: str, value: Any, dims: dict) -> np.ndarray:
    vec = _array(name, value, ("N", 3), np.float64, dims)
    norm = np.linalg.norm(vec, axis=1, keepdims=True)
    if (norm <= 0).any():
        raise InputError(f"{name} has a zero-length direction in row {int(np.argmin(norm))}")
    # Rows already unit length are kept bit for bit, so reading back is exact.
    return np.where(np.abs(norm - 1.0) > 1e-12, vec / norm, vec)


# --------------------------------------------------------------------------------------
# Free-form attributes (meta / params): scalars natively, arrays natively, rest as JSON

def _check_attr_dict(name: str, values: Mapping | None, reserved: tuple) -> dict:
    out = dict(values or {})
    for key, value in out.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise InputError(f"{name} key {key!r} must be a non-empty string without '/'")
        if key in reserved or key in _HOUSEKEEPING:
            raise InputError(f"{name} key '{key}' is reserved by the file format")
        _encode_attr(f"{name}['{key}']", value)
    return out


def _encode_attr(name: str, value: Any) -> tuple[Any, bool]:
    """(value as stored, stored as JSON?)"""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (bool, int, float, str)):
        return value, False
    if isinstance(value, np.ndarray) and value.dtype.kind in "biufc" and value.size:
        return value, False
    try:
        return json.dumps(value, default=_json_default), True
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} cannot be stored in an HDF5 attribute ({exc})") from None


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _write_attr_dict(obj: h5py.HLObject, values: Mapping) -> None:
    json_keys = []
    for key, value in values.items():
        stored, is_json = _encode_attr(key, value)
        obj.attrs[key] = stored
        if is_json:
            json_keys.append(key)
    if json_keys:
        obj.attrs["json_keys"] = json_keys


def _decode_scalar(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray) and value.dtype.kind in "OSU":
        return [_decode_scalar(v) for v in value.tolist()]
    return value


# --------------------------------------------------------------------------------------
# Atomic writes

def _temp_name(path: Path) -> Path:
    # Leading dot and no '.h5' ending: never mistaken for a finished file by globbing users.
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _commit(tmp: Path, final: Path) -> None:
    _fsync_file(tmp)
    os.replace(tmp, final)
    _fsync_dir(final.parent)


def atomic_write_h5(path: PathLike, fill: Callable[[h5py.File], None]) -> Path:
    """Create HDF5 file ``path`` by calling ``fill(file)`` on a temporary file in the same
    directory and renaming it into place.  If ``fill`` raises, the temporary file is
    removed and an existing ``path`` is left untouched."""
    final = Path(path)
    tmp = _temp_name(final)
    try:
        with h5py.File(tmp, "w") as f:
            fill(f)
            f.flush()
        _commit(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return final


def _write_header(g: h5py.Group, kind: str) -> None:
    g.attrs["format"] = kind
    g.attrs["format_version"] = FORMAT_VERSION
    g.attrs["complete"] = True


# --------------------------------------------------------------------------------------
# Validating reader

class _Reader:
    """Reads datasets/attributes of one open file, raising FormatError naming the file
    and field.  Named sizes (N, T, ...) are checked for consistency across datasets."""

    def __init__(self, f: h5py.File, label: str):
        self.f, self.label, self.dims = f, label, {}
        self.version = FORMAT_VERSION

    def fail(self, message: str):
        raise FormatError(f"{self.label}: {message}")

    def dataset(self, name: str, pattern: tuple, kinds: str, *, dtype=None,
                optional: bool = False, load: bool = True, finite: bool = True):
        """The validated array (or the h5py.Dataset if ``load`` is False); None if
        ``optional`` and absent.  ``kinds``: allowed dtype kinds; ``dtype``: exact dtype."""
        try:
            obj = self.f.get(name)
        except (KeyError, OSError, RuntimeError) as exc:
            self.fail(f"cannot read '{name}' ({_first_line(exc)})")
        if obj is None:
            if optional:
                return None
            self.fail(f"missing dataset '{name}'")
        if not isinstance(obj, h5py.Dataset):
            self.fail(f"'{name}' is a group, expected a dataset")
        if (dtype is not None and obj.dtype != np.dtype(dtype)) or obj.dtype.kind not in kinds:
            want = np.dtype(dtype).name if dtype is not None else _kinds_text(kinds)
            self.fail(f"dataset '{name}' has dtype {obj.dtype}, expected {want}")
        err = _shape_error(obj.shape or (), pattern, self.dims, name)
        if err:
            self.fail(f"dataset '{name}' has shape {obj.shape}, expected {err}")
        if not load:
            return obj
        try:
            arr = obj[()]
        except (OSError, RuntimeError) as exc:
            self.fail(f"cannot read dataset '{name}', file truncated or corrupt "
                      f"({_first_line(exc)})")
        if finite and arr.dtype.kind in "fc" and not np.isfinite(arr).all():
            self.fail(f"dataset '{name}' contains NaN or inf")
        return arr

    def attr(self, group: str, name: str, kind: str, *, optional: bool = False):
        """A scalar attribute of ``group`` ('' = root) as float/int/str/bool."""
        where = f"attribute '{name}'" + (f" of group '{group.rstrip('/')}'" if group else "")
        attrs = self.f[group].attrs if group else self.f.attrs
        if name not in attrs:
            if optional:
                return None
            self.fail(f"missing {where}")
        value = _decode_scalar(attrs[name])
        if isinstance(value, np.ndarray) and value.shape in ((), (1,)):
            value = _decode_scalar(value.reshape(-1)[0])
        ok = {"float": isinstance(value, (int, float)) and not isinstance(value, bool),
              "int": isinstance(value, int) and not isinstance(value, bool),
              "str": isinstance(value, str),
              "bool": isinstance(value, (bool, int))}[kind]
        if not ok:
            self.fail(f"{where} is {value!r}, expected {'a ' if kind != 'int' else 'an '}{kind}")
        if kind == "float":
            value = float(value)
            if not np.isfinite(value):
                self.fail(f"{where} is {value}, expected a finite number")
        return bool(value) if kind == "bool" else value

    def attr_dict(self, group: str, reserved: tuple) -> dict:
        attrs = self.f[group].attrs if group else self.f.attrs
        json_keys = set(_decode_scalar(attrs["json_keys"])) if "json_keys" in attrs else set()
        out = {}
        for key in attrs:
            if key in reserved or key in _HOUSEKEEPING:
                continue
            value = _decode_scalar(attrs[key])
            if key in json_keys:
                try:
                    value = json.loads(value)
                except (TypeError, ValueError):
                    self.fail(f"attribute '{key}' is not valid JSON")
            out[key] = value
        return out


def _kinds_text(kinds: str) -> str:
    names = {"f": "float", "i": "int", "u": "unsigned int", "c": "complex", "b": "bool"}
    return " or ".join(names[k] for k in kinds)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _check_file(path: PathLike) -> str:
    label = os.fspath(path)
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{label}: no such file")
    if p.is_dir():
        raise FormatError(f"{label}: is a directory, expected an HDF5 file")
    if p.stat().st_size == 0:
        raise FormatError(f"{label}: empty file (0 bytes), expected an HDF5 file")
    try:
        is_h5 = h5py.is_hdf5(p)
    except OSError as exc:
        raise FormatError(f"{label}: cannot read ({_first_line(exc)})") from None
    if not is_h5:
        raise FormatError(f"{label}: not an HDF5 file")
    return label


@contextlib.contextmanager
def _open(path: PathLike, expected: str | None = None,
          allow_partial: bool = False) -> Iterator[tuple[str, _Reader]]:
    """Open ``path`` read-only, check format/version/completeness; yield (kind, reader)."""
    label = _check_file(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise FormatError(f"{label}: cannot open as HDF5, file truncated or corrupt "
                          f"({_first_line(exc)})") from None
    with f:
        rd = _Reader(f, label)
        try:
            kind = _check_kind(rd, expected, allow_partial=allow_partial)
            yield kind, rd
        except (OSError, RuntimeError, KeyError) as exc:
            raise FormatError(f"{label}: cannot read, file truncated or corrupt "
                              f"({_first_line(exc)})") from None


def _check_kind(rd: _Reader, expected: str | None, group: str = "",
                allow_partial: bool = False) -> str:
    attrs = rd.f[group].attrs if group else rd.f.attrs
    if "format" not in attrs:
        rd.fail("not a sonarsim file (root attribute 'format' missing)" if not group
                else f"attribute 'format' of group '{group}' missing")
    kind = rd.attr(group, "format", "str")
    if kind not in KIND_NAMES:
        rd.fail(f"attribute 'format' is '{kind}', not a sonarsim format "
                f"({', '.join(KIND_NAMES)})")
    if expected is not None and kind != expected:
        rd.fail(f"attribute 'format' is '{kind}', expected '{expected}' "
                f"(this is a {KIND_NAMES[kind]} file, not a {KIND_NAMES[expected]} file)")
    version = rd.attr(group, "format_version", "int")
    if not group:
        rd.version = version
    if version > FORMAT_VERSION:
        rd.fail(f"format_version {version} is newer than this sonarsim reads "
                f"({FORMAT_VERSION}); upgrade sonarsim")
    if version < 1:
        rd.fail(f"attribute 'format_version' is {version}, expected >= 1")
    if not group and not allow_partial and \
            rd.attr(group, "complete", "bool", optional=True) is False:
        rd.fail("incomplete file (attribute 'complete' is false): the partial output of an "
                "interrupted run; resume that run or delete the file")
    return kind


def _construct(cls, label: str, fields_: dict):
    try:
        return cls(**fields_)
    except InputError as exc:
        raise FormatError(f"{label}: {exc}") from None


# --------------------------------------------------------------------------------------
# Transients

_TRANSIENT_ATTRS = ("path_start", "path_bin_width", "sound_speed", "fs", "oversample")


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
        self.transients = _array("transients", self.transients, ("N", "B", "T"),
                                 np.float32, dims)
        if self.transients.shape[1] < 1 or self.transients.shape[2] < 1:
            raise InputError(f"transients has shape {self.transients.shape}, "
                             "expected at least one bounce and one bin")
        self.tx = _array("tx", self.tx, ("N", 3), np.float64, dims)
        self.rx = _array("rx", self.rx, ("N", 3), np.float64, dims)
        self._validate_scalars()

    def _validate_scalars(self):
        self.path_start = _float("path_start", self.path_start)
        self.path_bin_width = _float("path_bin_width", self.path_bin_width, positive=True)
        self.sound_speed = _float("sound_speed", self.sound_speed, positive=True)
        self.fs = _float("fs", self.fs, positive=True)
        self.oversample = _int("oversample", self.oversample, minimum=1)
        nominal = self.sound_speed / (self.fs * self.oversample)
        if abs(self.path_bin_width - nominal) > 1e-3 * nominal:
            raise InputError(f"path_bin_width {self.path_bin_width:.6g} m does not match "
                             f"sound_speed / (fs * oversample) = {nominal:.6g} m")
        self.meta = _check_attr_dict("meta", self.meta, _TRANSIENT_ATTRS)

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
        if isinstance(indices, (int, np.integer)):
            indices = [indices]
        return Transients(self.transients[indices], self.path_start, self.path_bin_width,
                          self.sound_speed, self.fs, self.oversample, self.tx[indices],
                          self.rx[indices], dict(self.meta))

    def __repr__(self) -> str:
        return (f"Transients(N={self.n_pings}, B={self.n_bounces}, T={self.n_bins}, "
                f"path {self.path_start:.4g}..{self.path_end:.4g} m, fs={self.fs:g} Hz)")

    # ---- files
    def write(self, path: PathLike) -> Path:
        """Write a transients file atomically; returns the path."""
        return atomic_write_h5(path, self._write_group)

    def _write_group(self, g: h5py.Group, data: bool = True) -> None:
        _write_header(g, KIND_TRANSIENTS)
        if data:
            g.create_dataset("transients", data=self.transients)
        g.create_dataset("pings/tx", data=self.tx)
        g.create_dataset("pings/rx", data=self.rx)
        for name in _TRANSIENT_ATTRS:
            g.attrs[name] = getattr(self, name)
        _write_attr_dict(g, self.meta)

    @classmethod
    def read(cls, path: PathLike) -> "Transients":
        """Read and validate a transients file (FormatError on any problem)."""
        with _open(path, KIND_TRANSIENTS) as (_, rd):
            return _construct(cls, rd.label, cls._read_fields(rd))

    @staticmethod
    def _read_fields(rd: _Reader, load: bool = True, prefix: str = "") -> dict:
        group = prefix.rstrip("/")
        # The transients' T (bins) is not the waveforms' T: share only the ping count N.
        outer = rd.dims
        rd.dims = {k: v for k, v in outer.items() if k == "N"}
        fields_ = {"transients": rd.dataset(prefix + "transients", ("N", "B", "T"), "f",
                                            dtype=np.float32, load=load),
                   "tx": rd.dataset(prefix + "pings/tx", ("N", 3), "f"),
                   "rx": rd.dataset(prefix + "pings/rx", ("N", 3), "f")}
        for name in _TRANSIENT_ATTRS:
            fields_[name] = rd.attr(group, name, "int" if name == "oversample" else "float")
        fields_["meta"] = rd.attr_dict(group, _TRANSIENT_ATTRS)
        rd.dims = outer | {"N": rd.dims["N"]}
        return fields_


# --------------------------------------------------------------------------------------
# Sonar dataset

_DATASET_ATTRS = ("fs", "sound_speed", "source", "start_sample", "snr_db", "seed")


@dataclass(eq=False)
class SonarDataset:
    """Time-domain sonar measurements with their geometry.

    waveforms: float32 [N, T]; sample k of ping i is at time (start_sample + k) / fs
        after transmission (group delay removed).
    tx, rx: float64 [N, 3] positions (m); boresight: float64 [N, 3] unit transmitter
        boresight (also the receiver's unless rx_boresight [N, 3] is given).
    pulse: float64 [L], the transmitted pulse sampled at fs.
    fs (Hz), sound_speed (m/s), source ('simulated', 'airsas', ...).
    temperatures: float64 [N] air temperature per ping (deg C) or None.
    gt_vertices float64 [V, 3] (m) / gt_faces int64 [F, 3]: ground-truth mesh or None.
    snr_db: SNR of the added noise (dB, see signals.add_noise) or None (no noise added).
    seed: random seed of the simulation or None.  transients: the rendered transients or None.
    meta: free-form settings (scene name, pulse name, ...).
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

    def __post_init__(self):
        dims: dict = {}
        self.waveforms = _array("waveforms", self.waveforms, ("N", "T"), np.float32, dims)
        if self.waveforms.shape[1] < 1:
            raise InputError("waveforms has no samples (shape "
                             f"{self.waveforms.shape}), expected at least one")
        self._validate_header(dims)

    def _validate_header(self, dims: dict) -> None:
        """Validate every field but ``waveforms`` (N taken from ``dims`` if present)."""
        self.tx = _array("tx", self.tx, ("N", 3), np.float64, dims)
        self.rx = _array("rx", self.rx, ("N", 3), np.float64, dims)
        self.boresight = _unit_rows("boresight", self.boresight, dims)
        if self.rx_boresight is not None:
            self.rx_boresight = _unit_rows("rx_boresight", self.rx_boresight, dims)
        self.pulse = _array("pulse", self.pulse, ("L",), np.float64, dims)
        if self.pulse.size == 0:
            raise InputError("pulse is empty")
        self.fs = _float("fs", self.fs, positive=True)
        self.sound_speed = _float("sound_speed", self.sound_speed, positive=True)
        if not isinstance(self.source, str) or not self.source:
            raise InputError(f"source must be a non-empty string, got {self.source!r}")
        self.start_sample = _int("start_sample", self.start_sample)
        if self.temperatures is not None:
            self.temperatures = _array("temperatures", self.temperatures, ("N",),
                                       np.float64, dims)
        if (self.gt_vertices is None) != (self.gt_faces is None):
            raise InputError("gt_vertices and gt_faces must be given together")
        if self.gt_vertices is not None:
            self.gt_vertices = _array("gt_vertices", self.gt_vertices, ("V", 3),
                                      np.float64, dims)
            self.gt_faces = _array("gt_faces", self.gt_faces, ("F", 3), np.int64, dims,
                                   kinds="iu")
            if self.gt_faces.size and (self.gt_faces.min() < 0 or
                                       self.gt_faces.max() >= len(self.gt_vertices)):
                raise InputError(f"gt_faces index out of range 0..{len(self.gt_vertices) - 1}")
        if self.snr_db is not None:
            self.snr_db = _float("snr_db", self.snr_db)
        if self.seed is not None:
            self.seed = _int("seed", self.seed, minimum=0)
        if self.transients is not None:
            if not isinstance(self.transients, Transients):
                raise InputError("transients must be a Transients object or None")
            if self.transients.n_pings != dims["N"][0]:
                raise InputError(f"transients has {self.transients.n_pings} pings, "
                                 f"the dataset {dims['N'][0]}")
            for name in ("tx", "rx"):
                if not np.allclose(getattr(self.transients, name), getattr(self, name),
                                   rtol=0, atol=1e-9):
                    raise InputError(f"transients.{name} differs from the dataset's {name} "
                                     "(transients must be rendered at the dataset's poses)")
        self.meta = _check_attr_dict("meta", self.meta, _DATASET_ATTRS)

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
        if isinstance(indices, (int, np.integer)):
            indices = [indices]
        pick = (lambda a: None if a is None else a[indices])
        return SonarDataset(
            waveforms=self.waveforms[indices], tx=self.tx[indices], rx=self.rx[indices],
            boresight=self.boresight[indices], pulse=self.pulse, fs=self.fs,
            sound_speed=self.sound_speed, source=self.source, start_sample=self.start_sample,
            temperatures=pick(self.temperatures), gt_vertices=self.gt_vertices,
            gt_faces=self.gt_faces, snr_db=self.snr_db, seed=self.seed,
            transients=None if self.transients is None else self.transients.select(indices),
            meta=dict(self.meta), rx_boresight=pick(self.rx_boresight))

    def __repr__(self) -> str:
        return (f"SonarDataset(source={self.source!r}, N={self.n_pings}, T={self.n_samples}, "
                f"fs={self.fs:g} Hz, c={self.sound_speed:g} m/s, "
                f"transients={'yes' if self.transients is not None else 'no'})")

    # ---- files
    def write(self, path: PathLike) -> Path:
        """Write a dataset file atomically; returns the path."""
        def fill(f: h5py.File) -> None:
            self._write_header_fields(f)
            f.create_dataset("waveforms", data=self.waveforms)
            if self.transients is not None:
                self.transients._write_group(f.create_group("transients"))
        return atomic_write_h5(path, fill)

    def _write_header_fields(self, f: h5py.Group) -> None:
        _write_header(f, KIND_DATASET)
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
        for name in _DATASET_ATTRS:
            if getattr(self, name) is not None:
                f.attrs[name] = getattr(self, name)
        _write_attr_dict(f, self.meta)

    @classmethod
    def read(cls, path: PathLike, *, transients: bool = True) -> "SonarDataset":
        """Read and validate a dataset file; ``transients=False`` skips loading them."""
        with _open(path, KIND_DATASET) as (_, rd):
            fields_ = cls._read_fields(rd)
            if fields_["transients"] is not None:
                fields_["transients"] = (_construct(Transients, rd.label, fields_["transients"])
                                         if transients else None)
            return _construct(cls, rd.label, fields_)

    @staticmethod
    def _read_fields(rd: _Reader, load: bool = True) -> dict:
        ds = rd.dataset
        fields_ = {
            "waveforms": ds("waveforms", ("N", "T"), "f", dtype=np.float32, load=load),
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
            "meta": rd.attr_dict("", _DATASET_ATTRS),
            "transients": None,
        }
        if (fields_["gt_vertices"] is None) != (fields_["gt_faces"] is None):
            rd.fail("dataset 'gt/vertices' and 'gt/faces' must both be present or both absent")
        if "transients" in rd.f:
            if not isinstance(rd.f["transients"], h5py.Group):
                rd.fail("'transients' is a dataset, expected a group")
            _check_kind(rd, KIND_TRANSIENTS, "transients")
            fields_["transients"] = Transients._read_fields(rd, load, "transients/")
        return fields_


# --------------------------------------------------------------------------------------
# Volume

_VOLUME_ATTRS = ("bounds", "method")


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
        self.volume = _array("volume", self.volume, ("nx", "ny", "nz"), np.complex64, dims,
                             kinds="fiuc")
        if 0 in self.volume.shape:
            raise InputError(f"volume has shape {self.volume.shape}, expected no empty axis")
        self.bounds = _array("bounds", self.bounds, (3, 2), np.float64, dims)
        if (self.bounds[:, 1] < self.bounds[:, 0]).any():
            raise InputError(f"bounds {self.bounds.tolist()} has an upper bound below its lower")
        if not isinstance(self.method, str) or not self.method:
            raise InputError(f"method must be a non-empty string, got {self.method!r}")
        self.params = _check_attr_dict("params", self.params, _VOLUME_ATTRS)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.volume.shape)

    def voxel_centers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [nx], y [ny], z [nz]) voxel-centre coordinates, metres."""
        return tuple(np.linspace(lo, hi, n) for (lo, hi), n in zip(self.bounds, self.shape))

    def voxel_size(self) -> np.ndarray:
        """[3] spacing of voxel centres (m); NaN along an axis with a single voxel."""
        n = np.asarray(self.shape, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(n > 1, (self.bounds[:, 1] - self.bounds[:, 0]) / (n - 1), np.nan)

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
            _write_header(f, KIND_VOLUME)
            f.create_dataset("volume", data=self.volume)
            f.attrs["bounds"] = self.bounds
            f.attrs["method"] = self.method
            _write_attr_dict(f, self.params)
        return atomic_write_h5(path, fill)

    @classmethod
    def read(cls, path: PathLike) -> "Volume":
        """Read and validate a volume file (FormatError on any problem)."""
        with _open(path, KIND_VOLUME) as (_, rd):
            return _construct(cls, rd.label, cls._read_fields(rd))

    @staticmethod
    def _read_fields(rd: _Reader, load: bool = True) -> dict:
        volume = rd.dataset("volume", ("nx", "ny", "nz"), "c", dtype=np.complex64, load=load)
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
                "params": rd.attr_dict("", _VOLUME_ATTRS)}


# --------------------------------------------------------------------------------------
# Any kind

_CLASSES = {KIND_TRANSIENTS: Transients, KIND_DATASET: SonarDataset, KIND_VOLUME: Volume}


def file_kind(path: PathLike) -> str:
    """The ``format`` of a sonarsim file ('sonarsim.dataset', ...), validated."""
    with _open(path) as (kind, _):
        return kind


def read_any(path: PathLike) -> Transients | SonarDataset | Volume:
    """Read a sonarsim file of any of the three kinds."""
    with _open(path) as (kind, rd):
        if kind == KIND_DATASET:
            fields_ = SonarDataset._read_fields(rd)
            if fields_["transients"] is not None:
                fields_["transients"] = _construct(Transients, rd.label, fields_["transients"])
            return _construct(SonarDataset, rd.label, fields_)
        return _construct(_CLASSES[kind], rd.label, _CLASSES[kind]._read_fields(rd))


@contextlib.contextmanager
def inspect(path: PathLike, allow_partial: bool = False) -> Iterator[tuple[str, dict]]:
    """Open a file and validate its schema without loading the large arrays; yield
    (kind, fields) where ``transients``/``waveforms``/``volume`` are open h5py.Dataset
    objects (valid inside the ``with`` block), everything else is loaded, and
    ``fields['format_version']`` is the file's version.  For a dataset file,
    ``fields['transients']`` is a fields dict of the same form or None.  With
    ``allow_partial`` an unfinished ``.partial`` file is accepted too: then
    ``fields['complete']`` is False and ``fields['pings_done']`` counts the pings written."""
    with _open(path, allow_partial=allow_partial) as (kind, rd):
        fields_ = _CLASSES[kind]._read_fields(rd, load=False)
        fields_["format_version"] = rd.version
        fields_["complete"] = rd.attr("", "complete", "bool", optional=True) is not False
        if not fields_["complete"] and "stream/done" in rd.f:
            fields_["pings_done"] = int(np.count_nonzero(rd.f["stream/done"][()]))
        yield kind, fields_


# --------------------------------------------------------------------------------------
# Streaming (resumable) dataset writer

@dataclass(frozen=True)
class TransientsLayout:
    """Layout of the transients a :class:`DatasetStreamWriter` stores with the waveforms
    (same meaning as the :class:`Transients` fields)."""

    n_bounces: int
    n_bins: int
    path_start: float
    path_bin_width: float
    sound_speed: float
    fs: float
    oversample: int
    meta: dict = field(default_factory=dict)


class DatasetStreamWriter:
    """Write a :class:`SonarDataset` file ping chunk by ping chunk, resumably.

    Data go to ``<path>.partial`` (root attribute ``complete = False``, which every reader
    refuses).  A boolean dataset ``stream/done`` [N] records the pings written so far; it
    is set only after their data are flushed.  Reopening with ``resume=True`` continues
    where an interrupted run stopped, provided every other field (geometry, pulse, fs, ...)
    is the same as before (else FormatError naming the field).  :meth:`finish` checks that
    every ping is written, removes the bookkeeping, sets ``complete = True`` and renames
    the file atomically to ``path``.  The result reads back equal to a one-shot
    :meth:`SonarDataset.write` of the same content.

    Keyword arguments are the :class:`SonarDataset` fields except ``waveforms`` (replaced
    by ``n_samples``) and ``transients`` (replaced by an optional :class:`TransientsLayout`).

    Usage::

        with DatasetStreamWriter("D.h5", n_samples=T, tx=..., rx=..., ...) as w:
            for start, stop in w.missing_ranges(chunk=256):
                w.write(start, waveforms_chunk, transients_chunk)
            w.finish()
    """

    def __init__(self, path: PathLike, *, n_samples: int, tx, rx, boresight, pulse, fs,
                 sound_speed, source: str, start_sample: int = 0, temperatures=None,
                 gt_vertices=None, gt_faces=None, snr_db=None, seed=None, meta=None,
                 rx_boresight=None, transients: TransientsLayout | None = None,
                 resume: bool = True):
        self.path = Path(path)
        self.partial_path = Path(os.fspath(path) + PARTIAL_SUFFIX)
        self.n_samples = _int("n_samples", n_samples, minimum=1)
        header = object.__new__(SonarDataset)
        header.__dict__.update(
            tx=tx, rx=rx, boresight=boresight, pulse=pulse, fs=fs, sound_speed=sound_speed,
            source=source, start_sample=start_sample, temperatures=temperatures,
            gt_vertices=gt_vertices, gt_faces=gt_faces, snr_db=snr_db, seed=seed,
            transients=None, meta=dict(meta or {}), rx_boresight=rx_boresight)
        header._validate_header({})
        self.header = header
        self.n_pings = len(header.tx)
        self.layout = transients
        self._t_header = None
        if transients is not None:
            t = object.__new__(Transients)
            t.__dict__.update(path_start=transients.path_start,
                              path_bin_width=transients.path_bin_width,
                              sound_speed=transients.sound_speed, fs=transients.fs,
                              oversample=transients.oversample, tx=header.tx, rx=header.rx,
                              meta=dict(transients.meta))
            t._validate_scalars()
            _int("n_bounces", transients.n_bounces, minimum=1)
            _int("n_bins", transients.n_bins, minimum=1)
            self._t_header = t
        self.resumed = False
        self._file: h5py.File | None = None
        if resume and self.partial_path.exists():
            self._file = self._reopen()
        if self._file is None:
            self._file = self._create()

    # ---- opening
    def _fingerprints(self) -> dict[str, str]:
        """A digest per header field, to detect a partial file written with other settings."""
        h = self.header
        items = {name: getattr(h, name) for name in (
            "tx", "rx", "boresight", "rx_boresight", "pulse", "fs", "sound_speed", "source",
            "start_sample", "temperatures", "gt_vertices", "gt_faces", "snr_db", "seed", "meta")}
        items["n_samples"] = self.n_samples
        if self.layout is not None:
            items["transients"] = {k: getattr(self.layout, k) for k in (
                "n_bounces", "n_bins", "path_start", "path_bin_width", "sound_speed", "fs",
                "oversample", "meta")}
        else:
            items["transients"] = None
        out = {}
        for key, value in items.items():
            digest = hashlib.sha256()
            if isinstance(value, np.ndarray):
                digest.update(str(value.dtype).encode() + str(value.shape).encode())
                digest.update(value.tobytes())
            else:
                digest.update(json.dumps(value, sort_keys=True, default=_json_default).encode())
            out[key] = digest.hexdigest()[:16]
        return out

    def _create(self) -> h5py.File:
        with contextlib.suppress(FileNotFoundError):
            self.partial_path.unlink()
        f = h5py.File(self.partial_path, "w")
        try:
            self.header._write_header_fields(f)
            f.attrs["complete"] = False
            f.create_dataset("waveforms", shape=(self.n_pings, self.n_samples),
                             dtype=np.float32, fillvalue=0)
            if self._t_header is not None:
                g = f.create_group("transients")
                self._t_header._write_group(g, data=False)
                g.create_dataset("transients", dtype=np.float32, fillvalue=0, shape=(
                    self.n_pings, self.layout.n_bounces, self.layout.n_bins))
            f.create_dataset("stream/done", shape=(self.n_pings,), dtype=bool, fillvalue=False)
            f["stream"].attrs["fingerprints"] = json.dumps(self._fingerprints())
            f.flush()
        except BaseException:
            f.close()
            raise
        return f

    def _reopen(self) -> h5py.File | None:
        """Open the existing partial file for resuming; None if it is unusable (corrupt
        after a hard kill, or not a partial file), in which case it is started again."""
        label = os.fspath(self.partial_path)
        try:
            f = h5py.File(self.partial_path, "r+")
        except OSError:
            return None
        try:
            stored = json.loads(f["stream"].attrs["fingerprints"])
            done = f["stream/done"]
            done_ok = done.shape == (self.n_pings,)
        except (KeyError, OSError, RuntimeError, TypeError, ValueError):
            f.close()
            return None
        for key, digest in self._fingerprints().items():
            if stored.get(key) != digest:
                f.close()
                raise FormatError(f"{label}: partial file of an earlier run has a different "
                                  f"'{key}'; delete it or run without resuming")
        if not done_ok:
            f.close()
            return None
        self.resumed = True
        return f

    # ---- progress
    @property
    def done(self) -> np.ndarray:
        """bool [N]: which pings are written."""
        return np.asarray(self._require_open()["stream/done"][()], dtype=bool)

    @property
    def n_done(self) -> int:
        return int(self.done.sum())

    def missing_ranges(self, chunk: int) -> list[tuple[int, int]]:
        """(start, stop) ping ranges, each at most ``chunk`` long, covering every ping
        not yet written (in order)."""
        chunk = _int("chunk", chunk, minimum=1)
        todo = ~self.done
        out = []
        i = 0
        while i < self.n_pings:
            if not todo[i]:
                i += 1
                continue
            j = i
            while j < self.n_pings and todo[j] and j - i < chunk:
                j += 1
            out.append((i, j))
            i = j
        return out

    # ---- writing
    def _require_open(self) -> h5py.File:
        if self._file is None:
            raise InputError(f"{self.partial_path}: stream writer is closed")
        return self._file

    def write(self, start: int, waveforms, transients=None) -> None:
        """Store pings ``start .. start + n - 1``: waveforms [n, T] (float32) and, if the
        writer has a transients layout, transients [n, B, T_bins]."""
        f = self._require_open()
        start = _int("start", start, minimum=0)
        dims: dict = {"T": (self.n_samples, "n_samples")}
        wf = _array("waveforms", waveforms, ("n", "T"), np.float32, dims)
        stop = start + wf.shape[0]
        if stop > self.n_pings:
            raise InputError(f"pings {start}..{stop - 1} exceed the dataset's {self.n_pings}")
        if (self.layout is None) != (transients is None):
            raise InputError("transients must be given exactly when the writer has a "
                             "transients layout")
        if transients is not None:
            dims.update(B=(self.layout.n_bounces, "layout"), K=(self.layout.n_bins, "layout"))
            tr = _array("transients", transients, ("n", "B", "K"), np.float32, dims)
            f["transients/transients"][start:stop] = tr
        f["waveforms"][start:stop] = wf
        f.flush()  # data on disk before the pings are marked done
        f["stream/done"][start:stop] = True
        f.flush()

    def finish(self) -> Path:
        """Complete the file and rename it to the final path atomically; returns it."""
        f = self._require_open()
        done = self.done
        if not done.all():
            missing = np.flatnonzero(~done)
            raise InputError(f"{self.partial_path}: {missing.size} pings not written yet "
                             f"(first: {int(missing[0])})")
        del f["stream"]
        f.attrs["complete"] = True
        f.flush()
        f.close()
        self._file = None
        _commit(self.partial_path, self.path)
        return self.path

    def close(self) -> None:
        """Close without finishing; the partial file stays for a later resume."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def discard(self) -> None:
        """Close and delete the partial file."""
        self.close()
        with contextlib.suppress(FileNotFoundError):
            self.partial_path.unlink()

    def __enter__(self) -> "DatasetStreamWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
