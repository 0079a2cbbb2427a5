"""Atomic file writes: write a temporary file beside the target, then rename it into place.

An interrupted or failed write never leaves a file at the target path that looks complete,
and an existing target stays untouched until the new file is finished. Every writer of the
project (HDF5 files, pictures, meshes, pose files, checkpoints) goes through
:func:`atomic_path`.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file (or, best effort, a directory) to disk."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on directories
        pass
    finally:
        os.close(fd)


def _default_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, keep_suffix: bool = True) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory; rename it onto ``path`` on success.

    The temporary name starts with a dot. ``keep_suffix`` keeps the target's suffix at its
    end (writers such as matplotlib and trimesh choose the format from it); without it the
    name ends in ``.tmp`` so that, e.g., no half-written ``*.h5`` matches a glob. On success
    the file gets the usual permissions, is flushed to disk and replaces the target
    atomically; if the body raises, the temporary file is removed.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    suffix = final.suffix if keep_suffix else ".tmp"
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=suffix, dir=final.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, _default_mode())  # mkstemp creates 0600
        fsync_path(tmp)
        os.replace(tmp, final)
        fsync_path(final.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
