"""Benchmark: memory and time of reverse-mode gradients through ``mi.render`` (issue 21 item 5).

For bounces 1..3, one child process per depth renders the bunny on the ground (shipped mesh,
``sonarsim.data``) from N poses of the reference scan in one batch sensor and measures:

* forward: ``mi.render(scene)`` (the primal, as a dataset render does);
* reverse: ``mi.render(scene, params)`` + ``dr.backward`` of a loss ⟨W, T⟩ into the vertex
  positions and the reflectance (path replay: ``sonar_transient.render_backward``);
* naive (``--naive``): the same derivative by plain AD through the primal (the splat's
  scatter recorded and differentiated), what path replay avoids.

Peak memory is Dr.Jit's allocation watermark (``drjit.detail.malloc_watermark``: every
array the kernels hold, histograms included) after a warm-up run, so compilation does not
count; the process's peak RSS is printed too. Times are wall-clock after ``dr.sync_thread``.

    .venv/bin/python benchmarks/bench_gradients.py [--poses 64] [--bounces 1,2,3] [--naive]
    .venv/bin/python benchmarks/bench_gradients.py --visibility

``--visibility`` measures instead the bias of ignoring visibility changes: the gradient of
a rigid translation of the cube (alone, and on the ground) and of the bunny on the ground
against central differences (docs/differentiable.md, "Visibility").
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np


def build(n_poses: int, bounces: int, spacing: float):
    """(mi, scene, params) with a batch sensor of ``n_poses`` poses of the reference scan."""
    from sonarsim import data, runtime
    from sonarsim.geometry import trajectory
    from sonarsim.render import path_window
    from sonarsim.scene import load_scene
    mi = runtime.mitsuba()
    from sonarsim.plugins import sonar   # after the variant is set
    spec = load_scene("cube")
    poses = trajectory("cylindrical", box=spec.box)
    index = np.linspace(0, len(poses) - 1, n_poses).round().astype(int)
    poses = poses[index]
    window = path_window(None, poses, box=spec.box)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "sonar_transient", "max_bounces": bounces,
                       "surface_spacing": spacing},
        "sensor": {"type": "sonar", "tx_origin": [1, 0, 0], "tx_boresight": [-1, 0, 0],
                   "film": {"type": "sonar_film", "temporal_bins": window.n_bins,
                            "start_opl": window.path_start,
                            "bin_width_opl": window.bin_width}},
        "bunny": {"type": "obj", "filename": str(data.path("bunny.obj")),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0]),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 1.0}}}})
    params = mi.traverse(scene)
    sonar.set_poses(params, poses.tx, poses.tx_boresight, poses.rx, poses.rx_boresight)
    params.update()
    return mi, scene, params


def measure(n_poses: int, bounces: int, spacing: float, naive: bool) -> dict:
    import drjit as dr
    mi, scene, params = build(n_poses, bounces, spacing)
    keys = ("bunny.vertex_positions", "bunny.bsdf.reflectance.value")
    shape = mi.render(scene, seed=1).shape
    weight = mi.TensorXf(np.random.default_rng(0).standard_normal(shape).astype(np.float32))
    backend = dr.JitBackend.LLVM if "llvm" in mi.variant() else dr.JitBackend.CUDA

    def forward():
        dr.eval(mi.render(scene, seed=1))

    def reverse():
        for key in keys:
            dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, seed=1, seed_grad=2)
        dr.backward(dr.sum(image * weight, axis=None))
        grads = [dr.grad(params[key]) for key in keys]
        dr.eval(grads)
        for key in keys:
            dr.disable_grad(params[key])
        params.update()

    def plain_ad():
        from sonarsim.plugins._path_vertex import HistogramSink
        integ, sensor = scene.integrator(), scene.sensors()[0]
        for key in keys:
            dr.enable_grad(params[key])
        params.update()
        ctx, roi, paths = integ._sensor_context(scene, sensor, 2, 0)
        hist = dr.zeros(mi.Float, ctx["n_hist"])
        ctx["reduce_mode"] = dr.ReduceMode.Auto
        integ._histograms(scene, HistogramSink([hist], ctx), ctx, roi, paths)
        dr.backward(dr.sum(hist * weight.array))
        dr.eval([dr.grad(params[key]) for key in keys])
        for key in keys:
            dr.disable_grad(params[key])
        params.update()

    out = {"bounces": bounces, "poses": n_poses, "bins": shape[-1]}
    cases = [("forward", forward), ("reverse", reverse)] + ([("naive", plain_ad)] if naive else [])
    for name, run in cases:
        run()                                   # warm-up: compile, build the strata
        dr.sync_thread()
        dr.flush_malloc_cache()
        dr.detail.malloc_clear_statistics()
        t0 = time.perf_counter()
        run()
        dr.sync_thread()
        out[f"{name}_s"] = time.perf_counter() - t0
        out[f"{name}_mib"] = dr.detail.malloc_watermark(backend) / 2**20
    out["rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def visibility() -> None:
    """AD (interior terms) against central differences of a rigid translation, one pose,
    piston beams (no beam edge), loss <W, T> with a smooth W, same random numbers."""
    import drjit as dr
    from sonarsim import data, runtime
    mi = runtime.mitsuba()
    print("scene                 bounces  axis        AD     FD 3mm     FD 1mm  AD/FD(3mm)")
    for mesh, bounces, ground in (("cube.obj", 1, False), ("cube.obj", 1, True),
                                  ("bunny.obj", 1, True), ("bunny.obj", 2, True)):
        d = {"type": "scene",
             "integrator": {"type": "sonar_transient", "max_bounces": bounces,
                            "surface_spacing": 2e-3, "tx_beam": "piston", "tx_beamwidth": 40.0,
                            "rx_beam": "piston", "rx_beamwidth": 40.0},
             "sensor": {"type": "sonar", "tx_origin": [0.6, 0.1, 0.35],
                        "rx_origin": [0.6, 0.14, 0.35], "tx_boresight": [-0.6, -0.1, -0.25],
                        "film": {"type": "sonar_film", "temporal_bins": 400, "start_opl": 0.9,
                                 "bin_width_opl": 0.002}},
             "target": {"type": "obj", "filename": str(data.path(mesh)),
                        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}},
             "ground": {"type": "rectangle",
                        "to_world": mi.ScalarTransform4f().scale([0.3, 0.3, 1.0]),
                        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 1.0}}}}
        if not ground:
            del d["ground"]
        scene = mi.load_dict(d)
        params = mi.traverse(scene)
        weight = np.broadcast_to(np.sin(np.arange(400) / 15.0), (bounces, 400)).astype(np.float32)
        key = "target.vertex_positions"
        base = np.array(params[key], np.float64).reshape(-1, 3)
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, seed=1, seed_grad=7)
        dr.backward(dr.sum(image * mi.TensorXf(weight.copy()), axis=None))
        grad = np.array(dr.grad(params[key]), np.float64).reshape(-1, 3).sum(axis=0)
        dr.disable_grad(params[key])

        def primal(offset):
            params[key] = mi.Float((base + offset).ravel().astype(np.float32))
            params.update()
            return float((mi.render(scene, seed=7).numpy().astype(np.float64) * weight).sum())

        name = f"{mesh[:-4]}{' + ground' if ground else ''}"
        for axis in range(3):
            fds = []
            for h in (3e-3, 1e-3):
                step = np.zeros(3)
                step[axis] = h
                fds.append((primal(step) - primal(-step)) / (2 * h))
            print(f"{name:20s}  {bounces:7d}  {'xyz'[axis]:>4s}  {grad[axis]:+9.5f}  "
                  f"{fds[0]:+9.5f}  {fds[1]:+9.5f}  {grad[axis] / fds[0]:10.3f}", flush=True)
        params[key] = mi.Float(base.ravel().astype(np.float32))
        params.update()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=64)
    ap.add_argument("--bounces", default="1,2,3")
    ap.add_argument("--spacing", type=float, default=8e-3, help="surface_spacing (m)")
    ap.add_argument("--naive", action="store_true", help="also plain AD through the primal")
    ap.add_argument("--visibility", action="store_true",
                    help="measure the bias of ignoring visibility changes instead")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.visibility:
        visibility()
        return 0
    if args.child is not None:
        print(json.dumps(measure(args.poses, args.child, args.spacing, args.naive)))
        return 0
    rows = []
    for b in (int(v) for v in args.bounces.split(",")):
        cmd = [sys.executable, __file__, "--child", str(b), "--poses", str(args.poses),
               "--spacing", str(args.spacing)] + (["--naive"] if args.naive else [])
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(r.stderr[-2000:], file=sys.stderr)
            return 1
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
    print(f"bunny + ground, {args.poses} poses, surface_spacing {args.spacing:g} m, "
          f"{rows[0]['bins']} bins; Dr.Jit peak memory (MiB) and time (s)")
    head = "bounces  forward MiB  reverse MiB  ratio  forward s  reverse s"
    if args.naive:
        head += "  naive MiB  naive s"
    print(head + "  child RSS MiB")
    for r in rows:
        line = (f"{r['bounces']:7d}  {r['forward_mib']:11.1f}  {r['reverse_mib']:11.1f}  "
                f"{r['reverse_mib'] / r['forward_mib']:5.2f}  {r['forward_s']:9.2f}  "
                f"{r['reverse_s']:9.2f}")
        if args.naive:
            line += f"  {r['naive_mib']:9.1f}  {r['naive_s']:7.2f}"
        print(line + f"  {r['rss_mib']:13.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
