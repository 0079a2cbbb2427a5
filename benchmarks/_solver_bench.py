"""What bench_gd.py and bench_nbp.py share: the test scene, timing one solver run in its own
process, and reading and printing that process's result (not a benchmark itself)."""
from __future__ import annotations

import json
import resource
import subprocess
import time

import numpy as np

RESULT = "RESULT "


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scene(shape):
    """(dataset, grid): 20 random point scatterers in the real AirSAS box, 180 pings at two
    heights, on a grid of ``shape`` voxels over that box."""
    from recon import synthetic
    from recon.grid import Grid
    from sonarsim import geometry
    box = geometry.AIRSAS_REAL_BOX
    pts = np.random.default_rng(0).uniform(box.lo, box.hi, (20, 3))
    ds = synthetic.point_dataset(pts, n_pings=180, heights=(0.05, 0.15),
                                 scene_box=np.stack([box.lo, box.hi], 1))
    return ds, Grid.from_box(box, tuple(shape))


def time_solve(ds, grid, *, network: bool, method: str, preset: str, iterations: int,
               threads: str, profile: bool, **overrides) -> dict:
    """One ``recon.solver.solve`` run: median wall and CPU seconds per step over the steps
    after the first (compilation), peak RSS (MB) and, with ``profile``, the
    :class:`recon.solver.PhaseTimer` rows. ``threads`` '1' = the deterministic one-thread
    mode, else all threads."""
    from recon import solver
    stamps, cpu = [], []
    timer = solver.PhaseTimer(skip=2) if profile else None
    solver.solve(ds, grid, network=network, method=method, preset=preset, iterations=iterations,
                 progress=False, deterministic=(threads == "1"), timer=timer,
                 callback=lambda i, r: (stamps.append(time.perf_counter()),
                                        cpu.append(time.process_time())), **overrides)
    out = {"s_per_step": float(np.median(np.diff(stamps[1:]))),
           "cpu_s_per_step": float(np.median(np.diff(cpu[1:]))),
           "peak_rss_mb": peak_rss_mb()}
    if timer is not None:
        out["profile"] = timer.rows()
        timer.close()
    return out


def emit(result: dict) -> None:
    """Print a child's result for :func:`run_child`."""
    print(RESULT + json.dumps(result))


def run_child(cmd: list[str]) -> tuple[dict | None, str]:
    """Run a benchmark child process; (its result, '') or (None, the last line of its stderr)."""
    proc = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(RESULT)]
    if proc.returncode or not lines:
        return None, " ".join(proc.stderr.strip().splitlines()[-1:])
    return json.loads(lines[-1][len(RESULT):]), ""


def print_profile(rows) -> None:
    """The PhaseTimer rows of a result: per phase wall, kernel, launches, compiled, CPU."""
    for name, sec, kern, n, comp, cpu in rows:
        print(f"    {name:<10}{sec:>8.3f} s  kernels {kern:>7.3f} s  "
              f"({n:.0f} launches, {comp:.0f} compiled)  other {sec - kern:>7.3f} s"
              f"  CPU {cpu:>7.3f} s")
