"""Backprojection throughput (voxel-pings per second) against a vectorised NumPy backprojector.

Usage: .venv/bin/python benchmarks/bench_backprojection.py [--pings N] [--full]

The dataset is synthetic (noise waveforms with an AirSAS-like geometry and a 608-sample
window starting at sample 217): throughput does not depend on the content. Times include
the signal preparation (matched filter, ×5 FFT upsampling) unless stated. The NumPy
backprojector (recon.backprojection.backproject_numpy: one vectorised pass over all voxels
per ping, linear interpolation) runs on a few pings and is extrapolated per voxel-ping.
``--full`` also runs the reference's largest job: 43 200 pings onto 150×150×120 voxels.
The machine is shared: repeat and take the best when numbers look odd.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def dataset(n_pings: int, n_samples: int = 608, start_sample: int = 217, seed: int = 0):
    from recon import synthetic
    from sonarsim import geometry, signals
    from sonarsim.dataset import SonarDataset
    heights = 0.005 + 0.005 * np.arange(int(np.ceil(n_pings / 360)))
    tx, rx, bore = synthetic.circular_poses(360, heights=heights)
    tx, rx, bore = tx[:n_pings], rx[:n_pings], bore[:n_pings]
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((n_pings, n_samples)).astype(np.float32)
    box = geometry.AIRSAS_REAL_BOX
    return SonarDataset(waveforms=w, tx=tx, rx=rx, boresight=bore,
                        pulse=signals.named_pulse("lfm-20k", 100e3), fs=100e3,
                        sound_speed=345.0, source="benchmark", start_sample=start_sample,
                        meta={"box": np.stack([box.lo, box.hi], axis=1).tolist()})


def timed(fn):
    import drjit as dr
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return out, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pings", type=int, default=1440)
    ap.add_argument("--numpy-pings", type=int, default=8)
    ap.add_argument("--full", action="store_true", help="also 43 200 pings × 150×150×120")
    args = ap.parse_args(argv)

    from recon import backprojection as bp
    from recon.grid import Grid
    from sonarsim import geometry

    box = geometry.AIRSAS_REAL_BOX
    grids = {"64^3": (64, 64, 64), "150x150x120": (150, 150, 120)}
    ds = dataset(args.pings)
    rows = []
    for name, shape in grids.items():
        g = Grid.from_box(box, shape)
        bp.backproject(ds.select(np.arange(16)), g, progress=False)        # compile
        _, t = timed(lambda: bp.backproject(ds, g, progress=False))
        prep = timed(lambda: [bp.upsampled_signals(ds, np.arange(b, min(b + bp.PINGS_PER_BLOCK, args.pings)), 5, False)
                              for b in range(0, args.pings, bp.PINGS_PER_BLOCK)])[1]
        vp = g.size * args.pings
        sub = ds.select(np.arange(args.numpy_pings))
        _, t_np = timed(lambda: bp.backproject_numpy(sub, g))
        np_rate = g.size * args.numpy_pings / t_np
        rows.append((name, args.pings, vp / t, vp / max(t - prep, 1e-9), np_rate, vp / t / np_rate,
                     peak_rss_mb()))
    if args.full:
        g = Grid.from_box(box, (150, 150, 120))
        big = dataset(43200)
        _, t = timed(lambda: bp.backproject(big, g, progress=True))
        rows.append(("150x150x120 full", 43200, g.size * 43200 / t, float("nan"), float("nan"),
                     float("nan"), peak_rss_mb()))
        print(f"full job: {t:.1f} s")
    print(f"{'grid':<18}{'pings':>7}{'Mvp/s (all)':>14}{'Mvp/s (kernel)':>16}{'NumPy Mvp/s':>13}"
          f"{'ratio':>8}{'peak RSS MB':>13}")
    for name, n, rate, krate, nrate, ratio, rss in rows:
        print(f"{name:<18}{n:>7}{rate / 1e6:>14.0f}{krate / 1e6:>16.0f}{nrate / 1e6:>13.1f}"
              f"{ratio:>8.0f}{rss:>13.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
