"""Gradient-descent cost: seconds per iteration and peak memory, and the linear model's
forward + adjoint against a vectorised NumPy implementation of the same job.

Usage: .venv/bin/python benchmarks/bench_gd.py [--iterations N] [--shape NX NY NZ]

Reference-sized iteration (reference code inr_reconstruction/): 5 pings × 200 range bins × ~4 800
rays (num_rays 5000 in the reference → 4 777 rays), on the AirSAS grid 150×150×120, with
Lambertian normals, occlusion and all priors on. The dataset is a synthetic set of point
scatterers on a 2-height AirSAS-like scan. The machine is shared: numbers are noisy.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def numpy_forward_adjoint(points, valid, shape_pjk, grid, x, target):
    """One linear-model data-gradient evaluation in NumPy: trilinear gather, sum over rays,
    residual, adjoint scatter (np.bincount). points [L, 3]; returns the gradient voxels."""
    P, J, K = shape_pjk
    lo, h = grid.bounds[:, 0], grid.spacing
    n = np.asarray(grid.shape)
    g = (points - lo) / h
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    flat = x.ravel()
    vals = np.zeros(len(points), complex)
    corners = []
    for c in np.ndindex(2, 2, 2):
        idx = i0 + np.array(c)
        inside = valid & np.all((idx >= 0) & (idx < n), axis=1)
        w = np.prod(np.where(np.array(c) == 1, f, 1 - f), axis=1) * inside
        lin = np.where(inside, (idx[:, 0] * n[1] + idx[:, 1]) * n[2] + idx[:, 2], 0)
        vals += w * flat[lin]
        corners.append((lin, w))
    y = vals.reshape(P, J, K).sum(axis=1)
    r = (y - target).reshape(P, 1, K)
    back = np.broadcast_to(r, (P, J, K)).ravel()
    grad = np.zeros(flat.size, complex)
    for lin, w in corners:
        grad += np.bincount(lin, weights=w * back.real, minlength=flat.size) \
            + 1j * np.bincount(lin, weights=w * back.imag, minlength=flat.size)
    return grad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--shape", type=int, nargs=3, default=(150, 150, 120))
    ap.add_argument("--rays", type=int, default=4777)
    ap.add_argument("--bins", type=int, default=200)
    args = ap.parse_args(argv)

    import drjit as dr
    from recon import forward as F
    from recon import gradient_descent as gd
    from recon import measurements, synthetic
    from recon.grid import Grid
    from sonarsim import geometry

    box = geometry.AIRSAS_REAL_BOX
    rng = np.random.default_rng(0)
    pts = rng.uniform(box.lo, box.hi, (20, 3))
    ds = synthetic.point_dataset(pts, n_pings=360, heights=(0.05, 0.15),
                                 scene_box=np.stack([box.lo, box.hi], 1))
    grid = Grid.from_box(box, tuple(args.shape))
    rows = []
    for label, kw in [("full model", dict(lambertian=True, occlusion_scale=1000.0, sparsity=10.0,
                                          smoothness=50.0, phase=0.1)),
                      ("linear model", dict(lambertian=False, occlusion_scale=0.0, sparsity=0.0))]:
        stamps = []
        t0 = time.perf_counter()
        gd.solve(ds, grid, iterations=args.iterations, n_rays=args.rays, bins_per_ping=args.bins,
                 reg_start=0, progress=False, callback=lambda i, r: stamps.append(time.perf_counter()),
                 **kw)
        per_it = np.median(np.diff(stamps)) if len(stamps) > 2 else (time.perf_counter() - t0)
        rows.append((label, per_it, peak_rss_mb()))

    # Linear model: Dr.Jit forward + AD backward vs NumPy forward + adjoint, same lanes.
    settings = gd.GDSettings(n_rays=args.rays, bins_per_ping=args.bins)
    speeds = measurements.sound_speeds(ds)
    tgt = gd.targets(ds, settings)
    first, last = gd.reachable_bins(ds, grid, speeds)
    sampler = gd._Sampler(tgt, first, last, settings, np.random.default_rng(1))
    pings, bins, roll = sampler.draw()
    geo = F.ping_geometry(ds, pings, bins, speeds)
    samples = F.EllipsoidSamples(geo, F.cone_directions(args.rays, 30.0))
    vf = F.VoxelField(grid)
    m = vf.m
    x = (rng.standard_normal(grid.size) + 1j * rng.standard_normal(grid.size)).astype(np.complex64)
    target = tgt[pings[:, None], bins]

    def jit_step():
        re, im = m.Float(x.real.copy()), m.Float(x.imag.copy())
        dr.enable_grad(re, im)
        y_re, y_im = F.render(vf.field(re, im), samples)
        t = target.ravel()
        loss = dr.sum(dr.square(y_re - m.Float(t.real.copy())) + dr.square(y_im - m.Float(t.imag.copy())))
        dr.backward(loss)
        return dr.grad(re), dr.grad(im)

    jit_step()
    dr.sync_thread()
    t0 = time.perf_counter()
    g_re, _ = jit_step()
    dr.eval(g_re)
    dr.sync_thread()
    t_jit = time.perf_counter() - t0
    points = np.array(samples.points).T.astype(np.float64)
    valid = np.array(samples.valid)
    t0 = time.perf_counter()
    numpy_forward_adjoint(points, valid, samples.shape, grid, x.reshape(grid.shape), target)
    t_np = time.perf_counter() - t0

    lanes = int(np.prod(samples.shape))
    print(f"grid {grid.shape}, {settings.pings_per_iteration} pings x {args.bins} bins x {args.rays} rays "
          f"= {lanes / 1e6:.1f} M samples per iteration")
    print(f"{'run':<16}{'s/iteration':>13}{'peak RSS MB':>13}")
    for label, per_it, rss in rows:
        print(f"{label:<16}{per_it:>13.3f}{rss:>13.0f}")
    print(f"linear data gradient: Dr.Jit {t_jit:.3f} s, NumPy {t_np:.3f} s, ratio {t_np / t_jit:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
