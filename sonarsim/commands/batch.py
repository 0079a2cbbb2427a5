"""``sonarsim batch MANIFEST --out DIR``: many simulations on dask.distributed.

Expands and validates the whole manifest first with the commands' own rules (nothing runs
if a job is bad, two jobs would write one file, or a file in DIR is not the result of the
job that would write it), skips jobs whose complete output exists, runs the others on a
local cluster (default), an existing Dask scheduler (``--scheduler tcp://host:8786``) or
this process (``--scheduler sequential``), and records every job in ``DIR/batch.csv``.
See docs/batch.md.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

HELP = "Run a manifest of many simulations (sweeps, mesh sets) on dask.distributed."
OUTPUTS = ()    # --out is a directory; each job locks its own outputs, run_batch locks DIR

log = logging.getLogger("sonarsim.batch")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..batch import MAX_JOBS
    from ..batch_engine import DEFAULT_RETRIES
    parser.add_argument("manifest", type=Path, metavar="MANIFEST.toml",
                        help="batch manifest (docs/batch.md)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="output directory (created; on a cluster it must be on a file "
                             "system the workers share)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="Dask scheduler to submit to, e.g. tcp://host:8786 (default: a "
                             "local cluster); 'sequential' runs the jobs in this process")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="local cluster: worker processes (default: one per 2 cores, at most "
                             "one per job, 2 GiB of memory each; one per GPU when GPUs exist; "
                             "more than the cores are reduced to the cores, with a warning)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="Dr.Jit threads per worker (default: the cores divided among the "
                             "local workers; on an existing cluster the worker's own setting)")
    parser.add_argument("--retries", type=int, default=DEFAULT_RETRIES, metavar="N",
                        help=f"extra attempts of a job that fails for a reason that may pass "
                             f"(a busy output, a lost connection, memory; default "
                             f"{DEFAULT_RETRIES}); bad input and bugs are not retried")
    parser.add_argument("--max-jobs", type=int, default=MAX_JOBS, metavar="N",
                        help=f"refuse a manifest that expands to more jobs (default {MAX_JOBS}; "
                             "a guard against a typo in a sweep)")
    parser.add_argument("--force", action="store_true",
                        help="replace files in DIR that are not the result of the job that "
                             "writes them (otherwise refused before anything runs)")
    parser.add_argument("--dry-run", action="store_true",
                        help="validate the manifest and list the jobs; run nothing")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _log(message: str) -> None:
    """The library's ``batch: ...`` lines through the ``sonarsim.batch`` logger (the CLI
    prefixes ``sonarsim batch:``; ``--quiet`` keeps only the warnings)."""
    text = message.removeprefix("batch: ")
    if text.startswith("warning: "):
        log.warning("%s", text.removeprefix("warning: "))
    else:
        log.info("%s", text)


def run(args: argparse.Namespace) -> int:
    from ..batch import job_state, plan_batch, run_batch
    from ..batch_engine import Engine, check_scheduler
    from ..errors import InputError
    from ..threads import check_threads
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    check_threads(args.threads)
    check_scheduler(args.scheduler)
    if args.max_jobs < 1:
        raise InputError(f"--max-jobs must be >= 1, got {args.max_jobs}")
    if args.scheduler and args.scheduler != "sequential" and (args.workers or False):
        raise InputError("--workers sizes a local cluster; it contradicts --scheduler")
    plan = plan_batch(args.manifest, args.out, log=_log, max_jobs=args.max_jobs,
                      force=args.force)
    for note in plan.warnings:
        log.warning("%s", note)
    if args.dry_run:
        for job in plan.jobs:
            state = "complete" if job_state(job).complete else "to run"
            steps = "".join(f" + {s.label}" for s in job.recon)
            print(f"{job.name}{steps}  [{state}]  {job.where}")
        log.info("%d job(s) valid; nothing run (--dry-run)", len(plan.jobs))
        return 0
    with Engine(args.scheduler, workers=args.workers, threads=args.threads,
                retries=args.retries, variant=getattr(args, "variant", None), log=_log) as engine:
        result = run_batch(plan, engine, progress=not args.no_progress, log=_log)
    counts = {s: list(result.status.values()).count(s)
              for s in ("done", "skipped", "failed", "not run")}
    print(f"batch: {counts['done']} done, {counts['skipped']} skipped (complete before), "
          f"{counts['failed'] + counts['not run']} failed; {result.csv}")
    for name in result.failed:
        log.warning("FAILED %s: %s", name, result.errors.get(name, ""))
    return 1 if result.failed else 0
