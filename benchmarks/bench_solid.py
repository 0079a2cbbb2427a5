"""Solid extraction (recon.solid.solidify): time and memory of each preset's rule on a
Table-2-sized field, and step 5 against a straightforward voxel-by-voxel march.

Usage: .venv/bin/python benchmarks/bench_solid.py [--shape NX NY NZ] [--repeats N]

The field: a speckled shell of a 19 cm cube standing on the ground in the simulator's box
(complex values of random phase, Rayleigh magnitudes on the faces, a dim haze elsewhere), and
256 sensor positions on the Table-2 cylinder (radius 0.85 m, heights 0.1–0.8 m). Rules: `nbp`
(0.3 of the peak, quorum 0.8) and `gd` (|σ| smoothed by 0.7 voxel, 1.7 × the Otsu level,
quorum 1), both with close 3, K 256 and step 6 (docs/reconstruction.md "Solid output").
Step 5's reference: for a sample of empty voxels, walk voxel by voxel toward each of 16
sensors (NumPy per voxel and direction), extrapolated to all empty voxels of the occupied
set's bounding box and 256 sensors. The occupied counts printed are no quality measure (the
synthetic speckle is not a fitted field; quality: docs/reconstruction.md). The machine is
shared: ratios in one run are the reliable part.

Measured 2026-11-28 (2 shared cores, CI running beside it): step 1 1.8 ms (nbp) / 54 ms (gd:
the blur and the Otsu level), the whole solid 3.9 / 3.5 s, peak 30 / 18 MiB traced; step 5
3.6 s against ≈ 8 h for the voxel-by-voxel march (8 000×).
"""
from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

BOUNDS = np.array([[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]])


def speckled_cube(shape, rng):
    axes = [np.linspace(b[0], b[1], n) for b, n in zip(BOUNDS, shape)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    h = 0.095
    inside = (np.abs(x) <= h) & (np.abs(y) <= h) & (z <= 2 * h)
    pitch = (BOUNDS[:, 1] - BOUNDS[:, 0]) / (np.array(shape) - 1)
    shell_depth = 1.5 * pitch.max()
    shell = inside & ((np.abs(x) > h - shell_depth) | (np.abs(y) > h - shell_depth)
                      | (z > 2 * h - shell_depth))
    mag = np.where(shell, rng.rayleigh(0.6, shape), 0.03 * rng.random(shape))
    return (mag * np.exp(2j * np.pi * rng.random(shape))).astype(np.complex64)


def sensors(count=256):
    angle = np.linspace(0, 2 * np.pi, count, endpoint=False)
    height = np.linspace(0.1, 0.8, count)
    return np.stack([0.85 * np.cos(angle), 0.85 * np.sin(angle), height], axis=1)


def timed(fn, repeats):
    times, peak = [], 0
    for _ in range(repeats):
        tracemalloc.start()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        peak = max(peak, tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    return out, float(np.median(times)), peak


def march(occupied, start, direction):
    """Straightforward: step one voxel at a time (rounded) until an occupied voxel or the edge."""
    shape = np.array(occupied.shape)
    t = 1
    while True:
        p = start + np.round(t * direction).astype(int)
        if np.any(p < 0) or np.any(p >= shape):
            return False
        if occupied[tuple(p)]:
            return True
        t += 1


def main():
    from recon import solid
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=3, default=[125, 125, 94])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    shape = tuple(args.shape)
    field = speckled_cube(shape, np.random.default_rng(0))
    scan = sensors()
    voxels = int(np.prod(shape))
    common = dict(min_fraction=0.1, close=3, floor=True, hidden=256, sensors=scan, bounds=BOUNDS,
                  cavity_floor=0.02, part_volume=1.5e-6, part_height=0.05)
    rules = {"nbp": dict(threshold=0.3, quorum=0.8, smooth=1.0),
             "gd": dict(threshold=1.7, threshold_mode="otsu", blur=0.7, quorum=1.0, smooth=1.0)}
    print(f"field {shape} = {voxels / 1e6:.2f} M voxels, {len(scan)} sensors, median of {args.repeats}")
    for name, rule in rules.items():
        step1 = {k: v for k, v in rule.items() if k in ("threshold", "threshold_mode", "blur")}
        _, t1, m1 = timed(lambda: solid.thresholded(field, step1["threshold"], step1.get("blur", 0.0),
                                                    step1.get("threshold_mode", "peak")), args.repeats)
        out, t, m = timed(lambda: solid.solidify(field, **common, **rule), args.repeats)
        print(f"{name:4s} step 1 {t1 * 1e3:7.1f} ms ({voxels / t1 / 1e6:6.1f} M voxels/s, peak "
              f"{m1 / 2**20:5.0f} MiB); whole solid {t:6.2f} s ({voxels / t / 1e6:5.2f} M voxels/s, "
              f"peak {m / 2**20:5.0f} MiB), {int(out.sum())} voxels occupied")
    # step 7 alone (a Gaussian of the indicator and one labelling)
    _, t7, m7 = timed(lambda: solid.smooth_boundary(out, 1.0), args.repeats)
    print(f"step 7 (smooth 1 voxel) {t7 * 1e3:7.1f} ms ({voxels / t7 / 1e6:6.1f} M voxels/s, "
          f"peak {m7 / 2**20:5.0f} MiB)")
    # step 5 against the straightforward march
    occupied = solid.fill_enclosed(solid.close_gaps(solid.thresholded(field, 0.3), 3), True)
    spacing = (BOUNDS[:, 1] - BOUNDS[:, 0]) / (np.array(shape) - 1)
    relative = scan - BOUNDS[:, 0]
    _, t_fast, _ = timed(lambda: solid.hidden_from(occupied, spacing, relative, 256, 1.0), 1)
    lo, hi = np.argwhere(occupied).min(0), np.argwhere(occupied).max(0) + 1
    box = occupied[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    empty = np.argwhere(~box) + lo
    rng = np.random.default_rng(1)
    sample = empty[rng.choice(len(empty), size=min(200, len(empty)), replace=False)]
    centre = np.argwhere(occupied).mean(0)
    directions = solid.sensor_directions(relative / spacing, 16, centre)
    t0 = time.perf_counter()
    for v in sample:
        for d in directions:
            march(occupied, v, d)
    per_walk = (time.perf_counter() - t0) / (len(sample) * len(directions))
    t_slow = per_walk * len(empty) * 256
    print(f"step 5 (K 256, q 1): {t_fast:.2f} s; a voxel-by-voxel NumPy march: {per_walk * 1e6:.0f} µs "
          f"per walk × {len(empty)} empty voxels × 256 sensors ≈ {t_slow / 60:.0f} min "
          f"(extrapolated from {len(sample)} × {len(directions)} walks): {t_slow / t_fast:.0f}× slower")


if __name__ == "__main__":
    main()
