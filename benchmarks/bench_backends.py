"""Benchmark: the renderer on two Dr.Jit backends (CPU ``llvm_ad_mono``, GPU ``cuda_ad_mono``).

Mitsuba's independent sampler draws the same PCG32 numbers on both backends, so a scene
rendered with the same seed should give the same histograms up to float rounding (Embree on
the CPU and OptiX on the GPU intersect in float32; scatter-adds run in another order). This
script renders fixed scenes of the shipped bunny (sonarsim.data) through ``mi.render`` and
saves or compares the arrays:

* ``snippet``: the pose of issue 21's snippet, 2 bounces, seed 1 (docs/differentiable.md);
* ``batch64``: one batch sensor of 64 poses on a ring, 1 bounce, piston beams, seed 5;
* ``grad_vertices``, ``grad_reflectance``: reverse mode through ``mi.render(scene, params)``
  of ⟨W, T⟩ (W a smooth weight over the bins) for 6 poses: the path-replay adjoint;
* ``coherent``: complex (``amplitude='coherent'``) histograms, 2 bounces, seed 2;

then times a render of N poses on the Table-2 time axis (14 040 bins) after a warm-up
(compilation excluded) and prints pose-bins per second and the Dr.Jit memory watermark.

    python benchmarks/bench_backends.py --save ref_cpu.npz          # on the CPU
    SONARSIM_VARIANT=cuda_ad_mono python benchmarks/bench_backends.py --compare ref_cpu.npz

A GPU machine rarely has libLLVM, so the reference is made on the CPU and carried along.
Measured results: docs/differentiable.md, "Variants".
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

PISTON = {"tx_beam": "piston", "tx_beamwidth": 40.0, "rx_beam": "piston", "rx_beamwidth": 40.0}


def bunny_scene(mi, bounces, bins=400, start=0.6, integrator=None):
    from sonarsim import data
    return mi.load_dict({"type": "scene",
        "integrator": {"type": "sonar_transient", "max_bounces": bounces, **(integrator or {})},
        "sensor": {"type": "sonar", "tx_origin": [0.5, 0.0, 0.2], "rx_origin": [0.5, 0.03, 0.2],
                   "tx_boresight": [-1, 0, -0.2], "rx_boresight": [-1, 0, -0.2],
                   "film": {"type": "sonar_film", "temporal_bins": bins, "start_opl": start,
                            "bin_width_opl": 0.002}},
        "target": {"type": "obj", "filename": str(data.path("bunny.obj")),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}}})


def ring(n, radius=0.5, height=0.25):
    """(tx [n, 3], look [n, 3]): n monostatic poses on a circle, aimed at the bunny's middle."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    tx = np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, height)], axis=1)
    return tx, np.array([0.0, 0.0, 0.09]) - tx


def batch_scene(mi, n, bins, start, radius=0.5):
    from sonarsim.plugins import sonar
    scene = bunny_scene(mi, 1, bins=bins, start=start, integrator=PISTON)
    params = mi.traverse(scene)
    tx, look = ring(n, radius)
    sonar.set_poses(params, tx.astype(np.float32), look.astype(np.float32))
    params.update()
    return scene, params


def render_set(mi) -> dict[str, np.ndarray]:
    import drjit as dr
    out = {"snippet": mi.render(bunny_scene(mi, 2), seed=1).numpy()}
    scene, _ = batch_scene(mi, 64, 300, 0.7)
    out["batch64"] = mi.render(scene, seed=5).numpy()
    scene, params = batch_scene(mi, 6, 300, 0.7)
    keys = ("target.vertex_positions", "target.bsdf.reflectance.value")
    for key in keys:
        dr.enable_grad(params[key])
    params.update()
    image = mi.render(scene, params, seed=3, seed_grad=11)
    weight = np.broadcast_to(np.sin(np.arange(300) / 7.0), image.shape).astype(np.float32)
    dr.backward(dr.sum(image * mi.TensorXf(weight.copy()), axis=None))
    out["grad_vertices"] = np.array(dr.grad(params[keys[0]]), np.float64)
    out["grad_reflectance"] = np.array(dr.grad(params[keys[1]]), np.float64).ravel()
    out["coherent"] = mi.render(bunny_scene(mi, 2, integrator={"amplitude": "coherent"}),
                                seed=2).numpy()
    return out


def timed_render(mi, n_poses: int, bins: int = 14040) -> dict:
    import drjit as dr
    scene, _ = batch_scene(mi, n_poses, bins, 0.6, radius=0.85)
    dr.eval(mi.render(scene, seed=1))                       # compile
    dr.sync_thread()
    dr.detail.malloc_clear_statistics()
    t0 = time.perf_counter()
    image = mi.render(scene, seed=2)
    dr.eval(image)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    return {"poses": n_poses, "bins": bins, "seconds": seconds,
            "pose_bins_per_s": n_poses * bins / seconds,
            "drjit_peak_mib": dr.detail.malloc_watermark(dr.JitBackend.CUDA if "cuda" in
                                                         mi.variant() else dr.JitBackend.LLVM)
            / 2 ** 20}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    what = ap.add_mutually_exclusive_group()
    what.add_argument("--save", type=Path, metavar="REF.npz", help="write the arrays here")
    what.add_argument("--compare", type=Path, metavar="REF.npz",
                      help="compare with arrays saved by --save (e.g. on the other backend)")
    ap.add_argument("--poses", default="360,2160", help="poses of the timed renders ('' none)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args(argv)
    from sonarsim import runtime
    mi = runtime.mitsuba()
    import drjit as dr
    result = {"variant": mi.variant(), "drjit": dr.__version__, "mitsuba": mi.__version__}
    if args.save or args.compare:
        arrays = render_set(mi)
        if args.save:
            np.savez(args.save, **arrays)
            print(f"saved {len(arrays)} arrays to {args.save} ({mi.variant()})")
        else:
            ref = np.load(args.compare)
            print(f"{mi.variant()} against {args.compare}: relative L2 difference")
            for key, value in arrays.items():
                r = ref[key].astype(np.float64)
                err = float(np.linalg.norm(value.astype(np.float64) - r)
                            / max(float(np.linalg.norm(r)), 1e-30))
                result[f"relerr_{key}"] = err
                print(f"  {key:18s} {err:.2e}  (|ref| {np.linalg.norm(r):.3g})")
    for n in [int(v) for v in args.poses.split(",") if v.strip()]:
        row = timed_render(mi, n)
        result[f"render_{n}"] = row
        print(f"render {n} poses x {row['bins']} bins, 1 bounce: {row['seconds']:.3f} s, "
              f"{row['pose_bins_per_s']:.3g} pose-bins/s, Dr.Jit peak {row['drjit_peak_mib']:.0f} MiB")
    result["rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"process peak RSS {result['rss_mib']:.0f} MiB")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
