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
    """The summary metrics of a finished reconstruction step (its volume, and its
    evaluation if asked for, carry its id), else None."""
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
    if step.evaluate is None:
        return {}
    try:
        saved = json.loads(Path(step.eval_output).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or saved.get("batch_step_id") != step.step_id:
        return None
    return summary_metrics(saved.get("metrics", {}))
