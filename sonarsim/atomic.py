"""Atomic file writes: write a temporary file beside the target, then rename it into place.

An interrupted or failed write never leaves a file at the target path that looks complete,
and an existing target stays untouched until the new file is finished. Every writer of the
project (HDF5 files, pictures, meshes, pose files, checkpoints) goes through
:func:`atomic_path`, which also gives it:

* **a free-space check** before anything is written, when the writer knows how much it will
  write (``size``; :func:`check_free_space`);
* **one-line errors**: an ``OSError`` while writing (``ENOSPC`` on a full disk, a read-only
  file system, a permission), or a library's own error that says the disk is full (HDF5,
  OpenEXR), becomes a :class:`~sonarsim.errors.WriteError` naming the final path, and the
  temporary file is removed with any file the writer derived from its name
  (:func:`write_error`);
* **no leftovers of killed runs**: every write holds the target's output lock
  (:func:`sonarsim.outputs.output_lock`, released by the kernel when a process dies), so
  the next write of the same target, holding that lock, knows that any temporary file
  ``.NAME.<random>.tmp`` (or ``.NAME.<random>.SUFFIX``) beside it was left by a dead writer
  (kill -9, power loss) and removes it (:func:`remove_stale_temps`).
"""
from __future__ import annotations

import contextlib
import errno
import glob
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from .errors import WriteError

log = logging.getLogger(__name__)

#: errno values meaning "the disk is full" (no space, quota exceeded).
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
#: Bytes kept free beyond an estimate (file-system metadata, HDF5 headers): a fixed part
#: and a share of the estimate.
FREE_SPACE_MARGIN = 64 << 10
FREE_SPACE_SHARE = 0.02
_H5_ERRNO = re.compile(r"errno = (\d+)")


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


def _errno_of(exc: BaseException) -> int | None:
    """The errno of an OSError, also when HDF5 only wrote it into the message."""
    code = getattr(exc, "errno", None)
    if code:
        return code
    text = str(exc)
    found = _H5_ERRNO.search(text)
    if found:
        return int(found.group(1))
    # Libraries that wrap the C library's error in their own exception (OpenEXR's
    # RuntimeError "... No space left on device.") keep only its text.
    return next((c for c in DISK_FULL if os.strerror(c) in text), None)


def is_write_failure(exc: BaseException) -> bool:
    """Whether ``exc``, raised while writing, is the file system's refusal: an ``OSError``,
    or any error whose chain carries a disk-full errno (in HDF5's or another library's
    message)."""
    return isinstance(exc, OSError) or any(_errno_of(e) in DISK_FULL for e in _chain(exc))


def _chain(exc: BaseException | None) -> Iterator[BaseException]:
    """``exc`` and the exceptions it was raised from or while handling (HDF5's close after a
    failed write raises a second error that hides the first)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def write_error(path: str | os.PathLike, exc: BaseException) -> WriteError:
    """The one-line :class:`WriteError` for an ``OSError`` raised while writing ``path``
    (disk full if any error of its chain says so)."""
    codes = [_errno_of(e) for e in _chain(exc)]
    code = next((c for c in codes if c in DISK_FULL), codes[0])
    if code in DISK_FULL:
        reason = "no space left on the device (disk full); free some space or write elsewhere"
    elif code is not None and code in errno.errorcode:
        reason = os.strerror(code)
    else:
        text = str(exc).strip().splitlines()
        reason = text[0] if text else type(exc).__name__
    return WriteError(f"cannot write {os.fspath(path)}: {reason}")


def free_bytes(path: str | os.PathLike) -> int | None:
    """Free bytes on the file system of ``path`` (its nearest existing parent); None if
    unknown."""
    p = Path(os.path.abspath(os.fspath(path)))
    for candidate in (p, *p.parents):
        if candidate.exists():
            try:
                return shutil.disk_usage(candidate).free
            except OSError:
                return None
    return None


def check_free_space(path: str | os.PathLike, nbytes: float, what: str = "") -> None:
    """:class:`WriteError` (one line, before anything is written) when the file system of
    ``path`` has less than ``nbytes`` plus a margin (:data:`FREE_SPACE_MARGIN`,
    :data:`FREE_SPACE_SHARE`) free."""
    from .limits import gib
    free = free_bytes(path)
    need = nbytes * (1 + FREE_SPACE_SHARE) + FREE_SPACE_MARGIN
    if free is None or need <= free:
        return
    raise WriteError(f"cannot write {os.fspath(path)}: {what + ' ' if what else ''}needs about "
                     f"{gib(need)} but only {gib(free)} are free on that file system")


def _temp_patterns(final: Path) -> list[str]:
    # A writer may add to the temporary name it is given (pyevtk appends ".vti"): "*".
    stem = glob.escape(str(final.parent / f".{final.name}."))
    suffixes = {".tmp", final.suffix} - {""}
    return [f"{stem}{'?' * 8}{glob.escape(s)}*" for s in sorted(suffixes)]


def _remove_temp(tmp: Path) -> None:
    """Remove ``tmp`` and the files a writer derived from its name (``tmp`` + a suffix)."""
    for name in (str(tmp), *glob.glob(glob.escape(str(tmp)) + ".*")):
        with contextlib.suppress(FileNotFoundError, IsADirectoryError):
            os.unlink(name)


def remove_stale_temps(path: str | os.PathLike) -> int:
    """Remove the temporary files left beside ``path`` by earlier writers that died; returns
    the bytes freed. Call it only while holding ``path``'s output lock
    (:func:`sonarsim.outputs.output_lock`): then no live writer owns such a file."""
    freed = 0
    for name in (n for pattern in _temp_patterns(Path(path)) for n in glob.glob(pattern)):
        try:
            size = os.stat(name).st_size
            os.unlink(name)
        except OSError:
            continue
        freed += size
        log.info("removed %s, left by an interrupted run", name)
    return freed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, keep_suffix: bool = True,
                size: float | None = None) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory; rename it onto ``path`` on success.

    The temporary name starts with a dot. ``keep_suffix`` keeps the target's suffix at its
    end (writers such as matplotlib and trimesh choose the format from it); without it the
    name ends in ``.tmp`` so that, e.g., no half-written ``*.h5`` matches a glob. ``size``:
    the bytes the writer will write, if known (checked against the free space first). On
    success the file gets the usual permissions, is flushed to disk and replaces the target
    atomically; if the body raises, the temporary file is removed, and an ``OSError``
    becomes a one-line :class:`WriteError` naming ``path``.

    The write holds ``path``'s output lock (:func:`sonarsim.outputs.output_lock`) unless
    this process holds it already (a command holds its outputs' locks for the whole run), so
    two processes never write one target at once, and temporary files of dead earlier
    writers of ``path`` are removed first.
    """
    from .outputs import held_here, output_lock
    final = Path(path)
    with contextlib.ExitStack() as stack:
        if not held_here(final):
            stack.enter_context(output_lock(final))
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temps(final)
            if size is not None:
                check_free_space(final, size)
            fd, name = tempfile.mkstemp(prefix=f".{final.name}.",
                                        suffix=final.suffix if keep_suffix else ".tmp",
                                        dir=final.parent)
            os.close(fd)
        except OSError as exc:
            raise write_error(final, exc) from None
        tmp = Path(name)
        try:
            try:
                yield tmp
                os.chmod(tmp, _default_mode())  # mkstemp creates 0600
                fsync_path(tmp)
                os.replace(tmp, final)
            except Exception as exc:
                if not is_write_failure(exc):
                    raise
                raise write_error(final, exc) from None
            fsync_path(final.parent)
        finally:
            _remove_temp(tmp)
