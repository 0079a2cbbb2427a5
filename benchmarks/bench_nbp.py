"""Neural backprojection and gradient descent cost per iteration: seconds per optimiser step
and peak memory for ``--preset cpu`` and ``--preset reference`` (a few steps only).

Usage: .venv/bin/python benchmarks/bench_nbp.py [--iterations N] [--presets cpu,reference]

Scene: 20 synthetic point scatterers in the AirSAS box, a 2-height scan of 360 pings, the
125×125×94 grid of the simulated Table-2 scenes. Full forward model (Lambertian normals,
occlusion). The first two steps (kernel compilation) are excluded from the median. The
machine is shared: numbers are noisy.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--presets", default="cpu,reference")
    ap.add_argument("--shape", type=int, nargs=3, default=(125, 125, 94))
    args = ap.parse_args(argv)
    from recon import gradient_descent, nbp, synthetic
    from recon.grid import Grid
    from sonarsim import geometry
    box = geometry.AIRSAS_REAL_BOX
    pts = np.random.default_rng(0).uniform(box.lo, box.hi, (20, 3))
    ds = synthetic.point_dataset(pts, n_pings=180, heights=(0.05, 0.15),
                                 scene_box=np.stack([box.lo, box.hi], 1))
    grid = Grid.from_box(box, tuple(args.shape))
    print(f"grid {grid.shape}; {ds.n_pings} pings; {args.iterations} steps per run")
    print(f"{'method':<6}{'preset':<11}{'points/step':>12}{'s/step':>9}{'peak RSS MB':>13}")
    for preset in args.presets.split(","):
        for name, module in (("nbp", nbp), ("gd", gradient_descent)):
            stamps = []
            kw = dict(iterations=args.iterations, progress=False, preset=preset,
                      callback=lambda i, r: stamps.append(time.perf_counter()))
            if name == "gd":
                kw.update(init="random", lr_units="absolute", lr=1e-3)
            t0 = time.perf_counter()
            module.solve(ds, grid, **kw)
            per = np.median(np.diff(stamps[1:])) if len(stamps) > 3 else time.perf_counter() - t0
            s = module.settings_for(preset)
            n = s.pings_per_iteration * s.bins_per_ping * s.n_rays
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"{name:<6}{preset:<11}{n:>12}{per:>9.2f}{rss:>13.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
