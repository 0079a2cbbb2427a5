"""The reconstruction (and evaluation) step of ``sonarsim batch`` jobs: its schema and its code.

sonarsim never imports recon; recon plugs this module into the batch through the entry point
``sonarsim.batch_steps: reconstruct`` (pyproject.toml). The batch calls :func:`plan_step` for
every ``reconstruct`` table while it plans (nothing has run yet) and :func:`reconstruct` on a
worker once the job's dataset exists. The rules are the command line's own: the grid of
:func:`recon.grid.grid_from_options` checked by :mod:`recon.checks`, the solver's own option
checks, :func:`recon.export.check_threshold` for the evaluation.

A ``reconstruct`` table (docs/batch.md)::

    method = "backproject"     # a name of METHOD_MODULES or module:python.module
    label = "bp"               # output DIR/<job>.<label>.h5 (default: the method)
    shape = [64, 64, 48]       # or voxel_size = 0.0032 (m, default) over the scene box
    bounds = [x0, x1, y0, y1, z0, z1]
    evaluate = true            # or a table of recon.evaluation.evaluate_file options
    upsample = 5               # any other key: an option of the solver's solve()
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.batch import ReconStep, step_id_of, summary_metrics
from sonarsim.batch.naming import check_name
from sonarsim.dataset import SonarDataset
from sonarsim.errors import InputError, SonarsimError

from . import checks
from .export import DEFAULT_THRESHOLD, check_threshold
from .grid import DEFAULT_VOXEL_SIZE, box_bounds, grid_from_options

METHOD_MODULES = {"backproject": "recon.backprojection", "bp": "recon.backprojection",
                  "gd": "recon.gradient_descent", "pfa": "recon.pfa", "nbp": "recon.nbp"}
STEP_KEYS = ("method", "label", "shape", "voxel_size", "bounds", "evaluate")
NOT_OPTIONS = ("dataset", "grid", "progress", "callback", "checkpoint", "resume")
NOT_EVALUATE = ("path", "gt_mesh", "sweep")        # evaluate_file arguments the step sets
EVALUATE_DEFAULTS = {"images": False}              # a batch renders no views unless asked


def solver(method: str, where: str):
    """(module name, module) of a step's ``method``: a name of :data:`METHOD_MODULES` or
    ``module:python.module`` (any module with ``solve(dataset, grid, ...)``)."""
    module = method.split(":", 1)[1] if method.startswith("module:") else METHOD_MODULES.get(method)
    if module is None:
        raise InputError(f"{where}: unknown reconstruction method '{method}' (choose from "
                         f"{', '.join(METHOD_MODULES)} or module:python.module)")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise InputError(f"{where}: reconstruction method '{method}' is not available "
                         f"({exc})") from None
    if not callable(getattr(mod, "solve", None)):
        raise InputError(f"{where}: {module} has no solve()")
    return module, mod


# ----------------------------------------------------------------------------- types

def _type_error(key: str, value, default) -> str | None:
    """Why ``value`` cannot stand where ``default`` stands (None: it can). Numbers may be
    ints where floats are expected; None defaults accept anything."""
    if default is None or default is inspect.Parameter.empty:
        return None
    if isinstance(default, bool):
        ok, want = isinstance(value, bool), "true or false"
    elif isinstance(default, int):
        ok, want = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(default, float):
        ok, want = isinstance(value, (int, float)) and not isinstance(value, bool), "a number"
    elif isinstance(default, str):
        ok, want = isinstance(value, str), "a string"
    elif isinstance(default, (list, tuple)):
        ok, want = isinstance(value, (list, tuple)), "a list"
    else:
        return None
    return None if ok else f"{key} must be {want}, got {value!r}"


def _option_defaults(mod, options: dict) -> tuple[dict, bool]:
    """({option: default} a solver module accepts, whether it takes any keyword).

    The keywords of ``solve`` and, for a solver with a settings dataclass
    (``settings_for``), that dataclass's fields (``preset`` chooses their defaults).
    """
    sig = inspect.signature(mod.solve)
    defaults = {name: p.default for name, p in sig.parameters.items()
                if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and name not in NOT_OPTIONS}
    takes_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
    settings_for = getattr(mod, "settings_for", None)
    if takes_any and callable(settings_for):
        preset = options.get("preset", defaults.get("preset"))
        try:
            settings = settings_for(preset) if "preset" in defaults else settings_for()
        except (TypeError, ValueError):
            settings = None
        if dataclasses.is_dataclass(settings):
            defaults.update({f.name: getattr(settings, f.name)
                             for f in dataclasses.fields(settings)})
            takes_any = False
    return defaults, takes_any


def check_options(mod, module: str, options: dict, grid, where: str) -> None:
    """The solver options of a step, checked as the command line checks them: known names,
    types, the settings' ranges (``settings_for(...).validate()``) and the module's own
    ``check_options(grid, **options)`` if it has one (ranges and memory estimates)."""
    defaults, takes_any = _option_defaults(mod, options)
    unknown = [k for k in options if k not in defaults or k in NOT_OPTIONS]
    if unknown and (not takes_any or any(k in NOT_OPTIONS for k in unknown)):
        raise InputError(f"{where}: {module}.solve takes no option(s) {', '.join(unknown)}"
                         + (f" (options: {', '.join(sorted(defaults))})" if defaults else ""))
    for key, value in options.items():
        problem = _type_error(key, value, defaults.get(key))
        if problem:
            raise InputError(f"{where}: {problem}")
    try:
        settings_for = getattr(mod, "settings_for", None)
        if callable(settings_for):
            fields = {k: v for k, v in options.items() if k != "preset"}
            sig = inspect.signature(mod.solve).parameters
            fields = {k: v for k, v in fields.items() if k not in sig}
            settings = (settings_for(options["preset"], **fields) if "preset" in options
                        else settings_for(**fields))
            if hasattr(settings, "validate"):
                settings.validate()
        own = getattr(mod, "check_options", None)
        if callable(own):
            own(grid, **options)
    except SonarsimError as exc:
        raise InputError(f"{where}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: invalid option ({exc})") from None


def check_evaluate(value, where: str) -> dict | None:
    """The evaluation options of a step (``true``, ``false`` or a table of
    :func:`recon.evaluation.evaluate_file` keywords), with the batch's defaults; None for
    no evaluation."""
    from .evaluation import evaluate_file
    if isinstance(value, bool):
        return dict(EVALUATE_DEFAULTS) if value else None
    if not isinstance(value, dict):
        raise InputError(f"{where}: evaluate must be true, false or a table")
    params = inspect.signature(evaluate_file).parameters
    allowed = {k: p.default for k, p in params.items() if k not in NOT_EVALUATE}
    unknown = sorted(set(value) - set(allowed))
    if unknown:
        raise InputError(f"{where}: evaluate takes {', '.join(allowed)}, not "
                         f"{', '.join(unknown)}")
    for key, v in value.items():
        default = DEFAULT_THRESHOLD if key == "threshold" else allowed[key]
        problem = _type_error(f"evaluate {key}", v, default)
        if problem:
            raise InputError(f"{where}: {problem}")
    options = {**EVALUATE_DEFAULTS, **value}
    try:
        check_threshold(options.get("threshold", DEFAULT_THRESHOLD))
        if "crop" in options and options["crop"] is not None:
            _check_bounds6(options["crop"], "evaluate crop")
    except SonarsimError as exc:
        raise InputError(f"{where}: evaluate {exc}") from None
    return options


def _check_bounds6(value, what: str) -> list:
    try:
        b = np.asarray(value, float).reshape(3, 2)
    except (TypeError, ValueError):
        b = None
    if b is None or not np.all(np.isfinite(b)) or np.any(b[:, 1] < b[:, 0]):
        raise InputError(f"{what} must be [x0, x1, y0, y1, z0, z1] (m), lower <= upper")
    return b.tolist()


# ----------------------------------------------------------------------------- plan

def plan_step(raw: dict, where: str, job_name: str, job_id: str, out: Path,
              box=None) -> ReconStep:
    """Validate one ``reconstruct`` table of a job (nothing runs): the method, the label, the
    grid over ``box`` (the job's scene box; its memory is checked as the command line checks
    it), the solver's options and the evaluation options."""
    method = raw.get("method")
    if not isinstance(method, str):
        raise InputError(f"{where}: reconstruct needs a method ({', '.join(METHOD_MODULES)} "
                         "or module:python.module)")
    module, mod = solver(method, where)
    label = raw.get("label", method.split(".")[-1] if method.startswith("module:") else method)
    if not isinstance(label, str):
        raise InputError(f"{where}: reconstruct label {label!r} must be a string")
    check_name(label, where, "reconstruct label")
    shape = raw.get("shape")
    if shape is not None and (not isinstance(shape, list) or len(shape) != 3 or not all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in shape)):
        raise InputError(f"{where}: reconstruct shape must be [nx, ny, nz] positive integers")
    voxel = raw.get("voxel_size", DEFAULT_VOXEL_SIZE)
    if isinstance(voxel, bool) or not isinstance(voxel, (int, float)):
        raise InputError(f"{where}: reconstruct voxel_size must be a number (m)")
    bounds = raw.get("bounds")
    if bounds is not None:
        bounds = _check_bounds6(bounds, f"{where}: reconstruct bounds")
    options = {k: v for k, v in raw.items() if k not in STEP_KEYS}
    grid = None
    try:
        if box is not None:
            grid = grid_from_options(box_bounds(box), bounds, shape, voxel)
            checks.check_grid_memory(grid, checks.bytes_per_voxel_of(mod))
        elif shape is None:
            grid_from_options(np.zeros((3, 2)) if bounds is None else bounds, bounds, None,
                              voxel)                  # the voxel size's own checks
    except SonarsimError as exc:
        raise InputError(f"{where}: {exc}") from None
    check_options(mod, module, options, grid, where)
    evaluate = check_evaluate(raw.get("evaluate", False), where)
    params = dict(raw)
    return ReconStep(label=label, params=params, output=str(out / f"{job_name}.{label}.h5"),
                     eval_output=str(out / f"{job_name}.{label}.json"),
                     step_id=step_id_of(job_id, params), evaluate=evaluate,
                     settings={"module": module, "options": options,
                               "shape": None if shape is None else tuple(shape),
                               "voxel_size": float(voxel), "bounds": bounds})


# ----------------------------------------------------------------------------- run

def reconstruct(job, step: ReconStep) -> dict:
    """Reconstruct (and evaluate) a batch job's dataset as its step asks; {'ran': True,
    **metrics}. The grid is checked against the data as ``recon backproject`` checks it."""
    from .evaluation import evaluate_file, json_safe
    from .grid import scene_box_of
    from .metrics import load_gt_mesh
    s = step.settings
    mod = importlib.import_module(s["module"])
    dataset = SonarDataset.read(job.output)
    checks.check_signal(dataset, job.output, warn=lambda m: None)
    grid = grid_from_options(box_bounds(scene_box_of(dataset)), s["bounds"], s["shape"],
                             s["voxel_size"])
    checks.check_grid(dataset, grid, checks.bytes_per_voxel_of(mod))
    volume = mod.solve(dataset, grid, progress=False, **s["options"])
    del dataset
    volume.params.update(dataset=job.output, batch_step_id=step.step_id,
                         batch_step=json.dumps(step.params, sort_keys=True))
    if step.evaluate is None:
        volume.write(step.output)
        return {"ran": True}
    options = dict(step.evaluate)
    options["sweep"] = True
    crop = options.pop("crop", None)
    with atomic_path(step.output, keep_suffix=False) as tmp_volume:
        volume.write(tmp_volume)         # evaluated before it becomes the step's output
        result = evaluate_file(tmp_volume, load_gt_mesh(job.output), crop=crop, **options)
        result.pop("sweep", None)
        result["volume"] = step.output
        with atomic_path(step.eval_output) as tmp:
            tmp.write_text(json.dumps({"batch_step_id": step.step_id, "job": job.name,
                                       "metrics": json_safe(result)}, indent=1))
    return {"ran": True, **summary_metrics(json_safe(result))}
