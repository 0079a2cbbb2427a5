"""Progress of long runs and the messages of the command lines, for sonarsim and recon.

Two audiences, one call (:func:`progress_bar`):

* on a **terminal** (stderr is a TTY) a tqdm bar, as before;
* **elsewhere** (``cmd > log 2>&1``, nohup, a cluster job, a batch worker's log) a line
  through :mod:`logging` every ``SONARSIM_PROGRESS_INTERVAL`` seconds (default
  :data:`DEFAULT_INTERVAL_S`) while the work runs — stage, done/total, percentage, rate,
  elapsed time, ETA and the stage's latest figures (e.g. the loss) — and one closing line,
  for every stage that lasted at least one interval::

      recon nbp: fit 120/1000 it (12%), 6.62 it/s, elapsed 0:00:18, ETA 0:02:13, loss=0.0431
      recon nbp: fit done: 1000/1000 it in 0:02:31 (6.61 it/s), loss=0.0212

  The lines go to the logger ``sonarsim.progress``; they appear when that logger is
  enabled for INFO, which :func:`setup_logging` arranges for the command lines and which
  a Python user gets with ``logging.basicConfig(level=logging.INFO)``. Shorter stages
  print nothing.

:func:`setup_logging` is what both command lines call (``--quiet``: warnings and errors
only, no bars; default: progress and notes; ``--verbose``: also debug details). Messages
follow one rule: **results on stdout** (``print``), **diagnostics on stderr** (notes and
progress through ``logging.getLogger(__name__).info``, warnings through ``warnings.warn``
or ``.warning``: one line ``warning: ...`` each).
"""
from __future__ import annotations

import logging
import math
import os
import sys
import threading
import time
import warnings
import weakref

from .errors import InputError

LOGGER_NAME = "sonarsim.progress"
DEFAULT_INTERVAL_S = 10.0
INTERVAL_ENV = "SONARSIM_PROGRESS_INTERVAL"
PACKAGES = ("sonarsim", "recon")        # the loggers the command lines configure

QUIET, NORMAL, VERBOSE = -1, 0, 1
_state = {"quiet": False}


# ------------------------------------------------------------------------- logging set-up

class _StderrHandler(logging.StreamHandler):
    """A handler that writes to whatever ``sys.stderr`` is at the time of each record
    (pytest's capture and redirections replace it)."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


class _Formatter(logging.Formatter):
    """``PREFIX: message`` for notes, progress and debug lines; ``warning: message`` for
    warnings (the form the project's own warnings have always had); ``PREFIX: error:
    message`` for errors. One line each: newlines in a message become ``; ``."""

    def __init__(self, prefix: str):
        super().__init__()
        self.prefix = prefix

    def format(self, record: logging.LogRecord) -> str:
        text = "; ".join(part.strip() for part in record.getMessage().splitlines()
                         if part.strip())
        if record.levelno >= logging.ERROR:
            return f"{self.prefix}: error: {text}"
        if record.levelno >= logging.WARNING:
            return f"warning: {text}"
        return f"{self.prefix}: {text}"


def setup_logging(prefix: str, verbosity: int = NORMAL):
    """Send the ``sonarsim``/``recon`` loggers' records to stderr as one-line messages and
    route :func:`warnings.warn` there too; return a function that undoes all of it.

    ``verbosity``: :data:`QUIET` (-1; warnings and errors only, no progress bars),
    :data:`NORMAL` (0; also notes and progress), :data:`VERBOSE` (>= 1; also debug).
    ``prefix`` starts every non-warning line (e.g. ``"recon nbp"``).
    """
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 \
        else logging.DEBUG
    handler = _StderrHandler()
    handler.setFormatter(_Formatter(prefix))
    saved = []
    for name in PACKAGES:
        logger = logging.getLogger(name)
        saved.append((logger, logger.level, logger.propagate, list(logger.handlers)))
        logger.handlers = [handler]
        logger.setLevel(level)
        logger.propagate = False
    saved_quiet = _state["quiet"]
    _state["quiet"] = verbosity < 0
    saved_show = warnings.showwarning
    warn_log = logging.getLogger("sonarsim.warnings")

    def showwarning(message, category, filename, lineno, file=None, line=None):
        warn_log.warning("%s", message)

    warnings.showwarning = showwarning

    def undo() -> None:
        warnings.showwarning = saved_show
        _state["quiet"] = saved_quiet
        for logger, lvl, propagate, handlers in saved:
            logger.handlers = handlers
            logger.setLevel(lvl)
            logger.propagate = propagate

    return undo


def progress_interval() -> float:
    """Seconds between two progress lines in a log (``$SONARSIM_PROGRESS_INTERVAL``)."""
    text = os.environ.get(INTERVAL_ENV, "").strip()
    if not text:
        return DEFAULT_INTERVAL_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"${INTERVAL_ENV} must be a positive number of seconds, got {text!r}")
    return value


# ------------------------------------------------------------------------------- the bars

def progress_bar(total: int, enabled: bool, *, unit: str, desc: str, initial: int = 0,
                 leave: bool = True):
    """Progress over ``total`` steps of ``unit`` named ``desc`` (``bar.update(k)``,
    ``bar.set_postfix(...)``, ``bar.close()``, or ``with``).

    A tqdm bar when stderr is a terminal; timed log lines (:class:`LogProgress`) when it
    is not and ``sonarsim.progress`` logs INFO; silent when ``enabled`` is false, under
    ``--quiet``, or when neither applies.
    """
    from tqdm import tqdm
    if enabled and not _state["quiet"]:
        if _isatty(sys.stderr):
            return tqdm(total=total, initial=initial, unit=unit, desc=desc, leave=leave,
                        dynamic_ncols=True)
        if logging.getLogger(LOGGER_NAME).isEnabledFor(logging.INFO):
            return LogProgress(total, unit=unit, desc=desc, initial=initial)
    return tqdm(total=total, initial=initial, unit=unit, desc=desc, disable=True)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def format_duration(seconds: float) -> str:
    """``H:MM:SS`` (``?`` when unknown)."""
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _format_rate(rate: float, unit: str) -> str:
    if not rate > 0:
        return f"? {unit}/s"
    if rate >= 1:
        return f"{rate:.3g} {unit}/s"
    return f"{1 / rate:.3g} s/{unit}"


class LogProgress:
    """Progress reported as log lines at a steady interval (the non-terminal form of
    :func:`progress_bar`; the subset of tqdm's interface the project uses).

    A background thread writes a line every ``interval`` seconds while the bar is open,
    also when no step has finished since the last line (a long first step still shows
    that the run is alive); :meth:`close` writes the closing line if any line was written.
    """

    def __init__(self, total: int, *, unit: str, desc: str, initial: int = 0,
                 interval: float | None = None, logger: logging.Logger | None = None):
        self.total = int(total)
        self.n = int(initial)
        self.unit = unit
        self.desc = desc
        self.disable = False
        self._initial = int(initial)
        self._interval = progress_interval() if interval is None else float(interval)
        self._log = logger or logging.getLogger(LOGGER_NAME)
        self._postfix = ""
        self._start = time.monotonic()
        self._last = self._start
        self._lines = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=_tick, name=f"progress:{desc}", daemon=True,
                                        args=(weakref.ref(self), self._stop, self._interval))
        self._thread.start()

    # tqdm's interface -------------------------------------------------------------------
    def update(self, n: int = 1) -> None:
        self.n += int(n)
        if time.monotonic() - self._last >= self._interval:
            self._emit()

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kwargs) -> None:
        items = dict(ordered_dict or {}, **kwargs)
        self._postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def refresh(self) -> None:
        pass

    def write(self, text: str) -> None:
        self._log.info("%s", text)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        elapsed = time.monotonic() - self._start
        if self._lines or elapsed >= self._interval:
            rate = (self.n - self._initial) / elapsed if elapsed > 0 else math.nan
            tail = f", {self._postfix}" if self._postfix else ""
            status = "done" if self.n >= self.total else "stopped"
            self._log.info("%s %s: %d/%d %s in %s (%s)%s", self.desc, status, self.n,
                           self.total, self.unit, format_duration(elapsed),
                           _format_rate(rate, self.unit), tail)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        self._stop.set()     # a bar that was never closed stops its thread when collected

    # the lines ---------------------------------------------------------------------------
    def line(self) -> str:
        """The progress line as it would be written now."""
        now = time.monotonic()
        elapsed = now - self._start
        done = self.n - self._initial
        rate = done / elapsed if elapsed > 0 else math.nan
        left = self.total - self.n
        eta = left / rate if rate > 0 else math.nan
        pct = f" ({100.0 * self.n / self.total:.0f}%)" if self.total > 0 else ""
        tail = f", {self._postfix}" if self._postfix else ""
        return (f"{self.desc} {self.n}/{self.total} {self.unit}{pct}, "
                f"{_format_rate(rate, self.unit)}, elapsed {format_duration(elapsed)}, "
                f"ETA {format_duration(eta)}{tail}")

    def _emit(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._last = time.monotonic()
            self._lines += 1
            self._log.info("%s", self.line())


def _tick(ref, stop: threading.Event, interval: float) -> None:
    """The background thread of a :class:`LogProgress` (holding it only weakly)."""
    while True:
        bar = ref()
        if bar is None:
            return
        wait = max(0.01, interval - (time.monotonic() - bar._last))
        del bar
        if stop.wait(wait):
            return
        bar = ref()
        if bar is None:
            return
        if time.monotonic() - bar._last >= interval:
            bar._emit()
        del bar
