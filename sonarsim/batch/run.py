"""Running a planned batch on an engine and recording every job in ``batch.csv``."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .plan import Plan
from .records import dataset_record, step_record
from .table import CSV_NAME, BatchTable
from .tasks import run_reconstruction, run_simulation


@dataclass
class BatchResult:
    """Per job: 'done' (ran now), 'skipped' (complete before) or 'failed', and errors."""
    status: dict[str, str]
    errors: dict[str, str]
    csv: Path
    submitted: int

    @property
    def failed(self) -> list[str]:
        return [n for n, s in self.status.items() if s == "failed"]


def run_batch(plan: Plan, engine, *, progress: bool = True,
              log: Callable[[str], None] = print) -> BatchResult:
    """Run every job of ``plan`` that is not complete yet on ``engine`` (a
    :class:`sonarsim.batch_engine.Engine`); record every job in ``DIR/batch.csv``."""
    from ..outputs import output_lock
    todo = [j for j in plan.jobs if dataset_record(j.output, j.job_id) is None
            or any(step_record(s) is None for s in j.recon)]
    if todo:
        engine.start(len(todo))                  # a scheduler that cannot be reached: no DIR
    plan.out.mkdir(parents=True, exist_ok=True)
    with output_lock(plan.out / CSV_NAME):      # one batch per DIR at a time
        return _run_batch(plan, engine, progress, log)


def _run_batch(plan: Plan, engine, progress: bool, log: Callable[[str], None]) -> BatchResult:
    from ..batch_engine import Task
    table = BatchTable(plan)
    tasks: list[Task] = []
    status: dict[str, str] = {}
    errors: dict[str, str] = {}
    by_name = {j.name: j for j in plan.jobs}
    for job in plan.jobs:
        sim = dataset_record(job.output, job.job_id)
        sim_key = f"simulate/{job.name}"
        if sim is None:
            tasks.append(Task(sim_key, run_simulation, (job,), job=job.name))
        steps_done = {}
        for step in job.recon:
            rec = step_record(step) if sim is not None else None
            if rec is None:
                tasks.append(Task(f"reconstruct/{job.name}/{step.label}", run_reconstruction,
                                  (job, step), needs=(sim_key,) if sim is None else (),
                                  job=job.name))
            else:
                steps_done[step.label] = ("skipped", rec, None)
        if sim is not None and len(steps_done) == len(job.recon):
            status[job.name] = "skipped"
            table.update(job, "skipped", sim, None, steps_done)
    n_todo = len({t.job for t in tasks})
    log(f"batch: {len(plan.jobs)} job(s): {len(status)} complete already, {n_todo} to run; "
        f"outputs in {plan.out}")

    def on_job(name: str, outcomes: dict) -> None:
        job = by_name[name]
        sim_out = outcomes.get(f"simulate/{name}")
        sim = sim_out.result if sim_out is not None and sim_out.ok else None
        if sim_out is None:
            sim = dataset_record(job.output, job.job_id)
        steps = {}
        errs = [f"simulate: {sim_out.error}"] if sim_out is not None and not sim_out.ok else []
        ran = bool(sim_out is not None and sim_out.ok and sim_out.result.get("ran"))
        for step in job.recon:
            o = outcomes.get(f"reconstruct/{name}/{step.label}")
            if o is None:
                steps[step.label] = ("skipped", step_record(step), None)
            elif o.ok:
                ran |= bool(o.result.get("ran"))
                steps[step.label] = ("done" if o.result.get("ran") else "skipped", o.result,
                                     o.wall_s if o.result.get("ran") else None)
            else:
                steps[step.label] = ("failed", None, o.wall_s)
                if not (sim_out is not None and not sim_out.ok):
                    errs.append(f"{step.label}: {o.error}")
        state = "failed" if errs else ("done" if ran else "skipped")
        sim_wall = sim_out.wall_s if sim_out is not None and sim_out.ok and \
            sim_out.result.get("ran") else None
        status[name] = state
        if errs:
            errors[name] = "; ".join(errs)
        table.update(job, state, sim, sim_wall, steps, errors.get(name, ""))
        table.write()

    table.write(force=True)
    if tasks:
        try:
            engine.run(tasks, progress=progress, on_job=on_job)
        finally:
            table.write(force=True)
    return BatchResult(status=status, errors=errors, csv=table.path,
                       submitted=len(tasks))
