"""Running a planned batch on an engine and recording every job in ``batch.csv``."""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .plan import Job, Plan
from .records import dataset_record, step_record
from .table import CSV_NAME, BatchTable
from .tasks import run_reconstruction, run_simulation

NOT_RUN = "not run"     # the status of a job a stopped batch never finished


@dataclass
class BatchResult:
    """Per job: 'done' (ran now), 'skipped' (complete before), 'failed' or 'not run' (the
    batch stopped first), and errors."""
    status: dict[str, str]
    errors: dict[str, str]
    csv: Path
    submitted: int

    @property
    def failed(self) -> list[str]:
        return [n for n, s in self.status.items() if s in ("failed", NOT_RUN)]


@dataclass
class JobState:
    """What is on disk for a job before the batch runs: its dataset's record (None: to
    simulate) and each step's record (None: to reconstruct)."""
    sim: dict | None
    steps: dict[str, dict | None]

    @property
    def complete(self) -> bool:
        return self.sim is not None and all(r is not None for r in self.steps.values())


def job_state(job: Job) -> JobState:
    sim = dataset_record(job.output, job.job_id)
    return JobState(sim, {s.label: (step_record(s) if sim is not None else None)
                          for s in job.recon})


def run_batch(plan: Plan, engine, *, progress: bool = True,
              log: Callable[[str], None] = print) -> BatchResult:
    """Run every job of ``plan`` that is not complete yet on ``engine`` (a
    :class:`sonarsim.batch_engine.Engine`); record every job in ``DIR/batch.csv``.

    The directory's lock is taken before the engine starts, so a concurrent batch on the
    same ``DIR`` is refused before it starts a cluster; an engine that cannot start leaves
    no new directory behind.
    """
    from ..outputs import output_lock
    created = not plan.out.exists()
    try:
        plan.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from ..atomic import write_error
        raise write_error(plan.out, exc) from None
    try:
        with output_lock(plan.out / CSV_NAME):      # one batch per DIR at a time
            states = {j.name: job_state(j) for j in plan.jobs}
            if not all(s.complete for s in states.values()):
                engine.start(sum(not s.complete for s in states.values()))
            created = False
            return _run_batch(plan, engine, states, progress, log)
    finally:
        if created:                                 # nothing ran: leave no empty DIR
            with contextlib.suppress(OSError):
                plan.out.rmdir()


def _run_batch(plan: Plan, engine, states: dict[str, JobState], progress: bool,
               log: Callable[[str], None]) -> BatchResult:
    from ..batch_engine import Task
    table = BatchTable(plan, log=log)
    tasks: list[Task] = []
    status: dict[str, str] = {}
    errors: dict[str, str] = {}
    by_name = {j.name: j for j in plan.jobs}
    for job in plan.jobs:
        state = states[job.name]
        sim_key = f"simulate/{job.name}"
        if state.sim is None:
            tasks.append(Task(sim_key, run_simulation, (job,), job=job.name))
        steps_done = {}
        for step in job.recon:
            rec = state.steps[step.label]
            if rec is None:
                tasks.append(Task(f"reconstruct/{job.name}/{step.label}", run_reconstruction,
                                  (job, step), needs=(sim_key,) if state.sim is None else (),
                                  job=job.name))
            else:
                steps_done[step.label] = ("skipped", rec, None)
        if state.complete:
            status[job.name] = "skipped"
            table.update(job, "skipped", state.sim, None, steps_done)
    n_todo = len({t.job for t in tasks})
    log(f"batch: {len(plan.jobs)} job(s): {len(status)} complete already, {n_todo} to run; "
        f"outputs in {plan.out}")

    def on_job(name: str, outcomes: dict) -> None:
        job = by_name[name]
        sim_out = outcomes.get(f"simulate/{name}")
        sim = sim_out.result if sim_out is not None and sim_out.ok else None
        if sim_out is None:
            sim = states[name].sim
        steps = {}
        errs = [f"simulate: {sim_out.error}"] if sim_out is not None and not sim_out.ok else []
        ran = bool(sim_out is not None and sim_out.ok and sim_out.result.get("ran"))
        for step in job.recon:
            o = outcomes.get(f"reconstruct/{name}/{step.label}")
            if o is None:
                steps[step.label] = ("skipped", states[name].steps[step.label], None)
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
            for job in plan.jobs:            # stopped early (interrupt, lost scheduler)
                if job.name not in status:
                    status[job.name] = NOT_RUN
                    errors[job.name] = "the batch stopped before this job finished"
                    table.update(job, NOT_RUN, None, None, {}, errors[job.name])
            table.write(force=True, final=True)
    return BatchResult(status=status, errors=errors, csv=table.path,
                       submitted=len(tasks))
