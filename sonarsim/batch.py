"""Batch manifests: many simulations (each optionally reconstructed and evaluated) as one run.

A manifest (TOML, docs/batch.md) lists jobs, or sweeps whose product gives the jobs::

    [defaults]                  # every job: any simulate setting
    poses = "cylindrical:36:2"
    paths_per_pose = 500
    [[job]]                     # explicit jobs ...
    scene = "sphere"
    [[sweep]]                   # ... and products: a list is an axis
    mesh = "meshes/*.obj"       # a glob is an axis too
    snr_db = [10, 20]
    seed = [0, 1]

A job is one :func:`sonarsim.simulate.simulate` run. Its keys are the batch's own
(``name``, ``scene`` | ``mesh`` with ``fit``/``ground``, ``poses``, ``pulse``, ``fs``,
``pulse_samples``, ``reconstruct``) and every field of
:class:`sonarsim.simulate.SimulationSettings` (``snr_db``, ``seed``, ``paths_per_pose``, ...,
and whatever fields the simulator gains later), passed through as they are.

:func:`plan_batch` expands and validates the whole manifest before anything runs: every
scene and mesh is loaded, every trajectory, pulse and setting is checked, every output name
is unique; a bad job raises :class:`~sonarsim.errors.InputError` naming it.

**Identity.** A job's id is a digest of everything that determines its dataset: the
parameters, the effective settings (defaults included), the scene's geometry, the poses and
the pulse samples. It is stored in the dataset (meta ``batch_job_id``, with the parameters
as ``batch_job``). A re-run skips a job only when its output is a *complete* dataset (the
file's own completeness marker, checked by :func:`sonarsim.dataset.inspect`) with the same
id; anything else is simulated again (an interrupted one resumes from its ``.partial`` file).
Reconstructions store their own id (volume param ``batch_step_id``).

:func:`run_batch` runs the jobs on a :class:`sonarsim.batch_engine.Engine` and records
every job in ``DIR/batch.csv``.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import glob as globlib
import hashlib
import inspect as pyinspect
import io
import itertools
import json
import math
import re
import tempfile
import time
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import FormatError, InputError, SonarsimError

CSV_NAME = "batch.csv"
TOP_KEYS = ("defaults", "job", "sweep")
BATCH_KEYS = ("name", "scene", "mesh", "fit", "ground", "poses", "pulse", "fs",
              "pulse_samples", "reconstruct")
NOT_SETTINGS = ("pulse", "extra_meta", "log")    # SimulationSettings fields set by the batch
EXECUTION_ONLY = ("threads", "chunk_size")       # change the speed, never the output
DEFAULT_PULSE = "lfm-20k"
DEFAULT_FS = 100e3
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")
GLOB_CHARS = set("*?[")
# The reconstruction step is plugged in by the recon package through this entry-point group
# (recon/batch_step.py), so that sonarsim never imports recon: dependencies point one way.
RECON_ENTRY_POINTS = "sonarsim.batch_steps"
RECON_KEYS = ("method", "label", "shape", "voxel_size", "bounds", "evaluate")
EVALUATE_KEYS = ("threshold", "crop", "samples", "images", "normalize", "seed")
DEFAULT_VOXEL_SIZE = 0.0032      # metres, as `recon backproject`
SUMMARY_METRICS = ("iou", "best_iou", "chamfer_sq", "best_chamfer_sq", "chamfer_m",
                   "normal_consistency", "psnr_depth", "ssim_depth")


def settings_fields() -> dict[str, dataclasses.Field]:
    """The :class:`SimulationSettings` fields a job may set (all but the batch's own)."""
    from .simulate import SimulationSettings
    return {f.name: f for f in dataclasses.fields(SimulationSettings) if f.name not in NOT_SETTINGS}


# ----------------------------------------------------------------------------- data

@dataclass(frozen=True)
class ReconStep:
    """A reconstruction of a job's dataset, optionally evaluated against its GT mesh.

    ``options`` go to ``<module>.solve(dataset, grid, progress=False, **options)``;
    ``evaluate``: keyword arguments of ``recon.evaluation.evaluate_file`` or None.
    Outputs: ``output`` (volume .h5) and ``eval_output`` (metrics .json).
    """
    label: str
    module: str
    params: dict                  # as given (canonical), for the CSV and the id
    options: dict
    shape: tuple[int, int, int] | None
    voxel_size: float
    bounds: list | None
    evaluate: dict | None
    output: str
    eval_output: str
    step_id: str


@dataclass(frozen=True)
class Job:
    """One simulation: ``params`` (canonical, JSON-able: absolute paths, the settings as
    given), its ``job_id`` (see module doc), its ``output`` dataset, its reconstructions."""
    name: str
    where: str
    params: dict
    job_id: str
    output: str
    digests: dict
    recon: tuple[ReconStep, ...] = ()


@dataclass
class Plan:
    """A validated manifest: the jobs, their output directory and the scene warnings."""
    manifest: Path
    out: Path
    jobs: list[Job]
    warnings: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- manifest

def load_manifest(path: str | Path) -> dict:
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: manifest not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: manifest is a directory") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{where}: must be a table")
    return value


def _tables(value, where: str) -> list[dict]:
    items = value if isinstance(value, list) else [value]
    return [_table(v, f"{where}[{i}]") for i, v in enumerate(items)]


def _expand_mesh(value, where: str, base: Path) -> list[str]:
    """Absolute mesh paths for a path, a glob or a list of them (in order, globs sorted)."""
    items = value if isinstance(value, list) else [value]
    out = []
    for item in items:
        if not isinstance(item, str) or not item:
            raise InputError(f"{where}: mesh must be a path or a glob, got {item!r}")
        pattern = item if Path(item).is_absolute() else str(base / item)
        if GLOB_CHARS & set(item):
            found = sorted(globlib.glob(pattern))
            if not found:
                raise InputError(f"{where}: mesh glob '{item}' matches no file")
            out += [str(Path(p).resolve()) for p in found]
        else:
            out.append(str(Path(pattern).resolve()))
    return out


def expand_manifest(doc: dict, base: Path) -> list[tuple[str, dict]]:
    """(where, raw job parameters) for every job of a parsed manifest, in manifest order.

    ``[defaults]`` fill every job; in a ``[[sweep]]`` every list value is an axis (a
    list-valued setting is given as a list of lists) and the jobs are the product of the
    axes; ``mesh`` globs are axes wherever they appear.
    """
    unknown = sorted(set(doc) - set(TOP_KEYS))
    if unknown:
        raise InputError(f"manifest: unknown top-level key(s) {', '.join(unknown)} "
                         f"(expected {', '.join(TOP_KEYS)})")
    defaults = _table(doc.get("defaults", {}), "defaults")
    entries = [(f"job[{i}]" + (f" '{t['name']}'" if isinstance(t.get("name"), str) else ""),
                t, False) for i, t in enumerate(_tables(doc.get("job", []), "job"))]
    entries += [(f"sweep[{i}]", t, True)
                for i, t in enumerate(_tables(doc.get("sweep", []), "sweep"))]
    if not entries:
        raise InputError("manifest: no jobs (add [[job]] tables or a [[sweep]])")
    out = []
    for where, table, is_sweep in entries:
        merged = {**defaults, **table}
        axes: dict[str, list] = {}
        for key, value in merged.items():
            if key == "mesh":
                axes[key] = _expand_mesh(value if key in table or not isinstance(value, list)
                                         else value, where, base)
            elif is_sweep and key in table and isinstance(value, list) and key != "reconstruct":
                if not value:
                    raise InputError(f"{where}: sweep axis '{key}' is empty")
                axes[key] = value
        fixed = {k: v for k, v in merged.items() if k not in axes}
        for combo in itertools.product(*axes.values()):
            chosen = dict(zip(axes, combo))
            label = where
            shown = {k: v for k, v in chosen.items() if len(axes[k]) > 1}
            if shown:
                label += " {" + ", ".join(f"{k}={_short(v)}" for k, v in shown.items()) + "}"
            out.append((label, {**fixed, **chosen}))
    return out


def _short(value) -> str:
    if isinstance(value, str) and ("/" in value):
        return Path(value).name
    return str(value)


# ----------------------------------------------------------------------------- jobs

def _resolve(value: str, base: Path) -> str:
    p = Path(value)
    return str((p if p.is_absolute() else base / p).resolve())


def canonical_params(raw: dict, where: str, base: Path) -> dict:
    """The job's parameters with paths made absolute and defaults of the batch's own keys
    filled in (InputError naming ``where`` for unknown keys and wrong types)."""
    fields_ = settings_fields()
    unknown = sorted(set(raw) - set(BATCH_KEYS) - set(fields_))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; a job takes "
                         f"{', '.join(BATCH_KEYS)} and the simulation settings "
                         f"{', '.join(sorted(fields_))}")
    if ("scene" in raw) == ("mesh" in raw):
        raise InputError(f"{where}: needs exactly one of 'scene' (a scene TOML or shipped "
                         f"scene name) or 'mesh' (a mesh file)")
    p: dict[str, Any] = {}
    if "scene" in raw:
        scene = raw["scene"]
        if not isinstance(scene, str) or not scene:
            raise InputError(f"{where}: scene must be a TOML path or a shipped scene name")
        looks_like_path = scene.lower().endswith(".toml") or "/" in scene
        p["scene"] = _resolve(scene, base) if looks_like_path or (base / scene).exists() \
            else scene
        for key in ("fit", "ground"):
            if key in raw:
                raise InputError(f"{where}: '{key}' applies to 'mesh' jobs only")
    else:
        p["mesh"] = raw["mesh"] if Path(raw["mesh"]).is_absolute() else _resolve(raw["mesh"], base)
        for key in ("fit", "ground"):
            value = raw.get(key, True)
            if not isinstance(value, bool):
                raise InputError(f"{where}: {key} must be true or false")
            p[key] = value
    if "poses" not in raw:
        raise InputError(f"{where}: no poses (set 'poses' in [defaults] or in the job)")
    poses = raw["poses"]
    if not isinstance(poses, str) or not poses:
        raise InputError(f"{where}: poses must be a trajectory spec or a pose file")
    p["poses"] = _resolve(poses, base) if poses.lower().endswith((".csv", ".npy")) else poses
    pulse = raw.get("pulse", DEFAULT_PULSE)
    if not isinstance(pulse, str):
        raise InputError(f"{where}: pulse must be a string")
    p["pulse"] = _resolve(pulse, base) if pulse.lower().endswith(".npy") else pulse
    fs = raw.get("fs", DEFAULT_FS)
    if isinstance(fs, bool) or not isinstance(fs, (int, float)) or not fs > 0:
        raise InputError(f"{where}: fs must be a positive number (Hz)")
    p["fs"] = float(fs)
    if "pulse_samples" in raw:
        n = raw["pulse_samples"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise InputError(f"{where}: pulse_samples must be an integer >= 2")
        p["pulse_samples"] = n
    for key in sorted(set(raw) & set(fields_)):
        p[key] = raw[key]
    if "bounce_set" in p and "bounces" not in p and isinstance(p["bounce_set"], list) \
            and p["bounce_set"] and all(isinstance(b, int) for b in p["bounce_set"]):
        p["bounces"] = max(p["bounce_set"])            # as `sonarsim simulate`
    if "name" in raw:
        if not isinstance(raw["name"], str) or not raw["name"]:
            raise InputError(f"{where}: name must be a non-empty string")
        p["name"] = raw["name"]
    if "reconstruct" in raw:
        p["reconstruct"] = _tables(raw["reconstruct"], f"{where}: reconstruct")
    return p


def _settings_value(value):
    """TOML value -> settings value: lists become tuples (e.g. ``bounce_set``)."""
    if isinstance(value, list):
        return tuple(_settings_value(v) for v in value)
    return value


def _scene_toml_for_mesh(mesh: str, fit: bool, ground: bool) -> str:
    return (f"name = {json.dumps(Path(mesh).stem)}\nground = {str(ground).lower()}\n\n"
            f"[[object]]\nmesh = {json.dumps(mesh)}\nfit = {str(fit).lower()}\n")


def load_job_scene(params: dict):
    """The :class:`SceneSpec` of a job: its scene file / shipped scene, or its mesh on the
    ground (``fit``: scaled and placed into the scene box, see :mod:`sonarsim.scene`)."""
    from .scene import load_scene
    if "scene" in params:
        return load_scene(params["scene"])
    mesh = params["mesh"]
    if not Path(mesh).is_file():
        raise FormatError(f"{mesh}: mesh file not found")
    with tempfile.TemporaryDirectory(prefix="sonarsim-batch-") as tmp:
        toml = Path(tmp) / "scene.toml"
        toml.write_text(_scene_toml_for_mesh(mesh, params["fit"], params["ground"]))
        spec = load_scene(toml)
    # The temporary file must not leak into the dataset (meta scene_source).
    return dataclasses.replace(spec, source=f"mesh {mesh} (fit={str(params['fit']).lower()})")


def _digest(*parts) -> str:
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str(part.dtype).encode() + str(part.shape).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()


def scene_digest(spec) -> str:
    parts = [spec.name, spec.source, spec.box.lo, spec.box.hi,
             None if spec.ground is None else [spec.ground.albedo, list(spec.ground.size)]]
    for obj in spec.objects:
        parts += [obj.label, obj.albedo, obj.normals, np.asarray(obj.mesh.vertices, float),
                  np.asarray(obj.mesh.faces, np.int64),
                  None if obj.file_normals is None else np.asarray(obj.file_normals, float)]
    return _digest(*parts)


def poses_digest(poses) -> str:
    return _digest(poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight)


def build_simulation(params: dict, *, scene=None, poses=None):
    """(scene, poses, settings, digests) of a job's canonical ``params``; ``scene``/``poses``
    may be given when already loaded. The settings carry no batch metadata yet."""
    from .geometry import trajectory
    from .signals import pulse_from_spec
    from .simulate import SimulationSettings, simulation_window
    fields_ = settings_fields()
    spec = scene if scene is not None else load_job_scene(params)
    if poses is None:
        poses = trajectory(params["poses"], box=spec.box)
    pulse = pulse_from_spec(params["pulse"], params["fs"], params.get("pulse_samples"))
    values = {k: _settings_value(params[k]) for k in fields_ if k in params}
    try:
        settings = SimulationSettings(pulse=pulse, **values)
        settings.validate()
    except (TypeError, ValueError) as exc:
        if isinstance(exc, SonarsimError):
            raise
        raise InputError(f"invalid simulation setting ({exc})") from None
    simulation_window(poses, spec, pulse, settings.sound_speed, settings.oversample)
    effective = {k: getattr(settings, k) for k in fields_
                 if k not in EXECUTION_ONLY and not callable(getattr(settings, k))}
    digests = {"scene": scene_digest(spec), "poses": poses_digest(poses),
               "pulse": _digest(pulse.samples, pulse.fs, pulse.spec),
               "settings": _digest(effective)}
    return spec, poses, settings, digests


def identity_params(params: dict) -> dict:
    """The parameters that determine a job's dataset (no name, reconstruction or speed)."""
    return {k: v for k, v in params.items()
            if k not in ("name", "reconstruct") and k not in EXECUTION_ONLY}


def job_id_of(params: dict, digests: dict) -> str:
    """The job's id: its inputs as given (scene, poses, pulse references) and the digests of
    what they hold and of the effective settings (so ``seed = 0`` written out or left to
    its default is the same job)."""
    fields_ = settings_fields()
    inputs = {k: v for k, v in identity_params(params).items() if k not in fields_}
    return _digest(inputs, digests)[:20]


def job_meta(job: Job) -> dict:
    """What the batch adds to a dataset's meta (extra_meta of the settings)."""
    return {"poses": job.params["poses"], "batch_name": job.name, "batch_job_id": job.job_id,
            "batch_job": identity_params(job.params)}


# ----------------------------------------------------------------------------- names

def _name_value(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, str) and ("/" in value or value.lower().endswith((".npy", ".csv"))):
        value = Path(value).stem
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, (list, tuple)):
        value = "+".join(_name_value(v) for v in value)
    text = re.sub(r"[^A-Za-z0-9.+-]+", "-", str(value)).strip("-.")
    return text or "x"


def _stem(params: dict) -> str:
    ref = params.get("scene") or params.get("mesh")
    return _name_value(Path(ref).stem if "/" in ref else ref)


def _name_defaults() -> dict:
    fields_ = settings_fields()
    out = {k: (f.default if f.default is not dataclasses.MISSING else None)
           for k, f in fields_.items()}
    out.update(pulse=DEFAULT_PULSE, fs=DEFAULT_FS, fit=True, ground=True)
    return out


def default_names(all_params: list[dict]) -> list[str]:
    """Names from the parameters: the scene or mesh stem, then ``key-value`` for every
    parameter whose value differs between jobs (e.g. ``bunny_snr_db-20_seed-1``); a
    setting a job leaves out counts with its default value."""
    defaults = _name_defaults()
    keys: list[str] = []
    for p in all_params:
        for k in identity_params(p):
            if k not in keys and k not in ("scene", "mesh"):
                keys.append(k)
    value = lambda p, k: p.get(k, defaults.get(k))
    varying = [k for k in keys
               if len({json.dumps(value(p, k), sort_keys=True) for p in all_params}) > 1]
    return ["_".join([_stem(p)] + [f"{k}-{_name_value(value(p, k))}" for k in varying
                                   if k in p or k in defaults])
            for p in all_params]


def _format_name(template: str, params: dict, where: str) -> str:
    values = {k: _name_value(v) for k, v in params.items() if k != "reconstruct"}
    values["stem"] = _stem(params)
    try:
        name = template.format_map(values)
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(f"{where}: name template '{template}': {exc}") from None
    if not NAME_RE.match(name):
        raise InputError(f"{where}: name '{name}' must be letters, digits and . _ + - "
                         "(it becomes a file name)")
    return name


# ----------------------------------------------------------------------------- reconstruction

def recon_step(raw: dict, where: str, job_name: str, job_id: str, out: Path) -> ReconStep:
    """Validate one ``reconstruct`` table of a job."""
    plugin = recon_plugin(where)
    if "method" not in raw or not isinstance(raw["method"], str):
        raise InputError(f"{where}: reconstruct needs a method ({', '.join(plugin.METHOD_MODULES)} "
                         "or module:python.module)")
    method = raw["method"]
    module, solve = plugin.solver(method, where)
    label = raw.get("label", method.split(".")[-1] if method.startswith("module:") else method)
    if not isinstance(label, str) or not NAME_RE.match(label):
        raise InputError(f"{where}: reconstruct label {label!r} must be letters, digits, . _ + -")
    options = {k: v for k, v in raw.items() if k not in RECON_KEYS}
    sig = pyinspect.signature(solve)
    takes_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
    bad = [k for k in options if k not in sig.parameters or k in ("dataset", "grid", "progress")]
    if bad and not takes_any or any(k in ("dataset", "grid", "progress") for k in options):
        raise InputError(f"{where}: {module}.solve takes no option(s) {', '.join(bad)}")
    shape = raw.get("shape")
    if shape is not None and (not isinstance(shape, list) or len(shape) != 3 or not all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in shape)):
        raise InputError(f"{where}: reconstruct shape must be [nx, ny, nz] positive integers")
    voxel = raw.get("voxel_size", DEFAULT_VOXEL_SIZE)
    if isinstance(voxel, bool) or not isinstance(voxel, (int, float)) or not voxel > 0:
        raise InputError(f"{where}: reconstruct voxel_size must be positive (m)")
    bounds = raw.get("bounds")
    if bounds is not None:
        try:
            b = np.asarray(bounds, float).reshape(3, 2)
        except (TypeError, ValueError):
            b = None
        if b is None or not np.all(np.isfinite(b)) or np.any(b[:, 1] < b[:, 0]):
            raise InputError(f"{where}: reconstruct bounds must be [x0, x1, y0, y1, z0, z1] (m)")
        bounds = b.tolist()
    evaluate = raw.get("evaluate", False)
    if isinstance(evaluate, bool):
        evaluate = {} if evaluate else None
    elif isinstance(evaluate, dict):
        unknown = sorted(set(evaluate) - set(EVALUATE_KEYS))
        if unknown:
            raise InputError(f"{where}: evaluate takes {', '.join(EVALUATE_KEYS)}, not "
                             f"{', '.join(unknown)}")
        evaluate = dict(evaluate)
        evaluate.setdefault("images", False)
    else:
        raise InputError(f"{where}: evaluate must be true, false or a table")
    if evaluate is not None:
        evaluate.setdefault("images", False)
        threshold = evaluate.get("threshold", 0.2)
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) \
                or not 0 < threshold < 1:
            raise InputError(f"{where}: evaluate threshold must be in (0, 1)")
    params = dict(raw)
    step_id = _digest(job_id, params)[:20]
    return ReconStep(label=label, module=module, params=params, options=options,
                     shape=tuple(shape) if shape else None, voxel_size=float(voxel),
                     bounds=bounds, evaluate=evaluate,
                     output=str(out / f"{job_name}.{label}.h5"),
                     eval_output=str(out / f"{job_name}.{label}.json"), step_id=step_id)


# ----------------------------------------------------------------------------- planning

def plan_batch(manifest: str | Path, out: str | Path, *, log: Callable[[str], None] = print
               ) -> Plan:
    """Expand and validate every job of ``manifest`` for output directory ``out``.

    Nothing is written. Raises :class:`InputError` naming the first bad job.
    """
    manifest = Path(manifest)
    doc = load_manifest(manifest)
    base = manifest.resolve().parent
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: --out must be a directory")
    raw_jobs = expand_manifest(doc, base)
    scenes: dict[str, tuple] = {}
    poses_cache: dict[tuple, Any] = {}
    notes: list[str] = []
    drafts = []
    for where, raw in raw_jobs:
        params = canonical_params(raw, where, base)
        ref = json.dumps({k: params[k] for k in ("scene", "mesh", "fit", "ground") if k in params},
                         sort_keys=True)
        try:
            if ref not in scenes:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    scenes[ref] = (load_job_scene(params),)
                notes += [f"{_short(params.get('scene') or params['mesh'])}: "
                          f"{str(w.message)}" for w in caught]
            spec = scenes[ref][0]
            key = (params["poses"], spec.box.lo.tobytes(), spec.box.hi.tobytes())
            if key not in poses_cache:
                from .geometry import trajectory
                poses_cache[key] = trajectory(params["poses"], box=spec.box)
            _, _, _, digests = build_simulation(params, scene=spec, poses=poses_cache[key])
        except SonarsimError as exc:
            raise InputError(f"{where}: {exc}") from None
        drafts.append((where, params, digests))
    names = default_names([p for _, p, _ in drafts])
    jobs: list[Job] = []
    seen: dict[str, str] = {}
    same: dict[str, str] = {}
    ids = [job_id_of(p, d) for _, p, d in drafts]
    for (where, params, digests), name, job_id in zip(drafts, names, ids):
        if "name" in params:
            name = _format_name(params["name"], params, where)
        elif names.count(name) > 1:
            name = f"{name}-{job_id[:8]}"
        if job_id in same:
            raise InputError(f"{where}: the same simulation as {same[job_id]} (every setting "
                             "equal); remove one of them")
        same[job_id] = where
        if name in seen:
            raise InputError(f"{where}: output name '{name}' is also the name of {seen[name]}")
        seen[name] = where
        steps = tuple(recon_step(r, f"{where}: reconstruct[{i}]", name, job_id, out)
                      for i, r in enumerate(params.get("reconstruct", [])))
        labels = [s.label for s in steps]
        if len(set(labels)) != len(labels):
            raise InputError(f"{where}: two reconstructions share a label; set 'label'")
        jobs.append(Job(name=name, where=where, params=params, job_id=job_id,
                        output=str(out / f"{name}.h5"), digests=digests, recon=steps))
    return Plan(manifest=manifest, out=out, jobs=jobs, warnings=sorted(set(notes)))


# ----------------------------------------------------------------------------- outputs

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
    from .dataset import KIND_DATASET, inspect
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


def step_record(step: ReconStep) -> dict | None:
    """The summary metrics of a finished reconstruction step (its volume, and its
    evaluation if asked for, carry its id), else None."""
    from .dataset import KIND_VOLUME, inspect
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
    if saved.get("batch_step_id") != step.step_id:
        return None
    return summary_metrics(saved.get("metrics", {}))


def summary_metrics(result: dict) -> dict:
    return {k: result[k] for k in SUMMARY_METRICS if k in result}


def _discard_stale_partials(job: Job) -> None:
    """Delete unfinished files of this output name left by a job with other parameters
    (a partial of this very job is kept: the simulation resumes it)."""
    from .dataset import PARTIAL_SUFFIX, inspect
    from .simulate import scratch_path
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


# ----------------------------------------------------------------------------- task functions

class OutputBusy(RuntimeError):
    """Another process writes this output now (retried by the engine, unlike input errors)."""


@contextlib.contextmanager
def _locked(path: str):
    """The exclusive lock of an output (:func:`sonarsim.outputs.output_lock`); busy is an
    error worth retrying (e.g. a worker the scheduler gave up on is still finishing it)."""
    from .outputs import OutputBusyError, output_lock
    try:
        with output_lock(path):
            yield
    except OutputBusyError as exc:
        raise OutputBusy(str(exc)) from None


def run_simulation(job: Job) -> dict:
    """Worker side: simulate ``job`` unless its complete output exists; returns
    {'ran': bool, **fidelity}. The scene, poses and pulse must be what was validated."""
    from .simulate import simulate
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
    with _locked(job.output):
        if dataset_record(job.output, job.job_id) is None:   # not finished meanwhile
            _discard_stale_partials(job)
            simulate(spec, poses, job.output, settings, resume=True, progress=False)
    record = dataset_record(job.output, job.job_id)
    if record is None:
        raise FormatError(f"{job.output}: not a complete dataset of job '{job.name}' after "
                          "the simulation")
    return {"ran": True, **record, **({"notes": " | ".join(notes)} if notes else {})}


def run_reconstruction(job: Job, step: ReconStep, _needed: Any = None) -> dict:
    """Worker side: reconstruct (and evaluate) ``job``'s dataset unless done; returns
    {'ran': bool, **summary metrics}."""
    done = step_record(step)
    if done is not None:
        return {"ran": False, **done}
    plugin = recon_plugin(f"job '{job.name}'")
    with _locked(step.output):
        return plugin.reconstruct(job, step)


def recon_plugin(where: str):
    """The module that runs reconstruction steps, found through the ``sonarsim.batch_steps``
    entry point (``recon.batch_step`` when recon is installed)."""
    from importlib.metadata import entry_points
    found = list(entry_points(group=RECON_ENTRY_POINTS, name="reconstruct"))
    if not found:
        raise InputError(f"{where}: reconstruction steps need the recon package "
                         f"(no '{RECON_ENTRY_POINTS}' entry point is installed)")
    return found[0].load()


# ----------------------------------------------------------------------------- running

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


def _param_columns(jobs: list[Job]) -> list[str]:
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
    """Rows of an earlier batch.csv by job id (to keep the wall times of skipped jobs)."""
    try:
        with open(path, newline="") as fh:
            return {r.get("job_id", ""): r for r in csv.DictReader(fh)}
    except (OSError, csv.Error):
        return {}


class _Table:
    """The rows of DIR/batch.csv, rewritten atomically as jobs finish."""

    def __init__(self, plan: Plan):
        self.plan, self.path = plan, plan.out / CSV_NAME
        self.previous = read_previous_csv(self.path)
        self.rows: dict[str, dict] = {}
        self.fidelity_keys: list[str] = []
        self.metric_keys: list[str] = []
        self.last_write = 0.0
        for job in plan.jobs:
            row = {"job": job.name, "status": "pending", "output": job.output, "wall_s": None,
                   "error": "", "job_id": job.job_id,
                   **{("param", k): job.params.get(k) for k in _param_columns(plan.jobs)}}
            for step in job.recon:
                row[f"{step.label}_output"] = step.output
            self.rows[job.name] = row

    def update(self, job: Job, status: str, sim: dict | None, sim_wall, steps: dict,
               error: str = "") -> None:
        row = self.rows[job.name]
        old = self.previous.get(job.job_id, {})
        row["status"], row["error"] = status, error
        row["wall_s"] = sim_wall if sim_wall is not None else (old.get("wall_s") or None)
        if sim_wall is None and old.get("notes"):
            row["notes"] = old["notes"]
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

    def write(self, force: bool = False) -> None:
        if not force and time.monotonic() - self.last_write < 1.0:
            return
        from .atomic import atomic_path
        columns = ["job", "status", "output", "wall_s"] + self.fidelity_keys + ["error",
                                                                                "notes"]
        params = _param_columns(self.plan.jobs)
        # a setting named like a measured value (mc_snr_db: the target) gets its own column
        header = {("param", k): (f"{k}_requested" if k in self.fidelity_keys else k)
                  for k in params}
        columns += list(header) + ["job_id"]
        extra = []
        for row in self.rows.values():
            extra += [k for k in row if k not in columns and k not in extra
                      and k not in self.metric_keys]
        columns += sorted(extra) + self.metric_keys
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([header.get(k, k) for k in columns])
        for row in self.rows.values():
            w.writerow([_cell(row.get(k)) for k in columns])
        self.plan.out.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.path) as tmp:
            tmp.write_text(buf.getvalue())
        self.last_write = time.monotonic()


def run_batch(plan: Plan, engine, *, progress: bool = True,
              log: Callable[[str], None] = print) -> BatchResult:
    """Run every job of ``plan`` that is not complete yet on ``engine`` (a
    :class:`sonarsim.batch_engine.Engine`); record every job in ``DIR/batch.csv``."""
    from .outputs import output_lock
    todo = [j for j in plan.jobs if dataset_record(j.output, j.job_id) is None
            or any(step_record(s) is None for s in j.recon)]
    if todo:
        engine.start(len(todo))                  # a scheduler that cannot be reached: no DIR
    plan.out.mkdir(parents=True, exist_ok=True)
    with output_lock(plan.out / CSV_NAME):      # one batch per DIR at a time
        return _run_batch(plan, engine, progress, log)


def _run_batch(plan: Plan, engine, progress: bool, log: Callable[[str], None]) -> BatchResult:
    from .batch_engine import Task
    table = _Table(plan)
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
