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
    deconvolve = "wiener"      # or "inr", or {method = "inr", iterations = 100, ...}: fit the
                               # pulse-deconvolved data (made once per job and method)
    evaluate = true            # or a table of recon.evaluation.evaluate_file options, or a
                               # list of tables (each with its own 'name', default its protocol)
    upsample = 5               # any other key: an option of the solver's solve()

Files: ``DIR/<job>.<label>.h5`` (the volume), ``DIR/<job>.<label>.json`` (the metrics of a
single evaluation) or ``DIR/<job>.<label>.<name>.json`` (one per evaluation of a list),
``DIR/<job>.pd-<method>[-<digest>].h5`` (a deconvolved dataset, shared by the steps that ask
for the same deconvolution). The metrics files also record the step's wall times
(``wall_s``: deconvolution, solve, evaluation).
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import re
import time
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.batch import ReconStep, step_id_of, summary_metrics
from sonarsim.batch.naming import check_name
from sonarsim.batch.plan import Evaluation
from sonarsim.dataset import SonarDataset
from sonarsim.errors import InputError, SonarsimError
from sonarsim.identity import digest

from . import checks
from .export import DEFAULT_THRESHOLD, check_threshold
from .grid import DEFAULT_VOXEL_SIZE, box_bounds, grid_from_options

METHOD_MODULES = {"backproject": "recon.backprojection", "bp": "recon.backprojection",
                  "gd": "recon.gradient_descent", "pfa": "recon.pfa", "nbp": "recon.nbp"}
STEP_KEYS = ("method", "label", "shape", "voxel_size", "bounds", "evaluate", "deconvolve")
NOT_OPTIONS = ("dataset", "grid", "progress", "callback", "checkpoint", "resume")
NOT_EVALUATE = ("path", "gt")                      # evaluate_file arguments the step sets
EVALUATE_DEFAULTS = {"images": False}              # a batch renders no views unless asked
DECONVOLVED_WAIT_S = 24 * 3600                     # how long a step waits for a shared
                                                   # deconvolution another worker is making


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


def option_defaults(mod, options: dict) -> tuple[dict, bool]:
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
    defaults, takes_any = option_defaults(mod, options)
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


def _evaluation_options(value: dict, where: str) -> dict:
    """One table of :func:`recon.evaluation.evaluate_file` keywords, checked, with the
    batch's defaults."""
    from .evaluation import evaluate_file
    params = inspect.signature(evaluate_file).parameters
    allowed = {k: p.default for k, p in params.items() if k not in NOT_EVALUATE}
    unknown = sorted(set(value) - set(allowed) - {"name"})
    if unknown:
        raise InputError(f"{where}: evaluate takes {', '.join(allowed)} (and 'name' in a "
                         f"list), not {', '.join(unknown)}")
    for key, v in value.items():
        if key == "name":
            continue
        default = DEFAULT_THRESHOLD if key == "threshold" else allowed[key]
        problem = _type_error(f"evaluate {key}", v, default)
        if problem:
            raise InputError(f"{where}: {problem}")
    options = {**EVALUATE_DEFAULTS, **{k: v for k, v in value.items() if k != "name"}}
    try:
        check_threshold(options.get("threshold", DEFAULT_THRESHOLD))
        if options.get("crop") is not None:
            _check_bounds6(options["crop"], "evaluate crop")
        _check_choices(options)
    except SonarsimError as exc:
        raise InputError(f"{where}: evaluate {exc}") from None
    return options


def _check_choices(options: dict) -> None:
    """The evaluation's named choices against recon's own lists (``recon.evaluation``'s
    ``check_options`` when it has one: then every rule ``evaluate_file`` applies first)."""
    from . import evaluation, protocol_reference
    own = getattr(evaluation, "check_options", None)
    if callable(own):
        own(**options)
        return
    for key, choices in (("protocol", evaluation.PROTOCOLS),
                         ("mapping", tuple(protocol_reference.MAPPINGS))):
        if key in options and options[key] not in choices:
            raise InputError(f"{key}: choose one of {', '.join(choices)}, "
                             f"got {options[key]!r}")


def check_evaluate(value, where: str) -> list[tuple[str, dict]]:
    """The evaluations of a step as (name, options): ``true``/``false``, a table of
    :func:`recon.evaluation.evaluate_file` keywords (name ''), or a list of such tables,
    each named by its ``name`` (default: its ``protocol``; names must differ)."""
    if isinstance(value, bool):
        return [("", dict(EVALUATE_DEFAULTS))] if value else []
    if isinstance(value, dict):
        return [("", _evaluation_options(value, where))]
    if not isinstance(value, list) or not value or not all(isinstance(v, dict) for v in value):
        raise InputError(f"{where}: evaluate must be true, false, a table or a list of tables")
    out = []
    for i, table in enumerate(value):
        options = _evaluation_options(table, f"{where}: evaluate[{i}]")
        name = table.get("name", options.get("protocol", "exact"))
        if not isinstance(name, str):
            raise InputError(f"{where}: evaluate[{i}] name must be a string")
        check_name(name, f"{where}: evaluate[{i}]", "evaluation name")
        if name in (n for n, _ in out):
            raise InputError(f"{where}: two evaluations are named '{name}'; give each a "
                             "distinct 'name'")
        out.append((name, options))
    return out


def check_deconvolve(value, where: str) -> dict | None:
    """The pulse deconvolution a step fits (``recon.deconvolution.deconvolve``) as
    {'method', 'inr': INRSettings fields given}, or None."""
    from .deconvolution import METHODS, INRSettings, renamed_setting
    if value is None or value is False:
        return None
    spec = {"method": value} if isinstance(value, str) else value
    if not isinstance(spec, dict) or not isinstance(spec.get("method"), str):
        raise InputError(f"{where}: deconvolve must be one of {', '.join(METHODS)} or a table "
                         "with a 'method'")
    method = spec["method"]
    if method not in METHODS:
        raise InputError(f"{where}: deconvolve method must be one of {', '.join(METHODS)}, "
                         f"got {method!r}")
    inr = {k: v for k, v in spec.items() if k != "method"}
    if inr and method != "inr":
        raise InputError(f"{where}: deconvolve options {', '.join(sorted(inr))} apply to "
                         "method 'inr' only")
    fields = {f.name: f.default for f in dataclasses.fields(INRSettings)}
    for key, v in inr.items():
        if renamed_setting(key):
            raise InputError(f"{where}: deconvolve {renamed_setting(key)}")
        if key not in fields:
            raise InputError(f"{where}: deconvolve takes the INR settings "
                             f"{', '.join(fields)}, not {key!r}")
        problem = _type_error(f"deconvolve {key}", v, fields[key])
        if problem:
            raise InputError(f"{where}: {problem}")
    if method == "inr":
        try:
            INRSettings(**inr).validate()
        except SonarsimError as exc:
            raise InputError(f"{where}: deconvolve {exc}") from None
    return {"method": method, "inr": inr}


def _check_bounds6(value, what: str) -> list:
    try:
        b = np.asarray(value, float).reshape(3, 2)
    except (TypeError, ValueError):
        b = None
    if b is None or not np.all(np.isfinite(b)) or np.any(b[:, 1] < b[:, 0]):
        raise InputError(f"{what} must be [x0, x1, y0, y1, z0, z1] (m), lower <= upper")
    return b.tolist()


# ----------------------------------------------------------------------------- plan

def _manifest_words(message: str, keys) -> str:
    """A message of the command line's rules in a manifest's words: ``--voxel-size`` becomes
    ``voxel_size`` where that is a key of the step (``--max-memory`` and the like stay)."""
    return re.sub(r"--([a-z][a-z0-9-]*)",
                  lambda m: m.group(1).replace("-", "_")
                  if m.group(1).replace("-", "_") in keys else m.group(0), message)


def plan_step(raw: dict, where: str, job_name: str, job_id: str, out: Path,
              box=None) -> ReconStep:
    """Validate one ``reconstruct`` table of a job (nothing runs): the method, the label, the
    grid over ``box`` (the job's scene box; its memory is checked as the command line checks
    it), the solver's options, the deconvolution and the evaluation options. The checks are
    the command line's; their messages name the manifest's keys (``voxel_size``, not
    ``--voxel-size``)."""
    try:
        return _plan_step(raw, where, job_name, job_id, out, box)
    except InputError as exc:
        keys = set(STEP_KEYS)
        method = raw.get("method") if isinstance(raw, dict) else None
        if isinstance(method, str):
            try:
                keys |= set(option_defaults(solver(method, where)[1], raw)[0])
            except (SonarsimError, TypeError, ValueError):
                pass
        text = _manifest_words(str(exc), keys)
        if text == str(exc):
            raise
        raise InputError(text) from None


def _plan_step(raw: dict, where: str, job_name: str, job_id: str, out: Path,
               box=None) -> ReconStep:
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
    deconv = check_deconvolve(raw.get("deconvolve"), where)
    evaluations = check_evaluate(raw.get("evaluate", False), where)
    files = ()
    if deconv is not None:
        tag = deconv["method"] + (f"-{digest(deconv['inr'], length=8)}" if deconv["inr"]
                                  else "")
        deconv = {**deconv, "output": str(out / f"{job_name}.pd-{tag}.h5"),
                  "id": digest(job_id, deconv, length=20)}
        files = ((deconv["output"], "dataset", deconv["id"]),)
    params = dict(raw)
    return ReconStep(
        label=label, params=params, output=str(out / f"{job_name}.{label}.h5"),
        step_id=step_id_of(job_id, params),
        evaluations=tuple(Evaluation(name, opts, str(out / (f"{job_name}.{label}.{name}.json"
                                                             if name else
                                                             f"{job_name}.{label}.json")))
                          for name, opts in evaluations),
        files=files,
        settings={"module": module, "options": options,
                  "shape": None if shape is None else tuple(shape),
                  "voxel_size": float(voxel), "bounds": bounds, "deconvolve": deconv})


# ----------------------------------------------------------------------------- run

def deconvolved(job, spec: dict) -> SonarDataset:
    """The job's dataset deconvolved as ``spec`` says, made once and shared by the job's
    steps (the file carries the deconvolution's id as meta ``batch_job_id``; a step that
    finds another worker making it waits for it)."""
    from sonarsim.outputs import output_lock

    from .deconvolution import INRSettings, deconvolve
    from sonarsim.batch.records import existing_owner
    path = spec["output"]
    with output_lock(path, wait=DECONVOLVED_WAIT_S):
        if Path(path).exists() and existing_owner(path, "dataset", spec["id"]) is None:
            return SonarDataset.read(path)
        dataset = SonarDataset.read(job.output)
        inr = INRSettings(**spec["inr"]) if spec["method"] == "inr" else None
        result = deconvolve(dataset, spec["method"], inr_settings=inr, progress=False)
        result.meta["batch_job_id"] = spec["id"]
        result.meta["batch_name"] = f"{job.name} (deconvolved: {spec['method']})"
        result.write(path)
        return result


def _own_volume(step: ReconStep) -> bool:
    """True if the step's volume file is complete and this step's (its id in the params)."""
    from sonarsim.dataset import KIND_VOLUME, inspect
    path = Path(step.output)
    if not path.is_file():
        return False
    try:
        with inspect(path) as (kind, fields_):
            return kind == KIND_VOLUME and \
                (fields_.get("params") or {}).get("batch_step_id") == step.step_id
    except (SonarsimError, OSError):
        return False


def _own_metrics(step: ReconStep, evaluation: Evaluation) -> dict | None:
    """The saved metrics file of ``evaluation`` if it is this step's, else None."""
    try:
        saved = json.loads(Path(evaluation.output).read_text())
    except (OSError, ValueError):
        return None
    return saved if isinstance(saved, dict) and saved.get("batch_step_id") == step.step_id \
        else None


def reconstruct(job, step: ReconStep) -> dict:
    """Reconstruct (and evaluate) a batch job's dataset as its step asks; {'ran': True,
    **metrics} (an evaluation's metrics prefixed with its name). The grid is checked against
    the data as ``recon backproject`` checks it.

    A step whose volume is already there (complete, with this step's id) but one of whose
    metrics files is missing or not its own (e.g. deleted to re-evaluate with changed
    evaluation code) is not solved again: only the missing evaluations run, and the wall
    times of the solve are taken over from the step's remaining metrics files.

    The metrics files record each stage's wall time (``wall_s``) and this process's CPU time
    during it (``cpu_s``, user + system of all its threads; a stage's own CPU when one step
    runs per process at a time, as with the sequential scheduler)."""
    from .evaluation import evaluate_file, json_safe
    from .grid import scene_box_of
    from .groundtruth import load_ground_truth
    s = step.settings
    wall, cpu = {}, {}
    reuse = bool(step.evaluations) and _own_volume(step)
    if reuse:
        kept = [m for m in (_own_metrics(step, e) for e in step.evaluations) if m is not None]
        for times, key in ((wall, "wall_s"), (cpu, "cpu_s")):
            times.update({k: v for k, v in (kept[0].get(key, {}) if kept else {}).items()
                          if not k.startswith("evaluate")})
        wall["reused_volume"] = True
    else:
        mod = importlib.import_module(s["module"])
        t0, c0 = time.perf_counter(), time.process_time()
        if s.get("deconvolve"):
            dataset = deconvolved(job, s["deconvolve"])
            wall["deconvolve"] = time.perf_counter() - t0
            cpu["deconvolve"] = time.process_time() - c0
        else:
            dataset = SonarDataset.read(job.output)
        checks.check_signal(dataset, job.output, warn=lambda m: None)
        grid = grid_from_options(box_bounds(scene_box_of(dataset)), s["bounds"], s["shape"],
                                 s["voxel_size"])
        checks.check_grid(dataset, grid, checks.bytes_per_voxel_of(mod))
        t0, c0 = time.perf_counter(), time.process_time()
        volume = mod.solve(dataset, grid, progress=False, **s["options"])
        wall["solve"] = time.perf_counter() - t0
        cpu["solve"] = time.process_time() - c0
        del dataset
        volume.params.update(dataset=job.output, batch_step_id=step.step_id,
                             batch_step=json.dumps(step.params, sort_keys=True))
        if not step.evaluations:
            volume.write(step.output)
            return {"ran": True}
    metrics = {}
    gt = load_ground_truth(job.output)      # the dataset's placed mesh, named (its scene's cameras)
    import contextlib
    target = contextlib.nullcontext(Path(step.output)) if reuse else \
        atomic_path(step.output, keep_suffix=False)
    with target as tmp_volume:              # a reused volume is evaluated where it is
        if not reuse:
            volume.write(tmp_volume)        # evaluated before it becomes the step's output
        results = []
        for evaluation in step.evaluations:
            saved = _own_metrics(step, evaluation) if reuse else None
            if saved is not None:
                for times, key in ((wall, "wall_s"), (cpu, "cpu_s")):
                    for k, v in saved.get(key, {}).items():
                        if k.startswith("evaluate"):
                            times.setdefault(k, v)
                results.append((evaluation, saved["metrics"], False))
                continue
            options = dict(evaluation.options)
            options.setdefault("sweep", True)
            crop = options.pop("crop", None)
            t0, c0 = time.perf_counter(), time.process_time()
            result = evaluate_file(tmp_volume, gt, crop=crop, **options)
            stage = f"evaluate{'_' + evaluation.name if evaluation.name else ''}"
            wall[stage] = time.perf_counter() - t0
            cpu[stage] = time.process_time() - c0
            result["volume"] = step.output
            results.append((evaluation, json_safe(result), True))
        for evaluation, result, new in results:
            if new:
                with atomic_path(evaluation.output) as tmp:
                    tmp.write_text(json.dumps({"batch_step_id": step.step_id, "job": job.name,
                                               "evaluation": evaluation.name, "wall_s": wall,
                                               "cpu_s": cpu,
                                               "metrics": result}, indent=1))
            prefix = f"{evaluation.name}_" if evaluation.name else ""
            metrics.update({prefix + k: v for k, v in summary_metrics(result).items()})
    return {"ran": True, **metrics}
