"""Benchmark: jobs per hour of ``sonarsim batch`` for a 20-job sweep, sequential vs dask.

The sweep: 2 shipped scenes (sphere, cube) x 2 SNRs (10, 20 dB) x 5 seeds = 20 small
simulations (``--poses`` trajectory, single scattering, fixed sampling density: each job takes
about a second or two on one core). The same manifest runs

* ``sequential``: in this process, one job after the other, Dr.Jit on all cores
  (``--scheduler sequential``, no Dask): the baseline, like 20 ``simulate`` runs without
  paying 20 interpreter start-ups;
* ``local-default``: the default LocalCluster (one worker process per 2 cores, cores /
  workers Dr.Jit threads each; on 2 cores the same as ``local-1xN``);
* ``local-1xN``: one worker process with all cores as Dr.Jit threads (Dask's overhead alone);
* ``local-Nx1``: one worker process per core, one Dr.Jit thread each.

Each configuration gets a fresh output directory, so every job runs; the time includes
starting the cluster (workers import Mitsuba and compile the kernels, cached on disk after
the first run). A re-run of the last configuration measures the skip path (no job runs).
The start-up (cluster, and Mitsuba imported on every worker) is printed separately. The
outputs of every configuration are checked to hold the same waveforms.

Usage: .venv/bin/python benchmarks/bench_batch.py [--poses cylindrical:72:3]
       [--paths-per-pose 500] [--configs sequential,local-default,local-1xN,local-Nx1] [--keep]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONFIGS = ("sequential", "local-default", "local-1xN", "local-Nx1")


def manifest_text(poses: str, paths: int) -> str:
    from sonarsim.batch import settings_fields
    cheap = 'bounce1 = "cone"\n' if "bounce1" in settings_fields() else ""
    return (f'[defaults]\nposes = "{poses}"\nbounces = 1\npaths_per_pose = {paths}\n{cheap}\n'
            '[[sweep]]\nscene = ["sphere", "cube"]\nsnr_db = [10, 20]\nseed = [0, 1, 2, 3, 4]\n')


def engine_for(config: str, cores: int):
    from sonarsim.batch_engine import Engine
    quiet = lambda s: None
    if config == "sequential":
        return Engine("sequential", log=quiet)
    if config == "local-default":
        return Engine(log=quiet)
    if config == "local-1xN":
        return Engine(workers=1, threads=cores, log=quiet)
    if config == "local-Nx1":
        return Engine(workers=cores, threads=1, log=quiet)
    raise SystemExit(f"unknown config {config!r}; choose from {CONFIGS}")


def run_config(config: str, manifest: Path, out: Path, cores: int) -> dict:
    from sonarsim.batch import plan_batch, run_batch
    plan = plan_batch(manifest, out, log=lambda s: None)
    t0 = time.perf_counter()
    with engine_for(config, cores) as engine:
        engine.start(len(plan.jobs))
        if engine.client is not None:          # workers up and Mitsuba imported on each
            engine.client.run(_warm_up)
        startup = time.perf_counter() - t0
        result = run_batch(plan, engine, progress=False, log=lambda s: None)
        described = engine.description
    wall = time.perf_counter() - t0
    failed = result.failed
    if failed:
        raise SystemExit(f"{config}: {len(failed)} job(s) failed: {result.errors}")
    walls = []
    import csv
    with open(result.csv, newline="") as fh:
        walls = [float(r["wall_s"]) for r in csv.DictReader(fh) if r["wall_s"]]
    return {"config": config, "where": described, "jobs": len(plan.jobs), "wall_s": wall,
            "busy_s": sum(walls),
            "startup_s": startup,
            "jobs_per_hour": 3600 * len(plan.jobs) / wall,
            "median_job_s": statistics.median(walls) if walls else float("nan"),
            "outputs": {j.name: j.output for j in plan.jobs}}


def _warm_up() -> None:
    from sonarsim import runtime
    runtime.mitsuba()


def waveforms(path: str) -> np.ndarray:
    with h5py.File(path, "r") as f:
        return f["waveforms"][()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", default="cylindrical:72:3")
    ap.add_argument("--paths-per-pose", type=int, default=500)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--keep", action="store_true", help="keep the outputs (printed path)")
    args = ap.parse_args(argv)
    from sonarsim import runtime
    runtime.mitsuba()
    cores = os.cpu_count() or 1
    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    manifest = tmp / "sweep.toml"
    manifest.write_text(manifest_text(args.poses, args.paths_per_pose))
    try:
        load = os.getloadavg()[0]
        print(f"20-job sweep ({args.poses}, {args.paths_per_pose} paths/pose, 1 bounce) on "
              f"{cores} cores, load average {load:.1f} at start")
        rows = []
        for config in [c for c in args.configs.split(",") if c]:
            row = run_config(config, manifest, tmp / config, cores)
            rows.append(row)
            print(f"{config:>14}: {row['wall_s']:7.1f} s, {row['jobs_per_hour']:8.0f} jobs/h, "
                  f"median job {row['median_job_s']:.2f} s on its worker (sum {row['busy_s']:.1f} s), "
                  f"start-up {row['startup_s']:.1f} s  [{row['where']}]",
                  flush=True)
        last = rows[-1]
        t0 = time.perf_counter()
        again = run_config(last["config"], manifest, tmp / last["config"], cores)
        print(f"{'re-run':>14}: {time.perf_counter() - t0:7.1f} s for {again['jobs']} complete "
              "jobs (skipped, nothing simulated)")
        ref = rows[0]
        for row in rows[1:]:
            for name, path in row["outputs"].items():
                if not np.array_equal(waveforms(path), waveforms(ref["outputs"][name])):
                    raise SystemExit(f"{row['config']}: {name} differs from {ref['config']}")
        print(f"all configurations wrote identical waveforms; ratio to {ref['config']}: " +
              ", ".join(f"{r['config']} {r['jobs_per_hour'] / ref['jobs_per_hour']:.2f}x"
                        for r in rows[1:]))
        print(f"load average at the end {os.getloadavg()[0]:.1f} (timings are noisy on a "
              "shared machine)")
    finally:
        if args.keep:
            print(f"outputs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
