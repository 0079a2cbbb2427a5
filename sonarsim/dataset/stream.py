"""Resumable, chunk-by-chunk writing of a sonar dataset file (``sonarsim simulate``)."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import FormatError, InputError
from .attributes import check_attr_dict, decode_scalar, encode_attr, json_default
from .checks import as_array, as_int
from .h5io import PARTIAL_SUFFIX, PathLike, nbytes_of, ping_layout
from .sonar_dataset import DATASET_ATTRS, SonarDataset
from .transients import Transients

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


PER_PING = ("waveforms", "transients/transients")     # stored with h5io.ping_layout
_COPY_BLOCK_BYTES = 64 << 20


def _copy_compressed(src: h5py.Group, dst: h5py.Group, skip: tuple = (), prefix: str = "") -> None:
    """Copy ``src`` into ``dst`` (attributes, groups, datasets but ``skip``), the per-ping
    arrays (:data:`PER_PING`) block by block into compressed chunks."""
    for key, value in src.attrs.items():
        dst.attrs[key] = value
    for name, obj in src.items():
        if name in skip:
            continue
        path = prefix + name
        if isinstance(obj, h5py.Group):
            _copy_compressed(obj, dst.create_group(name), prefix=path + "/")
        elif path in PER_PING:
            data = dst.create_dataset(name, shape=obj.shape, dtype=obj.dtype,
                                      **ping_layout(obj.shape, obj.dtype))
            row = max(1, int(np.prod(obj.shape[1:])) * obj.dtype.itemsize)
            step = max(1, _COPY_BLOCK_BYTES // row)
            for a in range(0, obj.shape[0], step):
                data[a:a + step] = obj[a:a + step]
            for key, value in obj.attrs.items():
                data.attrs[key] = value
        else:
            src.copy(obj, dst, name=name)


def _dataset_header(**fields) -> SonarDataset:
    """A validated SonarDataset without waveforms (only its header fields are set)."""
    header = object.__new__(SonarDataset)
    header.__dict__.update(fields)
    header._validate_header({})
    return header


def _transients_header(layout: TransientsLayout, dataset: SonarDataset) -> Transients:
    """A validated Transients without data, at the poses of ``dataset``."""
    t = object.__new__(Transients)
    t.__dict__.update(path_start=layout.path_start, path_bin_width=layout.path_bin_width,
                      sound_speed=layout.sound_speed, fs=layout.fs,
                      oversample=layout.oversample, tx=dataset.tx, rx=dataset.rx,
                      meta=dict(layout.meta))
    t._validate_scalars()
    as_int("n_bounces", layout.n_bounces, minimum=1)
    as_int("n_bins", layout.n_bins, minimum=1)
    return t


class DatasetStreamWriter:
    """Write a :class:`SonarDataset` file ping chunk by ping chunk, resumably.

    Data go to ``<path>.partial`` (root attribute ``complete = False``, which every reader
    refuses).  A boolean dataset ``stream/done`` [N] records the pings written so far; it
    is set only after their data and their CRC-32 (``stream/crc`` [N] uint32, over the
    ping's waveform bytes and, if stored, its transients bytes) are flushed.  Reopening with
    ``resume=True`` continues where an interrupted run stopped, provided every other field
    (geometry, pulse, fs, ...) is the same as before (else FormatError naming the field);
    it first verifies every written ping against its checksum, and a ping whose data were
    damaged since (a disk error, a stray write) is marked missing and written again, with
    a warning. A partial file that cannot be read at all is started over.  The partial file
    is uncompressed (chunks written in any order, checksums verifiable in place);
    :meth:`finish` checks that every ping is written and writes ``path`` atomically as a
    copy without the bookkeeping, the waveforms and transients compressed like a one-shot
    :meth:`SonarDataset.write` (``h5io.ping_layout``), with ``complete = True``; the partial
    file is removed only then. The result reads back equal to a one-shot
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
        self.n_samples = as_int("n_samples", n_samples, minimum=1)
        self.header = _dataset_header(
            tx=tx, rx=rx, boresight=boresight, pulse=pulse, fs=fs, sound_speed=sound_speed,
            source=source, start_sample=start_sample, temperatures=temperatures,
            gt_vertices=gt_vertices, gt_faces=gt_faces, snr_db=snr_db, seed=seed,
            transients=None, meta=dict(meta or {}), rx_boresight=rx_boresight)
        self.n_pings = len(self.header.tx)
        self.layout = transients
        self._t_header = (None if transients is None
                          else _transients_header(transients, self.header))
        self.resumed = False
        self._wrote = False               # a chunk was stored by this writer or a resumed one
        self._file: h5py.File | None = None
        if resume and self.partial_path.exists():
            self._file = self._reopen()
        if self._file is None:
            self._file = self._create()

    def nbytes(self) -> int:
        """Bytes of the arrays the finished file holds (uncompressed)."""
        h = self.header
        rows = self.n_samples * 4 + (0 if self.layout is None
                                     else self.layout.n_bounces * self.layout.n_bins * 4)
        return self.n_pings * (rows + 5) + nbytes_of(
            h.tx, h.rx, h.boresight, h.rx_boresight, h.pulse, h.temperatures, h.gt_vertices,
            h.gt_faces)

    def _fail(self, exc: BaseException):
        """The one-line error for an OSError while writing; a partial file that holds no
        written ping is removed (one that does stays, to be resumed)."""
        from ..atomic import write_error
        with contextlib.suppress(Exception):
            self.close()
        if not self._wrote:
            with contextlib.suppress(OSError):
                self.partial_path.unlink()
        return write_error(self.partial_path, exc)

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
                digest.update(json.dumps(value, sort_keys=True, default=json_default).encode())
            out[key] = digest.hexdigest()[:16]
        return out

    def _create(self) -> h5py.File:
        from ..atomic import check_free_space
        with contextlib.suppress(FileNotFoundError):
            self.partial_path.unlink()
        check_free_space(self.partial_path, self.nbytes())
        try:
            return self._create_file()
        except OSError as exc:
            raise self._fail(exc) from None

    def _create_file(self) -> h5py.File:
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
            f.create_dataset("stream/crc", shape=(self.n_pings,), dtype=np.uint32, fillvalue=0)
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
            done_ok = done.shape == (self.n_pings,) and \
                f["stream/crc"].shape == (self.n_pings,)
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
        try:
            damaged = self._verify(f)
        except (KeyError, OSError, RuntimeError, TypeError, ValueError):
            f.close()
            return None
        if damaged:
            print(f"warning: {label}: {damaged} written pings fail their checksum (the file "
                  "was damaged); they are written again", file=sys.stderr)
        self.resumed = self._wrote = True
        return f

    def _row_crcs(self, f: h5py.File, start: int, stop: int, waveforms=None,
                  transients=None) -> np.ndarray:
        """CRC-32 [stop - start] uint32 of each ping's waveform (+ transients) bytes."""
        if waveforms is None:
            waveforms = f["waveforms"][start:stop]
            if self.layout is not None:
                transients = f["transients/transients"][start:stop]
        out = np.empty(stop - start, np.uint32)
        for i in range(stop - start):
            crc = zlib.crc32(np.ascontiguousarray(waveforms[i]).tobytes())
            if transients is not None:
                crc = zlib.crc32(np.ascontiguousarray(transients[i]).tobytes(), crc)
            out[i] = crc
        return out

    def _verify(self, f: h5py.File) -> int:
        """Mark every written ping whose data fail their checksum as missing; return how many."""
        done = np.asarray(f["stream/done"][()], dtype=bool)
        crc = np.asarray(f["stream/crc"][()], dtype=np.uint32)
        row_bytes = self.n_samples * 4 + (0 if self.layout is None else
                                          self.layout.n_bounces * self.layout.n_bins * 4)
        step = max(1, (64 << 20) // max(1, row_bytes))
        bad = np.zeros(self.n_pings, dtype=bool)
        for a in range(0, self.n_pings, step):
            b = min(self.n_pings, a + step)
            if done[a:b].any():
                bad[a:b] = done[a:b] & (self._row_crcs(f, a, b) != crc[a:b])
        if bad.any():
            done &= ~bad
            f["stream/done"][...] = done
            f.flush()
        return int(bad.sum())

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
        chunk = as_int("chunk", chunk, minimum=1)
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

    def write(self, start: int, waveforms, transients=None, stats=None) -> None:
        """Store pings ``start .. start + n - 1``: waveforms [n, T] (float32) and, if the
        writer has a transients layout, transients [n, B, T_bins]. ``stats``: optional
        mapping name -> float64 [n] of per-ping bookkeeping values (e.g. Monte-Carlo
        noise energies), kept with the partial file for a resumed run (:meth:`stats`)
        and dropped by :meth:`finish`."""
        f = self._require_open()
        try:
            self._write(f, start, waveforms, transients, stats)
        except OSError as exc:
            raise self._fail(exc) from None
        self._wrote = True

    def _write(self, f: h5py.File, start, waveforms, transients, stats) -> None:
        start = as_int("start", start, minimum=0)
        dims: dict = {"T": (self.n_samples, "n_samples")}
        wf = as_array("waveforms", waveforms, ("n", "T"), np.float32, dims)
        stop = start + wf.shape[0]
        if stop > self.n_pings:
            raise InputError(f"pings {start}..{stop - 1} exceed the dataset's {self.n_pings}")
        if (self.layout is None) != (transients is None):
            raise InputError("transients must be given exactly when the writer has a "
                             "transients layout")
        tr = None
        if transients is not None:
            dims.update(B=(self.layout.n_bounces, "layout"), K=(self.layout.n_bins, "layout"))
            tr = as_array("transients", transients, ("n", "B", "K"), np.float32, dims)
            f["transients/transients"][start:stop] = tr
        f["waveforms"][start:stop] = wf
        f["stream/crc"][start:stop] = self._row_crcs(f, start, stop, wf, tr)
        for name, values in (stats or {}).items():
            values = np.asarray(values, np.float64).reshape(-1)
            if values.shape != (stop - start,):
                raise InputError(f"stats '{name}' must have one value per ping ({stop - start})")
            key = f"stream/stats/{name}"
            if key not in f:
                f.create_dataset(key, shape=(self.n_pings,), dtype=np.float64, fillvalue=0)
            f[key][start:stop] = values
        f.flush()  # data and checksums on disk before the pings are marked done
        f["stream/done"][start:stop] = True
        f.flush()

    def stats(self, name: str) -> np.ndarray | None:
        """The per-ping values ``name`` stored by :meth:`write` (float64 [N], 0 for pings
        not written), or None if none were stored."""
        f = self._require_open()
        key = f"stream/stats/{name}"
        return np.asarray(f[key][()], np.float64) if key in f else None

    def finish(self, meta=None) -> Path:
        """Complete the file and rename it to the final path atomically; returns it.

        ``meta``: free-form values known only at the end (e.g. measured statistics),
        added to the dataset's meta."""
        f = self._require_open()
        try:
            return self._finish(f, meta)
        except OSError as exc:
            raise self._fail(exc) from None

    def _finish(self, f: h5py.File, meta) -> Path:
        from ..atomic import atomic_path
        done = self.done
        if not done.all():
            missing = np.flatnonzero(~done)
            raise InputError(f"{self.partial_path}: {missing.size} pings not written yet "
                             f"(first: {int(missing[0])})")
        extra = check_attr_dict("meta", meta, DATASET_ATTRS) if meta else {}
        f.flush()
        # The final file is a compressed copy (h5io.ping_layout) without the bookkeeping; the
        # partial file stays until the copy is in place, so a crash here loses nothing.
        with atomic_path(self.path, keep_suffix=False, size=self.nbytes()) as tmp, \
                h5py.File(tmp, "w") as out:
            _copy_compressed(f, out, skip=("stream",))
            json_keys = [decode_scalar(k) for k in np.atleast_1d(out.attrs.get("json_keys", []))]
            for key, value in extra.items():
                stored, is_json = encode_attr(key, value)
                out.attrs[key] = stored
                if is_json and key not in json_keys:
                    json_keys.append(key)
                elif not is_json and key in json_keys:
                    json_keys.remove(key)
            if json_keys:
                out.attrs["json_keys"] = json_keys
            elif "json_keys" in out.attrs:
                del out.attrs["json_keys"]
            out.attrs["complete"] = True
            out.flush()
        f.close()
        self._file = None
        self.partial_path.unlink()
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


class TransientsStreamWriter:
    """Write a transients file [N, B, T] chunk of poses by chunk (``sonarsim render``), atomically.

    ``header``: a validated :class:`Transients` with every field of the file but the
    histograms (e.g. a one-bin stand-in: only its N, B, attributes, poses and meta are
    used); ``n_bins``: T. The file is written under a temporary name beside ``path`` (root
    attribute ``complete = False``, free space checked first) and renamed to ``path`` when
    the ``with`` block ends normally after every pose was written; on an exception, or with
    poses missing, nothing is left at ``path``. Histograms are compressed
    (``h5io.ping_layout``)::

        with TransientsStreamWriter("T.h5", header, n_bins) as w:
            for start, hist in chunks:          # hist [n, B, T] float32
                w.write(start, hist)
    """

    def __init__(self, path: PathLike, header: Transients, n_bins: int):
        self.path = Path(path)
        self.header = header
        self.shape = (header.n_pings, header.n_bounces, as_int("n_bins", n_bins, minimum=1))
        self._written = np.zeros(self.shape[0], dtype=bool)
        self._stack: contextlib.ExitStack | None = None
        self._file: h5py.File | None = None

    def __enter__(self) -> "TransientsStreamWriter":
        from ..atomic import atomic_path, write_error
        stack = contextlib.ExitStack()
        size = int(np.prod(self.shape)) * 4 + nbytes_of(self.header.tx, self.header.rx)
        tmp = stack.enter_context(atomic_path(self.path, keep_suffix=False, size=size))
        try:
            f = stack.enter_context(h5py.File(tmp, "w"))
            self.header._write_group(f, data=False)
            f.attrs["complete"] = False                 # until the last pose is in
            f.create_dataset("transients", shape=self.shape, dtype=np.float32,
                             **ping_layout(self.shape, np.float32))
        except OSError as exc:
            stack.__exit__(*sys.exc_info())
            raise write_error(self.path, exc) from None
        except BaseException:
            stack.__exit__(*sys.exc_info())
            raise
        self._stack, self._file = stack, f
        return self

    def write(self, start: int, hist) -> None:
        """Store the histograms of poses ``start .. start + n - 1``: ``hist`` [n, B, T]."""
        from ..atomic import write_error
        if self._file is None:
            raise InputError(f"{self.path}: transients writer is not open (use it in a with block)")
        start = as_int("start", start, minimum=0)
        dims = {"B": (self.shape[1], "bounces"), "T": (self.shape[2], "n_bins")}
        h = as_array("transients", hist, ("n", "B", "T"), np.float32, dims)
        stop = start + h.shape[0]
        if stop > self.shape[0]:
            raise InputError(f"poses {start}..{stop - 1} exceed the file's {self.shape[0]}")
        try:
            self._file["transients"][start:stop] = h
        except OSError as exc:
            raise write_error(self.path, exc) from None
        self._written[start:stop] = True

    def __exit__(self, exc_type, exc, tb) -> None:
        stack, self._stack = self._stack, None
        if stack is None:
            return
        try:
            if exc_type is None:
                if not self._written.all():
                    missing = np.flatnonzero(~self._written)
                    raise InputError(f"{self.path}: {missing.size} poses not written "
                                     f"(first: {int(missing[0])}); nothing was kept")
                self._file.attrs["complete"] = True
        except BaseException:
            self._file = None
            stack.__exit__(*sys.exc_info())
            raise
        self._file = None
        stack.__exit__(exc_type, exc, tb)
