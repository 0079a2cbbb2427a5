"""Planning a batch: every job of a manifest expanded, validated and named before anything
runs (:func:`plan_batch`)."""
from __future__ import annotations

import collections
import dataclasses
import json
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..errors import FormatError, InputError, SonarsimError
from .identity import job_id_of, poses_digest, pulse_digest, scene_digest, settings_digest
from .manifest import canonical_params, expand_manifest, load_manifest, settings_fields, short
from .naming import check_name, default_names, format_name

# The reconstruction step is plugged in by the recon package through this entry-point group
# (recon/batch_step.py), so that sonarsim never imports recon: dependencies point one way.
RECON_ENTRY_POINTS = "sonarsim.batch_steps"


@dataclass(frozen=True)
class ReconStep:
    """A reconstruction of a job's dataset, optionally evaluated against its GT mesh.

    Made and run by the recon plugin (``recon.batch_step``): ``settings`` are its validated
    settings, opaque to sonarsim; ``params``: the ``reconstruct`` table as given (for the
    CSV and the id); ``evaluate``: evaluation options or None. Outputs: ``output`` (volume
    .h5) and ``eval_output`` (metrics .json, written when ``evaluate`` is not None).
    """
    label: str
    params: dict
    output: str
    eval_output: str
    step_id: str
    evaluate: dict | None = None
    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Job:
    """One simulation: ``params`` (canonical, JSON-able: absolute paths, the settings as
    given), its ``job_id`` (see :mod:`sonarsim.batch`), its ``output`` dataset, its
    reconstructions."""
    name: str
    where: str
    params: dict
    job_id: str
    output: str
    digests: dict
    recon: tuple[ReconStep, ...] = ()

    def outputs(self) -> list[str]:
        """Every file this job writes (dataset, volumes, metrics)."""
        out = [self.output]
        for step in self.recon:
            out.append(step.output)
            if step.evaluate is not None:
                out.append(step.eval_output)
        return out


@dataclass
class Plan:
    """A validated manifest: the jobs, their output directory and the scene warnings."""
    manifest: Path
    out: Path
    jobs: list[Job]
    warnings: list[str] = field(default_factory=list)


def recon_plugin(where: str):
    """The module that plans and runs reconstruction steps, found through the
    ``sonarsim.batch_steps`` entry point (``recon.batch_step`` when recon is installed)."""
    from importlib.metadata import entry_points
    found = list(entry_points(group=RECON_ENTRY_POINTS, name="reconstruct"))
    if not found:
        raise InputError(f"{where}: reconstruction steps need the recon package "
                         f"(no '{RECON_ENTRY_POINTS}' entry point is installed)")
    return found[0].load()


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
    from ..scene import load_scene
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


def build_simulation(params: dict, *, scene=None, poses=None):
    """(scene, poses, settings, digests) of a job's canonical ``params``; ``scene``/``poses``
    may be given when already loaded. The settings carry no batch metadata yet."""
    from ..geometry import trajectory
    from ..signals import pulse_from_spec
    from ..simulate import SimulationSettings, simulation_window
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
    digests = {"scene": scene_digest(spec), "poses": poses_digest(poses),
               "pulse": pulse_digest(pulse), "settings": settings_digest(settings)}
    return spec, poses, settings, digests


def recon_step(raw: dict, where: str, job_name: str, job_id: str, out: Path,
               box=None) -> ReconStep:
    """Validate one ``reconstruct`` table of a job (by the recon plugin's own rules)."""
    return recon_plugin(where).plan_step(raw, where, job_name, job_id, out, box)


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
                notes += [f"{short(params.get('scene') or params['mesh'])}: "
                          f"{str(w.message)}" for w in caught]
            spec = scenes[ref][0]
            key = (params["poses"], spec.box.lo.tobytes(), spec.box.hi.tobytes())
            if key not in poses_cache:
                from ..geometry import trajectory
                poses_cache[key] = trajectory(params["poses"], box=spec.box)
            _, _, _, digests = build_simulation(params, scene=spec, poses=poses_cache[key])
        except SonarsimError as exc:
            raise InputError(f"{where}: {exc}") from None
        drafts.append((where, params, digests, spec.box))
    names = default_names([d[1] for d in drafts])
    counts = collections.Counter(names)
    jobs: list[Job] = []
    seen: dict[str, str] = {}
    same: dict[str, str] = {}
    for (where, params, digests, box), name in zip(drafts, names):
        job_id = job_id_of(params, digests)
        if "name" in params:
            name = format_name(params["name"], params, where)
        elif counts[name] > 1:
            name = f"{name}-{job_id[:8]}"
        check_name(name, where)
        if job_id in same:
            raise InputError(f"{where}: the same simulation as {same[job_id]} (every setting "
                             "equal); remove one of them")
        same[job_id] = where
        if name in seen:
            raise InputError(f"{where}: output name '{name}' is also the name of {seen[name]}")
        seen[name] = where
        steps = tuple(recon_step(r, f"{where}: reconstruct[{i}]", name, job_id, out, box)
                      for i, r in enumerate(params.get("reconstruct", [])))
        labels = [s.label for s in steps]
        if len(set(labels)) != len(labels):
            raise InputError(f"{where}: two reconstructions share a label; set 'label'")
        jobs.append(Job(name=name, where=where, params=params, job_id=job_id,
                        output=str(out / f"{name}.h5"), digests=digests, recon=steps))
    return Plan(manifest=manifest, out=out, jobs=jobs, warnings=sorted(set(notes)))
