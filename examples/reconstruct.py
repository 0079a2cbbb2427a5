"""From a mesh to scored reconstructions, in Python: simulate, backproject, deconvolve, NBP.

The paper's pipeline (Reed et al. 2023) on the shipped Stanford bunny: simulate an AirSAS-style
dataset (20 kHz LFM, 20 dB SNR), reconstruct it by coherent backprojection (BP) of the
matched-filtered data, then deconvolve the pulse (Wiener) and fit the neural field (NBP) to the
deconvolved data; score both volumes against the ground-truth mesh (IoU, Chamfer) and draw
them under the ground truth with their scores (``recon.figures.comparison``).

    python examples/reconstruct.py --out reconstruct/        # 960 poses, 400 NBP steps, ~3 min
    python examples/reconstruct.py --quick --out /tmp/x       # seconds (the test suite's size)

Files: ``dataset.h5``, ``dataset_pd.h5``, ``bp.h5``, ``nbp.h5`` (docs/formats.md),
``comparison.png``, ``scores.json``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from recon import backprojection, deconvolution, export, metrics, nbp
from recon.grid import Grid, box_bounds, scene_box_of
from sonarsim import geometry
from sonarsim.dataset import SonarDataset
from sonarsim.scene import load_scene
from sonarsim.signals import pulse_from_spec
from sonarsim.simulate import SimulationSettings, simulate

SCENE = """\
ground = true
[[object]]
mesh = "bunny.obj"      # the reference's bunny, shipped with sonarsim (docs/data.md)
fit = true
"""
ABOVE_GROUND = [[-0.2, 0.2], [-0.2, 0.2], [0.005, 0.3]]   # score the object, not the ground


def comparison_figure(volumes: dict, scores: dict, bounds, gt, path: Path) -> Path:
    """:func:`recon.figures.comparison` (the figure of ``recon compare``): the ground truth
    (voxel centres inside the mesh, and its render) above one row per method: top and side
    maximum-intensity projections of |σ| above the ground on one colour scale, the render of
    its surface and its scores."""
    from recon import figures
    from sonarsim.dataset import Volume

    fig = figures.comparison([Volume(v, bounds, name) for name, v in volumes.items()], gt,
                             labels=list(volumes), crop=np.ravel(ABOVE_GROUND),
                             results=[{"iou": scores[name]["iou"],
                                       "chamfer_m": scores[name]["chamfer"]}
                                      for name in volumes])
    return figures.save(fig, path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("reconstruct"))
    parser.add_argument("--quick", action="store_true", help="a tiny run (the test suite's)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    scene_file = args.out / "scene.toml"
    scene_file.write_text(SCENE)

    # 1. Simulate: 120 angles x 8 heights of the AirSAS rig (16 x 3 for --quick).
    poses = geometry.trajectory("cylindrical:16:3" if args.quick else "cylindrical:120:8")
    settings = SimulationSettings(pulse=pulse_from_spec("lfm-20k"), snr_db=20.0, seed=1,
                                  mc_snr_db=None if args.quick else 30.0,
                                  surface_spacing=0.02 if args.quick else None)
    path = simulate(load_scene(scene_file), poses, args.out / "dataset.h5", settings,
                    resume=False)
    ds = SonarDataset.read(path)
    print(f"dataset: {ds.n_pings} pings x {ds.n_samples} samples, measured Monte-Carlo SNR "
          f"{ds.meta['mc_snr_db']:.1f} dB, effective SNR {ds.meta['effective_snr_db']:.1f} dB")

    # 2. Reconstruct on the scene box: backprojection of the matched-filtered data, then NBP
    #    on the Wiener-deconvolved data (the paper's pipeline: deconvolve, then fit).
    grid = Grid(box_bounds(scene_box_of(ds)), (24, 24, 18) if args.quick else (64, 64, 48))
    t0 = time.perf_counter()
    bp = backprojection.solve(ds, grid)
    t_bp = time.perf_counter() - t0
    ds_pd = deconvolution.deconvolve(ds, "wiener")
    ds_pd.write(args.out / "dataset_pd.h5")
    t0 = time.perf_counter()
    field = nbp.solve(ds_pd, grid, iterations=12 if args.quick else 400, seed=1,
                      progress=not args.quick,
                      **({"hash_levels": 4, "n_rays": 100, "bins_per_ping": 32,
                          "warm_start_iterations": 10} if args.quick else {}))
    t_nbp = time.perf_counter() - t0
    bp.write(args.out / "bp.h5")
    field.write(args.out / "nbp.h5")

    # 3. Score against the ground-truth mesh the dataset carries (above the ground).
    import trimesh
    gt = trimesh.Trimesh(ds.gt_vertices, ds.gt_faces, process=False)
    volumes = {"BP": bp.volume, "NBP": field.volume}
    scores = {}
    for name, volume in volumes.items():
        r = metrics.evaluate(volume, grid.bounds, gt, sweep=None, crop=ABOVE_GROUND,
                             n_samples=2000 if args.quick else 20000)
        scores[name] = {"iou": r["iou"], "chamfer": r["chamfer_m"]}
    scores["BP"]["seconds"], scores["NBP"]["seconds"] = t_bp, t_nbp
    for name, s in scores.items():
        print(f"{name:4s} IoU {s['iou']:.3f}  Chamfer {1e3 * s['chamfer']:.1f} mm  "
              f"({s['seconds']:.1f} s)")
    (args.out / "scores.json").write_text(json.dumps(scores, indent=1))
    figure = comparison_figure(volumes, scores, grid.bounds, gt, args.out / "comparison.png")
    print(f"figure: {figure}")
    return {"dataset": ds, "volumes": volumes, "scores": scores, "figure": figure,
            "grid": grid, "finite": all(np.isfinite(v).all() for v in volumes.values())}


if __name__ == "__main__":
    main()
