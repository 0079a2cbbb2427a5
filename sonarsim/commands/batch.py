"""``sonarsim batch MANIFEST --out DIR``: many simulations on dask.distributed.

Expands and validates the whole manifest first (nothing runs if a job is bad), skips jobs
whose complete output exists, runs the others on a local cluster (default), an existing
Dask scheduler (``--scheduler tcp://host:8786``) or this process (``--scheduler
sequential``), and records every job in ``DIR/batch.csv``. See docs/batch.md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "Run a manifest of many simulations (sweeps, mesh sets) on dask.distributed."
OUTPUTS = ()    # --out is a directory; each job locks its own outputs, run_batch locks DIR


def add_arguments(parser: argparse.ArgumentParser) -> None:
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
                             "one per job, 2 GiB of memory each; one per GPU when GPUs exist)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="Dr.Jit threads per worker (default: the cores divided among the "
                             "local workers; on an existing cluster the worker's own setting)")
    parser.add_argument("--retries", type=int, default=DEFAULT_RETRIES, metavar="N",
                        help=f"extra attempts of a job that fails unexpectedly (default "
                             f"{DEFAULT_RETRIES}; bad input such as a missing mesh is not "
                             "retried)")
    parser.add_argument("--dry-run", action="store_true",
                        help="validate the manifest and list the jobs; run nothing")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from ..batch import dataset_record, plan_batch, run_batch
    from ..batch_engine import Engine
    from ..errors import InputError
    for name in ("workers", "threads"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise InputError(f"--{name} must be >= 1, got {value}")
    if args.scheduler and args.scheduler != "sequential" and (args.workers or False):
        raise InputError("--workers sizes a local cluster; it contradicts --scheduler")
    plan = plan_batch(args.manifest, args.out, log=_log)
    for note in plan.warnings:
        _log(f"batch: warning: {note}")
    if args.dry_run:
        for job in plan.jobs:
            state = "complete" if dataset_record(job.output, job.job_id) is not None else "to run"
            steps = "".join(f" + {s.label}" for s in job.recon)
            print(f"{job.name}{steps}  [{state}]  {job.where}")
        _log(f"batch: {len(plan.jobs)} job(s) valid; nothing run (--dry-run)")
        return 0
    with Engine(args.scheduler, workers=args.workers, threads=args.threads,
                retries=args.retries, variant=getattr(args, "variant", None), log=_log) as engine:
        result = run_batch(plan, engine, progress=not args.no_progress, log=_log)
    counts = {s: list(result.status.values()).count(s) for s in ("done", "skipped", "failed")}
    _log(f"batch: {counts['done']} done, {counts['skipped']} skipped (complete before), "
         f"{counts['failed']} failed; {result.csv}")
    for name in result.failed:
        _log(f"batch: FAILED {name}: {result.errors.get(name, '')}")
    return 1 if result.failed else 0
