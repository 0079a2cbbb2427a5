"""Format identifiers and crash-safe HDF5 writing shared by all sonarsim files."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

import h5py

FORMAT_VERSION = 1
KIND_TRANSIENTS = "sonarsim.transients"
KIND_DATASET = "sonarsim.dataset"
KIND_VOLUME = "sonarsim.volume"
KIND_NAMES = {KIND_TRANSIENTS: "transients", KIND_DATASET: "sonar dataset",
              KIND_VOLUME: "volume"}
# Root attributes every file carries; never part of ``meta``/``params``.
HOUSEKEEPING = ("format", "format_version", "complete", "json_keys")
PARTIAL_SUFFIX = ".partial"

PathLike = str | os.PathLike


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


def commit(tmp: Path, final: Path) -> None:
    """Flush ``tmp`` to disk and rename it to ``final`` atomically."""
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
        commit(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return final


def write_header(g: h5py.Group, kind: str) -> None:
    """The housekeeping attributes of a finished file (or nested group) of ``kind``."""
    g.attrs["format"] = kind
    g.attrs["format_version"] = FORMAT_VERSION
    g.attrs["complete"] = True
