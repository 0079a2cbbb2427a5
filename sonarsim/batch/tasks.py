"""The functions a batch's workers run: one simulation, one reconstruction step."""
from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

from ..errors import FormatError, SonarsimError
from .identity import job_meta
from .locks import locked
from .plan import Job, ReconStep, build_simulation, recon_plugin
from .records import dataset_record, step_record


def _discard_stale_partials(job: Job) -> None:
    """Delete unfinished files of this output name left by a job with other parameters
    (a partial of this very job is kept: the simulation resumes it)."""
    from ..dataset import PARTIAL_SUFFIX, inspect
    from ..simulate import scratch_path
    out = Path(job.output)
    for partial in (Path(str(out) + PARTIAL_SUFFIX), Path(str(scratch_path(out)) + PARTIAL_SUFFIX)):
        if not partial.exists():
            continue
        try:
            with inspect(partial, allow_partial=True) as (_, fields_):
                ours = (fields_.get("meta") or {}).get("batch_job_id") == job.job_id
        except (SonarsimError, OSError):
            ours = False            # unreadable: the writer starts it again anyway
        if not ours:
            partial.unlink(missing_ok=True)


def run_simulation(job: Job) -> dict:
    """Worker side: simulate ``job`` unless its complete output exists; returns
    {'ran': bool, **fidelity}, with ``cpu_s`` (this process's CPU time, user + system of all
    its threads, during the simulation; batch.csv's column) when it ran. The scene, poses and
    pulse must be what was validated."""
    from ..simulate import simulate
    done = dataset_record(job.output, job.job_id)
    if done is not None:
        return {"ran": False, **done}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # reported once when the batch was planned
        spec, poses, settings, digests = build_simulation(job.params)
    changed = [k for k in digests if digests[k] != job.digests.get(k)]
    if changed:
        raise FormatError(f"job '{job.name}': the {', '.join(changed)} changed since the batch "
                          "was validated; run the batch again")
    settings.extra_meta = {**settings.extra_meta, **job_meta(job)}
    notes: list[str] = []
    if hasattr(settings, "log"):            # the simulator's one-line notices go to batch.csv
        settings.log = notes.append
    if not Path(job.output).parent.is_dir():
        raise FormatError(f"{Path(job.output).parent}: output directory not found on this "
                          "worker (the batch needs a file system shared with the workers)")
    c0 = time.process_time()
    with locked(job.output):
        if dataset_record(job.output, job.job_id) is None:   # not finished meanwhile
            _discard_stale_partials(job)
            simulate(spec, poses, job.output, settings, resume=True, progress=False)
    cpu_s = time.process_time() - c0
    record = dataset_record(job.output, job.job_id)
    if record is None:
        raise FormatError(f"{job.output}: not a complete dataset of job '{job.name}' after "
                          "the simulation")
    return {"ran": True, **record, "cpu_s": cpu_s,
            **({"notes": " | ".join(notes)} if notes else {})}


def run_reconstruction(job: Job, step: ReconStep, _needed: Any = None) -> dict:
    """Worker side: reconstruct (and evaluate) ``job``'s dataset unless done; returns
    {'ran': bool, **summary metrics}."""
    done = step_record(step)
    if done is not None:
        return {"ran": False, **done}
    plugin = recon_plugin(f"job '{job.name}'")
    with locked(step.output):
        return plugin.reconstruct(job, step)
