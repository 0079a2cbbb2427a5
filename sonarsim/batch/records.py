"""What a batch finds on disk: whether a job's dataset or a step's volume is complete and
its own (by the ids stored in the files), and the figures recorded in ``batch.csv``."""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import SonarsimError

SUMMARY_METRICS = ("iou", "best_iou", "chamfer_sq", "best_chamfer_sq", "chamfer_m",
                   "normal_consistency", "psnr_depth", "ssim_depth")


def summary_metrics(result: dict) -> dict:
    """The metrics of an evaluation that go into ``batch.csv``."""
    return {k: result[k] for k in SUMMARY_METRICS if k in result}


def fidelity(fields_: dict) -> dict:
    """Measured-fidelity values of a dataset (``mc_snr_db`` and any other ``*_snr_db``
    attribute or meta key but the declared ``snr_db``), as floats."""
    out = {}
    for source in (fields_, fields_.get("meta") or {}):
        for key, value in source.items():
            if key.endswith("snr_db") and key != "snr_db" and isinstance(value, (int, float)) \
                    and not isinstance(value, bool):
                out[key] = float(value)
    return out


def dataset_record(path: str | Path, job_id: str) -> dict | None:
    """The fidelity of ``path`` if it is a complete dataset of job ``job_id``, else None."""
    from ..dataset import KIND_DATASET, inspect
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with inspect(path) as (kind, fields_):
            if kind != KIND_DATASET or not fields_.get("complete", False):
                return None
            if (fields_.get("meta") or {}).get("batch_job_id") != job_id:
                return None
            return fidelity(fields_)
    except (SonarsimError, OSError):
        return None


def step_record(step) -> dict | None:
    """The summary metrics of a finished reconstruction step (its volume and each of its
    evaluations carry its id; an evaluation's metrics are prefixed with its name), else
    None."""
    from ..dataset import KIND_VOLUME, inspect
    path = Path(step.output)
    if not path.is_file():
        return None
    try:
        with inspect(path) as (kind, fields_):
            if kind != KIND_VOLUME or (fields_.get("params") or {}).get(
                    "batch_step_id") != step.step_id:
                return None
    except (SonarsimError, OSError):
        return None
    out: dict = {}
    for evaluation in step.evaluations:
        try:
            saved = json.loads(Path(evaluation.output).read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(saved, dict) or saved.get("batch_step_id") != step.step_id:
            return None
        prefix = f"{evaluation.name}_" if evaluation.name else ""
        out.update({prefix + k: v for k, v in summary_metrics(saved.get("metrics", {})).items()})
    return out


def existing_owner(path: str | Path, kind: str, ident: str) -> str | None:
    """None if ``path`` does not exist or is the output of the job or step ``ident``
    (``kind``: 'dataset', 'volume' or 'metrics'); else what it is, for a message."""
    from ..dataset import KIND_NAMES, inspect
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return None
    if path.is_dir():
        return "a directory"
    if kind == "metrics":
        try:
            saved = json.loads(path.read_text())
        except (OSError, ValueError):
            return "not a batch metrics file"
        if isinstance(saved, dict) and saved.get("batch_step_id") == ident:
            return None
        return "the metrics of another reconstruction"
    key = {"dataset": ("meta", "batch_job_id"), "volume": ("params", "batch_step_id")}[kind]
    try:
        with inspect(path, allow_partial=True) as (found, fields_):
            mine = (fields_.get(key[0]) or {}).get(key[1])
            complete = fields_.get("complete", True)
            name = KIND_NAMES.get(found, found)
    except (SonarsimError, OSError):
        return "not a readable sonarsim file"
    if mine == ident and complete:
        return None
    if not complete:
        return f"an incomplete {name}"
    if mine is not None:
        return f"a {name} of another batch {'job' if kind == 'dataset' else 'step'} " \
               "(other settings)"
    return f"a {name} not made by this batch"
