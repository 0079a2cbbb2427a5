"""SH scattering (``--scattering sh:L``, recon.scattering) against isotropic NBP: the cost of
one optimiser step, and the Table-2 metrics at a reduced size.

Usage:
  .venv/bin/python benchmarks/bench_scattering.py cost [--iterations N] [--scattering isotropic,sh:1,sh:2]
  .venv/bin/python benchmarks/bench_scattering.py shapes --out DIR [--shapes bunny,cube,cylinder]
        [--scattering sh:1] [--iterations 300] [--subsample 5 5] [--data DIR]

``cost``: the 20-point synthetic scene of benchmarks/bench_nbp.py (180 pings, 125×125×94
grid), preset nbp (deterministic: one thread), cold start; median wall and CPU seconds of the
steps after the first two (kernel compilation), each scattering in its own process.

``shapes``: the reduced Table-2 protocol of docs/evaluation.md (benchmarks/table2.py
``--subsample 5 5 --nbp-iterations 300``): the Wiener-deconvolved full-size scans
(``<data>/<shape>_20k_20dB_b1916cbb_pd-wiener.h5``), every 5th angle and height (2 160 pings),
preset nbp, seed 1, grid 125×125×94 over the reference's box; the volume is written to
``DIR/volumes/`` (with the network's parameters, ``*_params.npz``, and for SH fields also
the RMS-over-directions export, ``*_rms.h5``, scored as ``rms_reference`` / ``rms_exact``) and
scored by recon.evaluation.evaluate_file (reference and exact protocols,
τ 0.2 and the τ sweep, no images), one JSON line per cell in ``DIR/cells.jsonl`` (resumable:
a cell already there is skipped). The machine is shared: wall times are noisy, CPU times less.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULT = "RESULT "
DATA = Path("/work/cache/t2/data")
DATA_TAG = "20k_20dB_b1916cbb"


def make_scene(grid, settings, scattering: str):
    """The NBP scene of ``scattering`` (the settings hook's choice, recon.scattering)."""
    from recon import scattering as S
    from recon.field import NetworkScene
    degree = S.parse_scattering(scattering)
    return NetworkScene(grid, settings) if degree is None else S.ShNetworkScene(grid, settings,
                                                                              degree)


def fit_timed(ds, grid, scattering: str, **overrides):
    """(params, history, info, scene, per-step wall list, per-step CPU list)."""
    from recon import solver
    settings = solver.settings_for("nbp", network=True, **overrides)
    scene = make_scene(grid, settings, scattering)
    wall, cpu = [time.perf_counter()], [time.process_time()]

    def tick(it, record):
        wall.append(time.perf_counter())
        cpu.append(time.process_time())

    params, history, info = solver.fit(ds, grid, settings, scene, progress=False, callback=tick)
    return params, history, info, scene, np.diff(wall), np.diff(cpu)


def cost_one(scattering: str, iterations: int) -> None:
    sys.path.insert(0, str(HERE))
    from _solver_bench import scene
    ds, grid = scene((125, 125, 94))
    *_, wall, cpu = fit_timed(ds, grid, scattering, iterations=iterations, init="random",
                              warm_start_iterations=0)
    print(RESULT + json.dumps({"scattering": scattering, "s_per_step": float(np.median(wall[2:])),
                               "cpu_s_per_step": float(np.median(cpu[2:])),
                               "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                               / 1024.0}), flush=True)


def cost(args) -> None:
    print(f"median of steps 3-{args.iterations}, preset nbp, one thread (deterministic)")
    print(f"{'scattering':<12}{'s/step':>9}{'CPU s/step':>12}{'peak RSS MB':>13}")
    base = None
    for sc in args.scattering.split(","):
        out = subprocess.run([sys.executable, __file__, "cost-one", sc, str(args.iterations)],
                             capture_output=True, text=True)
        line = [x for x in out.stdout.splitlines() if x.startswith(RESULT)]
        if out.returncode or not line:
            print(f"{sc:<12} failed: {out.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(line[-1][len(RESULT):])
        base = base or r["cpu_s_per_step"]
        print(f"{sc:<12}{r['s_per_step']:>9.3f}{r['cpu_s_per_step']:>12.3f}"
              f"{r['peak_rss_mb']:>13.0f}   CPU ×{r['cpu_s_per_step'] / base:.2f}", flush=True)


# The reduced Table-2 protocol (docs/evaluation.md; the constants of benchmarks/table2.py)
GRID_BOUNDS = ((-0.2, 0.2), (-0.2, 0.2), (0.0, 0.3))
GRID_SHAPE = (125, 125, 94)
THRESHOLD = 0.2
CROP_Z = 0.005
SURFACE_SAMPLES, VOLUME_SAMPLES = 20_000, 50_000
ANGLES_PER_HEIGHT = 360


def subsampled(ds, every_angle: int, every_height: int):
    """Every n-th angle and height of a Table-2 scan (pings angle-fastest, 360 per height)."""
    idx = np.arange(ds.n_pings)
    keep = (((idx % ANGLES_PER_HEIGHT) % every_angle == 0)
            & ((idx // ANGLES_PER_HEIGHT) % every_height == 0))
    return ds.select(np.flatnonzero(keep))


def shapes(args) -> None:
    from recon import metrics
    from recon.evaluation import evaluate_file, json_safe
    from recon.grid import Grid
    from sonarsim.dataset import SonarDataset, Volume
    out = Path(args.out)
    (out / "volumes").mkdir(parents=True, exist_ok=True)
    cells = out / "cells.jsonl"
    done = set()
    if cells.is_file():
        done = {(c["shape"], c["scattering"]) for c in map(json.loads, cells.read_text().splitlines())}
    for sc in args.scattering.split(","):
        for shape in args.shapes.split(","):
            if (shape, sc) in done:
                continue
            raw = Path(args.data) / f"{shape}_{DATA_TAG}.h5"
            ds = subsampled(SonarDataset.read(raw.with_name(raw.stem + "_pd-wiener.h5")),
                            *args.subsample)
            grid = Grid(np.asarray(GRID_BOUNDS, dtype=np.float64), GRID_SHAPE)
            t0, c0 = time.perf_counter(), time.process_time()
            params, history, info, scene, wall, cpu = fit_timed(
                ds, grid, sc, iterations=args.iterations, seed=1)
            vol = scene.volume(params, grid)
            solve_s, solve_cpu = time.perf_counter() - t0, time.process_time() - c0
            p = {"scattering": sc, "iterations": args.iterations, "n_pings": int(ds.n_pings),
                 "solve_s": solve_s, "solve_cpu_s": solve_cpu,
                 "final_data_loss": float(history[-1]["data"]), **info}
            tag = f"nbp_{sc.replace(':', '')}_{shape}"
            vpath = out / "volumes" / f"{tag}.h5"
            Volume(volume=vol, bounds=np.asarray(grid.bounds), method="nbp",
                   params=json_safe(p)).write(vpath)
            np.savez(out / "volumes" / f"{tag}_params.npz", **{k: np.asarray(v) for k, v in params.items()})
            exports = {"": vpath}
            if hasattr(scene, "rms_volume"):
                exports["rms_"] = out / "volumes" / f"{tag}_rms.h5"
                Volume(volume=scene.rms_volume(params, grid), bounds=np.asarray(grid.bounds),
                       method="nbp", params=json_safe(dict(p, export="rms"))).write(exports["rms_"])
            gt = metrics.load_gt_mesh(raw)
            res = {"shape": shape, "scattering": sc, "volume": str(vpath), **p,
                   "step_s_median": float(np.median(wall[2:])),
                   "step_cpu_s_median": float(np.median(cpu[2:]))}
            for prefix, path in exports.items():
                for protocol in ("reference", "exact"):
                    crop = [-1e3, 1e3, -1e3, 1e3, CROP_Z, 1e3] if protocol == "exact" else None
                    r = evaluate_file(path, gt, threshold=THRESHOLD, samples=SURFACE_SAMPLES,
                                      crop=crop, protocol=protocol,
                                      volume_samples=VOLUME_SAMPLES, images=False, sweep=True)
                    r.pop("sweep", None)
                    res[prefix + protocol] = r
            with open(cells, "a") as f:
                f.write(json.dumps(json_safe(res), default=str) + "\n")
            ref = res["reference"]
            print(f"{shape} {sc}: reference IoU {ref.get('iou')} Chamfer² {ref.get('chamfer_sq')}"
                  f" solve {solve_s:.0f} s ({solve_cpu:.0f} CPU-s)", flush=True)


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["cost-one"]:
        cost_one(argv[1], int(argv[2]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    subs = ap.add_subparsers(dest="what", required=True)
    c = subs.add_parser("cost")
    c.add_argument("--iterations", type=int, default=8)
    c.add_argument("--scattering", default="isotropic,sh:1,sh:2")
    s = subs.add_parser("shapes")
    s.add_argument("--out", required=True)
    s.add_argument("--shapes", default="bunny,cube,cylinder")
    s.add_argument("--scattering", default="sh:1")
    s.add_argument("--iterations", type=int, default=300)
    s.add_argument("--subsample", type=int, nargs=2, default=(5, 5))
    s.add_argument("--data", default=os.environ.get("SONARSIM_T2_DATA", str(DATA)))
    args = ap.parse_args(argv)
    cost(args) if args.what == "cost" else shapes(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
