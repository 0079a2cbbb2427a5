"""Format identifiers and crash-safe HDF5 writing shared by all sonarsim files."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import h5py

from ..atomic import atomic_path, fsync_path

FORMAT_VERSION = 1
KIND_TRANSIENTS = "sonarsim.transients"
KIND_DATASET = "sonarsim.dataset"
KIND_VOLUME = "sonarsim.volume"
KIND_NAMES = {KIND_TRANSIENTS: "transients", KIND_DATASET: "sonar dataset",
              KIND_VOLUME: "volume"}
# Root attributes every file carries; never part of ``meta``/``params``.
HOUSEKEEPING = ("format", "format_version", "complete", "json_keys")
PARTIAL_SUFFIX = ".partial"
#: Why every reader refuses an unfinished file (root attribute ``complete = False``).
INCOMPLETE = ("incomplete file (attribute 'complete' is false): the partial output of an "
              "interrupted run; resume that run or delete the file")

PathLike = str | os.PathLike

#: How the big per-ping arrays (waveforms, transients) are stored: gzip level 1 after the
#: byte shuffle, in chunks of whole pings of about CHUNK_BYTES. Measured on a 720-pose bunny
#: render (93 MiB of transients) and the 54 000-ping bunny dataset (148 MiB of 20 dB
#: waveforms), docs/formats.md: transients to 31 %, noisy waveforms to 86 %.
COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
CHUNK_BYTES = 1 << 20
MAX_CHUNK_ROW_BYTES = 256 << 20    # a ping larger than this is stored contiguous


def ping_layout(shape: tuple, dtype) -> dict:
    """``create_dataset`` keywords for a per-ping array of ``shape`` (pings first):
    compressed chunks of whole pings (:data:`COMPRESSION`), or contiguous when empty or
    when one ping is huge."""
    import math
    import numpy as np
    row = int(np.dtype(dtype).itemsize) * math.prod(shape[1:])
    if not shape or shape[0] < 1 or row < 1 or row > MAX_CHUNK_ROW_BYTES:
        return {}
    rows = max(1, min(shape[0], CHUNK_BYTES // row))
    return {"chunks": (rows, *shape[1:]), **COMPRESSION}


def commit(tmp: Path, final: Path) -> None:
    """Flush ``tmp`` to disk and rename it to ``final`` atomically (the stream writer's
    ``.partial`` file, which lives across runs, is finished this way)."""
    fsync_path(tmp)
    os.replace(tmp, final)
    fsync_path(final.parent)


def nbytes_of(*arrays) -> int:
    """Bytes of the given arrays (None counts 0): what writing them uncompressed needs."""
    return sum(int(getattr(a, "nbytes", 0)) for a in arrays if a is not None)


def atomic_write_h5(path: PathLike, fill: Callable[[h5py.File], None],
                    size: float | None = None) -> Path:
    """Create HDF5 file ``path`` by calling ``fill(file)`` on a temporary file in the same
    directory and renaming it into place.  If ``fill`` raises, the temporary file is
    removed and an existing ``path`` is left untouched.  The temporary name does not end
    in ``.h5``, so it is never mistaken for a finished file. ``size``: bytes the file will
    hold, if known (the free space is checked first; :func:`sonarsim.atomic.atomic_path`);
    a full disk or another OS error is a one-line :class:`~sonarsim.errors.WriteError`."""
    final = Path(path)
    with atomic_path(final, keep_suffix=False, size=size) as tmp:
        with h5py.File(tmp, "w") as f:
            fill(f)
            f.flush()
    return final


def write_header(g: h5py.Group, kind: str) -> None:
    """The housekeeping attributes of a finished file (or nested group) of ``kind``."""
    g.attrs["format"] = kind
    g.attrs["format_version"] = FORMAT_VERSION
    g.attrs["complete"] = True
