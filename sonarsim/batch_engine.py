"""Run many independent tasks on dask.distributed: the execution engine of ``sonarsim batch``.

The engine knows nothing about sonar: it runs :class:`Task` objects (a module-level function,
its arguments and the tasks whose results it needs) and returns one :class:`Outcome` per task.
``sonarsim batch`` (:mod:`sonarsim.batch`) and ``benchmarks/table2.py --scheduler`` both go
through it.

Where the tasks run (:class:`Engine`):

* **a local cluster** (default): a ``distributed.LocalCluster`` of worker *processes*
  (one Dask thread each, so one task per process at a time), with the cores divided between
  the workers and Dr.Jit's own threads (:func:`plan_local_cluster`); when NVIDIA GPUs are
  present, one worker per GPU with ``CUDA_VISIBLE_DEVICES`` set to it and the
  ``cuda_ad_mono`` variant;
* **an existing cluster** (``scheduler="tcp://host:8786"``): started with ``dask scheduler``
  and ``dask worker`` (docs/batch.md); the workers need the same sonarsim installation and
  the same file system paths;
* **in this process** (``scheduler="sequential"``): the tasks one after the other, no Dask
  (for debugging and as the benchmark's baseline).

Failures: only what may pass is tried again. A task that raises one of
:data:`TRANSIENT_ERRORS` (a busy output lock, a lost connection, a timeout, memory) is
retried ``retries`` times by Dask; anything else fails at once with its one-line error: a
:class:`sonarsim.errors.SonarsimError` (bad input such as a missing mesh, a full disk) and
an unexpected exception (a bug: running it again gives the same error; its traceback goes to
the worker's log). A worker process that dies mid-task loses only that task, which Dask runs
again on another worker (up to Dask's ``distributed.scheduler.allowed-failures``, 3 by
default). Failed tasks are reported with their error; the others run on. A task whose needed
task failed is not run.
"""
from __future__ import annotations

import errno
import logging
import os
import shutil
import subprocess
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from .errors import InputError, SonarsimError

log = logging.getLogger(__name__)

SEQUENTIAL = "sequential"
MEMORY_PER_WORKER = 2 * 2**30    # bytes a worker may need (a full 54 000-ping scan: ~1.5 GB)
DEFAULT_RETRIES = 2
THREADS_PER_WORKER = 2           # Dr.Jit threads per local CPU worker by default (measured)
DASK_MALLOC_TRIM = "65536"       # Dask's default MALLOC_TRIM_THRESHOLD_ for workers (see below)


# ----------------------------------------------------------------------------- tasks

@dataclass(frozen=True)
class Task:
    """One unit of work.

    ``fn(*args, *needed_results, **kwargs)`` runs on a worker; ``fn`` must be importable there
    (a module-level function, or one Dask can pickle by value, such as a script's). ``needs``:
    keys of tasks that must succeed first; their results are appended to ``args`` unless
    ``pass_needed`` is false. ``job``: the job it belongs to; progress counts jobs, a job being
    finished when all its tasks are.
    """
    key: str
    fn: Callable
    args: tuple = ()
    kwargs: Mapping = field(default_factory=dict)
    needs: tuple[str, ...] = ()
    job: str = ""
    pass_needed: bool = True

    @property
    def job_name(self) -> str:
        return self.job or self.key


@dataclass
class Outcome:
    """What became of a task: ``status`` 'done' or 'failed', the function's ``result``
    (done), the ``error`` (one line, failed), the task's ``wall_s`` on its worker (s)."""
    key: str
    status: str
    result: Any = None
    error: str = ""
    wall_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == "done"


@dataclass(frozen=True)
class _Returned:
    """What the worker-side wrapper returns: the result, or a user error (not retried)."""
    ok: bool
    value: Any = None
    error: str = ""
    wall_s: float = 0.0


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


class TransientError(RuntimeError):
    """Raise it (or a subclass) from a task for a failure that may pass, e.g. an output
    another process still holds: the engine runs the task again (``retries``)."""


#: OSError numbers that may pass: busy, interrupted, a network file system's hiccup.
TRANSIENT_ERRNOS = (errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.EIO, errno.ESTALE)
#: What a task may raise and still succeed when run again.
TRANSIENT_ERRORS = (TransientError, MemoryError, TimeoutError, ConnectionError)


def is_transient(exc: BaseException) -> bool:
    """Whether running a task again may succeed after ``exc`` (see the module docstring)."""
    if isinstance(exc, SonarsimError):
        return False
    if isinstance(exc, TRANSIENT_ERRORS):
        return True
    return isinstance(exc, OSError) and exc.errno in TRANSIENT_ERRNOS


def run_task(fn: Callable, args: tuple, kwargs: Mapping, threads: int | None,
             variant: str | None, pass_needed: bool, *needed: _Returned) -> _Returned:
    """Worker-side wrapper of a task: variant and Dr.Jit threads, then ``fn``, timed.

    A failed needed task makes this one fail without running. A transient error
    (:func:`is_transient`) propagates, so that Dask retries the task; any other exception
    becomes a returned one-line failure that is not retried (an unexpected one is marked
    as such and its traceback logged).
    """
    for dep in needed:
        if not dep.ok:
            return _Returned(False, error=f"not run: a task it needs failed ({dep.error})")
    t0 = time.perf_counter()
    try:
        from . import runtime
        if variant:
            runtime.set_variant(variant)
        from .threads import dr_threads
        with dr_threads(threads):
            passed = tuple(d.value for d in needed) if pass_needed else ()
            value = fn(*args, *passed, **dict(kwargs))
    except Exception as exc:
        if is_transient(exc):
            raise
        message = _one_line(exc)
        if not isinstance(exc, SonarsimError):
            log.error("task failed unexpectedly", exc_info=True)
            message = f"unexpected {message} (a bug; the worker log has the traceback)"
        return _Returned(False, error=message, wall_s=time.perf_counter() - t0)
    return _Returned(True, value=value, wall_s=time.perf_counter() - t0)


def check_tasks(tasks: Sequence[Task]) -> list[Task]:
    """The tasks in an order where every task comes after the tasks it needs (InputError
    for duplicate keys, unknown needs or cycles)."""
    by_key: dict[str, Task] = {}
    for t in tasks:
        if t.key in by_key:
            raise InputError(f"two tasks have the key '{t.key}'")
        by_key[t.key] = t
    order: list[Task] = []
    state: dict[str, int] = {}

    def visit(t: Task, path: tuple[str, ...]) -> None:
        if state.get(t.key) == 2:
            return
        if state.get(t.key) == 1:
            raise InputError(f"tasks need each other in a cycle: {' -> '.join(path + (t.key,))}")
        state[t.key] = 1
        for k in t.needs:
            if k not in by_key:
                raise InputError(f"task '{t.key}' needs unknown task '{k}'")
            visit(by_key[k], path + (t.key,))
        state[t.key] = 2
        order.append(t)

    for t in tasks:
        visit(t, ())
    return order


# ----------------------------------------------------------------------------- resources

def detect_gpus() -> list[str]:
    """Ids of the NVIDIA GPUs this process may use ([] when none or no driver).

    ``CUDA_VISIBLE_DEVICES`` is honoured when set; otherwise ``nvidia-smi -L`` is asked.
    """
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        ids = [v.strip() for v in visible.split(",") if v.strip()]
        return [] if ids in ([], ["-1"]) else ids
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return []
    try:
        out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, line in enumerate(l for l in out.splitlines() if l.startswith("GPU "))]


def total_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


@dataclass(frozen=True)
class ClusterPlan:
    """A local cluster: ``n_workers`` processes, each running one task at a time with
    ``threads`` Dr.Jit threads; ``gpus``: one device id per worker (cuda_ad_mono) or ()."""
    n_workers: int
    threads: int
    gpus: tuple[str, ...] = ()

    @property
    def variant(self) -> str | None:
        return "cuda_ad_mono" if self.gpus else None

    def describe(self) -> str:
        if self.gpus:
            return (f"{self.n_workers} worker(s), one per GPU ({', '.join(self.gpus)}), "
                    f"cuda_ad_mono")
        return (f"{self.n_workers} worker process(es) x {self.threads} Dr.Jit thread(s)")


def plan_local_cluster(n_tasks: int, *, cores: int | None = None, gpus: Sequence[str] = (),
                       workers: int | None = None, threads: int | None = None,
                       memory: int | None = None, variant: str | None = None) -> ClusterPlan:
    """How to divide this machine between Dask workers and Dr.Jit threads.

    With GPUs (and no explicit ``llvm`` variant): one worker per GPU. On the CPU: one worker
    (one task at a time) per :data:`THREADS_PER_WORKER` cores, at most one per task and one
    per 2 GiB of memory; the cores go to the workers' Dr.Jit threads. Measured on 2 cores
    (benchmarks/bench_batch.py): one worker with 2 threads did 4 000 small jobs/h, two
    workers with 1 thread each 2 400. ``workers`` and ``threads`` override the defaults.
    """
    from .threads import check_threads
    cores = max(1, cores or os.cpu_count() or 1)
    n_tasks = max(1, int(n_tasks))
    threads = check_threads(threads)
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers
                                or workers < 1):
        raise InputError(f"--workers must be a positive integer, got {workers}")
    use_gpus = tuple(gpus) if gpus and not (variant or "").startswith("llvm") else ()
    if use_gpus:
        n = workers or len(use_gpus)
        chosen = tuple(use_gpus[i % len(use_gpus)] for i in range(n))
        return ClusterPlan(n, threads or max(1, cores // n), chosen)
    if workers is None:
        cap = max(1, cores // THREADS_PER_WORKER)
        if memory:
            cap = min(cap, max(1, memory // MEMORY_PER_WORKER))
        workers = max(1, min(n_tasks, cap))
    elif workers > max_workers(cores, memory):
        cap = max_workers(cores, memory)
        warn(f"--workers {workers} is more than this machine can run at once ({cores} "
             f"core(s){', ' + str(memory // 2**30) + ' GiB' if memory else ''}); using {cap}")
        workers = cap
    return ClusterPlan(int(workers), int(threads or max(1, cores // workers)))


def max_workers(cores: int, memory: int | None = None) -> int:
    """The most local worker processes that make sense: one per core, and one per
    :data:`MEMORY_PER_WORKER` of memory."""
    cap = max(1, cores)
    if memory:
        cap = min(cap, max(1, memory // MEMORY_PER_WORKER))
    return cap


def warn(message: str) -> None:
    """A one-line warning of the engine (the CLI prints it as ``warning: ...``)."""
    import warnings
    warnings.warn(message, stacklevel=3)


def check_scheduler(scheduler: str | None) -> str | None:
    """A ``--scheduler`` value: None (local cluster), ``'sequential'``, or a Dask address
    ``[tcp|tls|ucx|inproc|ws|wss]://host:port`` or ``host:port`` (one-line InputError)."""
    import re
    if scheduler is None or scheduler == SEQUENTIAL:
        return scheduler
    if not isinstance(scheduler, str) or not re.match(
            r"^((tcp|tls|ucx|inproc|ws|wss)://)?[A-Za-z0-9_.\-\[\]:]+:[0-9]{1,5}$"
            r"|^(tcp|tls|ucx|inproc|ws|wss)://[A-Za-z0-9_.\-\[\]:/]+$", scheduler):
        raise InputError(f"--scheduler {scheduler!r}: expected 'sequential' or a Dask "
                         "scheduler address such as tcp://host:8786")
    return scheduler


# ----------------------------------------------------------------------------- engine

class Engine:
    """Where tasks run; a context manager that starts and stops a local cluster if needed.

    ``scheduler``: None (a local cluster), an address such as ``tcp://host:8786`` (an
    existing cluster), or ``'sequential'`` (this process, no Dask). ``client``: an existing
    ``distributed.Client`` to use instead (tests). ``workers``/``threads``: local cluster
    size (see :func:`plan_local_cluster`); ``threads`` also sets Dr.Jit's threads per task on
    an existing cluster (default: the worker's own setting). ``retries``: extra attempts of a
    task that failed unexpectedly. ``variant``: Mitsuba variant for every task (default: each
    worker's ``SONARSIM_VARIANT``, cuda_ad_mono on a local GPU cluster).
    """

    def __init__(self, scheduler: str | None = None, *, workers: int | None = None,
                 threads: int | None = None, retries: int = DEFAULT_RETRIES,
                 variant: str | None = None, client=None, dashboard: bool = True,
                 log=print):
        if int(retries) != retries or retries < 0:
            raise InputError(f"--retries must be an integer >= 0, got {retries}")
        from .threads import check_threads
        threads = check_threads(threads)
        scheduler = check_scheduler(scheduler) if client is None else scheduler
        self.scheduler, self.workers, self.threads = scheduler, workers, threads
        self.retries, self.variant, self.dashboard, self.log = int(retries), variant, dashboard, log
        self.client, self._own, self._own_client, self.plan = client, [], False, None
        self.task_threads = threads
        self.description = "existing client" if client is not None else ""

    @property
    def sequential(self) -> bool:
        return self.scheduler == SEQUENTIAL

    def __enter__(self) -> "Engine":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for obj in reversed(self._own):
            try:
                obj.close()
            except Exception:       # closing a cluster that lost its workers may complain
                pass
        self._own = []
        if self._own_client:
            self.client, self._own_client = None, False

    def start(self, n_tasks: int) -> None:
        """Start (or connect to) the cluster for ``n_tasks`` tasks and say where they run."""
        if self.client is not None or self.sequential:
            if self.sequential:
                self.description = "this process, one task after the other"
            return
        Client = _distributed().Client
        if self.scheduler:
            try:
                self.client = Client(self.scheduler, timeout="20s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise InputError(f"cannot connect to the Dask scheduler at {self.scheduler} "
                                 f"({_one_line(exc)})") from None
            self._own.append(self.client)
            self._own_client = True
            n = len(self.client.scheduler_info().get("workers", {}))
            self.description = f"Dask scheduler {self.scheduler} ({n} worker(s) now)"
            self._check_versions()
        else:
            self.plan = plan_local_cluster(n_tasks, gpus=detect_gpus(), workers=self.workers,
                                           threads=self.threads, memory=total_memory(),
                                           variant=self.variant)
            cluster = self._local_cluster(self.plan)
            self._own.append(cluster)
            self.client = Client(cluster)
            self._own.append(self.client)
            self._own_client = True
            self.task_threads = self.threads or self.plan.threads
            if self.plan.variant and not self.variant:
                self.variant = self.plan.variant
            self.description = f"local cluster: {self.plan.describe()}"
        self.log(f"batch: running on {self.description}")
        self.log(f"batch: dashboard {self.dashboard_address()}")

    def dashboard_address(self) -> str:
        import importlib.util
        if self.client is None:
            return "none"
        if self.scheduler is None and importlib.util.find_spec("bokeh") is None:
            return "not available (the dashboard needs bokeh: pip install 'bokeh>=3.1')"
        return self.client.dashboard_link

    def _local_cluster(self, plan: ClusterPlan):
        import importlib.util
        import dask
        from distributed import LocalCluster
        with_dashboard = self.dashboard and importlib.util.find_spec("bokeh") is not None
        address = ":8787" if with_dashboard else None
        memory = total_memory()
        limit = max(MEMORY_PER_WORKER, memory // plan.n_workers) if memory else "auto"
        if os.environ.get("MALLOC_TRIM_THRESHOLD_") == DASK_MALLOC_TRIM:
            del os.environ["MALLOC_TRIM_THRESHOLD_"]    # left here by an earlier Dask cluster
        # The nannies copy this into this process's environment before each spawn (also of a
        # restarted worker); a variable already in the environment wins over the config, so
        # it is set here too.
        environment = worker_environment(plan)
        dask.config.set({"distributed.nanny.pre-spawn-environ": environment})
        os.environ.update(environment)
        if not plan.gpus:
            return LocalCluster(n_workers=plan.n_workers, threads_per_worker=1, processes=True,
                                dashboard_address=address, memory_limit=limit,
                                silence_logs=logging.CRITICAL)
        from distributed import Scheduler, SpecCluster
        return SpecCluster(scheduler={"cls": Scheduler, "options": {
                               "dashboard_address": address}},
                           workers=gpu_worker_specs(plan, limit), silence_logs=logging.CRITICAL)

    def _check_versions(self) -> None:
        from . import __version__
        try:
            seen = self.client.run(_sonarsim_version)
        except Exception as exc:
            self.log(f"batch: warning: cannot ask the workers for their sonarsim version "
                     f"({_one_line(exc)})")
            return
        other = sorted({v for v in seen.values() if v != __version__})
        if other:
            self.log(f"batch: warning: workers run sonarsim {', '.join(other)}, this is "
                     f"{__version__}")

    # ---- running
    def run(self, tasks: Sequence[Task], *, progress: bool = True,
            on_job: Callable[[str, dict[str, Outcome]], None] | None = None
            ) -> dict[str, Outcome]:
        """Run ``tasks`` (see :class:`Task`); returns {key: Outcome}. ``on_job(job, outcomes)``
        is called in this process as each job's last task finishes."""
        from .progress import progress_bar
        ordered = check_tasks(tasks)
        if not ordered:
            return {}
        self.start(len(ordered))
        jobs: dict[str, list[str]] = {}
        for t in ordered:
            jobs.setdefault(t.job_name, []).append(t.key)
        outcomes: dict[str, Outcome] = {}
        bar = progress_bar(len(jobs), progress, unit="job", desc="batch")
        pending = {job: set(keys) for job, keys in jobs.items()}

        def finished(outcome: Outcome, task: Task) -> None:
            outcomes[outcome.key] = outcome
            left = pending[task.job_name]
            left.discard(outcome.key)
            if not left:
                bar.update(1)
                if on_job is not None:
                    on_job(task.job_name, {k: outcomes[k] for k in jobs[task.job_name]})

        try:
            if self.sequential:
                self._run_here(ordered, finished)
            else:
                self._run_dask(ordered, finished)
        finally:
            bar.close()
        return outcomes

    def _run_here(self, ordered: list[Task], finished) -> None:
        results: dict[str, _Returned] = {}
        for t in ordered:
            needed = [results[k] for k in t.needs]
            for attempt in range(self.retries + 1):
                try:
                    got = run_task(t.fn, t.args, t.kwargs, self.task_threads, self.variant,
                                   t.pass_needed, *needed)
                    break
                except Exception as exc:       # transient (is_transient): retried
                    got = _Returned(False, error=_one_line(exc))
            results[t.key] = got
            finished(_outcome(t.key, got), t)

    def _run_dask(self, ordered: list[Task], finished) -> None:
        from distributed import as_completed
        client = self.client
        token = uuid.uuid4().hex[:8]
        futures, by_future = {}, {}
        for t in ordered:
            fut = client.submit(run_task, t.fn, t.args, dict(t.kwargs), self.task_threads,
                                self.variant, t.pass_needed, *[futures[k] for k in t.needs],
                                key=f"{_key_prefix(t.key)}-{token}", retries=self.retries,
                                pure=False)
            futures[t.key] = fut
            by_future[fut.key] = t
        tasks_by_key = {t.key: t for t in ordered}
        try:
            for fut in as_completed(list(futures.values())):
                t = by_future[fut.key]
                if fut.status == "finished":
                    outcome = _outcome(t.key, fut.result())
                else:
                    failed_need = next((k for k in t.needs if futures[k].status == "error"),
                                       None)
                    error = (f"not run: task '{failed_need}' it needs failed" if failed_need
                             else _one_line(fut.exception()))
                    outcome = Outcome(t.key, "failed", error=error)
                finished(outcome, tasks_by_key[t.key])
        except BaseException:
            client.cancel(list(futures.values()))
            raise


def _distributed():
    """The ``distributed`` module (InputError in one line when dask is not installed)."""
    try:
        import distributed
    except ModuleNotFoundError:
        raise InputError("running jobs on a Dask cluster needs dask.distributed: pip install "
                         "'sonarsim[batch]' (or run them here: --scheduler sequential)") from None
    return distributed


def _key_prefix(key: str) -> str:
    """A Dask key without characters Dask treats specially."""
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in key)


def _outcome(key: str, got: _Returned) -> Outcome:
    return Outcome(key, "done" if got.ok else "failed", result=got.value, error=got.error,
                   wall_s=got.wall_s)


def _sonarsim_version() -> str:
    from . import __version__
    return __version__


def worker_environment(plan: ClusterPlan) -> dict:
    """The environment Dask's nannies set before starting a local worker process.

    Dask's default (``distributed.nanny.pre-spawn-environ``) sets
    ``MALLOC_TRIM_THRESHOLD_=65536`` and one OpenMP/MKL/OpenBLAS thread; measured on 2 cores,
    a small simulation then took about 1.7x as long in a worker as in the submitting process
    (median 1.0 s against 0.6 s), and as long as there without it. So: glibc's default
    malloc, and the worker's share of the cores for the BLAS/OpenMP libraries.
    """
    n = str(max(1, plan.threads))
    return {"OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n}


def gpu_worker_specs(plan: ClusterPlan, memory_limit) -> dict:
    """``SpecCluster`` worker specs: one Nanny per GPU of ``plan``, each seeing only its GPU
    (``CUDA_VISIBLE_DEVICES``) and running the cuda_ad_mono variant."""
    from distributed import Nanny
    return {f"gpu-{i}-{gpu}": {"cls": Nanny, "options": {
                "nthreads": 1, "memory_limit": memory_limit,
                "env": {"CUDA_VISIBLE_DEVICES": gpu, "SONARSIM_VARIANT": "cuda_ad_mono"}}}
            for i, gpu in enumerate(plan.gpus)}
