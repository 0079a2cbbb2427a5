"""Output files of the commands: no silent replacement, one writer at a time.

* :func:`check_output` refuses, before any work, an output path that names a directory,
  whose directory does not exist, or that already exists (unless ``force``).
* :func:`output_lock` holds an exclusive lock on an output for the whole run, so a second
  process writing the same output (or its scratch files: ``<out>.partial``,
  ``.<out>.noiseless``, the temporary files of :func:`sonarsim.atomic.atomic_path`) fails at
  once with a clear message instead of interleaving with the first. The lock is
  ``fcntl.flock`` on a hidden file ``.<name>.lock`` beside the output; the kernel releases it
  when the process ends, however it ends, and the file is removed on a normal exit.

The command line applies both to every file option a command declares (see
:mod:`sonarsim.cli_common`), and adds ``--force`` to those commands.
"""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Iterable, Iterator

from .errors import InputError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no locking
    fcntl = None


_HELD: dict[str, int] = {}     # output locks this process holds (absolute path -> depth)


def held_here(path: str | os.PathLike) -> bool:
    """Whether this process holds the output lock of ``path`` (:func:`output_lock`)."""
    return _HELD.get(os.path.abspath(os.fspath(path)), 0) > 0


def inherit_lock(path: str | os.PathLike) -> None:
    """Count ``path``'s output lock as held by this process without taking it: for a worker
    process whose parent holds that lock for the whole run and waits for the worker (the
    parent's flock would refuse the worker otherwise)."""
    key = os.path.abspath(os.fspath(path))
    _HELD[key] = _HELD.get(key, 0) + 1


class OutputBusyError(InputError):
    """Another process holds the lock of an output."""


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of output ``path``: ``.<name>.lock`` in the same directory."""
    p = Path(path)
    return p.with_name(f".{p.name}.lock")


def check_output(path: str | os.PathLike, *, force: bool = False, option: str = "--out",
                 exists_ok: bool = False) -> Path:
    """Validate an output file path before any work (one-line :class:`InputError`).

    Refuses a directory, a parent that is not a directory and (unless ``force`` or
    ``exists_ok``) an existing file. A missing parent directory is created later by the
    lock (as the atomic writers always did).
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{option} {p}: is a directory, expected a file name")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{option} {p}: {parent} is not a directory")
            break
    if p.exists() and not (force or exists_ok):
        raise InputError(f"{option} {p}: file exists; pass --force to replace it")
    return p


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, wait: float = 0.0) -> Iterator[Path]:
    """Hold the exclusive lock of output ``path`` (and its scratch files) while inside.

    Raises :class:`OutputBusyError` if another process (or another open lock in this
    process) holds it: at once, or after waiting up to ``wait`` seconds for it (e.g. for a
    file another worker is making and this one will then read).
    """
    lock = lock_path(path)
    key = os.path.abspath(os.fspath(path))
    if fcntl is None:  # pragma: no cover
        yield lock
        return
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{path}: cannot create the output directory ({exc.strerror})") \
            from None
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(f"{path}: cannot create the lock file {lock} "
                             f"({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            if wait > 0:
                time.sleep(min(1.0, wait))
                wait -= 1.0
                continue
            raise OutputBusyError(f"{path}: another process is writing this output (lock "
                                  f"{lock} is held); wait for it to finish or choose another "
                                  "output") from None
        # The previous holder may have removed the lock file between our open and flock:
        # then we hold a lock on a deleted file, and must lock the current one instead.
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    _HELD[key] = _HELD.get(key, 0) + 1
    try:
        with contextlib.suppress(OSError):      # the pid is for people; a full disk is fine
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        yield lock
    finally:
        _HELD[key] -= 1
        if not _HELD[key]:
            del _HELD[key]
        with contextlib.suppress(FileNotFoundError):
            os.unlink(lock)
        os.close(fd)


@contextlib.contextmanager
def output_locks(paths: Iterable[str | os.PathLike]) -> Iterator[None]:
    """Locks of several outputs at once (sorted, so two runs cannot deadlock)."""
    unique = sorted({os.path.abspath(os.fspath(p)) for p in paths})
    with contextlib.ExitStack() as stack:
        for p in unique:
            stack.enter_context(output_lock(p))
        yield


def finished_request(path: str | os.PathLike, request_id: str) -> bool:
    """Whether ``path`` is a complete sonarsim file whose meta ``request_id`` is ``request_id``
    (the same command with the same settings already finished it)."""
    from .dataset import inspect
    from .errors import SonarsimError
    try:
        with inspect(path) as (_, fields):
            return (fields.get("meta") or {}).get("request_id") == request_id
    except (SonarsimError, OSError):
        return False
