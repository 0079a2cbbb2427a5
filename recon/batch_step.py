"""The reconstruction (and evaluation) step of ``sonarsim batch`` jobs.

sonarsim never imports recon; recon plugs this module into the batch engine through the
entry point ``sonarsim.batch_steps: reconstruct`` (pyproject.toml), so a batch job can be
followed by ``recon.<method>.solve`` and ``recon evaluate``'s metrics.
"""
from __future__ import annotations

import importlib
import json
from pathlib import Path

from sonarsim.atomic import atomic_path
from sonarsim.batch import summary_metrics
from sonarsim.dataset import SonarDataset
from sonarsim.errors import InputError

from .evaluation import evaluate_file, json_safe
from .grid import Grid
from .metrics import load_gt_mesh

METHOD_MODULES = {"backproject": "recon.backprojection", "bp": "recon.backprojection",
                  "gd": "recon.gradient_descent", "pfa": "recon.pfa", "nbp": "recon.nbp"}


def solver(method: str, where: str):
    """(module name, solve function) of a step's ``method``: a name of :data:`METHOD_MODULES`
    or ``module:python.module`` (any module with ``solve(dataset, grid, ...)``)."""
    module = method.split(":", 1)[1] if method.startswith("module:") else METHOD_MODULES.get(method)
    if module is None:
        raise InputError(f"{where}: unknown reconstruction method '{method}' (choose from "
                         f"{', '.join(METHOD_MODULES)} or module:python.module)")
    try:
        return module, importlib.import_module(module).solve
    except ModuleNotFoundError as exc:
        raise InputError(f"{where}: reconstruction method '{method}' is not available "
                         f"({exc})") from None
    except AttributeError:
        raise InputError(f"{where}: {module} has no solve()") from None


def reconstruct(job, step) -> dict:
    """Reconstruct (and evaluate) a batch job's dataset as its step asks; {'ran': True, **metrics}."""
    dataset = SonarDataset.read(job.output)
    if step.shape is not None:
        grid = Grid.from_dataset(dataset, step.shape, step.bounds)
    else:
        probe = Grid.from_dataset(dataset, (2, 2, 2), step.bounds)
        shape = tuple(int(round((hi - lo) / step.voxel_size)) + 1 for lo, hi in probe.bounds)
        grid = Grid(probe.bounds, shape)
    volume = importlib.import_module(step.module).solve(dataset, grid, progress=False,
                                                        **step.options)
    del dataset
    volume.params.update(dataset=job.output, batch_step_id=step.step_id,
                         batch_step=json.dumps(step.params, sort_keys=True))
    if step.evaluate is None:
        volume.write(step.output)
        return {"ran": True}
    options = dict(step.evaluate)
    options["sweep"] = True
    crop = options.pop("crop", None)
    tmp_volume = Path(step.output).with_name(f".{Path(step.output).name}.eval.h5")
    volume.write(tmp_volume)         # evaluated before it becomes the step's output
    try:
        result = evaluate_file(tmp_volume, load_gt_mesh(job.output), crop=crop, **options)
        result.pop("sweep", None)
        result["volume"] = step.output
        with atomic_path(step.eval_output) as tmp:
            tmp.write_text(json.dumps({"batch_step_id": step.step_id, "job": job.name,
                                       "metrics": json_safe(result)}, indent=1))
        tmp_volume.replace(step.output)
    finally:
        tmp_volume.unlink(missing_ok=True)
    return {"ran": True, **summary_metrics(json_safe(result))}
