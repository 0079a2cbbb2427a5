"""Output locks as the batch uses them: a busy output is worth retrying (unlike bad input)."""
from __future__ import annotations

import contextlib

from ..batch_engine import TransientError


class OutputBusy(TransientError):
    """Another process writes this output now (retried by the engine, unlike input errors)."""


@contextlib.contextmanager
def locked(path: str):
    """The exclusive lock of an output (:func:`sonarsim.outputs.output_lock`); busy is an
    error worth retrying (e.g. a worker the scheduler gave up on is still finishing it)."""
    from ..outputs import OutputBusyError, output_lock
    try:
        with output_lock(path):
            yield
    except OutputBusyError as exc:
        raise OutputBusy(str(exc)) from None
