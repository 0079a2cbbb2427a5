"""Backprojection throughput (voxel-pings per second): the fused kernel, the CLI, NumPy, PyTorch.

Usage: .venv/bin/python benchmarks/bench_backprojection.py [--pings N] [--shape NX NY NZ]
       [--variant llvm_ad_mono|cuda_ad_mono] [--no-cli] [--full] [--dataset D.h5]

Rows, all on the same synthetic dataset (noise waveforms, AirSAS-like geometry, a 608-sample
window starting at sample 217: throughput does not depend on the content) and grid:

* ``backproject (auto)``: ``recon.backprojection.backproject``, the code path of
  ``recon backproject`` (signal preparation included: matched filter, ×5 FFT upsampling);
* ``... unrolled C-order``: the same kernel with lanes in plain C order (the layout before
  the 4×4×4 lane bricks); ``... symbolic``: the ``drjit.while_loop`` form (CUDA's default);
* ``kernel only``: ``delay_and_sum`` on signals prepared beforehand;
* ``recon backproject (CLI)``: the command itself on the dataset saved to a temporary HDF5
  file, run as a subprocess (start-up, reading, grid, writing included), and the start-up
  alone (``recon backproject --help``);
* ``NumPy``: ``backproject_numpy`` (float64, one vectorised pass per ping) on a few pings,
  extrapolated per voxel-ping; ``PyTorch``: a straightforward delay-and-sum (gather + linear
  interpolation, pings in chunks) when ``torch`` is importable (not a dependency).

``--dataset D.h5`` replaces the synthetic data by a real dataset file: ``--pings N`` of its
pings, evenly spaced over the scan (``--pings 0:STOP:STEP`` for the CLI, which reads the same
file), on its scene box, so the CLI row and the kernel rows are the same job measured in one
run; the CLI row's extra time is start-up, reading, signal preparation not hidden behind the
kernels, and writing.

Where the time goes (2-core AMD EPYC Zen 4 VM, AVX-512, LLVM backend, 2026-11-24; the kernel's
IR from ``drjit.kernel_history()`` compiled with the same libLLVM 19 for znver4): 5.5 x86
instructions per voxel-ping (88 per 16 lanes and ping): the signal's packet gather 58 % (16
pointer extractions, 16 loads of 16 bytes, ~20 inserts/shuffles), its address arithmetic and
window select 9 %, the two distances, index and tent 24 % (2 vsqrtps, 9 FMAs), register spills
7 %. Replacing the gather by arithmetic on its index doubles the speed (0.87e9 -> 1.7-1.9e9
voxel-pings per CPU-second), so the gather is half the time. Launch overhead (tracing 16
pings of constants in Python) is ~1 ms per launch, ~3 % at 125x125x94; signal preparation
(matched filter, x5 FFT upsampling, packing) ~90 us per 718-sample ping, ~5 % of a full job,
done by a background thread. Before 2026-11-24 the packet gather silently fell back to four
16-wide ``vgatherdps`` per voxel-ping (the NumPy block was not 64-byte aligned): 3.4
instructions per voxel-ping but half the speed.

On one H100 (``cuda_ad_mono``, symbolic loop, 2026-11-24), 43 200 pings x 150x150x120 voxels:
kernel 1.7e11 voxel-pings/s, ``backproject`` all-in (signals prepared by 15 host threads)
1.1e11; the PyTorch delay-and-sum on the same signals 6.9e9 (25x and 16x slower).

Columns: wall time, CPU time (all threads; for the CLI the child's), voxel-pings per second of
wall time and per CPU-second, ratio to NumPy. On a shared machine the wall-time figures
depend on the load; the per-CPU-second figure, times the number of cores, estimates the idle
machine when the kernel scales over the cores. ``--full`` adds the reference's largest job
(43 200 pings onto 150×150×120 voxels). Peak RSS of this process and of the CLI child.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def peak_rss_mb(who=resource.RUSAGE_SELF) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0


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
                        pulse=signals.named_pulse("lfm-20k", signals.AIRSAS_FS), fs=signals.AIRSAS_FS,
                        sound_speed=345.0, source="benchmark", start_sample=start_sample,
                        meta={"box": np.stack([box.lo, box.hi], axis=1).tolist()})


def timed(fn, sync=True):
    """(result, wall s, CPU s of this process) of fn()."""
    import drjit as dr
    if sync:
        dr.sync_thread()
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    if sync:
        dr.sync_thread()
    return out, time.perf_counter() - t0, time.process_time() - c0


def run_child(cmd):
    """(wall s, CPU s, peak RSS MB) of a subprocess."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {r.stderr.strip()[-400:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, after.ru_maxrss / 1024.0


def torch_delay_and_sum(ds, grid, upsample: int, chunk: int = 8, buf=None):
    """Straightforward PyTorch delay-and-sum (gather + linear interpolation), pings in chunks.
    ``buf``: the pings' interpolation buffer prepared beforehand (else prepared here)."""
    import torch
    from recon import backprojection as bp
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    n_pings, n_t = np.asarray(ds.waveforms).shape
    n_up = n_t * upsample
    consts = torch.as_tensor(bp.ping_constants(ds, upsample), device=dev)
    pts = torch.as_tensor(grid.points().astype(np.float32), device=dev)
    if buf is None:
        buf = bp.upsampled_signals(ds, np.arange(n_pings), upsample, False)
    sig = torch.as_tensor(buf[..., 0] + 1j * buf[..., 1], device=dev)
    sig = torch.cat([sig, torch.zeros(n_pings, 1, dtype=sig.dtype, device=dev)], dim=1)
    acc = torch.zeros(len(pts), dtype=torch.complex64, device=dev)
    for p0 in range(0, n_pings, chunk):
        q = consts[p0:p0 + chunk]
        path = (torch.linalg.norm(pts[None] - q[:, None, 0:3], dim=-1)
                + torch.linalg.norm(pts[None] - q[:, None, 3:6], dim=-1))
        u = path * q[:, 6:7] + q[:, 7:8]
        ok = (u >= 0) & (u <= n_up - 1)
        k = torch.floor(u).clamp(0, n_up - 1).long()
        f = (u - k).clamp(0, 1)
        s = sig[p0:p0 + chunk]
        val = (1 - f) * torch.gather(s, 1, k) + f * torch.gather(s, 1, k + 1)
        acc += torch.where(ok, val, torch.zeros((), dtype=val.dtype, device=dev)).sum(0)
    if dev == "cuda":
        torch.cuda.synchronize()
    return acc.cpu().numpy().reshape(grid.shape)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pings", type=int, default=720)
    ap.add_argument("--shape", type=int, nargs=3, default=(150, 150, 120))
    ap.add_argument("--numpy-pings", type=int, default=4)
    ap.add_argument("--torch-pings", type=int, default=16)
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: SONARSIM_VARIANT or llvm_ad_mono)")
    ap.add_argument("--repeat", type=int, default=3, help="interleaved runs of each kernel form (median)")
    ap.add_argument("--no-cli", action="store_true", help="skip the recon backproject subprocess")
    ap.add_argument("--no-variants", action="store_true", help="only the default kernel form")
    ap.add_argument("--full", action="store_true", help="also 43 200 pings × 150×150×120")
    ap.add_argument("--dataset", default=None, help="a dataset file (HDF5) instead of synthetic data")
    args = ap.parse_args(argv)
    if args.variant:
        os.environ["SONARSIM_VARIANT"] = args.variant   # read by sonarsim.runtime (and the CLI child)

    import drjit as dr
    from recon import backprojection as bp
    from recon import straightforward
    from recon._jit import jit
    from recon.grid import Grid
    from sonarsim import geometry

    m = jit()
    box = geometry.AIRSAS_REAL_BOX
    g = Grid.from_box(box, tuple(args.shape))
    if args.dataset:
        from sonarsim.dataset import SonarDataset
        full = SonarDataset.read(args.dataset)
        step = max(1, full.n_pings // args.pings)
        args.pings = min(args.pings, -(-full.n_pings // step))
        cli_pings = f"0:{step * args.pings}:{step}"
        ds = full.select(np.arange(0, step * args.pings, step))
        del full
        if ds.meta.get("box") is not None:
            g = Grid(np.asarray(ds.meta["box"], dtype=np.float64), tuple(args.shape))
    else:
        ds = dataset(args.pings)
    vp = g.size * args.pings
    rows = []
    best_cpu = {}

    def row(name, wall, cpu, n_vp=vp, rss=None):
        rows.append((name, wall, cpu, n_vp / wall, n_vp / cpu if cpu > 0 else float("nan"),
                     peak_rss_mb() if rss is None else rss))

    blocks, prep_wall, prep_cpu = timed(lambda: [
        bp.upsampled_signals(ds, np.arange(b, min(b + bp.PINGS_PER_BLOCK, args.pings)), 5, False)
        for b in range(0, args.pings, bp.PINGS_PER_BLOCK)], sync=False)
    consts = bp.ping_constants(ds, 5)
    n_up = blocks[0].shape[1]
    forms = [("backproject (auto)", lambda: bp.backproject(ds, g, progress=False))]
    if not args.no_variants:
        forms += [("backproject unrolled C-order",
                   lambda: bp.backproject(ds, g, progress=False, loop="unrolled", brick=None)),
                  ("backproject symbolic loop",
                   lambda: bp.backproject(ds, g, progress=False, loop="symbolic"))]
    forms += [("kernel only (delay_and_sum)",
               lambda: bp.delay_and_sum(iter(blocks), consts, g, n_up))]
    bp.backproject(ds.select(np.arange(16)), g, progress=False)                # compile
    if not args.no_variants:
        bp.backproject(ds.select(np.arange(16)), g, progress=False, loop="symbolic")
    # Interleaved repeats: load changes on a shared machine hit every form alike.
    runs = {name: [] for name, _ in forms}
    for _ in range(args.repeat):
        for name, fn in forms:
            runs[name].append(timed(fn)[1:])
    for name, _ in forms:
        wall, cpu = np.median(np.array(runs[name]), axis=0)
        row(name, wall, cpu)
        best_cpu[name] = min(c for _, c in runs[name])
    row("  signal preparation alone", prep_wall, prep_cpu)
    del blocks, forms

    if not args.no_cli:
        with tempfile.TemporaryDirectory() as tmp:
            src, out = Path(tmp) / "d.h5", Path(tmp) / "v.h5"
            exe = [sys.executable, "-m", "recon.cli", "backproject"]
            grid_args = ["--bounds", *map(str, g.bounds.ravel()), "--shape", *map(str, g.shape)]
            if args.dataset:
                src = Path(args.dataset)
                grid_args += ["--pings", cli_pings]
            else:
                ds.write(src)
            w, c, r = run_child(exe + ["--help"])
            row("recon start-up (--help)", w, c, rss=r)
            w, c, r = run_child(exe + [str(src), *grid_args, "--out", str(out), "--no-progress"])
            row("recon backproject (CLI)", w, c, rss=r)

    sub = ds.select(np.arange(args.numpy_pings))
    _, wall, cpu = timed(lambda: straightforward.backproject_numpy(sub, g), sync=False)
    np_rate = g.size * args.numpy_pings / wall
    row("NumPy float64 (extrapolated)", wall * args.pings / args.numpy_pings,
        cpu * args.pings / args.numpy_pings)
    try:
        import torch  # noqa: F401
    except ImportError:
        print("PyTorch: not importable, skipped")
    else:
        n_torch = min(args.torch_pings, ds.n_pings)
        tsub = ds.select(np.arange(n_torch))
        torch_delay_and_sum(tsub, g, 5)
        _, wall, cpu = timed(lambda: torch_delay_and_sum(tsub, g, 5), sync=False)
        row("PyTorch delay-and-sum (extrap.)", wall * args.pings / n_torch,
            cpu * args.pings / n_torch)

    if args.full:
        big = dataset(43200)
        gf = Grid.from_box(box, (150, 150, 120))
        _, wall, cpu = timed(lambda: bp.backproject(big, gf, progress=True))
        row("full job 43200 x 150x150x120", wall, cpu, n_vp=gf.size * 43200)

    print(f"variant {os.environ.get('SONARSIM_VARIANT') or 'llvm_ad_mono'}, {m.__name__}, "
          f"{dr.thread_count()} Dr.Jit threads, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}; grid {g.shape} = {g.size} voxels, {args.pings} pings"
          + (f" of {args.dataset} ({cli_pings}), {ds.waveforms.shape[1]} samples" if args.dataset else ""))
    print(f"{'':<34}{'wall s':>8}{'CPU s':>8}{'Mvp/s':>9}{'Mvp/CPU-s':>11}{'x NumPy':>9}{'RSS MB':>8}")
    for name, wall, cpu, rate, cpu_rate, rss in rows:
        print(f"{name:<34}{wall:>8.2f}{cpu:>8.2f}{rate / 1e6:>9.0f}{cpu_rate / 1e6:>11.0f}"
              f"{rate / np_rate:>9.1f}{rss:>8.0f}")
    ref = rows[0]
    print(f"(median of {args.repeat} interleaved runs for the rows above the preparation; best "
          f"Mvp/CPU-s: " + ", ".join(f"{k} {vp / c / 1e6:.0f}" for k, c in best_cpu.items()) + ")")
    print(f"idle-machine estimate for {ref[0]}: {ref[4] * os.cpu_count() / 1e9:.2f}e9 vp/s "
          f"(median per CPU-second x {os.cpu_count()} cores), "
          f"{vp / best_cpu[ref[0]] * os.cpu_count() / 1e9:.2f}e9 from the best run")
    by_name = {r[0]: r for r in rows}
    torch_row = by_name.get("PyTorch delay-and-sum (extrap.)")
    if torch_row is not None:
        print("ratio to the PyTorch delay-and-sum (voxel-pings/s of wall time): " + ", ".join(
            f"{name} {by_name[name][3] / torch_row[3]:.1f}x" for name in
            ("kernel only (delay_and_sum)", "backproject (auto)", "recon backproject (CLI)")
            if name in by_name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
