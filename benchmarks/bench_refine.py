"""Cost of one `recon refine` step: render a batch of pings through ``mi.render`` and
back-propagate a waveform-domain gradient to the vertices (the work of every optimiser step).

    python benchmarks/bench_refine.py DATASET.h5 [--pings-per-batch 64] [--bounces 1 2]
        [--edge-length 0.005] [--patch-size 0.025 | --affine] [--repeats 2] [--out result.json]

The mesh is the dataset's ground-truth mesh remeshed to --edge-length (the size the refinement
works at); the ground is the dataset's. Prints one JSON line per bounce count: faces, pings,
seconds (wall, best of --repeats after one warm-up) and CPU seconds (user+sys of the process)
for the forward render and for forward + backward. ``--patch-size``: the support stage's
scene instead (the mesh cut into patches of that size, one albedo each; the backward pass
then also yields the per-patch albedo gradients), with its scene-building time. ``--affine``:
the affine stage's step instead (the vertices a function of its five parameters, the
gradient carried back to them). On a shared machine report CPU time.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def measure(ds, mesh, bounces: int, n_pings: int, repeats: int, patch_size=None,
            affine: bool = False) -> dict:
    from recon import refine
    from sonarsim import runtime
    mi = runtime.mitsuba()
    import drjit as dr
    settings = refine.RefineSettings(bounces=bounces)
    _, window, _ = refine.dataset_chain(ds, settings)
    index = np.linspace(0, ds.n_pings - 1, n_pings).astype(int)
    rows = []
    labels = None if patch_size is None else refine.patch_labels(mesh.vertices, mesh.faces,
                                                                 patch_size)
    with tempfile.TemporaryDirectory() as workdir:
        t_build, c_build = time.perf_counter(), cpu_seconds()
        scene = refine.RenderedScene(mesh, ds, window, refine.dataset_ground(ds), settings, workdir,
                                     labels)
        t_build, c_build = time.perf_counter() - t_build, cpu_seconds() - c_build
        v0, _ = scene.vertices
        pivot, half = refine.affine_frame(mesh.vertices, 0.008)
        for rep in range(repeats + 1):
            params = [mi.Float(np.zeros(n, np.float32)) for n in (3, 2)]   # log-scales, shift
            if affine:
                for q in params:
                    dr.enable_grad(q)
                v = refine._affine_ad(mi, dr, v0, pivot, half, *params)
            else:
                v = mi.Float(v0)
                dr.enable_grad(v)
            albedo = mi.Float(np.ones(scene.n_patches if labels is not None else 1, np.float32))
            dr.enable_grad(albedo)
            t0, c0 = time.perf_counter(), cpu_seconds()
            hist = scene.render(v, albedo, index, seed=rep)
            h = hist.numpy()
            t1, c1 = time.perf_counter(), cpu_seconds()
            weight = mi.TensorXf(np.ones(h.shape, np.float32))
            dr.backward(dr.sum(hist * weight, axis=None))
            (dr.grad(params[0]) if affine else dr.grad(v)).numpy()
            rows.append((t1 - t0, c1 - c0, time.perf_counter() - t0, cpu_seconds() - c0))
    best = min(rows[1:], key=lambda r: r[2])
    return {"bounces": bounces, "faces": int(len(mesh.faces)), "pings": int(n_pings),
            "gradient_of": "affine parameters" if affine else "vertices",
            "patches": int(scene.n_patches) if labels is not None else None,
            "build_s": round(t_build, 3), "build_cpu_s": round(c_build, 3),
            "bins": int(window[2]), "forward_s": round(best[0], 3), "forward_cpu_s": round(best[1], 3),
            "step_s": round(best[2], 3), "step_cpu_s": round(best[3], 3)}


def main(argv=None) -> int:
    from recon import refine
    from sonarsim.dataset import SonarDataset
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--pings-per-batch", type=int, default=64)
    p.add_argument("--bounces", type=int, nargs="+", default=[1, 2])
    p.add_argument("--edge-length", type=float, default=5e-3)
    p.add_argument("--patch-size", type=float, default=None,
                   help="measure the support stage's patch scene (patch size, m)")
    p.add_argument("--affine", action="store_true",
                   help="measure the affine stage's step (gradient of its five parameters)")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    ds = SonarDataset.read(args.dataset)
    if ds.gt_vertices is None:
        p.error(f"{args.dataset} has no ground-truth mesh")
    v, f = refine.remesh(ds.gt_vertices, ds.gt_faces, args.edge_length)
    mesh = trimesh.Trimesh(v, f, process=False)
    if args.affine and args.patch_size is not None:
        p.error("--affine and --patch-size measure different stages: give one")
    results = [measure(ds, mesh, b, args.pings_per_batch, args.repeats, args.patch_size,
                       args.affine)
               for b in args.bounces]
    for r in results:
        print(json.dumps(r))
    if args.out is not None:
        from sonarsim.atomic import atomic_path
        with atomic_path(args.out) as tmp:
            tmp.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
