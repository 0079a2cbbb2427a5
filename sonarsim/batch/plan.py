"""Planning a batch: every job of a manifest expanded, validated and named before anything
runs (:func:`plan_batch`)."""
from __future__ import annotations

import collections
import dataclasses
import json
import re
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
class Evaluation:
    """One evaluation of a step's volume: its ``name`` ('' for a step's only one), its
    options (opaque to sonarsim) and its metrics file ``output`` (.json)."""
    name: str
    options: dict
    output: str


@dataclass(frozen=True)
class ReconStep:
    """A reconstruction of a job's dataset, optionally evaluated against its GT mesh.

    Made and run by the recon plugin (``recon.batch_step``): ``settings`` are its validated
    settings, opaque to sonarsim; ``params``: the ``reconstruct`` table as given (for the
    CSV and the id). Outputs: ``output`` (the volume .h5), one metrics .json per
    :class:`Evaluation`, and ``files``: other files the step writes, as (path, kind, id)
    with kind 'dataset' (e.g. a deconvolved dataset several steps share, carrying ``id`` as
    its meta ``batch_job_id``).
    """
    label: str
    params: dict
    output: str
    step_id: str
    evaluations: tuple[Evaluation, ...] = ()
    files: tuple[tuple[str, str, str], ...] = ()
    settings: dict = field(default_factory=dict)

    @property
    def evaluate(self) -> dict | None:
        """The options of the first evaluation, or None (no evaluation)."""
        return self.evaluations[0].options if self.evaluations else None

    @property
    def eval_output(self) -> str | None:
        return self.evaluations[0].output if self.evaluations else None


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
        """Every final file this job writes (dataset, volumes, metrics, shared files)."""
        out = [self.output]
        for step in self.recon:
            out += [step.output] + [e.output for e in step.evaluations]
            out += [path for path, _, _ in step.files if path not in out]
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


def build_simulation(params: dict, *, scene=None, poses=None, pulse=None,
                     digests: dict | None = None):
    """(scene, poses, settings, digests) of a job's canonical ``params``; ``scene``/``poses``/
    ``pulse`` may be given when already loaded, ``digests`` of scene/poses/pulse when already
    known. The settings carry no batch metadata yet."""
    from ..geometry import trajectory
    from ..signals import pulse_from_spec
    from ..simulate import SimulationSettings
    fields_ = settings_fields()
    spec = scene if scene is not None else load_job_scene(params)
    if poses is None:
        poses = trajectory(params["poses"], box=spec.box)
    if pulse is None:
        pulse = pulse_from_spec(params["pulse"], params["fs"], params.get("pulse_samples"))
    values = {k: _settings_value(params[k]) for k in fields_ if k in params}
    try:
        settings = SimulationSettings(pulse=pulse, **values)
        settings.validate()
    except (TypeError, ValueError) as exc:
        if isinstance(exc, SonarsimError):
            raise
        raise InputError(f"invalid simulation setting ({exc})") from None
    known = digests or {}
    digests = {"scene": known.get("scene") or scene_digest(spec),
               "poses": known.get("poses") or poses_digest(poses),
               "pulse": known.get("pulse") or pulse_digest(pulse),
               "settings": settings_digest(settings)}
    return spec, poses, settings, digests


def preflight(spec, poses, settings) -> None:
    """The simulation's checks before any work, exactly as ``sonarsim simulate`` makes them
    (:func:`sonarsim.simulate.preflight`: settings, sample rate, pulse, recorded window,
    memory estimate)."""
    from ..simulate import preflight as simulation_preflight
    simulation_preflight(spec, poses, settings)


def manifest_terms(message: str) -> str:
    """A message of the command line's rules in the manifest's words: ``--paths-per-pose``
    becomes ``paths_per_pose`` for every job key (other options, e.g. ``--force``, stay)."""
    keys = set(settings_fields()) | {"fs", "pulse_samples", "pulse", "poses"}
    return re.sub(r"--([a-z][a-z0-9-]*)",
                  lambda m: m.group(1).replace("-", "_")
                  if m.group(1).replace("-", "_") in keys else m.group(0), message)


def check_integrator(settings, cache: dict) -> None:
    """Build the integrator a job renders with once per distinct beams/estimator setting
    (its plugin validates them: an unknown beam pattern is refused at plan time)."""
    from ..identity import digest
    from ..render import make_integrator
    key = digest(settings.bounces, settings.beams, settings.bounce1, settings.amplitude,
                 settings.surface_spacing, settings.speckle_seed)
    if key not in cache:
        try:
            make_integrator(settings.bounces, settings.beams, bounce1=settings.bounce1,
                            amplitude=settings.amplitude,
                            surface_spacing=settings.surface_spacing,
                            speckle_seed=settings.speckle_seed)
        except InputError as exc:           # Mitsuba quotes the plugin's whole traceback
            lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
            raise InputError(f"integrator settings: {lines[-1]}" if len(lines) > 1
                             else str(exc)) from None
        cache[key] = True


def recon_step(raw: dict, where: str, job_name: str, job_id: str, out: Path,
               box=None) -> ReconStep:
    """Validate one ``reconstruct`` table of a job (by the recon plugin's own rules)."""
    return recon_plugin(where).plan_step(raw, where, job_name, job_id, out, box)


MAX_JOBS = 10_000     # jobs a manifest may expand to without --max-jobs (a typo guard)


class _Loader:
    """Scenes, poses and their digests, each loaded once however many jobs share them."""

    def __init__(self):
        self.scenes: dict[str, Any] = {}
        self.poses: dict[tuple, tuple] = {}
        self.pulses: dict[tuple, tuple] = {}
        self.integrators: dict = {}
        self.notes: list[str] = []

    def job(self, params: dict):
        from ..geometry import trajectory
        ref = json.dumps({k: params[k] for k in ("scene", "mesh", "fit", "ground")
                          if k in params}, sort_keys=True)
        if ref not in self.scenes:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                spec = load_job_scene(params)
            self.notes += [f"{short(params.get('scene') or params['mesh'])}: "
                           f"{str(w.message)}" for w in caught]
            self.scenes[ref] = (spec, scene_digest(spec))
        spec, s_digest = self.scenes[ref]
        key = (params["poses"], spec.box.lo.tobytes(), spec.box.hi.tobytes())
        if key not in self.poses:
            poses = trajectory(params["poses"], box=spec.box)
            self.poses[key] = (poses, poses_digest(poses))
        poses, p_digest = self.poses[key]
        key = (json.dumps(params["pulse"], sort_keys=True), params["fs"],
               params.get("pulse_samples"))
        if key not in self.pulses:
            from ..signals import pulse_from_spec
            pulse = pulse_from_spec(params["pulse"], params["fs"], params.get("pulse_samples"))
            self.pulses[key] = (pulse, pulse_digest(pulse))
        pulse, u_digest = self.pulses[key]
        spec, poses, settings, digests = build_simulation(
            params, scene=spec, poses=poses, pulse=pulse,
            digests={"scene": s_digest, "poses": p_digest, "pulse": u_digest})
        preflight(spec, poses, settings)
        check_integrator(settings, self.integrators)
        return spec, digests


def plan_batch(manifest: str | Path, out: str | Path, *, log: Callable[[str], None] = print,
               max_jobs: int | None = MAX_JOBS, force: bool = False) -> Plan:
    """Expand and validate every job of ``manifest`` for output directory ``out``.

    Nothing is written and nothing runs. Raises :class:`InputError` naming the first bad
    job: a setting the simulator or the reconstruction refuses, more than ``max_jobs``
    jobs (None: no cap), two jobs writing one file (:func:`check_collisions`), or an
    existing file in ``out`` that is not the result of the job that would write it, unless
    ``force`` (:func:`check_existing`). Linear in the number of jobs.
    """
    manifest = Path(manifest)
    doc = load_manifest(manifest)
    base = manifest.resolve().parent
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: --out must be a directory")
    raw_jobs = expand_manifest(doc, base, max_jobs=max_jobs)
    loader = _Loader()
    drafts = []
    for where, raw in raw_jobs:
        params = canonical_params(raw, where, base)
        try:
            spec, digests = loader.job(params)
        except SonarsimError as exc:
            raise InputError(f"{where}: {manifest_terms(str(exc))}") from None
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
    plan = Plan(manifest=manifest, out=out, jobs=jobs, warnings=sorted(set(loader.notes)))
    check_collisions(plan)
    check_existing(plan, force=force)
    return plan


def job_files(job: Job) -> list[tuple[str, str]]:
    """(path, what) of every file ``job`` may write, once each: its dataset and the dataset's
    partial, scratch and lock files; each step's volume, metrics, shared files (e.g. a
    deconvolved dataset) and their locks."""
    from ..dataset import PARTIAL_SUFFIX
    from ..outputs import lock_path
    from ..simulate import scratch_path
    out = Path(job.output)
    files = {str(out): "dataset", str(out) + PARTIAL_SUFFIX: "partial dataset",
             str(scratch_path(out)): "noiseless scratch file",
             str(scratch_path(out)) + PARTIAL_SUFFIX: "partial scratch file",
             str(lock_path(out)): "lock file"}
    for step in job.recon:
        files[step.output] = f"'{step.label}' volume"
        files[str(lock_path(step.output))] = f"'{step.label}' lock file"
        for e in step.evaluations:
            files[e.output] = f"'{step.label}' metrics" + (f" '{e.name}'" if e.name else "")
        for path, kind, _ in step.files:
            files.setdefault(path, f"'{step.label}' {kind}")
            files.setdefault(str(lock_path(path)), f"'{step.label}' {kind} lock file")
    return list(files.items())


def check_collisions(plan: Plan) -> None:
    """InputError if two jobs (or a job and ``batch.csv``) would write the same file, e.g.
    job ``a``'s ``bp`` volume ``a.bp.h5`` and job ``a.bp``'s dataset."""
    from ..outputs import lock_path
    from .table import CSV_NAME
    csv = plan.out / CSV_NAME
    owner: dict[str, str] = {str(csv): "the batch table", str(lock_path(csv)): "the batch lock"}
    for job in plan.jobs:
        for path, what in job_files(job):
            mine = f"the {what} of {job.where} '{job.name}'"
            other = owner.get(path)
            if other is not None:
                raise InputError(f"{job.where}: {Path(path).name} would be both {mine} and "
                                 f"{other}; rename one of them ('name' or 'label')")
            owner[path] = mine


def check_existing(plan: Plan, force: bool = False) -> None:
    """InputError if a final output of a job exists in ``plan.out`` and is not that job's
    own result (a dataset or volume without the job's id, or anything else), unless
    ``force``: a batch never replaces a file it did not make for this very job."""
    if force or not plan.out.is_dir():
        return
    from .records import existing_owner
    for job in plan.jobs:
        for path, kind, ident in [(job.output, "dataset", job.job_id)] + \
                [(s.output, "volume", s.step_id) for s in job.recon] + \
                [(e.output, "metrics", s.step_id) for s in job.recon for e in s.evaluations] + \
                [f for s in job.recon for f in s.files]:
            problem = existing_owner(path, kind, ident)
            if problem:
                raise InputError(f"{job.where}: {path} exists and is {problem}, not the result "
                                 f"of job '{job.name}'; pass --force to replace it, or choose "
                                 "another --out")
