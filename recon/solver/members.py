"""Ensemble members fitted side by side, one worker process each.

A deterministic fit runs on one Dr.Jit thread (a fixed summation order), so a K-member
ensemble fitted one after another leaves every other core idle. :func:`fit_members` fits up
to :func:`member_processes` members at once, each in a fresh ``python -m
recon.solver.member_worker`` process, and returns the same volumes, to the bit, as fitting
them in turn: each member is the same single-threaded fit with its own seed.

Fresh interpreters rather than :mod:`multiprocessing`: a forked child of a process whose
Dr.Jit thread pool runs is not safe, and a spawned one re-runs the caller's ``__main__``
(a script without a ``if __name__ == "__main__"`` guard would start the run again). The
dataset goes to the workers once, pickled into a temporary file; each worker reports every
iteration as a line on its stdout, which the parent turns into one progress bar and the
run's ``callback`` (records carry ``member``); the worker's stderr is the parent's.
"""
from __future__ import annotations

import json
import os
import pickle
import queue as queue_module
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from sonarsim import limits, outputs
from sonarsim.errors import SonarsimError
from sonarsim.progress import progress_bar

REPORT = "member-report "          # prefix of a worker's iteration lines


def available_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # not Linux
        return os.cpu_count() or 1


def run_variant() -> str:
    """The variant this run uses: the one selected, else the one asked for
    (``SONARSIM_VARIANT``): not yet selected, a GPU run would otherwise be planned, and its
    workers started, as a CPU run."""
    from sonarsim import runtime
    return runtime.current_variant() or runtime.requested_variant()


def member_processes(members: int, settings, grid, network: bool, dataset, timer=None) -> int:
    """How many members to fit at once: 1 (in this process, one after another) unless the
    fits are deterministic single-threaded CPU fits and there are spare cores; never more
    than the members, the cores, Dr.Jit's thread count (``--threads``), or what the memory
    limit holds (each worker: the run's estimate plus its copy of the dataset). A run with a
    ``timer`` (a profile of this process) stays in one process. In a Dask worker the count
    follows the Dr.Jit threads ``sonarsim batch`` gives each task."""
    from sonarsim import runtime
    from .resources import memory_estimate
    if members < 2 or not settings.deterministic or timer is not None:
        return 1
    if run_variant().startswith("cuda"):
        return 1
    import drjit as dr
    count = min(members, available_cores(), int(dr.thread_count()))
    limit, _ = limits.memory_limit()
    if limit is not None:
        per_worker = memory_estimate(grid, settings, network) + dataset.nbytes()
        count = min(count, max(1, limit // max(per_worker, 1)))
    return max(1, int(count))


def fit_members(jobs: list[dict], processes: int, *, progress: bool, callback, desc: str,
                iterations: int) -> list[tuple]:
    """Run :func:`recon.solver.loop.fit_member` for every keyword set in ``jobs`` (each with
    the same ``dataset``) on ``processes`` worker processes at a time; returns their
    (volume, run) in the order of ``jobs``. A failed member stops the others; its error is
    raised here (a :class:`~sonarsim.errors.SonarsimError` as itself)."""
    variant = run_variant()
    reports: queue_module.Queue = queue_module.Queue()
    bar = progress_bar(iterations * len(jobs), progress, unit="it",
                       desc=f"{desc} ×{len(jobs)} ({processes} at once)", leave=False)
    running: dict[int, subprocess.Popen] = {}
    readers: list[threading.Thread] = []
    with tempfile.TemporaryDirectory(prefix="sonarsim-members-") as tmp:
        tmp = Path(tmp)
        data = tmp / "dataset.pkl"
        with open(data, "wb") as f:
            pickle.dump(jobs[0]["dataset"], f, protocol=pickle.HIGHEST_PROTOCOL)
        for k, job in enumerate(jobs):
            # a checkpoint whose lock this process holds (the command's --checkpoint) is
            # written by the worker under that lock: the worker inherits it
            ck = job.get("checkpoint")
            locks = [str(ck)] if ck is not None and outputs.held_here(ck) else []
            with open(tmp / f"job{k}.pkl", "wb") as f:
                pickle.dump(({key: v for key, v in job.items() if key != "dataset"}, locks), f,
                            protocol=pickle.HIGHEST_PROTOCOL)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        waiting, finished = list(range(len(jobs))), {}
        try:
            while waiting or running:
                while waiting and len(running) < processes:
                    k = waiting.pop(0)
                    cmd = [sys.executable, "-m", "recon.solver.member_worker", variant, str(data),
                           str(tmp / f"job{k}.pkl"), str(tmp / f"result{k}.pkl")]
                    running[k] = subprocess.Popen(cmd, stdout=subprocess.PIPE, env=env, text=True)
                    readers.append(threading.Thread(target=_read_reports, daemon=True,
                                                    args=(k, running[k].stdout, reports)))
                    readers[-1].start()
                _drain(reports, bar, callback, timeout=0.5)
                for k, proc in list(running.items()):
                    if proc.poll() is not None:
                        del running[k]
                        finished[k] = _result(tmp / f"result{k}.pkl", proc.returncode, k)
            for t in readers:
                t.join()
            _drain(reports, bar, callback, timeout=0)
            return [finished[k] for k in range(len(jobs))]
        finally:
            bar.close()
            for proc in running.values():
                proc.kill()
            for proc in running.values():
                proc.wait()


def _result(path: Path, returncode: int, member: int) -> tuple:
    """A worker's (volume, run), or its error raised."""
    if path.exists():
        with open(path, "rb") as f:
            outcome = pickle.load(f)
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome
    raise SonarsimError(f"ensemble member {member + 1} stopped without a result (exit status "
                        f"{returncode}); its output is above")


def _read_reports(member: int, stream, reports) -> None:
    for line in stream:
        if line.startswith(REPORT):
            iteration, record = json.loads(line[len(REPORT):])
            reports.put((member, iteration, record))
        else:                       # anything else a worker prints goes on to our stderr
            sys.stderr.write(line)
    stream.close()


def _drain(reports, bar, callback, timeout: float) -> None:
    """Pass the workers' iteration reports on to the bar and the callback."""
    while True:
        try:
            member, iteration, record = reports.get(timeout=timeout)
        except queue_module.Empty:
            return
        timeout = 0
        bar.update(1)
        if callback is not None:
            callback(iteration, dict(record, member=member))
