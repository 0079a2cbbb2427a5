"""Benchmark: ``sonarsim simulate`` end to end on the fitted Stanford bunny.

The reference's simulated scan: 54 000 poses (360 angles x 150 heights), 10 000 paths per
pose, 3 bounces, 20 kHz LFM, 20 dB SNR. ``--poses N`` runs an evenly spread subset
(every k-th pose of the scan, k = 54000 // N) and projects time and file size linearly to
the full scan; peak memory is bounded by one chunk and does not grow with N.

Also times the signal stage (bounce sum, pulse convolution, decimation) against a
straightforward NumPy implementation (np.convolve per ping, then decimate).

Usage: .venv/bin/python benchmarks/bench_simulate.py [--poses 2000] [--paths 10000]
       [--threads N] [--mesh ../shared/data/meshes/bunny.obj] [--keep]
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FULL_SCAN = 54_000


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def numpy_signal_stage(hist: np.ndarray, pulse_os: np.ndarray, k: int, n_samples: int) -> np.ndarray:
    """The straightforward version: per ping, sum bounces, np.convolve, take every k-th."""
    out = np.empty((hist.shape[0], n_samples), np.float32)
    for i in range(hist.shape[0]):
        full = np.convolve(hist[i].sum(axis=0, dtype=np.float64), pulse_os)
        out[i] = full[:n_samples * k:k]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=2000, help="poses to run (<= 54000)")
    parser.add_argument("--paths", type=int, default=10_000, help="paths per pose")
    parser.add_argument("--bounces", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="Dr.Jit threads (default: all)")
    parser.add_argument("--snr-db", type=float, default=20.0)
    parser.add_argument("--mesh", type=Path, default=ROOT.parent / "shared/data/meshes/bunny.obj")
    parser.add_argument("--keep", action="store_true", help="keep the output file")
    args = parser.parse_args()

    from sonarsim import simulate as sim
    from sonarsim.geometry import trajectory
    from sonarsim.scene import load_scene

    if not args.mesh.is_file():
        print(f"mesh not found: {args.mesh}", file=sys.stderr)
        return 2
    step = max(1, FULL_SCAN // max(1, args.poses))
    while step > 1 and math.gcd(step, 360) > 1:   # spread the subset over angles and heights
        step += 1
    workdir = Path(tempfile.mkdtemp(prefix="bench_simulate_"))
    scene_file = workdir / "bunny.toml"
    scene_file.write_text(f'name = "bunny (fitted)"\n[[object]]\nmesh = "{args.mesh.resolve()}"\n'
                          f'fit = true\n')
    spec = load_scene(scene_file)
    poses = trajectory("cylindrical", box=spec.box)[np.arange(0, FULL_SCAN, step)]
    n = len(poses)
    settings = sim.SimulationSettings(pulse=sim.make_pulse("lfm-20k", 100e3),
                                      snr_db=args.snr_db, paths_per_pose=args.paths,
                                      bounces=args.bounces, seed=0, threads=args.threads)
    out = workdir / "bunny.h5"
    rss0 = peak_rss_mib()
    t0 = time.perf_counter()
    sim.simulate(spec, poses, out, settings, resume=False, progress=sys.stderr.isatty())
    wall = time.perf_counter() - t0
    size = out.stat().st_size
    peak = peak_rss_mib()

    # Signal stage alone on one chunk-sized batch of synthetic histograms.
    crop, window = sim.simulation_window(poses, spec, settings.pulse, settings.sound_speed, 20)
    rng = np.random.default_rng(0)
    batch = 64
    hist = (rng.random((batch, args.bounces, window.n_bins), dtype=np.float32)
            * (rng.random((batch, args.bounces, window.n_bins)) < 0.02)).astype(np.float32)
    pulse_os = sim.oversampled_pulse(settings.pulse.samples, 20)
    t1 = time.perf_counter()
    ours = sim.transients_to_waveforms(hist, pulse_os, 20, crop.num_samples)
    t_fft = time.perf_counter() - t1
    t1 = time.perf_counter()
    ref = numpy_signal_stage(hist[:16], pulse_os, 20, crop.num_samples)
    t_np = (time.perf_counter() - t1) * batch / 16
    assert np.allclose(ours[:16], ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())

    scale = FULL_SCAN / n
    rows = [
        ("scene", f"{spec.name}: {len(spec.gt_mesh().faces)} triangles + ground"),
        ("poses run", f"{n} (every {step}th of the 54 000-pose scan, crop window of the subset)"),
        ("paths/pose, bounces", f"{args.paths}, {args.bounces}"),
        ("window", f"{crop.num_samples} samples, {window.n_bins} bins"),
        ("Dr.Jit threads", f"{args.threads or 'all'}"),
        ("wall time", f"{wall:.1f} s  ({n * args.paths / wall / 1e6:.2f} M paths/s, "
                      f"{n / wall:.0f} poses/s)"),
        ("projected full scan", f"{wall * scale / 60:.1f} min"),
        ("peak memory (RSS)", f"{peak:.0f} MiB (before the run: {rss0:.0f} MiB)"),
        ("output file", f"{size / 2**20:.1f} MiB; projected full scan "
                        f"{size * scale / 2**20:.0f} MiB"),
        ("signal stage (FFT)", f"{batch / t_fft:.0f} pings/s"),
        ("signal stage (np.convolve)", f"{batch / t_np:.0f} pings/s  -> FFT is "
                                       f"{t_np / t_fft:.1f}x faster"),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    if args.keep:
        print(f"kept {out}")
    else:
        out.unlink()
        scene_file.unlink()
        os.rmdir(workdir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
