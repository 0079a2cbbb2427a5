"""Neural-backprojection (hash grid + MLP) iteration cost beside gradient descent on voxels:
seconds per optimiser step and peak memory for ``--preset cpu`` and ``--preset reference``,
on one thread (the deterministic default) and on all threads (``--no-deterministic``).

Usage: .venv/bin/python benchmarks/bench_nbp.py [--iterations N] [--presets cpu,reference]
                                                [--threads 1,all] [--profile] [--no-gd]

Scene: 20 synthetic point scatterers in the AirSAS box, a 2-height scan of 360 pings, the
125×125×94 grid of the simulated Table-2 scenes. Full forward model (Lambertian normals,
occlusion s_occ 500) for both scenes, no priors, cold start (no warm start: its cost is once
per run). Each configuration runs in its own process (peak RSS is per configuration); the
first two steps (kernel compilation) are excluded from the median. ``--profile`` adds where a
step's time goes (:class:`recon.solver.PhaseTimer`). ``SONARSIM_VARIANT=cuda_ad_mono`` runs it on a GPU.
No NumPy counterpart: a NumPy hash-grid encoding identical to ``drjit.nn``'s is not cheap
(benchmarks/bench_gd.py compares the voxel forward model with NumPy). The machine is shared:
numbers are noisy.
"""
from __future__ import annotations

import argparse
import os
import sys

from _solver_bench import emit, print_profile, run_child, scene, time_solve


def one(method, preset, threads, iterations, shape, profile):
    from recon import solver
    ds, grid = scene(shape)
    # The full model for both scenes, whatever the representation's defaults.
    kw = dict(init="random", warm_start_iterations=0, lambertian=True, occlusion_scale=500.0)
    if method == "gd":
        kw.update(lr_units="absolute", lr=1e-3)
    out = time_solve(ds, grid, network=(method == "nbp"), method=method, preset=preset,
                     iterations=iterations, threads=threads, profile=profile, **kw)
    s = solver.settings_for(preset, network=(method == "nbp"))
    out["points"] = s.pings_per_iteration * s.bins_per_ping * s.n_rays
    emit(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--presets", default="cpu,reference")
    ap.add_argument("--threads", default="1,all", help="'1' (deterministic), 'all' or both")
    ap.add_argument("--shape", type=int, nargs=3, default=(125, 125, 94))
    ap.add_argument("--profile", action="store_true", help="where the time of a step goes")
    ap.add_argument("--no-gd", action="store_true", help="only the network")
    ap.add_argument("--one", nargs=3, metavar=("METHOD", "PRESET", "THREADS"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        one(*args.one, args.iterations, args.shape, args.profile)
        return 0
    from sonarsim import runtime
    print(f"variant {runtime.requested_variant()}; grid {tuple(args.shape)}; "
          f"median of steps 3-{args.iterations}")
    print(f"{'method':<7}{'preset':<11}{'threads':>8}{'points/step':>12}{'s/step':>9}"
          f"{'CPU s/step':>12}{'peak RSS MB':>13}")
    for preset in args.presets.split(","):
        for method in ("nbp",) if args.no_gd else ("nbp", "gd"):
            for threads in args.threads.split(","):
                cmd = [sys.executable, os.path.abspath(__file__), "--one", method, preset,
                       threads, "--iterations", str(args.iterations), "--shape",
                       *map(str, args.shape)] + (["--profile"] if args.profile else [])
                r, error = run_child(cmd)
                if r is None:
                    print(f"{method:<7}{preset:<11}{threads:>8}  failed: {error}", flush=True)
                    continue
                print(f"{method:<7}{preset:<11}{threads:>8}{r['points']:>12}"
                      f"{r['s_per_step']:>9.3f}{r['cpu_s_per_step']:>12.3f}"
                      f"{r['peak_rss_mb']:>13.0f}", flush=True)
                print_profile(r.get("profile", []))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
