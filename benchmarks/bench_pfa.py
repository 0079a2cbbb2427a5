"""Polar formatting (recon.pfa) against backprojection: time, memory, and the far-field error.

Usage: .venv/bin/python benchmarks/bench_pfa.py [--pings N] [--shape NX NY NZ] [--no-psf]

1. **Speed and memory.** One synthetic dataset (noise waveforms, AirSAS-like cylindrical
   geometry: 72 angles × N/72 heights, 718-sample window) reconstructed by PFA and by
   Dr.Jit backprojection (×5 upsampling) on the same grid over the simulated scene box;
   each method runs in its own process so that its peak RSS is its own.
2. **Far-field error** (``--no-psf`` skips it). A unit point scatterer at distance d from
   the reference point (the grid centre (0, 0, 0.15) of the simulated box), along x
   (horizontal, towards a side of the scan) and along z, imaged by PFA and BP on a small
   grid around the true position (0.5 mm voxels): the position error of the peak, the
   peak magnitude (1 = perfectly focused unit scatterer for PFA) and the −3 dB width along x.
The machine is shared: numbers are noisy; ratios measured in one run are the reliable part.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import time

import numpy as np

SIM_BOUNDS = [[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]]
C = 345.0


def cylindrical(n_pings: int):
    from recon import synthetic
    n_h = max(1, n_pings // 72)
    # AirSAS: TX at rig height 0.285 m + h - 0.1775 (scene z = 0 on the turntable), h = 5..750 mm
    heights = np.linspace(0.005, 0.75, n_h) + 0.285 - 0.1775
    return synthetic.circular_poses(72, radius=0.85, heights=heights, target=(0.0, 0.0, 0.15))


def noise_dataset(n_pings: int, n_samples: int = 718, start_sample: int = 217):
    from sonarsim import signals
    from sonarsim.dataset import SonarDataset
    tx, rx, bore = cylindrical(n_pings)
    w = np.random.default_rng(0).standard_normal((len(tx), n_samples)).astype(np.float32)
    return SonarDataset(waveforms=w, tx=tx, rx=rx, boresight=bore,
                        pulse=signals.named_pulse("lfm-20k", signals.AIRSAS_FS), fs=signals.AIRSAS_FS,
                        sound_speed=C, source="benchmark", start_sample=start_sample)


def _run(method: str, n_pings: int, shape, queue) -> None:
    from recon import backprojection, pfa
    from recon.grid import Grid
    ds = noise_dataset(n_pings)
    grid = Grid(SIM_BOUNDS, shape)
    if method == "bp":
        from recon._jit import jit
        jit()
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    if method == "pfa":
        pfa.solve(ds, grid, progress=False)
    else:
        import drjit as dr
        backprojection.solve(ds, grid, progress=False)
        dr.sync_thread()
    elapsed = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    queue.put({"method": method, "n_pings": len(ds.waveforms), "time_s": elapsed,
               "peak_rss_mb": peak, "rss_before_mb": base})


def speed(n_pings: int, shape, repeats: int) -> None:
    ctx = mp.get_context("spawn")
    rows = []
    for _ in range(repeats):
        for method in ("pfa", "bp"):
            q = ctx.Queue()
            p = ctx.Process(target=_run, args=(method, n_pings, shape, q))
            p.start()
            rows.append(q.get())
            p.join()
    voxels = int(np.prod(shape))
    print(f"\nspeed: {rows[0]['n_pings']} pings x {'x'.join(map(str, shape))} voxels "
          f"(median of {repeats})")
    print(f"{'method':>6} {'time (s)':>9} {'voxel-pings/s':>14} {'peak RSS (MB)':>14} "
          f"{'RSS before (MB)':>16}")
    med = {}
    for m in ("pfa", "bp"):
        r = [x for x in rows if x["method"] == m]
        t = float(np.median([x["time_s"] for x in r]))
        med[m] = t
        print(f"{m:>6} {t:9.2f} {voxels * r[0]['n_pings'] / t:14.3g} "
              f"{max(x['peak_rss_mb'] for x in r):14.0f} {r[0]['rss_before_mb']:16.0f}")
    print(f"PFA is {med['bp'] / med['pfa']:.1f}x faster than backprojection")


def psf(distances) -> None:
    from recon import backprojection, pfa, synthetic
    from recon.grid import Grid
    x0 = np.array([0.0, 0.0, 0.15])
    tx, rx, bore = cylindrical(72 * 30)
    print("\nfar-field error: unit point at x0 + d·axis, reference point x0 = (0, 0, 0.15) m, "
          "72 angles x 30 heights (5..750 mm), R = 0.85 m")
    print(f"{'axis':>4} {'d (cm)':>6} | {'PFA err (mm)':>12} {'PFA peak':>8} {'PFA -3dB x (mm)':>15}"
          f" | {'BP err (mm)':>11} {'BP -3dB x (mm)':>14}")
    for axis in (0, 2):
        for d in distances:
            p = x0.copy()
            p[axis] += d
            ds = synthetic.point_dataset([p], poses=(tx, rx, bore), sound_speed=C)
            half = 0.01
            grid = Grid(np.stack([p - half, p + half], axis=1), (41, 41, 41))
            out = []
            for vol in (pfa.solve(ds, grid, reference_point=x0, progress=False).volume,
                        backprojection.backproject(ds, grid, progress=False)):
                m = np.abs(vol)
                i = np.unravel_index(np.argmax(m), m.shape)
                err = np.linalg.norm(grid.position_of(i) - p) * 1e3
                line = m[:, i[1], i[2]]
                width = np.count_nonzero(line >= line.max() / np.sqrt(2)) * grid.spacing[0] * 1e3
                out.append((err, float(m.max()), width))
            print(f"{'xyz'[axis]:>4} {d * 100:6.0f} | {out[0][0]:12.1f} {out[0][1]:8.2f} "
                  f"{out[0][2]:15.1f} | {out[1][0]:11.1f} {out[1][2]:14.1f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pings", type=int, default=2160)
    ap.add_argument("--shape", type=int, nargs=3, default=(64, 64, 48))
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-psf", action="store_true")
    ap.add_argument("--distances", type=float, nargs="+", default=(0.0, 0.01, 0.02, 0.04, 0.08, 0.12))
    args = ap.parse_args(argv)
    speed(args.pings, tuple(args.shape), args.repeats)
    if not args.no_psf:
        psf(args.distances)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
