"""Dr.Jit thread counts: the one range rule (:func:`check_threads`) and the scoping shared by
the rendering entry points (render, simulate), the CLI and ``sonarsim batch``."""
from __future__ import annotations

import contextlib
from typing import Iterator

from .errors import InputError

MAX_THREADS = 1024     # Dr.Jit worker threads; more only exhausts the process's thread limit


def check_threads(threads, option: str = "--threads") -> int | None:
    """``threads`` as an int in 1..:data:`MAX_THREADS` (None stays None: Dr.Jit's default);
    one-line InputError naming ``option`` otherwise."""
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, (int, float)) \
            or int(threads) != threads or threads < 1:
        raise InputError(f"{option} must be an integer >= 1, got {threads!r}")
    if threads > MAX_THREADS:
        raise InputError(f"{option} must be at most {MAX_THREADS}, got {threads}")
    return int(threads)


@contextlib.contextmanager
def dr_threads(threads: int | None) -> Iterator[None]:
    """Run the enclosed Dr.Jit work on ``threads`` threads (None: leave Dr.Jit's setting,
    all cores unless changed), then restore the previous count."""
    if threads is None:
        yield
        return
    import drjit as dr
    before = dr.thread_count()
    dr.set_thread_count(int(threads))
    try:
        yield
    finally:
        dr.set_thread_count(before)
