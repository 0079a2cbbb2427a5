"""``DIR/batch.csv``: one row per job (status, outputs, wall time, measured fidelity,
parameters, reconstruction metrics), rewritten atomically as jobs finish."""
from __future__ import annotations

import csv
import io
import json
import math
import time
from pathlib import Path
from typing import Any

from .identity import identity_params

CSV_NAME = "batch.csv"


def param_columns(jobs) -> list[str]:
    """The parameter columns of ``jobs``: the usual ones first, then the others sorted."""
    first = ["scene", "mesh", "fit", "ground", "poses", "pulse", "fs", "snr_db", "seed",
             "paths_per_pose", "bounces"]
    keys = {k for j in jobs for k in identity_params(j.params)}
    return [k for k in first if k in keys] + sorted(keys - set(first))


def _cell(value) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value)
    return value


def read_previous_csv(path: Path) -> dict[str, dict]:
    """Rows of an earlier batch.csv by job id (to keep the wall times of skipped jobs); {}
    for a missing, unreadable or corrupt file (the table is rebuilt from the outputs)."""
    try:
        with open(path, newline="", encoding="utf-8", errors="strict") as fh:
            return {r.get("job_id") or "": r for r in csv.DictReader(fh)}
    except (OSError, csv.Error, UnicodeDecodeError, ValueError):
        return {}


class BatchTable:
    """The rows of DIR/batch.csv, rewritten atomically as jobs finish."""

    def __init__(self, plan, log=print):
        self.plan, self.path, self.log = plan, plan.out / CSV_NAME, log
        self.failed_write = ""
        self.previous = read_previous_csv(self.path)
        self.rows: dict[str, dict] = {}
        self.fidelity_keys: list[str] = []
        self.metric_keys: list[str] = []
        self.last_write = 0.0
        self.columns = param_columns(plan.jobs)
        for job in plan.jobs:
            row = {"job": job.name, "status": "pending", "output": job.output, "wall_s": None,
                   "error": "", "job_id": job.job_id,
                   **{("param", k): job.params.get(k) for k in self.columns}}
            for step in job.recon:
                row[f"{step.label}_output"] = step.output
            self.rows[job.name] = row

    def update(self, job, status: str, sim: dict | None, sim_wall, steps: dict,
               error: str = "") -> None:
        row = self.rows[job.name]
        old = self.previous.get(job.job_id, {})
        row["status"], row["error"] = status, error
        row["wall_s"] = sim_wall if sim_wall is not None else (old.get("wall_s") or None)
        if sim_wall is None:    # not simulated by this run: keep what the run that did measured
            if old.get("notes"):
                row["notes"] = old["notes"]
            if old.get("cpu_s") and "cpu_s" not in (sim or {}):
                sim = {**(sim or {}), "cpu_s": float(old["cpu_s"])}
        for key, value in (sim or {}).items():
            if key == "notes":
                row["notes"] = value
            elif key != "ran":
                row[key] = value
                if key not in self.fidelity_keys:
                    self.fidelity_keys.append(key)
                    self.fidelity_keys.sort(key=lambda k: (k != "mc_snr_db", k))
        for label, (step_status, metrics, wall) in steps.items():
            row[f"{label}_status"] = step_status
            row[f"{label}_wall_s"] = wall if wall is not None else (
                old.get(f"{label}_wall_s") or None)
            for key, value in (metrics or {}).items():
                if key == "ran":
                    continue
                col = f"{label}_{key}"
                row[col] = value
                if col not in self.metric_keys:
                    self.metric_keys.append(col)

    def text(self) -> str:
        """The CSV text of the table now."""
        columns = ["job", "status", "output", "wall_s"] + self.fidelity_keys + ["error",
                                                                                "notes"]
        # a setting named like a measured value (mc_snr_db: the target) gets its own column
        header = {("param", k): (f"{k}_requested" if k in self.fidelity_keys else k)
                  for k in self.columns}
        columns += list(header) + ["job_id"]
        known = set(columns) | set(self.metric_keys)
        extra: dict[str, None] = {}
        for row in self.rows.values():
            for k in row:
                if k not in known:
                    extra.setdefault(k)
        columns += sorted(extra) + self.metric_keys
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([header.get(k, k) for k in columns])
        for row in self.rows.values():
            w.writerow([_cell(row.get(k)) for k in columns])
        return buf.getvalue()

    def write(self, force: bool = False, final: bool = False) -> None:
        """Rewrite the file (at most once a second unless ``force``). A write that fails (a
        full disk) is reported once and tried again later; only the ``final`` one raises
        (:class:`~sonarsim.errors.WriteError`, one line), so the jobs run on meanwhile."""
        if not force and time.monotonic() - self.last_write < 1.0:
            return
        from ..atomic import atomic_path
        from ..errors import WriteError
        text = self.text()
        self.last_write = time.monotonic()
        try:
            with atomic_path(self.path, size=len(text.encode())) as tmp:
                tmp.write_text(text)
        except WriteError as exc:
            if final:
                raise
            if str(exc) != self.failed_write:
                self.log(f"batch: warning: {exc}; the jobs go on, the table is written again "
                         "later")
                self.failed_write = str(exc)
            return
        self.failed_write = ""
