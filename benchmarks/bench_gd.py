"""Gradient-descent (voxel) iteration cost: seconds per iteration and peak memory at the 'cpu'
and 'reference' sampling sizes, on one thread (the deterministic default) and on all threads
(``--no-deterministic``), and the forward model of one ping against a straightforward NumPy
implementation of the same model (same samples; the two results are compared too).

Usage: .venv/bin/python benchmarks/bench_gd.py [--sizes cpu,reference] [--iterations N]
                                               [--threads 1,all] [--profile] [--shape NX NY NZ]

Sizes (recon.solver.PRESETS sampling): 'cpu' = 5 pings × 64 bins × 600 rays, 'reference' =
5 pings × 200 bins × 4 777 rays (the reference code's num_rays 5000, max_weights 200) per
iteration, on the AirSAS grid 150×150×120, with the full model (Lambertian normals from the
trilinear gradient, occlusion s_occ 1000) and the AirSAS priors (sparsity, smoothness,
phase) on from the first step. Scene: 20 synthetic point scatterers in the AirSAS box, a
2-height scan of 360 pings. Each configuration runs in its own process (peak RSS is per
configuration); the first two iterations (kernel compilation or cache loads) are excluded
from the median. CPU s/it is the process's CPU time per iteration (on a shared machine the
steadier figure for one thread). ``--profile`` adds where one iteration's time goes
(:class:`recon.solver.PhaseTimer`). ``SONARSIM_VARIANT=cuda_ad_mono`` runs it on a GPU (the
thread setting is then moot). The machine is shared: numbers are noisy.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from _solver_bench import emit, print_profile, run_child, scene, time_solve

SIZES = ("cpu", "reference")
FULL = dict(lambertian=True, occlusion_scale=1000.0, sparsity=10.0, smoothness=50.0, phase=0.1,
            reg_start=0, init="random", lr_units="absolute", lr=1e-3)


# ---------------------------------------------------------------------------------------
# NumPy forward model of one ping (the same model as recon.forward.render)

def numpy_render(points, dirs, t, valid, shape_jk, grid, x, occlusion_scale):
    """ŷ [K] complex of one ping: trilinear σ (zero outside the grid) and its exact gradient,
    Lambertian factor max(0, ⟨∇|σ|, d⟩/‖∇|σ|‖), transmittance exp(−2·s_occ·Σ_{i<k}|σ_i|Δt_i),
    summed over the J rays. points, dirs [J·K, 3], t [J·K], valid [J·K] bool (lane j·K + k)."""
    J, K = shape_jk
    lo, h = grid.bounds[:, 0], grid.spacing
    n = np.asarray(grid.shape)
    g = (points - lo) / h
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    flat = x.ravel()
    s = np.zeros(len(points), complex)
    grad = np.zeros((len(points), 3), complex)
    for c in np.ndindex(2, 2, 2):
        idx = i0 + np.array(c)
        inside = valid & np.all((idx >= 0) & (idx < n), axis=1)
        lin = np.where(inside, (idx[:, 0] * n[1] + idx[:, 1]) * n[2] + idx[:, 2], 0)
        v = np.where(inside, flat[lin], 0)
        wk = np.where(np.array(c) == 1, f, 1 - f)                  # per-axis weights [L, 3]
        s += np.prod(wk, axis=1) * v
        for a in range(3):
            dw = (1.0 if c[a] else -1.0) / h[a] * np.prod(np.delete(wk, a, axis=1), axis=1)
            grad[:, a] += dw * v
    mag = np.sqrt(np.abs(s) ** 2 + 1e-20)
    gm = (grad.real * s.real[:, None] + grad.imag * s.imag[:, None]) / mag[:, None]
    lam = np.maximum(0.0, np.sum(gm * dirs, axis=1) / np.sqrt(np.sum(gm ** 2, axis=1) + 1e-30))
    tt = t.reshape(J, K)
    step = np.empty_like(tt)
    step[:, :-1] = tt[:, 1:] - tt[:, :-1]
    step[:, -1] = step[:, -2] if K > 1 else 0.0
    dens = (mag * valid).reshape(J, K) * step
    trans = np.exp(-2.0 * occlusion_scale * (np.cumsum(dens, axis=1) - dens))
    return np.sum((s * valid).reshape(J, K) * lam.reshape(J, K) * trans, axis=0)


def forward_vs_numpy(ds, grid, size, repeats=3):
    """(Dr.Jit s, NumPy s, max relative difference) for the full forward model of one ping."""
    import drjit as dr
    from recon import forward as F
    from recon import measurements, solver
    settings = solver.settings_for(size, **FULL)
    speeds = measurements.sound_speeds(ds)
    tgt = solver.targets(ds, settings)
    first, last = solver.reachable_bins(ds, grid, speeds)
    one = solver.settings_for(size, **dict(FULL, pings_per_iteration=1))
    pings, bins, _ = solver.Sampler(tgt, first, last, one, np.random.default_rng(1)).draw()
    samples = F.EllipsoidSamples(F.ping_geometry(ds, pings, bins, speeds),
                                 F.cone_directions(settings.n_rays, settings.beamwidth_deg))
    vf = F.VoxelField(grid)
    m = vf.m
    rng = np.random.default_rng(2)
    x = (rng.standard_normal(grid.size) + 1j * rng.standard_normal(grid.size)).astype(np.complex64)
    re, im = m.Float(x.real.copy()), m.Float(x.imag.copy())
    eps = 0.5 * float(np.min(vf.h))

    def jit_forward():
        y = F.render(vf.field(re, im), samples, lambertian_eps=eps,
                     occlusion_scale=settings.occlusion_scale)
        dr.eval(y)
        dr.sync_thread()
        return y

    jit_forward()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        y_re, y_im = jit_forward()
        times.append(time.perf_counter() - t0)
    _, J, K = samples.shape
    pts = np.array(samples.points).T.astype(np.float64)
    dirs = np.array(samples.dirs).T.astype(np.float64)
    t0 = time.perf_counter()
    y_np = numpy_render(pts, dirs, np.asarray(samples.t, np.float64), np.asarray(samples.valid),
                        (J, K), grid, x.reshape(grid.shape), settings.occlusion_scale)
    t_np = time.perf_counter() - t0
    y = np.asarray(y_re) + 1j * np.asarray(y_im)
    diff = float(np.abs(y - y_np).max() / max(np.abs(y_np).max(), 1e-30))
    return float(np.median(times)), t_np, diff


# ---------------------------------------------------------------------------------------
# One configuration (in its own process)

def one(size, threads, iterations, shape, profile):
    from recon import gradient_descent as gd
    ds, grid = scene(shape)
    out = time_solve(ds, grid, network=False, method="gd", preset=size, iterations=iterations,
                     threads=threads, profile=profile, **FULL)
    s = gd.settings_for(size)
    out["samples"] = s.pings_per_iteration * s.bins_per_ping * s.n_rays
    if threads != "1":
        out["forward_jit_s"], out["forward_numpy_s"], out["forward_diff"] = \
            forward_vs_numpy(ds, grid, size)
    emit(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--sizes", default=",".join(SIZES))
    ap.add_argument("--threads", default="1,all", help="'1' (deterministic), 'all' or both")
    ap.add_argument("--shape", type=int, nargs=3, default=(150, 150, 120))
    ap.add_argument("--profile", action="store_true", help="where the time of an iteration goes")
    ap.add_argument("--one", nargs=2, metavar=("SIZE", "THREADS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        one(args.one[0], args.one[1], args.iterations, args.shape, args.profile)
        return 0
    from sonarsim import runtime
    print(f"variant {runtime.requested_variant()}; grid {tuple(args.shape)}; full model "
          f"(Lambertian, occlusion, sparsity + smoothness + phase priors); "
          f"median of iterations 3-{args.iterations}")
    print(f"{'size':<11}{'threads':>8}{'samples/it':>12}{'s/iteration':>13}{'CPU s/it':>10}"
          f"{'peak RSS MB':>13}"
          f"{'1-ping forward: Dr.Jit s':>26}{'NumPy s':>9}{'ratio':>7}{'max rel diff':>14}")
    for size in args.sizes.split(","):
        for threads in args.threads.split(","):
            cmd = [sys.executable, os.path.abspath(__file__), "--one", size, threads,
                   "--iterations", str(args.iterations), "--shape", *map(str, args.shape)]
            if args.profile:
                cmd.append("--profile")
            r, error = run_child(cmd)
            if r is None:
                print(f"{size:<11}{threads:>8}  failed: {error}")
                continue
            fwd = ""
            if "forward_jit_s" in r:
                fwd = (f"{r['forward_jit_s']:>26.4f}{r['forward_numpy_s']:>9.2f}"
                       f"{r['forward_numpy_s'] / r['forward_jit_s']:>6.0f}x{r['forward_diff']:>14.1e}")
            print(f"{size:<11}{threads:>8}{r['samples']:>12}{r['s_per_step']:>13.3f}"
                  f"{r['cpu_s_per_step']:>10.3f}{r['peak_rss_mb']:>13.0f}{fwd}", flush=True)
            print_profile(r.get("profile", []))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
