"""Cost of `recon refine`'s unexplained image (``recon.unexplained.unexplained_image``):
rendering the kept mesh for the imaged pings, the weights, and the coherent backprojections
(the data over all the pings, the unexplained signal over each elevation half) — against a
straightforward NumPy backprojection of the same signals.

    python benchmarks/bench_unexplained.py DATASET.h5 [--pings 2160] [--shape 125 125 94]
        [--numpy-pings 16] [--edge-length 0.008] [--out result.json]

The mesh is the dataset's ground-truth mesh remeshed to --edge-length (the size `recon refine`
works at), the ground the dataset's, the grid the box of the ground-truth mesh ± 5 cm (the
Table-2 grid's voxel count by default). Prints one JSON line: seconds (wall) and CPU seconds per
stage, pings per second of the whole image, the peak RSS, and the ratio of the NumPy
backprojection (``recon.straightforward.backproject_numpy``, float64, on ``--numpy-pings`` pings,
scaled to all) to the Dr.Jit one per ping. On a shared machine report CPU time.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def timed(fn):
    w0, c0 = time.perf_counter(), cpu_seconds()
    out = fn()
    return out, time.perf_counter() - w0, cpu_seconds() - c0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--pings", type=int, default=2160)
    parser.add_argument("--shape", type=int, nargs=3, default=(125, 125, 94))
    parser.add_argument("--numpy-pings", type=int, default=16)
    parser.add_argument("--edge-length", type=float, default=0.008)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    import trimesh

    from recon import backprojection, measurements, straightforward, unexplained
    from recon.grid import Grid
    from recon.pulse_chain import Envelope
    from recon.refine import RefineSettings, dataset_ground, remesh
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(args.dataset, transients=False)
    if ds.gt_vertices is None:
        raise SystemExit("the dataset holds no ground-truth mesh to render")
    v, f = remesh(np.asarray(ds.gt_vertices, np.float64), np.asarray(ds.gt_faces, np.int64),
                  args.edge_length)
    mesh = trimesh.Trimesh(v, f, process=False)
    lo, hi = mesh.bounds[0] - 0.05, mesh.bounds[1] + 0.05
    lo[2] = max(lo[2], 0.0)
    grid = Grid(np.stack([lo, hi], axis=1), tuple(args.shape))
    pings = unexplained.residual_pings(np.arange(ds.n_pings), args.pings)
    settings, ground = RefineSettings(), dataset_ground(ds)

    m, w_render, c_render = timed(lambda: unexplained.model_waveforms(
        ds, mesh, 1.0, pings, settings, ground))
    z = measurements.matched_filtered(ds, pings)

    def weights():
        return unexplained.unexplained_weights(np.abs(z),
                                               Envelope(ds.pulse, ds.n_samples)(m)[0]) * z
    u, w_weights, c_weights = timed(weights)
    sub = dataclasses.replace(ds.select(pings), waveforms=u.astype(np.complex64),
                              waveform_kind=measurements.DECONVOLVED)
    backprojection.backproject(sub.select(np.arange(4)), grid, progress=False)   # compile once
    halves = unexplained.elevation_halves(ds, pings, grid)
    lower = np.ones(len(pings), bool) if halves is None else halves[0]
    parts = [(z, np.ones(len(pings), bool)), (u, lower)] + ([] if halves is None else [(u, ~lower)])
    _, w_bp, c_bp = timed(lambda: [backprojection.backproject(
        dataclasses.replace(sub.select(np.flatnonzero(rows)),
                            waveforms=s[rows].astype(np.complex64)), grid, progress=False)
        for s, rows in parts])
    few = sub.select(np.arange(min(args.numpy_pings, len(pings))))
    _, w_np, c_np = timed(lambda: straightforward.backproject_numpy(few, grid))
    _, w_jit_few, c_jit_few = timed(lambda: backprojection.backproject(few, grid, progress=False))
    total = w_render + w_weights + w_bp
    row = {"dataset": str(args.dataset), "pings": int(len(pings)), "faces": int(len(f)),
           "voxels": int(np.prod(args.shape)),
           "render_s": round(w_render, 2), "render_cpu_s": round(c_render, 2),
           "weights_s": round(w_weights, 2), "backprojections_s": round(w_bp, 2),
           "backprojections_cpu_s": round(c_bp, 2), "image_s": round(total, 2),
           "pings_per_s": round(len(pings) / total, 1),
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0),
           "numpy_bp_s_per_ping": round(w_np / few.n_pings, 4),
           "drjit_bp_s_per_ping": round(w_bp / (2 * len(pings)), 5),
           "numpy_over_drjit": round((w_np / few.n_pings) / (w_bp / (2 * len(pings))), 1),
           "numpy_over_drjit_same_pings": round(w_np / max(w_jit_few, 1e-9), 1)}
    print(json.dumps(row))
    if args.out is not None:
        args.out.write_text(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
