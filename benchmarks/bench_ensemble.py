"""Ensemble members side by side (``recon.solver.members``) against the same members fitted in
turn in one process: wall time, fitted steps per second, peak memory, and whether the two
volumes agree to the bit.

Usage: .venv/bin/python benchmarks/bench_ensemble.py [--method nbp|gd] [--members K]
                                                     [--iterations N] [--shape NX NY NZ]

Scene: the 20 point scatterers of bench_gd / bench_nbp (180 pings, the real AirSAS box), the
method's preset with ``--iterations`` steps, deterministic (one Dr.Jit thread per fit), solid
output. Each mode runs in its own process; its peak memory is the largest of that process
and, side by side, of its member workers (``RUSAGE_CHILDREN``), so the sum over the workers
running at once is up to ``min(K, cores)`` times the worker figure. The in-turn run is the
straightforward implementation the parallel one must equal. The machine is shared: the ratio
of one run is the reliable part; the full-size measurement is in docs/reconstruction.md
("Ensemble members side by side").

Measured 2026-11-29 (2 cores, a Table-2 GD fit running on one of them): NBP, 3 members × 40
steps, 64 × 64 × 48: in turn 51.6 s, side by side 39.5 s (× 1.31; each worker 558 MB, the
parent 179 MB against 586 MB in turn), volumes identical.
"""
from __future__ import annotations

import argparse
import hashlib
import resource
import sys
import time

from _solver_bench import emit, run_child, scene


def one(method: str, members: int, iterations: int, shape, parallel: bool) -> dict:
    from recon import solver
    ds, grid = scene(shape)
    start = time.perf_counter()
    vol = solver.solve(ds, grid, network=(method == "nbp"), method=method, preset=method,
                       iterations=iterations, ensemble=members, progress=False,
                       parallel_members=parallel)
    wall = time.perf_counter() - start
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return {"wall_s": wall, "steps_per_s": members * iterations / wall, "peak_rss_mb": own,
            "worker_peak_rss_mb": kids,
            "digest": hashlib.sha256(vol.volume.tobytes()).hexdigest()[:16]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", choices=("nbp", "gd"), default="nbp")
    ap.add_argument("--members", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--shape", type=int, nargs=3, default=[64, 64, 48])
    ap.add_argument("--child", choices=("parallel", "turn"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        emit(one(args.method, args.members, args.iterations, args.shape, args.child == "parallel"))
        return
    from recon.solver.members import available_cores
    print(f"{args.method}: {args.members} members × {args.iterations} steps, grid "
          f"{tuple(args.shape)}, {available_cores()} cores")
    results = {}
    for mode in ("turn", "parallel"):
        cmd = [sys.executable, __file__, "--method", args.method, "--members", str(args.members),
               "--iterations", str(args.iterations), "--shape", *map(str, args.shape),
               "--child", mode]
        res, err = run_child(cmd)
        if res is None:
            print(f"  {mode}: failed ({err})")
            return
        results[mode] = res
        workers = (f", {res['worker_peak_rss_mb']:.0f} MB per worker" if mode == "parallel"
                   else "")
        print(f"  {'in turn' if mode == 'turn' else 'side by side':12s} {res['wall_s']:7.1f} s wall, "
              f"{res['steps_per_s']:6.2f} steps/s, peak {res['peak_rss_mb']:.0f} MB here"
              f"{workers}, volume {res['digest']}")
    turn, par = results["turn"], results["parallel"]
    print(f"  side by side / in turn: × {turn['wall_s'] / par['wall_s']:.2f} faster; volumes "
          f"{'identical' if turn['digest'] == par['digest'] else 'DIFFERENT'}")


if __name__ == "__main__":
    main()
