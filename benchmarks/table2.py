"""The reference's Table 2 in one command: every method, every shape, both evaluation protocols.

Reed et al., "Neural Volumetric Reconstruction for Coherent Synthetic Aperture Sonar"
(SIGGRAPH 2023), Table 2 compares backprojection, gradient descent, polar formatting and
neural backprojection on simulated AirSAS scans (20 kHz LFM, 20 dB SNR) with Chamfer, IoU,
LPIPS and PSNR. This script runs that comparison on the shapes at hand (bunny, cube,
cylinder: the reference's GT meshes from ``../shared/data/meshes`` where present, else the
shipped procedural cube and cylinder) and adds the SNR sweep (0 / 10 / 20 dB) and the 5 kHz
row for one shape.

A **cell** is one (method, shape, SNR, bandwidth) under one :class:`Settings`. The table runs
as a ``sonarsim batch`` (docs/batch.md): :func:`manifest` writes ``<out>/batch/table2.toml``,
one job per dataset (shape, SNR, bandwidth; simulated from a pose file of the table's
cylindrical poses) whose ``reconstruct`` steps are the cells (deconvolve where the method
asks, reconstruct, evaluate with both protocols of ``recon evaluate``), and the batch engine
runs it (``--scheduler``: in this process by default, or on a Dask cluster). The batch's
records make it resumable: finished datasets, volumes and metrics are kept (job and step ids
are stored in the files), an interrupted run goes on where it stopped. Datasets are named by
what the simulation depends on only (a solver setting never re-simulates); a step's label
carries a digest of its table and of the solver's effective settings (presets in code
included). ``--data DIR`` adopts scans simulated before (e.g. outside the batch) that are a
job's simulation by its parameters (poses, pulse, scene, recorded settings:
:func:`simulation_mismatches`) instead of simulating them again. Outputs in ``--out``:

* ``table2.md``  -- the table in the reference's layout (Chamfer, IoU, LPIPS, PSNR per method,
                    mean over shapes) for each protocol with the published row beside ours;
                    per-shape rows; the SNR sweep and the 5 kHz row;
* ``table2.csv`` -- every cell, both protocols, machine readable; plus the published rows;
* ``table2.png`` -- per shape: GT render, and per method the MIP over y and a render of the
                    τ = 0.2 surface side by side;
* ``table2.json`` -- settings, every cell (``cells``), timings (stage times per cell: dataset,
                    deconvolve, solve, evaluate; the run prints their sums, its wall and CPU time);
                    the NBP + refine rows (``refined``);
* ``batch/``      -- the manifest, the batch's ``batch.csv``, datasets, volumes, metrics, and
                    the refined meshes beside the NBP volumes they start from.

After the batch, each main NBP cell's solid is refined through the renderer (``recon refine``
with its defaults, the quick size with a few steps; :func:`refine_results`): the row "NBP +
recon refine", the project's whole pipeline, which the paper does not have (``--no-refine``
leaves it out).

    .venv/bin/python benchmarks/table2.py --out bench_out/table2 [--quick] [--methods bp,pfa]
"""
from __future__ import annotations

import argparse
import csv
import importlib
import json
import math
import os
import resource
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np

from recon.solver.settings import PRESETS
from sonarsim import identity

ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------ the settings, in one place

SHAPES = ("bunny", "cube", "cylinder")
MAIN_SNR_DB = 20.0
MAIN_BANDWIDTH = "20k"
SWEEP_SNR_DB = (0.0, 10.0, 20.0)            # for SWEEP_SHAPE, at MAIN_BANDWIDTH
SWEEP_BANDWIDTHS = ("5k",)                   # for SWEEP_SHAPE, at MAIN_SNR_DB
PULSES = {"20k": "lfm-20k", "5k": "lfm-5k"}  # the reference's analytic LFMs, 30->10 / 22.5->17.5 kHz
THRESHOLD = 0.2
CROP_Z = 0.005        # exact protocol: evaluate z >= 5 mm (leaves out the ground plane)
GRID_BOUNDS = ((-0.2, 0.2), (-0.2, 0.2), (0.0, 0.3))   # the reference's simulated scene box
PROTOCOLS = ("reference", "exact")

# Simulation (the reference's Table-2 data: single scattering, 20 dB on the dataset's signal
# power, seed 1). Monte-Carlo fidelity: the simulator's own default target (mc_snr_db) picks
# the paths per pose unless a size fixes them. Keys that this version of
# sonarsim.simulate.SimulationSettings lacks are ignored.
SIMULATION = {"bounces": 1, "bounce_set": (1,), "seed": 1, "amplitude": "intensity",
              "mc_snr_db": None}   # None: sonarsim.simulate.DEFAULT_MC_SNR_DB

# Reference numbers: the paper's Table 2 (the project page's table.png; mean over the 8
# simulated scenes, 54 000 poses, 125 x 125 x 94 voxels). PSNR sits beside our depth PSNR
# (the reference's image metrics use depth renders by default, evaluate/main_image_space_loss.py).
REFERENCE = {
    "Backprojection": {"chamfer_sq": 1.36e-4, "iou": 0.2928, "lpips": 0.1215, "psnr": 15.783},
    "Gradient Descent": {"chamfer_sq": 2.21e-4, "iou": 0.4309, "lpips": 0.1236, "psnr": 15.117},
    "PFA": {"chamfer_sq": 2.13e-4, "iou": 0.3586, "lpips": 0.1238, "psnr": 15.048},
    "Neural BP (Ours)": {"chamfer_sq": 1.12e-4, "iou": 0.5194, "lpips": 0.0988, "psnr": 17.918},
}


@dataclass(frozen=True)
class Settings:
    """How much of the reference protocol a run does.

    Poses: every ``angle_step``-th of the 360 angles and every ``height_step``-th of the 150
    heights of the reference's cylindrical scan (the aperture keeps its extent; reference
    1, 1 = 54 000). ``paths_per_pose`` None = the simulator's fidelity default. ``shape``:
    voxels over the scene box (reference 125 x 125 x 94). ``gd_iterations`` /
    ``nbp_iterations``: optimiser steps. ``samples``: surface samples per mesh (Chamfer);
    ``volume_samples``: GT volume samples of the reference protocol; ``view_resolution``:
    image size for both protocols' image metrics (None = each protocol's own: 256 / 512).
    ``sweep_methods``: methods of the SNR-sweep and bandwidth rows (None = all).
    ``threshold_sweep``: also report each metric at its best τ (0.05 … 0.95).
    ``deconvolution``: how the GD and NBP cells' data are pulse-deconvolved ('wiener': seconds;
    'inr': the paper's neural deconvolution, about 0.1 s per ping on 2 CPU cores).
    ``nbp_warm_start_iterations``: the NBP network's fit to BP before its iterations (None:
    the preset's; the quick size uses 5, where the preset's 300 cost most of the CI run).
    ``surface_spacing``: the simulator's surface-strata spacing (m; None = its default, 8 mm;
    the quick size uses 16 mm: a quarter less simulation, MC SNR 35 instead of 38 dB).
    ``figure_resolution`` / ``figure_dpi``: the render size and dpi of ``table2.png``.
    ``solver_output``: what GD and NBP export ('field': the fitted field, e.g. to apply another
    solid extraction post hoc; 'solid'; None: their preset's).
    ``refine_options``: the ``recon refine`` options of the NBP + refine row (() = the
    command's defaults; the quick size runs a few steps on a quarter of the pings).
    """
    angle_step: int
    height_step: int
    paths_per_pose: int | None
    shape: tuple[int, int, int]
    gd_iterations: int
    nbp_iterations: int
    samples: int = 20_000
    volume_samples: int = 50_000
    view_resolution: int | None = None
    sweep_methods: tuple[str, ...] | None = None
    threshold_sweep: bool = True
    deconvolution: str = "wiener"     # 'wiener' or 'inr' (recon.deconvolution) for GD and NBP
    nbp_warm_start_iterations: int | None = None   # None: the nbp preset's (its BP warm start)
    surface_spacing: float | None = None   # simulator's surface strata (m); None: its default
    solver_output: str | None = None  # GD/NBP 'output' ('field' or 'solid'); None: the preset's
    figure_resolution: int = 160      # table2.png: render size (pixels) and dpi
    figure_dpi: int = 100
    refine_options: tuple[str, ...] = ()   # `recon refine` options of the NBP + refine row
                                           # (() = the command's defaults)

    @property
    def n_poses(self) -> int:
        return len(range(0, 360, self.angle_step)) * len(range(0, 150, self.height_step))

    @property
    def n_pings(self) -> int:
        """Pings each reconstruction sees (every pose of the scan)."""
        return self.n_poses

    def data_digest(self) -> str:
        """Digest of what the simulation depends on only (poses, fidelity, the module-level
        simulation constants): the dataset's file name. Solver, grid and evaluation settings
        never re-simulate."""
        key = {"angle_step": self.angle_step, "height_step": self.height_step,
               "paths_per_pose": self.paths_per_pose, "simulation": SIMULATION, "pulses": PULSES}
        if self.surface_spacing is not None:      # (absent: the digests of earlier scans hold)
            key["surface_spacing"] = self.surface_spacing
        key = json.dumps(key, sort_keys=True, default=str)
        return identity.digest(key, length=8)

    def digest(self) -> str:
        """Short digest of these settings and the module-level simulation constants: part of
        every file name, so files of other settings are never reused."""
        key = json.dumps({"settings": asdict(self), "simulation": SIMULATION, "pulses": PULSES,
                          "threshold": THRESHOLD, "crop_z": CROP_Z, "bounds": GRID_BOUNDS},
                         sort_keys=True, default=str)
        return identity.digest(key, length=8)


SIZES = {
    # the reference's size; the solvers' steps are their frozen presets' (one home)
    "default": Settings(angle_step=1, height_step=1, paths_per_pose=None, shape=(125, 125, 94),
                        gd_iterations=PRESETS["gd"]["iterations"],
                        nbp_iterations=PRESETS["nbp"]["iterations"]),
    "quick": Settings(angle_step=20, height_step=15, paths_per_pose=300, shape=(25, 25, 19),
                      gd_iterations=5, nbp_iterations=3, samples=1000, volume_samples=3000,
                      view_resolution=32, sweep_methods=("pfa",), threshold_sweep=False,
                      nbp_warm_start_iterations=5, surface_spacing=0.016,
                      figure_resolution=48, figure_dpi=50,
                      refine_options=("--pings", "::4", "--envelope-steps", "2",
                                      "--waveform-steps", "1", "--wrap", "0", "--smooth", "0",
                                      "--grow-unexplained", "0", "--edge-length", "0.02")),
}


@dataclass(frozen=True)
class Method:
    """A reconstructor of the table: the ``sonarsim batch`` reconstruction method ``key``
    (its module: :data:`recon.batch_step.METHOD_MODULES`, the one method -> module map) with
    the options ``options(settings)``.

    ``deconvolved``: the method fits the pulse-deconvolved dataset (the paper's pipeline:
    deconvolve, then NBP; its GD baseline is NBP without the network, on the same data),
    made once per dataset by the batch step's ``deconvolve`` (``Settings.deconvolution``)."""
    key: str
    label: str                       # the reference's row name (REFERENCE)
    options: Callable[[Settings], dict] = field(default=lambda s: {})
    deconvolved: bool = False

    @property
    def module(self) -> str:
        from recon.batch_step import METHOD_MODULES
        return METHOD_MODULES[self.key]


METHODS = (
    Method("bp", "Backprojection"),
    Method("gd", "Gradient Descent",
           lambda s: {"iterations": s.gd_iterations, "seed": SIMULATION["seed"],
                      **({} if s.solver_output is None else {"output": s.solver_output})}, True),
    Method("pfa", "PFA"),
    Method("nbp", "Neural BP (Ours)",
           lambda s: {"iterations": s.nbp_iterations, "seed": SIMULATION["seed"],
                      **({} if s.nbp_warm_start_iterations is None else
                         {"warm_start_iterations": s.nbp_warm_start_iterations}),
                      **({} if s.solver_output is None else {"output": s.solver_output})}, True),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}
# Not a batch method: ``recon refine`` of each main NBP cell's solid, after the batch
# (:func:`refine_results`); no published row (the paper has no refinement).
REFINE = Method("refine", "NBP + recon refine")


@dataclass(frozen=True)
class Cell:
    method: str
    shape: str
    snr_db: float
    bandwidth: str

    @property
    def name(self) -> str:
        return f"{self.method}_{self.shape}_{self.bandwidth}_{self.snr_db:g}dB"

    @property
    def dataset_name(self) -> str:
        return f"{self.shape}_{self.bandwidth}_{self.snr_db:g}dB"


def available_methods(keys: list[str] | None) -> tuple[list[Method], list[str]]:
    """(methods whose module imports and has ``solve``, notes on the others)."""
    if keys is not None:
        unknown = set(keys) - set(METHOD_BY_KEY)
        if unknown:
            raise SystemExit(f"--methods: unknown {sorted(unknown)}; choose from {list(METHOD_BY_KEY)}")
    chosen, notes = [], []
    for m in METHODS:
        if keys is not None and m.key not in keys:
            continue
        try:
            module = importlib.import_module(m.module)
        except ModuleNotFoundError as exc:
            if exc.name != m.module:
                raise
            notes.append(f"{m.label}: not run ({m.module} does not exist)")
            continue
        if not callable(getattr(module, "solve", None)):
            notes.append(f"{m.label}: not run ({m.module} has no solve())")
            continue
        chosen.append(m)
    return chosen, notes


def cells_of(methods: list[str], shapes: list[str], settings: Settings) -> list[Cell]:
    """Every cell of the table: all methods x shapes at the main SNR and bandwidth, then the
    SNR sweep and the other bandwidths for the first shape (the bunny when at hand)."""
    cells = [Cell(m, s, MAIN_SNR_DB, MAIN_BANDWIDTH) for s in shapes for m in methods]
    sweep = [m for m in methods if settings.sweep_methods is None or m in settings.sweep_methods]
    if shapes:
        cells += [Cell(m, shapes[0], snr, MAIN_BANDWIDTH) for snr in SWEEP_SNR_DB
                  if snr != MAIN_SNR_DB for m in sweep]
        cells += [Cell(m, shapes[0], MAIN_SNR_DB, bw) for bw in SWEEP_BANDWIDTHS for m in sweep]
    return cells


# ------------------------------------------------------------------------ one cell

def scene_spec(name: str, out: Path, source: str = "auto") -> tuple[str, str] | None:
    """(scene spec for load_scene, description of its source), or None if unavailable.

    The shared meshes are the reference's GT meshes in the rig frame at the reference's scale,
    used as they are (``fit = false``) on the reference's ground plane (0.4 x 0.4 m, albedo 1).
    """
    from sonarsim import data
    mesh = data.root() / "meshes" / f"{name}.obj"
    if source in ("auto", "shared") and mesh.is_file():
        toml = out / "data" / f"{name}.toml"
        toml.parent.mkdir(parents=True, exist_ok=True)
        text = f'name = "{name}"\nground = true\n\n[[object]]\nmesh = "{mesh}"\nfit = false\n'
        if not toml.is_file() or toml.read_text() != text:
            toml.write_text(text)
        return str(toml), f"shipped reference mesh {mesh.name}"
    if source == "shared":
        raise SystemExit(f"scene {name!r}: {mesh} not found (--scene-source shared)")
    if name in ("cube", "cylinder"):
        return name, f"shipped procedural scene '{name}'"
    return None


def cylindrical_indices(settings: Settings) -> np.ndarray:
    """Indices into the reference's 360 x 150 cylindrical scan (height-major, angle fastest)
    of every ``angle_step``-th angle and ``height_step``-th height."""
    from sonarsim.geometry import CYLINDRICAL_ANGLES, cylindrical_grid
    idx = np.arange(cylindrical_grid()[0].size)
    keep = ((idx % CYLINDRICAL_ANGLES) % settings.angle_step == 0) & \
           ((idx // CYLINDRICAL_ANGLES) % settings.height_step == 0)
    return np.flatnonzero(keep)


def cylindrical_poses(settings: Settings, box):
    """Every angle_step-th angle and height_step-th height of the reference's 360 x 150 scan."""
    from sonarsim.geometry import cylindrical_grid, rig_poses
    angles, heights = cylindrical_grid()
    keep = cylindrical_indices(settings)
    return rig_poses(angles[keep], heights[keep], box=box)


def poses_file(settings: Settings, box, out: Path) -> Path:
    """The table's poses as a ``sonarsim batch`` pose file (``.npy``, one row per ping: TX,
    RX, TX boresight, RX boresight; docs/batch.md), written once per pose set and box."""
    poses = cylindrical_poses(settings, box)
    table = np.concatenate([poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight], axis=1)
    key = identity.digest(np.ascontiguousarray(table), length=8)
    path = out / "data" / f"poses_{settings.angle_step}x{settings.height_step}_{key}.npy"
    if not path.is_file():
        from sonarsim.atomic import atomic_path
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, table)
    return path


def job_name(cell: Cell, settings: Settings) -> str:
    """The batch job (= dataset) of a cell: named by what the simulation depends on only."""
    return f"{cell.dataset_name}_{settings.data_digest()}"


def step_label(method: Method, step: dict) -> str:
    """The batch step (= volume and metrics files) of a method: the method and a digest of
    the step's table *and* of the solver's effective settings (its code presets included:
    a preset changed in code gives new files instead of reusing volumes made with the old
    one)."""
    from recon import batch_step
    from sonarsim.identity import digest
    mod = importlib.import_module(method.module)
    options = {k: v for k, v in step.items() if k not in batch_step.STEP_KEYS}
    effective = batch_step.option_defaults(mod, options)[0]
    return f"{method.key}-{digest(step, {**effective, **options}, length=8)}"


def evaluations(settings: Settings) -> list[dict]:
    """The two evaluations of every volume (``recon evaluate``'s options as batch
    ``evaluate`` tables): exact, crop z >= 5 mm (the ground plane is not in the GT meshes),
    threshold sweep; reference, as the reference evaluates: the whole box, ground included."""
    common = {"threshold": THRESHOLD, "samples": settings.samples, "images": True,
              "volume_samples": settings.volume_samples, "sweep": settings.threshold_sweep}
    if settings.view_resolution:
        common["view_resolution"] = settings.view_resolution
    return [{"name": "reference", "protocol": "reference", **common},
            {"name": "exact", "protocol": "exact",
             "crop": [-1e3, 1e3, -1e3, 1e3, CROP_Z, 1e3], **common}]


def manifest(cells: list[Cell], settings: Settings, out: Path, source: str = "auto"
             ) -> tuple[dict, dict[str, tuple[str, str]]]:
    """(the ``sonarsim batch`` manifest of the table, {cell name: (job name, step label)}).

    A job per dataset (shape, SNR, bandwidth): the cylindrical poses of ``settings``
    (:func:`poses_file`), the table's simulation settings; one ``reconstruct`` step per cell
    of that dataset, on the whole grid over the scene box, pulse-deconvolved first where the
    method asks (one deconvolved file per job, shared), evaluated with both protocols."""
    from sonarsim.scene import load_scene
    # absolute paths: the manifest lives in out/batch and resolves relative paths against its
    # own folder, not against the working directory a relative --out was given in
    out = Path(out).resolve()
    jobs: dict[str, dict] = {}
    where: dict[str, tuple[str, str]] = {}
    bounds = [v for pair in GRID_BOUNDS for v in pair]
    for cell in cells:
        name = job_name(cell, settings)
        if name not in jobs:
            found = scene_spec(cell.shape, out, source)
            if found is None:
                raise SystemExit(f"scene {cell.shape}: no shared mesh and no shipped scene")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")      # the batch reports them once
                box = load_scene(found[0]).box
            job = {"name": name, "scene": found[0],
                   "poses": str(poses_file(settings, box, out)),
                   "pulse": PULSES[cell.bandwidth], "snr_db": float(cell.snr_db),
                   **{k: (list(v) if isinstance(v, tuple) else v)
                      for k, v in SIMULATION.items() if v is not None}}
            if settings.paths_per_pose is not None:
                job["paths_per_pose"] = int(settings.paths_per_pose)
            if settings.surface_spacing is not None:
                job["surface_spacing"] = float(settings.surface_spacing)
            job["reconstruct"] = []
            jobs[name] = job
        m = METHOD_BY_KEY[cell.method]
        step = {"method": m.key, "shape": list(settings.shape), "bounds": bounds,
                **m.options(settings)}
        if m.deconvolved:
            step["deconvolve"] = settings.deconvolution
        step["evaluate"] = evaluations(settings)
        label = step_label(m, step)
        jobs[name]["reconstruct"].append({"label": label, **step})
        where[cell.name] = (name, label)
    return {"job": list(jobs.values())}, where


def write_manifest(doc: dict, path: Path) -> None:
    """``doc`` (jobs with ``reconstruct`` lists) as a TOML manifest (``sonarsim batch``)."""
    import tomli_w
    from sonarsim.atomic import atomic_path
    text = "# benchmarks/table2.py: Table 2 as a sonarsim batch (docs/batch.md)\n\n" + tomli_w.dumps(doc)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


# ------------------------------------------------------- adopting datasets simulated before

def simulation_mismatches(path: Path, job) -> list[str]:
    """What differs between the dataset ``path`` and what batch ``job`` would simulate (empty:
    the same simulation). Compared: the poses (TX, RX and both boresights of every ping), the
    pulse (samples, rate, spec), the scene (box, ground, every object's mesh, albedo and
    normals, from the dataset's recorded ``scene_source``) and every simulation setting the
    dataset records (SNR, seed, sound speed, bounces, oversampling, beams, amplitude model,
    Monte-Carlo target or explicit sampling, bounce-1 estimator, speckle seed, transients).
    The simulator's code version is not compared: an adopted scan is the same simulation by
    its parameters, made by the sonarsim of its ``generator`` meta."""
    from sonarsim.batch.plan import build_simulation
    from sonarsim.dataset import KIND_DATASET, SonarDataset, inspect
    from sonarsim.errors import SonarsimError
    from sonarsim.render import DEFAULT_BEAMS
    from sonarsim.scene import load_scene
    try:
        with inspect(path) as (kind, f):
            if kind != KIND_DATASET or not f.get("complete", False):
                return ["not a complete sonar dataset"]
        data = SonarDataset.read(path, transients=False)
    except (SonarsimError, OSError) as exc:
        return [f"unreadable ({exc})"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec, poses, s, _ = build_simulation(job.params)
    meta = data.meta or {}
    bad: list[str] = []

    def same(name, ours, theirs, tol=0.0):
        a, b = np.asarray(ours), np.asarray(theirs)
        ok = a.shape == b.shape and (np.array_equal(a, b) if a.dtype.kind in "OUSb" or tol == 0
                                     else np.allclose(a, b, rtol=0, atol=tol))
        if not ok:
            bad.append(name)

    if data.n_pings != len(poses.tx):
        return [f"{data.n_pings} pings, the job has {len(poses.tx)}"]
    same("tx", poses.tx, data.tx, 1e-9)
    same("rx", poses.rx, data.rx, 1e-9)
    same("tx boresight", poses.tx_boresight, data.boresight, 1e-9)
    same("rx boresight", poses.rx_boresight, data.receiver_boresight, 1e-9)
    same("pulse", s.pulse.samples, data.pulse, 1e-12)
    same("fs", s.pulse.fs, data.fs)
    same("pulse spec", str(s.pulse.spec), str(meta.get("pulse_spec")))
    same("snr_db", float(s.snr_db), float(data.snr_db))
    same("seed", int(s.seed), int(data.seed))
    same("sound speed", float(s.sound_speed), float(data.sound_speed))
    expected = {"bounces": int(s.bounces), "bounce_set": [b + 1 for b in s.bounce_index],
                "oversample": int(s.oversample), "amplitude_model": s.amplitude,
                "beams": {**DEFAULT_BEAMS, **dict(s.beams or {})},
                "mc_snr_target_db": None if s.target_mc_snr_db is None else float(s.target_mc_snr_db),
                "bounce1_estimator": s.bounce1,
                "speckle_seed": int(s.speckle_seed) if s.amplitude == "coherent" else None}
    if s.paths_per_pose is not None:
        expected["paths_per_pose"] = int(s.paths_per_pose)
    if s.surface_spacing is not None:
        expected["surface_spacing"] = float(s.surface_spacing)
    for key, value in expected.items():
        if meta.get(key) != value:
            bad.append(f"{key} {meta.get(key)!r} (the job: {value!r})")
    if bool(s.keep_transients) != bool(data.transients is not None):
        bad.append("transients")
    source = meta.get("scene_source")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            theirs = load_scene(source)
    except (SonarsimError, OSError, TypeError) as exc:
        return bad + [f"scene: its source {source!r} cannot be loaded ({exc})"]
    same("scene box", [spec.box.lo, spec.box.hi], [theirs.box.lo, theirs.box.hi], 1e-12)
    same("ground", repr(spec.ground), repr(theirs.ground))
    if len(spec.objects) != len(theirs.objects):
        bad.append("scene objects")
    else:
        for i, (a, b) in enumerate(zip(spec.objects, theirs.objects)):
            same(f"object[{i}] vertices", a.mesh.vertices, b.mesh.vertices, 1e-12)
            same(f"object[{i}] faces", a.mesh.faces, b.mesh.faces)
            same(f"object[{i}] albedo", repr(a.albedo), repr(b.albedo))
            same(f"object[{i}] normals", repr(a.normals), repr(b.normals))
    return bad


def adopt_datasets(plan, data_dir: Path, log: Callable[[str], None] = print) -> dict[str, str]:
    """Give every job of ``plan`` without its dataset yet a scan from ``data_dir`` that is the
    same simulation (:func:`simulation_mismatches` empty): the scan is copied to the job's
    output with the batch's job metadata added, so the batch skips its simulation. The files
    in ``data_dir`` are only read. Returns {job name: adopted path}."""
    from sonarsim.batch.identity import job_meta
    from sonarsim.batch.records import dataset_record
    from sonarsim.dataset import SonarDataset
    if not data_dir.is_dir():
        raise SystemExit(f"--data {data_dir}: not a directory")
    candidates = sorted(p for p in data_dir.glob("*.h5") if "_pd-" not in p.name
                        and ".pd-" not in p.name)
    adopted = {}
    for job in plan.jobs:
        if dataset_record(job.output, job.job_id) is not None:
            continue
        n_pings = len(np.load(job.params["poses"], mmap_mode="r"))
        for path in candidates:
            try:
                from sonarsim.dataset import inspect
                with inspect(path) as (_, f):
                    if int(f["tx"].shape[0]) != n_pings:
                        continue
            except Exception:           # noqa: BLE001 -- not a dataset: not a candidate
                continue
            problems = simulation_mismatches(path, job)
            if problems:
                log(f"--data: {path.name} is not job {job.name}'s simulation: "
                    + "; ".join(problems[:4]))
                continue
            data = SonarDataset.read(path)
            data.meta = {**(data.meta or {}), **job_meta(job),
                         "adopted_from": str(path.resolve())}
            Path(job.output).parent.mkdir(parents=True, exist_ok=True)
            data.write(job.output)
            if dataset_record(job.output, job.job_id) is None:
                raise SystemExit(f"--data: {job.output}: the adopted copy is not job "
                                 f"{job.name}'s dataset")
            log(f"--data: job {job.name}: adopted {path} (the same simulation: poses, pulse, "
                "scene and settings compared)")
            adopted[job.name] = str(path)
            break
    return adopted


def run_batch(cells: list[Cell], settings: Settings, out: Path, source: str = "auto",
              scheduler: str = "sequential", workers: int | None = None,
              data_dir: Path | None = None) -> list[dict]:
    """Run the table as a ``sonarsim batch`` in ``out/batch`` (simulate, deconvolve,
    reconstruct, evaluate: the batch's resume, locks and records) and return one result
    dict per cell (:func:`cell_result`). ``scheduler``: 'sequential' (this process, the
    default), 'local' (a Dask LocalCluster of ``workers``) or a scheduler address."""
    from sonarsim.batch import plan_batch, run_batch as batch_run
    from sonarsim.batch_engine import Engine
    doc, where = manifest(cells, settings, out, source)
    path = out / "batch" / "table2.toml"
    write_manifest(doc, path)
    plan = plan_batch(path, out / "batch", log=lambda m: print(m, flush=True))
    if data_dir is not None:
        adopt_datasets(plan, data_dir, log=lambda m: print(m, flush=True))
    with Engine(None if scheduler == "local" else scheduler, workers=workers) as engine:
        result = batch_run(plan, engine, progress=False, log=lambda m: print(m, flush=True))
    if result.failed:
        raise SystemExit("table2: cells failed:\n" + "\n".join(
            f"{n}: {result.errors.get(n, result.status[n])}" for n in result.failed))
    jobs = {j.name: j for j in plan.jobs}
    sim_times = _simulation_times(result.csv)
    return [cell_result(cell, jobs[where[cell.name][0]], where[cell.name][1], settings,
                        plan.warnings, sim_times) for cell in cells]


def _scene_note(note: str, scene: str) -> str:
    """A batch plan's scene warning ('<file>: <scene path>: <message>') as its message."""
    rest = note.split(": ", 1)[-1]
    return rest[len(scene) + 2:] if rest.startswith(scene + ": ") else rest


def _simulation_times(csv_path: Path) -> dict[str, tuple[float | None, float | None]]:
    """{job: (simulation wall time, its CPU time) (s)} from the batch's ``batch.csv`` (None
    where the job's scan was not simulated by this batch, e.g. adopted with ``--data``)."""
    def number(text):
        return float(text) if text else None
    with open(csv_path, newline="") as fh:
        return {r["job"]: (number(r.get("wall_s")), number(r.get("cpu_s")))
                for r in csv.DictReader(fh)}


def cell_result(cell: Cell, job, label: str, settings: Settings, notes: list[str],
                sim_times: dict) -> dict:
    """One cell from the batch's files: cell keys, ``time_s`` (the solve's wall time),
    ``stages_s`` (dataset, deconvolve, solve, evaluate; wall) and ``stages_cpu_s`` (the same
    stages' CPU time, user + system; None where not recorded), the ``volume`` and ``dataset``
    paths, the measured SNR and ``exact`` and ``reference`` metrics (``recon evaluate``'s)."""
    from sonarsim.dataset import inspect
    step = next(s for s in job.recon if s.label == label)
    metrics, wall, cpu = {}, {}, {}
    for evaluation in step.evaluations:
        saved = json.loads(Path(evaluation.output).read_text())
        metrics[evaluation.name] = {k: v for k, v in saved["metrics"].items() if k != "sweep"}
        wall, cpu = saved.get("wall_s", {}), saved.get("cpu_s", {})
    with inspect(job.output) as (_, f):
        measured = (f.get("meta") or {}).get("effective_snr_db", f.get("snr_db"))
        mc = (f.get("meta") or {}).get("mc_snr_db")
        n_pings = int(f["tx"].shape[0])
    deconv = step.settings.get("deconvolve")
    evaluate_s = sum(v for k, v in wall.items() if k.startswith("evaluate") and v)
    evaluate_cpu = [v for k, v in cpu.items() if k.startswith("evaluate")]
    sim_wall, sim_cpu = sim_times.get(job.name, (None, None))
    m = METHOD_BY_KEY[cell.method]
    return {"cell": cell.name, "method": cell.method, "label": m.label, "shape": cell.shape,
            "snr_db": float(cell.snr_db), "bandwidth": cell.bandwidth,
            "settings_digest": settings.digest(), "job": job.name, "step": label,
            "dataset": job.output, "fitted": deconv["output"] if deconv else job.output,
            "volume": step.output, "time_s": wall.get("solve"), "measured_snr_db": measured,
            "mc_snr_db": mc, "n_pings": n_pings,
            "notes": [f"scene {cell.shape}: {_scene_note(n, job.params['scene'])}"
                      for n in notes
                      if Path(n.split(": ", 1)[0]).stem == Path(job.params["scene"]).stem],
            "reference": metrics["reference"], "exact": metrics["exact"],
            "evaluate_s": evaluate_s,
            "stages_s": {"dataset_s": sim_wall, "deconvolve_s": wall.get("deconvolve"),
                         "solve_s": wall.get("solve"), "evaluate_s": evaluate_s},
            "stages_cpu_s": {"dataset_s": sim_cpu, "deconvolve_s": cpu.get("deconvolve"),
                             "solve_s": cpu.get("solve"),
                             "evaluate_s": sum(evaluate_cpu) if evaluate_cpu else None}}


# ------------------------------------------------------------- the NBP + refine row

def refine_key(options: tuple[str, ...]) -> str:
    """Digest of what a refinement depends on besides its dataset and NBP solid: the options
    and the command's defaults in code (a changed default makes new files, as a changed
    preset does for the batch's cells)."""
    from recon.commands import refine as command
    from recon.refine import RefineSettings
    from recon.unexplained import RESIDUAL_PINGS, UNEXPLAINED_BEYOND
    key = {"options": list(options), "settings": asdict(RefineSettings()),
           "wrap": command.DEFAULT_WRAP, "smooth": command.DEFAULT_SMOOTH,
           "shrink": command.DEFAULT_SHRINK, "seal": command.DEFAULT_SEAL,
           "start": "a solid's parts all kept; non-finite gradients cleared",
           "seat": [command.SEAT_BY_DEFAULT, "z_min + voxel + lift"],
           "unexplained": [command.DEFAULT_UNEXPLAINED, RESIDUAL_PINGS, UNEXPLAINED_BEYOND]}
    return identity.digest(json.dumps(key, sort_keys=True, default=str), length=8)


def _start_refine(dataset: str, volume: str, mesh: str, history: str, options: list[str],
                  threads: int, log: Path):
    """Start ``recon refine DATASET --init VOLUME --out MESH`` with ``options`` in a child
    process (its output to ``log``); returns (process, start time). :func:`_finished_refine`
    reaps it. A child, not a fork of this process: Dr.Jit's threads do not survive fork."""
    import subprocess
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "recon.cli", "refine", dataset, "--init",
                                 volume, "--out", mesh, "--history", history, "--no-progress",
                                 "--threads", str(threads), "--force", *options],
                                stdout=fh, stderr=subprocess.STDOUT)
    return proc, time.perf_counter()


def _finished_refine(proc, t0: float) -> dict | None:
    """A :func:`_start_refine` child's exit status, wall and CPU seconds (user + system, its
    own rusage) if it has ended, else None (does not block)."""
    pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
    if pid == 0:
        return None
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"rc": proc.returncode, "wall_s": time.perf_counter() - t0,
            "cpu_s": usage.ru_utime + usage.ru_stime}


def refine_results(results: list[dict], settings: Settings, workers: int | None = None
                   ) -> tuple[list[dict], list[str]]:
    """The NBP + refine row: ``recon refine`` of each main NBP cell's solid on its dataset
    (``settings.refine_options``), the mesh scored with both evaluations of the table
    (:func:`evaluations`; a mesh has no threshold sweep). Files beside the NBP volume,
    ``<volume stem>.refine-<key>.ply`` / ``.json`` (history) / ``.<protocol>.json`` (metrics,
    with the wall and CPU seconds); a later run reuses them. Shapes run in ``workers``
    processes at once (default 2, one thread each). Returns (rows shaped as
    :func:`cell_result`'s, notes on refinements that failed)."""
    from recon.evaluation import evaluate_file, json_safe
    from sonarsim.atomic import atomic_path
    nbp = [r for r in main_rows(results) if r["method"] == "nbp"]
    label = f"refine-{refine_key(settings.refine_options)}"
    todo, rows, notes = [], [], []
    for r in nbp:
        stem = Path(r["volume"]).with_suffix("")
        files = {"mesh": f"{stem}.{label}.ply", "history": f"{stem}.{label}.json",
                 **{p: f"{stem}.{label}.{p}.json" for p in PROTOCOLS}}
        todo.append((r, files))
    n_workers = max(1, min(workers or 2, len(todo)))
    threads = 1 if n_workers > 1 else (os.cpu_count() or 1)
    runs, queue, running = {}, [(r, f) for r, f in todo
                                 if not all(Path(f[p]).is_file() for p in PROTOCOLS)], []
    try:
        while queue or running:         # at most n_workers children at once
            while queue and len(running) < n_workers:
                r, files = queue.pop(0)
                running.append((r, _start_refine(r["dataset"], r["volume"], files["mesh"],
                                                 files["history"], list(settings.refine_options),
                                                 threads, Path(files["mesh"]).with_suffix(".log"))))
            time.sleep(0.2)
            for item in list(running):
                r, (proc, t0) = item
                ended = _finished_refine(proc, t0)
                if ended is not None:
                    runs[r["shape"]] = ended
                    running.remove(item)
    finally:                            # an interrupted table leaves no refinement running
        for _, (proc, _) in running:
            proc.kill()
            proc.wait()
    for r, files in todo:
        if r["shape"] in runs:
            run = runs[r["shape"]]
            if run["rc"] != 0:
                notes.append(f"{REFINE.label} {r['shape']}: recon refine exited with "
                             f"{run['rc']} (its output: {Path(files['mesh']).with_suffix('.log')}); "
                             "no row")
                continue
            for evaluation in evaluations(settings):
                opts = {k: v for k, v in evaluation.items()
                        if k not in ("name", "threshold", "sweep")}
                t0, c0 = time.perf_counter(), time.process_time()
                found = evaluate_file(Path(files["mesh"]), r["dataset"], **opts)
                saved = {"job": r["job"], "evaluation": evaluation["name"],
                         "metrics": {k: v for k, v in found.items() if k != "sweep"},
                         "wall_s": {"solve": run["wall_s"], "evaluate": time.perf_counter() - t0},
                         "cpu_s": {"solve": run["cpu_s"], "evaluate": time.process_time() - c0}}
                with atomic_path(Path(files[evaluation["name"]])) as tmp:
                    Path(tmp).write_text(json.dumps(json_safe(saved), indent=1, default=str))
        if not all(Path(files[p]).is_file() for p in PROTOCOLS):
            continue
        saved = {p: json.loads(Path(files[p]).read_text()) for p in PROTOCOLS}
        # the refinement's times are in every evaluation's file; the evaluations' add up
        wall = {"solve": saved["reference"]["wall_s"]["solve"],
                "evaluate": sum(saved[p]["wall_s"]["evaluate"] for p in PROTOCOLS)}
        cpu = {"solve": saved["reference"]["cpu_s"]["solve"],
               "evaluate": sum(saved[p]["cpu_s"]["evaluate"] for p in PROTOCOLS)}
        rows.append({**{k: r[k] for k in ("snr_db", "bandwidth", "shape", "job", "dataset",
                                          "measured_snr_db", "mc_snr_db", "n_pings")},
                     "cell": f"refine_{r['shape']}_{r['bandwidth']}_{r['snr_db']:g}dB",
                     "method": REFINE.key, "label": REFINE.label,
                     "settings_digest": settings.digest(), "step": label,
                     "init": r["volume"], "fitted": r["dataset"], "volume": files["mesh"],
                     "time_s": wall["solve"], "notes": [],
                     "reference": saved["reference"]["metrics"],
                     "exact": saved["exact"]["metrics"], "evaluate_s": wall["evaluate"],
                     "stages_s": {"refine_s": wall["solve"], "evaluate_s": wall["evaluate"]},
                     "stages_cpu_s": {"refine_s": cpu["solve"],
                                      "evaluate_s": cpu["evaluate"]}})
    return rows, notes


def stage_sums(results: list[dict], key: str = "stages_s") -> tuple[dict, list[str]]:
    """({stage: seconds summed over ``results``' cells}, [stages some cell lacks]) of the
    cells' ``key`` (``stages_s`` wall, ``stages_cpu_s`` CPU); a job's simulation counts once
    (its cells share it)."""
    totals, missing, jobs_seen = {}, set(), set()
    for r in results:
        for k, v in (r.get(key) or {}).items():
            if k == "dataset_s":
                if r["job"] in jobs_seen:
                    continue
                jobs_seen.add(r["job"])
            totals[k] = totals.get(k, 0.0) + (v or 0.0)
            if v is None and not (k == "deconvolve_s" and r["method"] in ("bp", "pfa")):
                missing.add(k[:-2])
    return totals, sorted(missing)


# ------------------------------------------------------------------------------ outputs

def fmt(value, spec: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return format(value, spec)


def finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


TABLE_KEYS = {"chamfer_sq": ".2e", "iou": ".4f", "lpips": ".4f", "psnr_depth": ".3f"}


def mean_over(rows: list[dict], protocol: str, key: str):
    """Mean of ``row[protocol][key]`` over rows, None if any row lacks a finite value."""
    vals = [r[protocol].get(key) for r in rows]
    return float(np.mean(vals)) if vals and all(finite(v) for v in vals) else None


def main_rows(results: list[dict]) -> list[dict]:
    return [r for r in results if r["snr_db"] == MAIN_SNR_DB and r["bandwidth"] == MAIN_BANDWIDTH]


def write_markdown(path: Path, results, methods, summary: str, notes: list[str]) -> None:
    main = main_rows(results)
    shapes = sorted({r["shape"] for r in main})
    lines = ["# Table 2", "", f"Settings: {summary}.", "",
             f"Threshold τ = {THRESHOLD} on the min–max-normalised magnitude; the per-shape rows "
             "add each metric at its best τ of the sweep and the mean angle between reconstructed "
             "and GT surface normals. LPIPS is not computed (n/a; docs/evaluation.md). PSNR = depth "
             "renders. Chamfer = squared, mean each way, summed (m²).", ""]
    for protocol in PROTOCOLS:
        title = {"reference": "the reference's protocol (`recon evaluate --protocol reference`)",
                 "exact": "the exact protocol (`recon evaluate`, ground left out: z ≥ 5 mm)"}
        lines += [f"## Mean over {', '.join(shapes)} at 20 kHz / 20 dB — {title[protocol]}", "",
                  "| Method | Chamfer ↓ | IoU ↑ | LPIPS ↓ | PSNR ↑ | | published: Chamfer "
                  "| IoU | LPIPS | PSNR | | ours at best τ: Chamfer | IoU | normal error (°) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for m in methods:
            sel = [r for r in main if r["method"] == m.key]
            ref = REFERENCE.get(m.label)
            ours = " | ".join(fmt(mean_over(sel, protocol, k), spec)
                              for k, spec in TABLE_KEYS.items())
            best = " | ".join(fmt(mean_over(sel, protocol, k), spec) for k, spec in
                              (("best_chamfer_sq", ".2e"), ("best_iou", ".4f"),
                               ("normal_error_deg", ".1f")))
            published = ("– | – | – | –" if ref is None else
                         f"{ref['chamfer_sq']:.2e} | {ref['iou']:.4f} | {ref['lpips']:.4f} | "
                         f"{ref['psnr']:.3f}")
            lines.append(f"| {m.label} | {ours} | | {published} | | {best} |")
        lines.append("")
    lines += ["## Per shape (20 kHz / 20 dB)", "",
              "| shape | method | protocol | Chamfer | Chamfer best @ τ | IoU | IoU best @ τ | "
              "normal error (°) | PSNR depth | SSIM depth | time (s) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(main, key=lambda r: (r["shape"], [m.key for m in methods].index(r["method"]))):
        for protocol in PROTOCOLS:
            e = r[protocol]
            lines.append(
                f"| {r['shape']} | {r['label']} | {protocol} | {fmt(e.get('chamfer_sq'), '.2e')} "
                f"| {fmt(e.get('best_chamfer_sq'), '.2e')} @ "
                f"{fmt(e.get('best_chamfer_sq_threshold'), '.2f')} "
                f"| {fmt(e.get('iou'), '.4f')} | {fmt(e.get('best_iou'), '.4f')} @ "
                f"{fmt(e.get('best_iou_threshold'), '.2f')} | {fmt(e.get('normal_error_deg'), '.1f')} "
                f"| {fmt(e.get('psnr_depth'), '.2f')} | "
                f"{fmt(e.get('ssim_depth'), '.3f')} | {fmt(r.get('time_s'), '.1f')} |")
    sweep = [r for r in results if r not in main]
    if sweep:
        lines += ["", f"## SNR sweep and bandwidth ({sweep[0]['shape']}, reference protocol)", "",
                  "| method | bandwidth | SNR (dB) | measured SNR (dB) | Chamfer | IoU | PSNR depth |",
                  "|---|---|---|---|---|---|---|"]
        shape = sweep[0]["shape"]
        rows = [r for r in results if r["shape"] == shape]
        for r in sorted(rows, key=lambda r: (r["method"], r["bandwidth"], r["snr_db"])):
            if r in main and not any(s["method"] == r["method"] for s in sweep):
                continue
            e = r["reference"]
            lines.append(f"| {r['label']} | {r['bandwidth']} | {r['snr_db']:g} | "
                         f"{fmt(r.get('measured_snr_db'), '.1f')} | "
                         f"{fmt(e.get('chamfer_sq'), '.2e')} | {fmt(e.get('iou'), '.4f')} | "
                         f"{fmt(e.get('psnr_depth'), '.2f')} |")
    lines += cost_lines(results)
    if notes:
        lines += ["", "Notes:", ""] + [f"* {n}" for n in sorted(set(notes))]
    path.write_text("\n".join(lines) + "\n")


def cost_lines(results: list[dict]) -> list[str]:
    """The table's cost section: each stage summed over the cells as they recorded it (wall and
    CPU seconds; a job's simulation once), so a resumed run that recomputes nothing writes the
    same table. A run's own wall time, which depends on what it found done, is in
    ``table2.json`` (``total_s``) and on stdout."""
    wall, missing = stage_sums(results, "stages_s")
    cpu, _ = stage_sums(results, "stages_cpu_s")
    if not wall:
        return []
    lines = ["", "## Cost (each stage summed over the cells, as recorded when they ran)", "",
             "| stage | wall (s) | CPU, user + sys (s) |", "|---|---|---|"]
    for key, seconds in wall.items():
        lines.append(f"| {key[:-2]} | {seconds:.0f} | {fmt(cpu.get(key), '.0f')} |")
    lines.append(f"| all stages | {sum(wall.values()):.0f} | {sum(cpu.values()):.0f} |")
    lines += ["", "Cells run side by side (`--workers`) overlap, so a run's wall time is below the "
              "summed wall; simulations are counted once per dataset."
              + (f" Not recorded by some cells: {', '.join(missing)}." if missing else "")]
    return lines


CSV_KEYS = ("iou", "best_iou", "best_iou_threshold", "mesh_iou", "chamfer_sq", "chamfer_m",
            "best_chamfer_sq", "best_chamfer_sq_threshold", "normal_error_deg",
            "psnr_depth", "ssim_depth", "psnr_shaded", "ssim_shaded", "lpips", "empty")


def write_csv(path: Path, results) -> None:
    def cell(v):
        return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("source", "protocol", "shape", "method", "snr_db", "bandwidth", "threshold")
                   + CSV_KEYS + ("time_s",))
        for r in results:
            for protocol in PROTOCOLS:
                w.writerow(["ours", protocol, r["shape"], r["label"], r["snr_db"], r["bandwidth"],
                            THRESHOLD] + [cell(r[protocol].get(k)) for k in CSV_KEYS]
                           + [cell(r.get("time_s"))])
        for label, ref in REFERENCE.items():
            values = {"iou": ref["iou"], "chamfer_sq": ref["chamfer_sq"], "lpips": ref["lpips"],
                      "psnr_depth": ref["psnr"]}
            w.writerow(["published", "reference", "mean of 8", label, MAIN_SNR_DB,
                        MAIN_BANDWIDTH, ""] + [cell(values.get(k)) for k in CSV_KEYS] + [""])


def write_figure(path: Path, results, methods, resolution: int = 160, dpi: int = 100) -> None:
    """One row per shape: the GT render, then per method its MIP over y and the render of its
    τ surface (the panels of recon.figures, as recon compare draws them)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from recon import export, figures, metrics, views
    from sonarsim.dataset import Volume

    main = main_rows(results)
    shapes = sorted({r["shape"] for r in main})
    cams = views.Turntable(n_views=8, resolution=resolution)
    view = 1                                             # azimuth 45°
    n_cols = 1 + 2 * len(methods)
    fig, axs = plt.subplots(len(shapes), n_cols, figsize=(2.3 * n_cols, 2.5 * len(shapes)),
                            squeeze=False, constrained_layout=True)
    for ax in axs.ravel():
        ax.axis("off")
    crop_box = np.array([[-1e3, 1e3], [-1e3, 1e3], [CROP_Z, 1e3]])
    for i, shape in enumerate(shapes):
        row = [r for r in main if r["shape"] == shape]
        gt = metrics.load_gt_mesh(row[0]["dataset"])
        figures.render_panel(axs[i, 0], gt, cams, view, f"{shape}: GT")
        for j, m in enumerate(methods):
            r = next((r for r in row if r["method"] == m.key), None)
            if r is None:
                continue
            e = r["reference"]
            title = f"IoU {fmt(e.get('iou'), '.3f')}, C² {fmt(e.get('chamfer_sq'), '.1e')}"
            if str(r["volume"]).endswith(".ply"):          # the NBP + refine row: a mesh
                import trimesh
                axs[i, 1 + 2 * j].text(0.5, 0.5, f"{m.label}:\na mesh, no MIP", ha="center",
                                       va="center", fontsize=7)
                figures.render_panel(axs[i, 2 + 2 * j], trimesh.load(r["volume"], process=False),
                                     cams, view, f"{m.label}: {title}")
                continue
            vol = Volume.read(r["volume"])
            v, b = export.crop_volume(vol.volume, vol.bounds, crop_box)
            mag = export.normalized_magnitude(v)
            axs[i, 1 + 2 * j].axis("on")
            figures.mip_panel(axs[i, 1 + 2 * j], mag, b, 1, f"{m.label}: MIP over y", ticks=False)
            figures.render_panel(axs[i, 2 + 2 * j], export.mesh_from_volume(v, b, THRESHOLD), cams,
                                 view, title)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


# --------------------------------------------------------------------------------- main

def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "table2")
    ap.add_argument("--quick", action="store_true", help="the small CI size (SIZES['quick'])")
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--scene-source", choices=("auto", "shared", "shipped"), default="auto",
                    help="shared: the shipped reference GT meshes (sonarsim.data); shipped: the "
                         "procedural cube and cylinder; auto: reference meshes where present")
    ap.add_argument("--methods", default=None,
                    help=f"comma list of {list(METHOD_BY_KEY)} (default: all available)")
    ap.add_argument("--no-sweep", action="store_true", help="only the 20 kHz / 20 dB cells")
    ap.add_argument("--no-refine", action="store_true",
                    help="leave out the NBP + recon refine row (recon refine of each NBP solid)")
    ap.add_argument("--angle-step", type=int)
    ap.add_argument("--height-step", type=int)
    ap.add_argument("--paths-per-pose", type=int)
    ap.add_argument("--subsample", type=int, nargs=2, metavar=("ANGLES", "HEIGHTS"),
                    help=argparse.SUPPRESS)     # removed: refused in one line (settings_from)
    ap.add_argument("--shape", type=int, nargs=3)
    ap.add_argument("--gd-iterations", type=int)
    ap.add_argument("--nbp-iterations", type=int)
    ap.add_argument("--samples", type=int)
    ap.add_argument("--volume-samples", type=int)
    ap.add_argument("--view-resolution", type=int, help="image size of both protocols' renders")
    ap.add_argument("--sweep-methods", help="comma list: methods of the SNR/bandwidth rows")
    ap.add_argument("--no-threshold-sweep", action="store_true",
                    help="metrics at τ only (no best-τ sweep of the exact protocol)")
    ap.add_argument("--solver-output", choices=("field", "solid"),
                    help="what GD and NBP export (default: their preset's)")
    ap.add_argument("--deconvolution", choices=("wiener", "inr"),
                    help="pulse deconvolution of the GD and NBP cells' data (default wiener)")
    ap.add_argument("--data", type=Path, default=None, metavar="DIR",
                    help="adopt scans from DIR (read only) that are the same simulation as a "
                         "job's (poses, pulse, scene and settings compared) instead of "
                         "simulating them")
    ap.add_argument("--scheduler", default="sequential", metavar="ADDRESS",
                    help="where the batch's jobs run: 'sequential' (this process, the default), "
                         "'local' (a Dask LocalCluster, see --workers) or a Dask scheduler "
                         "address; docs/batch.md")
    ap.add_argument("--workers", type=int, default=None,
                    help="worker processes of --scheduler local (default: the batch's choice)")
    return ap.parse_args(argv)


def settings_from(args) -> Settings:
    settings = SIZES["quick" if args.quick else "default"]
    overrides = {k: getattr(args, k) for k in ("angle_step", "height_step", "paths_per_pose",
                                               "gd_iterations", "nbp_iterations", "samples",
                                               "volume_samples", "view_resolution",
                                               "deconvolution", "solver_output")
                 if getattr(args, k) is not None}
    if args.sweep_methods:
        overrides["sweep_methods"] = tuple(m for m in args.sweep_methods.split(",") if m)
    if args.no_threshold_sweep:
        overrides["threshold_sweep"] = False
    if args.shape:
        overrides["shape"] = tuple(args.shape)
    if args.subsample:          # one line, exit 2 (the project's bad-input convention)
        print("table2: --subsample: removed (the table runs as a sonarsim batch, which "
              "simulates each scan it reconstructs): use --angle-step A --height-step H for a "
              "scan of every A-th angle and H-th height", file=sys.stderr)
        raise SystemExit(2)
    return replace(settings, **overrides)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    from sonarsim import runtime
    runtime.mitsuba()
    settings = settings_from(args)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    methods, notes = available_methods(args.methods.split(",") if args.methods else None)
    if not methods:
        raise SystemExit("no reconstruction method available")
    shapes = [s for s in args.shapes.split(",") if s]
    usable = []
    for s in shapes:
        found = scene_spec(s, out, args.scene_source)
        if found is None:
            notes.append(f"scene {s}: skipped (no shared mesh and no shipped scene)")
        else:
            usable.append(s)
            notes.append(f"scene {s}: {found[1]}")
    if not usable:
        raise SystemExit("no shape could be simulated")
    if "bunny" in usable:       # the sweep shape: the bunny when at hand
        usable.remove("bunny")
        usable.insert(0, "bunny")
    cells = cells_of([m.key for m in methods], usable, settings)
    if args.no_sweep:
        cells = [c for c in cells if c.snr_db == MAIN_SNR_DB and c.bandwidth == MAIN_BANDWIDTH]
    summary = (f"{'quick' if args.quick else 'default'} size (digest {settings.digest()}): "
               f"cylindrical scan, every {settings.angle_step} of 360 angles × every "
               f"{settings.height_step} of 150 heights = {settings.n_poses} poses (reference "
               f"54 000), paths/pose {settings.paths_per_pose or 'simulator default (mc_snr_db)'}, "
               f"single scattering, grid {'×'.join(map(str, settings.shape))}, GD "
               f"{settings.gd_iterations} / NBP {settings.nbp_iterations} iterations, "
               f"{settings.deconvolution} deconvolution for GD and NBP, "
               f"{settings.samples} surface and {settings.volume_samples} volume samples")
    print(summary, flush=True)
    results = run_batch(cells, settings, out, args.scene_source, args.scheduler, args.workers,
                        args.data)
    refined = []
    if not args.no_refine and any(m.key == "nbp" for m in methods):
        refined, failed = refine_results(results, settings, args.workers)
        notes += failed
        if refined:
            methods = methods + [REFINE]
    rows = results + refined        # every row of the table: the batch's cells, then refine's
    for r in rows:
        notes += r.get("notes", [])
        e, x = r["reference"], r["exact"]
        stages, cpu = r["stages_s"], r.get("stages_cpu_s") or {}
        solve, solve_cpu = (stages.get("solve_s", stages.get("refine_s")),
                            cpu.get("solve_s", cpu.get("refine_s")))
        print(f"{r['cell']:>28}: solve {fmt(solve, '.1f')} s "
              f"({fmt(solve_cpu, '.0f')} CPU-s), evaluate "
              f"{fmt(stages.get('evaluate_s'), '.1f')} s ({fmt(cpu.get('evaluate_s'), '.0f')} "
              f"CPU-s) | reference: IoU "
              f"{fmt(e['iou'], '.3f')}, C² {fmt(e['chamfer_sq'], '.2e')}, PSNR "
              f"{fmt(e.get('psnr_depth'), '.2f')} | exact: IoU {fmt(x['iou'], '.3f')}, C² "
              f"{fmt(x['chamfer_sq'], '.2e')}", flush=True)
    write_markdown(out / "table2.md", rows, methods, summary, notes)
    write_csv(out / "table2.csv", rows)
    from recon.evaluation import json_safe
    previous = out / "table2.json"
    try:
        before = json.loads(previous.read_text())
        same_cells = before.get("cells", []) + before.get("refined", []) == \
            json.loads(json.dumps(json_safe(rows), default=str))
    except (OSError, ValueError):
        same_cells = False
    if not (same_cells and (out / "table2.png").is_file()):   # a resume that changed nothing
        write_figure(out / "table2.png", rows, methods, settings.figure_resolution,
                     settings.figure_dpi)
    total = time.perf_counter() - t_start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    (out / "table2.json").write_text(json.dumps(json_safe(
        {"summary": summary, "settings": asdict(settings), "simulation": SIMULATION,
         "pulses": PULSES, "threshold": THRESHOLD, "crop_z_m": CROP_Z, "cells": results,
         "refined": refined,
         "notes": sorted(set(notes)), "published": REFERENCE, "total_s": total,
         "peak_rss_mb": peak_mb, "n_pings": settings.n_pings}), indent=1, allow_nan=False, default=str))
    print((out / "table2.md").read_text())
    usage = resource.getrusage(resource.RUSAGE_SELF)
    for key, what in (("stages_s", "wall"), ("stages_cpu_s", "CPU, user+sys")):
        totals, missing = stage_sums(rows, key)
        print(f"stages ({what}, s, summed over cells; cells of an earlier run count their own): "
              + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in totals.items())
              + (f" (not recorded: {', '.join(missing)})" if missing else ""))
    print(f"total {total:.0f} s wall, {usage.ru_utime + usage.ru_stime:.0f} s CPU (user+sys) "
          f"in this process, peak RSS {peak_mb:.0f} MB; outputs in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
