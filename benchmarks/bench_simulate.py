"""Benchmark: ``sonarsim simulate`` on the fitted Stanford bunny — fidelity against time,
and the full 54 000-pose scan at the default fidelity.

Part 1 (``--part snr``): Monte-Carlo SNR after matched filtering (measured from two
independent half-estimates, :mod:`sonarsim.fidelity`) against rendering time, on
``--snr-poses`` poses spread over the scan, for the bounce-1 estimators 'cone' (the TX-cone
path tracer, the old default) and 'surface' (stratified surface quadrature, the new one)
at several densities, and for the default 3-bounce configuration.

Part 2 (``--part scan``): ``simulate`` of ``--poses`` poses (every k-th pose of the
54 000-pose scan, spread over angles and heights) at the default fidelity (automatic
density for ``--mc-snr-db``, 30 dB) with 20 dB total SNR; wall time and file size are
projected linearly to the full scan (the pilot's fixed cost is counted once); peak memory
is bounded by one chunk plus the N×T noiseless waveforms. The non-rendering time is
profiled: pulse convolution, matched-filter statistics, writing, the noise pass.

Also times the signal stage (bounce sum, pulse convolution, decimation) against a
straightforward NumPy implementation (np.convolve per ping, then decimate).

Usage: .venv/bin/python benchmarks/bench_simulate.py [--part snr|scan|both]
       [--poses 2000] [--snr-poses 48] [--threads N] [--mesh PATH] [--keep]
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from sonarsim import data

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


def scan_subset(spec, n: int):
    from sonarsim.geometry import trajectory
    step = max(1, FULL_SCAN // max(1, n))
    while step > 1 and math.gcd(step, 360) > 1:   # spread the subset over angles and heights
        step += 1
    return trajectory("cylindrical", box=spec.box)[np.arange(0, FULL_SCAN, step)], step


def print_rows(rows) -> None:
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")


def part_snr(spec, args) -> None:
    """MC SNR after matched filtering against time, old (cone) and new (surface) bounce 1."""
    from sonarsim import simulate as sim
    from sonarsim.halves import Sampling
    from sonarsim.signals import AIRSAS_FS, pulse_from_spec
    poses, _ = scan_subset(spec, args.snr_poses)
    scene = spec.to_mitsuba()
    print(f"\n## Monte-Carlo SNR after matched filtering vs time ({len(poses)} bunny poses "
          f"spread over the scan; seconds for all of them, 2 half-estimates each)\n")
    print("| bounces | bounce-1 estimator | density | time (s) | s/pose | MC SNR (dB) |")
    print("|---|---|---|---|---|---|")
    # Bounce 1 alone, then all three bounces (with the surface estimator bounces >= 2
    # continue from the surface samples, so the spacing sets their density too).
    configs = [((1,), "cone", Sampling(p, None)) for p in (10_000, 100_000, 1_000_000)]
    configs += [((1,), "surface", Sampling(2, sp)) for sp in (10e-3, 5e-3, 2.5e-3)]
    configs += [((1, 2, 3), "cone", Sampling(p, None)) for p in (10_000, 100_000, 1_000_000)]
    configs += [((1, 2, 3), "surface", Sampling(2, sp)) for sp in (8e-3, 4e-3, 2e-3)]
    for bounces, est, sampling in configs:
        s = sim.SimulationSettings(pulse=pulse_from_spec("lfm-20k", AIRSAS_FS), bounces=max(bounces),
                                   paths_per_pose=sampling.paths_per_pose, bounce1=est,
                                   surface_spacing=sampling.surface_spacing, seed=1,
                                   threads=args.threads)
        crop, window = sim.simulation_window(poses, spec, s.pulse, s.sound_speed, s.oversample)
        sim.measure_fidelity(scene, poses[:2], s, sampling, crop, window)   # compile
        r = sim.measure_fidelity(scene, poses, s, sampling, crop, window)
        density = (f"{sampling.paths_per_pose} paths" if est == "cone"
                   else f"{sampling.surface_spacing * 1e3:g} mm strata")
        print(f"| {','.join(map(str, bounces))} | {est} | {density.strip()} | "
              f"{r['seconds']:.1f} | {r['seconds'] / len(poses):.3f} | {r['mc_snr_db']:.1f} |",
              flush=True)


class Profile:
    """Wall time spent inside selected functions (monkeypatched wrappers)."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self._undo = []

    def wrap(self, owner, name: str, label: str) -> None:
        original = getattr(owner, name)

        def timed(*a, **kw):
            t0 = time.perf_counter()
            try:
                return original(*a, **kw)
            finally:
                self.seconds[label] += time.perf_counter() - t0

        setattr(owner, name, timed)
        self._undo.append((owner, name, original))

    def restore(self) -> None:
        for owner, name, original in reversed(self._undo):
            setattr(owner, name, original)


def part_scan(spec, args) -> None:
    from sonarsim import fidelity
    from sonarsim import simulate as sim
    from sonarsim.dataset import SonarDataset, stream
    from sonarsim.runtime import mitsuba
    from sonarsim.signals import AIRSAS_FS, pulse_from_spec
    mitsuba()
    integrator = sys.modules["sonarsim.plugins.sonar_transient"].SonarTransientIntegrator

    poses, step = scan_subset(spec, args.poses)
    n = len(poses)
    settings = sim.SimulationSettings(pulse=pulse_from_spec("lfm-20k", AIRSAS_FS), snr_db=20.0,
                                      bounces=3, seed=0, threads=args.threads)
    workdir = Path(tempfile.mkdtemp(prefix="bench_simulate_"))
    out = workdir / "bunny.h5"
    prof = Profile()
    prof.wrap(sim, "choose_sampling", "pilot (density choice)")
    prof.wrap(integrator, "render_transients", "render (two halves)")
    prof.wrap(sim, "transients_to_waveforms", "pulse convolution + decimation")
    prof.wrap(fidelity.PingStats, "measure", "matched-filter statistics")
    prof.wrap(stream.DatasetStreamWriter, "write", "writing (HDF5)")
    prof.wrap(sim, "ping_noise", "noise generation")
    prof.wrap(fidelity, "noise_budget", "noise budget (signal power)")
    rss0 = peak_rss_mib()
    t0 = time.perf_counter()
    try:
        sim.simulate(spec, poses, out, settings, resume=False, progress=sys.stderr.isatty())
    finally:
        prof.restore()
    wall = time.perf_counter() - t0
    size = out.stat().st_size
    peak = peak_rss_mib()
    ds = SonarDataset.read(out, transients=False)
    pilot = prof.seconds["pilot (density choice)"]
    per_pose = (wall - pilot) / n
    projected = pilot + per_pose * FULL_SCAN

    # Signal stage alone on one chunk-sized batch of synthetic histograms.
    crop, window = sim.simulation_window(poses, spec, settings.pulse, settings.sound_speed, 20)
    rng = np.random.default_rng(0)
    batch = 64
    hist = (rng.random((batch, 3, window.n_bins), dtype=np.float32)
            * (rng.random((batch, 3, window.n_bins)) < 0.02)).astype(np.float32)
    pulse_os = sim.oversampled_pulse(settings.pulse.samples, 20)
    t1 = time.perf_counter()
    ours = sim.transients_to_waveforms(hist, pulse_os, 20, crop.num_samples)
    t_fft = time.perf_counter() - t1
    t1 = time.perf_counter()
    ref = numpy_signal_stage(hist[:16], pulse_os, 20, crop.num_samples)
    t_np = (time.perf_counter() - t1) * batch / 16
    assert np.allclose(ours[:16], ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())

    scale = FULL_SCAN / n
    meta = ds.meta
    print(f"\n## Scan at the default fidelity ({n} poses = every {step}th of the 54 000-pose "
          f"scan)\n")
    rows = [
        ("scene", f"{spec.name}: {len(spec.gt_mesh().faces)} triangles + ground"),
        ("sampling", f"{meta['sampling'].get('sampling')} ({meta['sampling'].get('mode')})"),
        ("bounces", "3, all summed"),
        ("window", f"{crop.num_samples} samples, {window.n_bins} bins"),
        ("Dr.Jit threads", f"{args.threads or 'all'}"),
        ("measured MC SNR (after MF)", f"{meta['mc_snr_db']:.1f} dB"),
        ("effective SNR (--snr-db 20)", f"{meta['effective_snr_db']:.2f} dB"),
        ("wall time", f"{wall:.1f} s (pilot {pilot:.1f} s, then {per_pose * 1e3:.1f} ms/pose)"),
        ("projected full scan", f"{projected / 60:.1f} min (pilot once + 54 000 poses)"),
        ("peak memory (RSS)", f"{peak:.0f} MiB (before the run: {rss0:.0f} MiB); the "
                              f"noise pass holds N x T float32 = "
                              f"{FULL_SCAN * crop.num_samples * 4 / 2**20:.0f} MiB at full scan"),
        ("output file", f"{size / 2**20:.1f} MiB; projected full scan "
                        f"{size * scale / 2**20:.0f} MiB"),
        ("signal stage (FFT)", f"{batch / t_fft:.0f} pings/s"),
        ("signal stage (np.convolve)", f"{batch / t_np:.0f} pings/s  -> FFT is "
                                       f"{t_np / t_fft:.1f}x faster"),
    ]
    print_rows(rows)
    print("\nprofile (wall s, share of the run; nested calls counted in each):")
    for label, sec in sorted(prof.seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {label:<34} {sec:8.2f} s  {100 * sec / wall:5.1f} %")
    if args.keep:
        print(f"kept {out}")
    else:
        out.unlink()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("snr", "scan", "both"), default="both")
    parser.add_argument("--poses", type=int, default=2000, help="poses of the scan run")
    parser.add_argument("--snr-poses", type=int, default=48, help="poses of the SNR table")
    parser.add_argument("--threads", type=int, default=None, help="Dr.Jit threads (default: all)")
    parser.add_argument("--mesh", type=Path, default=data.path("bunny.obj"))
    parser.add_argument("--keep", action="store_true", help="keep the output file")
    args = parser.parse_args()

    from sonarsim.scene import load_scene
    if not args.mesh.is_file():
        print(f"mesh not found: {args.mesh}", file=sys.stderr)
        return 2
    workdir = Path(tempfile.mkdtemp(prefix="bench_simulate_scene_"))
    scene_file = workdir / "bunny.toml"
    scene_file.write_text(f'name = "bunny (fitted)"\n[[object]]\nmesh = "{args.mesh.resolve()}"\n'
                          f'fit = true\n')
    spec = load_scene(scene_file)
    if args.part in ("snr", "both"):
        part_snr(spec, args)
    if args.part in ("scan", "both"):
        part_scan(spec, args)
    scene_file.unlink()
    os.rmdir(workdir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
