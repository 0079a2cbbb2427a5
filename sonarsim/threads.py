"""Dr.Jit thread-count scoping shared by the rendering entry points (render, simulate)."""
from __future__ import annotations

import contextlib
from typing import Iterator


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
