"""The reference's Table 2 in one command: every method, every shape, both evaluation protocols.

Reed et al., "Neural Volumetric Reconstruction for Coherent Synthetic Aperture Sonar"
(SIGGRAPH 2023), Table 2 compares backprojection, gradient descent, polar formatting and
neural backprojection on simulated AirSAS scans (20 kHz LFM, 20 dB SNR) with Chamfer, IoU,
LPIPS and PSNR. This script runs that comparison on the shapes at hand (bunny, cube,
cylinder: the reference's GT meshes from ``../shared/data/meshes`` where present, else the
shipped procedural cube and cylinder) and adds the SNR sweep (0 / 10 / 20 dB) and the 5 kHz
row for one shape.

A **cell** is one (method, shape, SNR, bandwidth) under one :class:`Settings`;
:func:`run_cell` computes it independently (simulating the dataset if needed,
reconstructing, evaluating with both protocols of ``recon evaluate``) and stores
``<out>/cells/<cell>.json``: finished cells are kept, so an interrupted run resumes where it
stopped (the settings' digest is part of every file name). Outputs in ``--out``:

* ``table2.md``  -- the table in the reference's layout (Chamfer, IoU, LPIPS, PSNR per method,
                    mean over shapes) for each protocol with the published row beside ours;
                    per-shape rows; the SNR sweep and the 5 kHz row;
* ``table2.csv`` -- every cell, both protocols, machine readable; plus the published rows;
* ``table2.png`` -- per shape: GT render, and per method the MIP over y and a render of the
                    τ = 0.2 surface side by side;
* ``table2.json`` -- settings, every cell, timings.

    .venv/bin/python benchmarks/table2.py --out bench_out/table2 [--quick] [--methods bp,pfa]
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import importlib
import json
import math
import resource
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np

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
    subsample_angle: int = 1          # reconstruct from every n-th angle / height of the
    subsample_height: int = 1         # simulated scan (the dataset is not re-simulated)

    @property
    def n_poses(self) -> int:
        return len(range(0, 360, self.angle_step)) * len(range(0, 150, self.height_step))

    @property
    def n_pings(self) -> int:
        """Pings each reconstruction sees (after ``subsample_*``)."""
        return (len(range(0, 360, self.angle_step * self.subsample_angle))
                * len(range(0, 150, self.height_step * self.subsample_height)))

    def data_digest(self) -> str:
        """Digest of what the simulation depends on only (poses, fidelity, the module-level
        simulation constants): the dataset's file name. Solver, grid and evaluation settings
        never re-simulate."""
        key = json.dumps({"angle_step": self.angle_step, "height_step": self.height_step,
                          "paths_per_pose": self.paths_per_pose, "simulation": SIMULATION,
                          "pulses": PULSES}, sort_keys=True, default=str)
        return hashlib.sha1(key.encode()).hexdigest()[:8]

    def digest(self) -> str:
        """Short digest of these settings and the module-level simulation constants: part of
        every file name, so files of other settings are never reused."""
        key = json.dumps({"settings": asdict(self), "simulation": SIMULATION, "pulses": PULSES,
                          "threshold": THRESHOLD, "crop_z": CROP_Z, "bounds": GRID_BOUNDS},
                         sort_keys=True, default=str)
        return hashlib.sha1(key.encode()).hexdigest()[:8]


SIZES = {
    "default": Settings(angle_step=1, height_step=1, paths_per_pose=None, shape=(125, 125, 94),
                        gd_iterations=1000, nbp_iterations=1000),
    "quick": Settings(angle_step=20, height_step=15, paths_per_pose=300, shape=(25, 25, 19),
                      gd_iterations=5, nbp_iterations=3, samples=1000, volume_samples=3000,
                      view_resolution=32, sweep_methods=("pfa",), threshold_sweep=False),
}


@dataclass(frozen=True)
class Method:
    """A reconstructor: ``<module>.solve(dataset, grid, progress=False, **options(settings))``.

    ``deconvolved``: the method fits the pulse-deconvolved dataset (the paper's pipeline:
    deconvolve, then NBP; its GD baseline is NBP without the network, on the same data),
    made once per dataset with ``Settings.deconvolution`` (:func:`ensure_deconvolved`)."""
    key: str
    label: str                       # the reference's row name (REFERENCE)
    module: str
    options: Callable[[Settings], dict] = field(default=lambda s: {})
    deconvolved: bool = False


METHODS = (
    Method("bp", "Backprojection", "recon.backprojection"),
    Method("gd", "Gradient Descent", "recon.gradient_descent",
           lambda s: {"iterations": s.gd_iterations, "seed": SIMULATION["seed"]}, True),
    Method("pfa", "PFA", "recon.pfa"),
    Method("nbp", "Neural BP (Ours)", "recon.nbp",
           lambda s: {"iterations": s.nbp_iterations, "seed": SIMULATION["seed"]}, True),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}


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


def cylindrical_poses(settings: Settings, box):
    """Every angle_step-th angle and height_step-th height of the reference's 360 x 150 scan."""
    from sonarsim.geometry import CYLINDRICAL_ANGLES, cylindrical_grid, rig_poses
    angles, heights = cylindrical_grid()
    idx = np.arange(angles.size)
    keep = ((idx % CYLINDRICAL_ANGLES) % settings.angle_step == 0) & \
           ((idx // CYLINDRICAL_ANGLES) % settings.height_step == 0)
    return rig_poses(angles[keep], heights[keep], box=box)


def simulation_settings(cell: Cell, settings: Settings):
    from sonarsim import signals, simulate
    values = {k: v for k, v in SIMULATION.items() if v is not None}
    values.update(pulse=signals.pulse_from_spec(PULSES[cell.bandwidth], signals.AIRSAS_FS), snr_db=cell.snr_db,
                  paths_per_pose=settings.paths_per_pose,
                  extra_meta={"poses": f"cylindrical 360x150, every {settings.angle_step} "
                                       f"angle(s), every {settings.height_step} height(s)"})
    known = {f.name for f in fields(simulate.SimulationSettings)}
    return simulate.SimulationSettings(**{k: v for k, v in values.items() if k in known})


def ensure_dataset(cell: Cell, settings: Settings, out: Path, source: str = "auto"
                   ) -> tuple[Path, list[str], str]:
    """(dataset path, notes, scene source): simulated once per (shape, SNR, bandwidth,
    settings) and reused (the simulator writes atomically: an existing file is complete)."""
    from sonarsim.scene import load_scene
    from sonarsim.simulate import simulate
    found = scene_spec(cell.shape, out, source)
    if found is None:
        raise SystemExit(f"scene {cell.shape}: no shared mesh and no shipped scene")
    spec_text, src = found
    path = out / "data" / f"{cell.dataset_name}_{settings.data_digest()}.h5"
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        spec = load_scene(spec_text)
    notes = [f"scene {cell.shape}: {str(w.message).split(': ', 1)[-1]}" for w in caught]
    if not path.is_file():
        simulate(spec, cylindrical_poses(settings, spec.box), path,
                 simulation_settings(cell, settings), resume=True, progress=False)
    return path, notes, src


def subsampled(ds, settings: Settings):
    """Every ``subsample_angle``-th angle and ``subsample_height``-th height of a dataset
    simulated with :func:`cylindrical_poses` (pings ordered angle-fastest, 360 / angle_step
    per height)."""
    if settings.subsample_angle == 1 and settings.subsample_height == 1:
        return ds
    per_height = len(range(0, 360, settings.angle_step))
    idx = np.arange(ds.n_pings)
    keep = (((idx % per_height) % settings.subsample_angle == 0)
            & ((idx // per_height) % settings.subsample_height == 0))
    return ds.select(np.flatnonzero(keep))


def ensure_deconvolved(data: Path, settings: Settings) -> Path:
    """The pulse-deconvolved dataset of ``data`` (``recon deconvolve`` with
    ``settings.deconvolution``), made once beside it and reused. Wiener filters each ping
    on its own: the whole scan is deconvolved (seconds) and subsampled later; the INR is
    fitted to the subsampled pings only (its cost grows with pings)."""
    from recon.deconvolution import deconvolve
    from sonarsim.dataset import SonarDataset
    sub = (settings.deconvolution != "wiener"
           and (settings.subsample_angle, settings.subsample_height) != (1, 1))
    tag = f"_sub{settings.subsample_angle}x{settings.subsample_height}" if sub else ""
    path = data.with_name(f"{data.stem}{tag}_pd-{settings.deconvolution}.h5")
    if not path.is_file():     # written atomically: an existing file is complete
        ds = SonarDataset.read(data)
        deconvolve(subsampled(ds, settings) if sub else ds, settings.deconvolution,
                   progress=False).write(path)
    return path


def evaluate_both(volume_path: Path, gt, settings: Settings) -> dict:
    """{protocol: metrics} of one volume (``recon evaluate``'s evaluate_file).

    exact: crop z >= 5 mm (the ground plane is not in the GT meshes), sweep of τ;
    reference: as the reference evaluates, the whole box (ground included), IoU sweep.
    """
    from recon.evaluation import evaluate_file
    out = {}
    for protocol in PROTOCOLS:
        crop = [-1e3, 1e3, -1e3, 1e3, CROP_Z, 1e3] if protocol == "exact" else None
        res = evaluate_file(volume_path, gt, threshold=THRESHOLD, samples=settings.samples,
                            crop=crop, protocol=protocol, volume_samples=settings.volume_samples,
                            view_resolution=settings.view_resolution,
                            sweep=settings.threshold_sweep)
        res.pop("sweep", None)
        out[protocol] = res
    return out


def run_cell(method: str, shape: str, snr_db: float, bandwidth: str, settings: Settings,
             out: Path, source: str = "auto") -> dict:
    """Compute one cell (or load it if ``<out>/cells/<cell>_<digest>.json`` exists) and return
    its result dict: cell keys, ``time_s`` (reconstruction), ``volume`` path, ``exact`` and
    ``reference`` metrics, ``notes``. Independent of every other cell (safe to run in
    parallel: files are written atomically)."""
    from sonarsim.atomic import atomic_path
    cell = Cell(method, shape, float(snr_db), bandwidth)
    digest = settings.digest()
    record = out / "cells" / f"{cell.name}_{digest}.json"
    if record.is_file():
        return json.loads(record.read_text())
    from recon import metrics
    from recon.grid import Grid
    from sonarsim.dataset import SonarDataset, Volume
    m = METHOD_BY_KEY[method]
    stages = {}
    t0 = time.perf_counter()
    data, notes, src = ensure_dataset(cell, settings, out, source)
    stages["dataset_s"] = time.perf_counter() - t0
    volume_path = out / "volumes" / f"{cell.name}_{digest}.h5"
    volume_path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    fitted = ensure_deconvolved(data, settings) if m.deconvolved else data
    stages["deconvolve_s"] = time.perf_counter() - t0
    ds = SonarDataset.read(fitted)
    if ds.n_pings != settings.n_pings:     # an INR-deconvolved subset is already subsampled
        ds = subsampled(ds, settings)
    elapsed = None
    if volume_path.is_file():
        vol = Volume.read(volume_path)
        elapsed = vol.params.get("table2_time_s")
    else:
        grid = Grid(np.asarray(GRID_BOUNDS, dtype=np.float64), settings.shape)
        t0 = time.perf_counter()
        vol = importlib.import_module(m.module).solve(ds, grid, progress=False,
                                                      **m.options(settings))
        elapsed = time.perf_counter() - t0
        vol.params["table2_time_s"] = float(elapsed)
        vol.write(volume_path)
    gt = metrics.load_gt_mesh(data)
    t0 = time.perf_counter()
    result = {"cell": cell.name, "method": method, "label": m.label, "shape": shape,
              "snr_db": float(snr_db), "bandwidth": bandwidth, "settings_digest": digest,
              "scene_source": src, "dataset": str(data), "fitted": str(fitted), "volume": str(volume_path),
              "time_s": elapsed, "measured_snr_db": ds.meta.get("effective_snr_db", ds.snr_db),
              "mc_snr_db": ds.meta.get("mc_snr_db"), "n_pings": int(ds.n_pings),
              "notes": notes, **evaluate_both(volume_path, gt, settings)}
    result["evaluate_s"] = time.perf_counter() - t0
    result["stages_s"] = {**stages, "solve_s": elapsed, "evaluate_s": result["evaluate_s"]}
    from recon.evaluation import json_safe
    record.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(record) as tmp:
        Path(tmp).write_text(json.dumps(json_safe(result), indent=1, allow_nan=False,
                                        default=str))
    return json.loads(record.read_text())


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
            ref = REFERENCE[m.label]
            ours = " | ".join(fmt(mean_over(sel, protocol, k), spec)
                              for k, spec in TABLE_KEYS.items())
            best = " | ".join(fmt(mean_over(sel, protocol, k), spec) for k, spec in
                              (("best_chamfer_sq", ".2e"), ("best_iou", ".4f"),
                               ("normal_error_deg", ".1f")))
            lines.append(f"| {m.label} | {ours} | | {ref['chamfer_sq']:.2e} | {ref['iou']:.4f} "
                         f"| {ref['lpips']:.4f} | {ref['psnr']:.3f} | | {best} |")
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
    if notes:
        lines += ["", "Notes:", ""] + [f"* {n}" for n in sorted(set(notes))]
    path.write_text("\n".join(lines) + "\n")


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


def write_figure(path: Path, results, methods) -> None:
    """One row per shape: the GT render, then per method its MIP over y and the render of its
    τ surface (the panels of recon.figures, as recon compare draws them)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from recon import export, figures, metrics, views
    from sonarsim.dataset import Volume

    main = main_rows(results)
    shapes = sorted({r["shape"] for r in main})
    cams = views.Turntable(n_views=8, resolution=160)
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
            vol = Volume.read(r["volume"])
            v, b = export.crop_volume(vol.volume, vol.bounds, crop_box)
            mag = export.normalized_magnitude(v)
            axs[i, 1 + 2 * j].axis("on")
            figures.mip_panel(axs[i, 1 + 2 * j], mag, b, 1, f"{m.label}: MIP over y", ticks=False)
            e = r["reference"]
            figures.render_panel(axs[i, 2 + 2 * j], export.mesh_from_volume(v, b, THRESHOLD), cams,
                                 view, f"IoU {fmt(e.get('iou'), '.3f')}, "
                                       f"C² {fmt(e.get('chamfer_sq'), '.1e')}")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_cells_on_cluster(cells, settings: "Settings", out: Path, source: str,
                         scheduler: str) -> None:
    """Compute the cells as jobs of sonarsim's batch engine (docs/batch.md) on a Dask cluster
    (``scheduler``: an address, or 'local' for a LocalCluster): one task per dataset, and
    one per cell that waits for its dataset. Each cell leaves its record in ``out/cells``,
    where the sequential loop of :func:`main` then finds it."""
    from sonarsim.batch_engine import Engine, Task
    data, tasks = {}, []
    for cell in cells:
        key = f"data/{cell.dataset_name}"
        data.setdefault(key, Task(key, ensure_dataset, (cell, settings, out, source)))
        tasks.append(Task(f"cell/{cell.name}", run_cell, (cell.method, cell.shape, cell.snr_db,
                          cell.bandwidth, settings, out, source), needs=(key,),
                          pass_needed=False))
    with Engine(None if scheduler == "local" else scheduler) as engine:
        outcomes = engine.run(list(data.values()) + tasks)
    failed = [f"{k}: {o.error}" for k, o in outcomes.items() if not o.ok]
    if failed:
        raise SystemExit("cells failed on the cluster:\n" + "\n".join(failed))


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
    ap.add_argument("--angle-step", type=int)
    ap.add_argument("--height-step", type=int)
    ap.add_argument("--paths-per-pose", type=int)
    ap.add_argument("--subsample", type=int, nargs=2, metavar=("ANGLES", "HEIGHTS"),
                    help="reconstruct from every ANGLES-th angle and HEIGHTS-th height of the "
                         "simulated scan (the dataset is simulated once at its own size)")
    ap.add_argument("--shape", type=int, nargs=3)
    ap.add_argument("--gd-iterations", type=int)
    ap.add_argument("--nbp-iterations", type=int)
    ap.add_argument("--samples", type=int)
    ap.add_argument("--volume-samples", type=int)
    ap.add_argument("--view-resolution", type=int, help="image size of both protocols' renders")
    ap.add_argument("--sweep-methods", help="comma list: methods of the SNR/bandwidth rows")
    ap.add_argument("--no-threshold-sweep", action="store_true",
                    help="metrics at τ only (no best-τ sweep of the exact protocol)")
    ap.add_argument("--deconvolution", choices=("wiener", "inr"),
                    help="pulse deconvolution of the GD and NBP cells' data (default wiener)")
    ap.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="compute the cells as jobs on this Dask scheduler ('local': a "
                         "LocalCluster; default: one after the other in this process); "
                         "see docs/batch.md")
    return ap.parse_args(argv)


def settings_from(args) -> Settings:
    settings = SIZES["quick" if args.quick else "default"]
    overrides = {k: getattr(args, k) for k in ("angle_step", "height_step", "paths_per_pose",
                                               "gd_iterations", "nbp_iterations", "samples",
                                               "volume_samples", "view_resolution",
                                               "deconvolution")
                 if getattr(args, k) is not None}
    if args.sweep_methods:
        overrides["sweep_methods"] = tuple(m for m in args.sweep_methods.split(",") if m)
    if args.no_threshold_sweep:
        overrides["threshold_sweep"] = False
    if args.shape:
        overrides["shape"] = tuple(args.shape)
    if args.subsample:
        if min(args.subsample) < 1:
            raise SystemExit("--subsample: both steps must be >= 1")
        overrides["subsample_angle"], overrides["subsample_height"] = args.subsample
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
               f"54 000), reconstructed from {settings.n_pings} pings (every "
               f"{settings.subsample_angle} angle(s) × {settings.subsample_height} height(s)), paths/pose {settings.paths_per_pose or 'simulator default (mc_snr_db)'}, "
               f"single scattering, grid {'×'.join(map(str, settings.shape))}, GD "
               f"{settings.gd_iterations} / NBP {settings.nbp_iterations} iterations, "
               f"{settings.samples} surface and {settings.volume_samples} volume samples")
    print(summary, flush=True)
    if args.scheduler:
        run_cells_on_cluster(cells, settings, out, args.scene_source, args.scheduler)
    results = []
    for cell in cells:
        t0 = time.perf_counter()
        r = run_cell(cell.method, cell.shape, cell.snr_db, cell.bandwidth, settings, out,
                     args.scene_source)
        results.append(r)
        notes += r.get("notes", [])
        e, x = r["reference"], r["exact"]
        print(f"{cell.name:>28}: {time.perf_counter() - t0:6.1f} s | reference: IoU "
              f"{fmt(e['iou'], '.3f')}, C² {fmt(e['chamfer_sq'], '.2e')}, PSNR "
              f"{fmt(e.get('psnr_depth'), '.2f')} | exact: IoU {fmt(x['iou'], '.3f')}, C² "
              f"{fmt(x['chamfer_sq'], '.2e')}", flush=True)
    write_markdown(out / "table2.md", results, methods, summary, notes)
    write_csv(out / "table2.csv", results)
    write_figure(out / "table2.png", results, methods)
    total = time.perf_counter() - t_start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    from recon.evaluation import json_safe
    (out / "table2.json").write_text(json.dumps(json_safe(
        {"summary": summary, "settings": asdict(settings), "simulation": SIMULATION,
         "pulses": PULSES, "threshold": THRESHOLD, "crop_z_m": CROP_Z, "cells": results,
         "notes": sorted(set(notes)), "published": REFERENCE, "total_s": total,
         "peak_rss_mb": peak_mb, "n_pings": settings.n_pings}), indent=1, allow_nan=False, default=str))
    print((out / "table2.md").read_text())
    stage_totals = {}
    for r in results:      # cells loaded from an earlier run report their own stage times
        for k, v in (r.get("stages_s") or {}).items():
            stage_totals[k] = stage_totals.get(k, 0.0) + (v or 0.0)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    print("stages (s, summed over cells): "
          + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in stage_totals.items()))
    print(f"total {total:.0f} s wall, {usage.ru_utime + usage.ru_stime:.0f} s CPU (user+sys) "
          f"in this process, peak RSS {peak_mb:.0f} MB; outputs in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
