"""Render a sonar pose with ``mi.render`` and differentiate it (docs/differentiable.md).

Part 1 is the snippet of issue 21: a scene with the ``sonar_transient`` integrator, a
``sonar`` sensor and its ``sonar_film``, the reference's bunny (shipped with sonarsim);
``mi.render`` returns the per-bounce histograms over round-trip path length, TensorXf
(max_bounces, temporal_bins).

Part 2 differentiates it: the bunny is moved by an unknown offset, and gradient descent on
⟨T − T_measured⟩² through ``mi.render(scene, params)`` (gradients with respect to the mesh's
vertex positions, constrained here to a rigid translation) finds the offset again from the
histograms of a few poses of one batch sensor.

    python examples/mitsuba_render.py            # ~1 min on 2 cores
    python examples/mitsuba_render.py --quick    # fewer steps (the tests)
"""
from __future__ import annotations

import argparse

import numpy as np

from sonarsim import data, runtime


def part1(mi):
    scene = mi.load_dict({"type": "scene",
        "integrator": {"type": "sonar_transient", "max_bounces": 2},
        "sensor": {"type": "sonar", "tx_origin": [0.5, 0.0, 0.2], "rx_origin": [0.5, 0.03, 0.2],
                   "tx_boresight": [-1, 0, -0.2], "rx_boresight": [-1, 0, -0.2],
                   "film": {"type": "sonar_film", "temporal_bins": 400,
                            "start_opl": 0.6, "bin_width_opl": 0.002}},
        "target": {"type": "obj", "filename": str(data.path("bunny.obj")),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}}})
    T = mi.render(scene, seed=1)          # TensorXf, shape (max_bounces, temporal_bins)
    energy = T.numpy().sum(axis=1)
    print(f"mi.render: {type(T).__name__} {tuple(T.shape)}; energy per bounce "
          + ", ".join(f"{e:.3g}" for e in energy))
    return T


def part2(mi, steps: int, true_offset=(0.004, -0.003, 0.002)):
    from sonarsim.plugins import sonar   # after the variant is set (runtime.mitsuba())
    import drjit as dr
    angles = np.radians([0.0, 60.0, 120.0, 180.0, 240.0, 300.0])
    tx = np.stack([0.5 * np.cos(angles), 0.5 * np.sin(angles), np.full(6, 0.25)], axis=1)
    look = np.array([0.0, 0.0, 0.09]) - tx
    scene = mi.load_dict({"type": "scene",
        "integrator": {"type": "sonar_transient", "max_bounces": 1, "tx_beam": "piston",
                       "tx_beamwidth": 40.0, "rx_beam": "piston", "rx_beamwidth": 40.0},
        "sensor": {"type": "sonar", "tx_origin": [1, 0, 0], "tx_boresight": [-1, 0, 0],
                   "film": {"type": "sonar_film", "temporal_bins": 300,
                            "start_opl": 0.7, "bin_width_opl": 0.002}},
        "target": {"type": "obj", "filename": str(data.path("bunny.obj")),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}}})
    params = mi.traverse(scene)
    sonar.set_poses(params, tx, look)                     # a batch sensor: 6 monostatic poses
    rest = np.array(params["target.vertex_positions"]).reshape(-1, 3)

    def place(offset):
        params["target.vertex_positions"] = mi.Float((rest + offset).ravel().astype(np.float32))
        params.update()

    place(np.asarray(true_offset))
    measured = mi.render(scene, seed=1)                   # the "measurement"
    opt = mi.ad.Adam(lr=5e-4)                             # metres per step, at most
    opt["offset"] = mi.Vector3f(0.0, 0.0, 0.0)            # the unknown, from zero
    start = mi.Point3f(*(mi.Float(rest[:, i]) for i in range(3)))
    for step in range(steps):
        params["target.vertex_positions"] = dr.ravel(start + opt["offset"])
        params.update()
        T = mi.render(scene, params, seed=2 + step, seed_grad=1000 + step)
        dr.backward(dr.sum(dr.square(T - measured), axis=None))
        opt.step()
    offset = dr.detach(opt["offset"])
    found = np.array(offset).ravel()
    error = float(np.linalg.norm(found - np.asarray(true_offset)))
    print(f"offset found {np.round(found * 1e3, 2).tolist()} mm, true "
          f"{np.round(np.asarray(true_offset) * 1e3, 2).tolist()} mm: error {error * 1e3:.2f} mm "
          f"after {steps} steps")
    return found, error


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer descent steps (tests)")
    args = ap.parse_args(argv)
    mi = runtime.mitsuba()
    part1(mi)
    part2(mi, 25 if args.quick else 60)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
