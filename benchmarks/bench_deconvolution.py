"""Benchmark of pulse deconvolution (recon.deconvolution): Wiener and INR.

Wiener: seconds per ping on [N, T] waveforms against a straightforward NumPy version
(ping by ping, full complex FFTs), whose output it must match. INR: seconds per Adam
iteration and per ping·iteration for a batch of P pings × T samples, with the default
network and the reference's (20 levels, 128 × 3 hidden), and peak memory (ru_maxrss of
a fresh process per configuration). ``--inr-quality``: what cheaper INR settings cost in
quality — iterations, hash levels, MLP size, and a warm start from the previous batch's
network — on a reflector train with known positions (median −6 dB mainlobe width, share of
peaks within one sample of the truth, in-band residual), beside Wiener and the matched filter.

    .venv/bin/python benchmarks/bench_deconvolution.py [--quick] [--inr-quality]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def _waveforms(n_pings, n_t, seed=0):
    from recon import deconvolution as dc
    from sonarsim import signals
    rng = np.random.default_rng(seed)
    p = signals.named_pulse("lfm-20k", signals.AIRSAS_FS)
    w = np.zeros((n_pings, n_t))
    for i in range(n_pings):
        w[i, rng.integers(50, n_t - 50, 6)] = rng.uniform(0.3, 1.0, 6)
    s, _ = signals.add_noise(dc.convolve(w, p), 20.0, rng)
    return s.astype(np.float32), p


def wiener_numpy(s, p, lam):
    """Straightforward reference: one ping at a time, full complex FFTs, np.fft (the same
    FFT length as recon.deconvolution, since the inverse filter's response wraps)."""
    import scipy.fft
    n_t = s.shape[1]
    n = scipy.fft.next_fast_len(n_t + len(p) - 1, real=True)
    P = np.fft.fft(p, n)
    h = np.zeros(n)
    h[0] = 1
    h[1:(n + 1) // 2] = 2
    if n % 2 == 0:
        h[n // 2] = 1
    out = np.empty(s.shape, np.complex64)
    for i in range(len(s)):
        W = np.fft.fft(s[i].astype(np.float64), n) * np.conj(P) / (np.abs(P) ** 2 + lam)
        out[i] = np.fft.ifft(W * h)[:n_t]
    return out


def bench_wiener(n_pings, n_t, repeats):
    from recon import deconvolution as dc
    s, p = _waveforms(n_pings, n_t)
    times, times_np = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out, info = dc.wiener(s, p)
        times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ref = wiener_numpy(s, p, info["lambda"])
        times_np.append(time.perf_counter() - t0)
    err = float(np.max(np.abs(out - ref)) / np.max(np.abs(ref)))
    t, t_np = float(np.median(times)), float(np.median(times_np))
    print(f"wiener  {n_pings} x {n_t}: {t:.3f} s ({t / n_pings * 1e6:.1f} us/ping, "
          f"{n_pings / t:.0f} pings/s); straightforward NumPy {t_np:.3f} s; "
          f"speed-up {t_np / t:.1f}x; max rel. difference {err:.1e} (includes the λ estimate "
          f"in the timed call)")


def _inr_child(cfg: dict) -> dict:
    from recon import deconvolution as dc
    s, p = _waveforms(cfg["pings"], cfg["samples"])
    target = s.astype(np.float64) / np.abs(s).max()
    st = dc.INRSettings(iterations=cfg["warm"] + cfg["iters"], **cfg["net"])
    stamps = []
    dc.inr_batch(target, p, st, 0, lambda loss, parts: stamps.append(time.perf_counter()))
    per_it = np.diff(stamps)[cfg["warm"]:]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"s_per_iter": float(np.median(per_it)), "rss_mb": rss}


def bench_inr(pings, samples, warm, iters):
    configs = [("default (16 levels, 32 x 2)", {}),
               ("reference net (20 levels, 128 x 3)",
                {"hash_levels": 20, "mlp_width": 128, "mlp_hidden": 3})]
    for label, net in configs:
        cfg = {"pings": pings, "samples": samples, "warm": warm, "iters": iters, "net": net}
        out = subprocess.run([sys.executable, __file__, "--child", json.dumps(cfg)],
                             capture_output=True, text=True, env=os.environ)
        if out.returncode != 0:
            print(f"inr {label}: failed: {out.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        t = r["s_per_iter"]
        print(f"inr     {label}, {pings} pings x {samples} samples: {t:.3f} s/iteration "
              f"(median of {iters} after {warm} warm-up), {t / pings * 1e3:.2f} ms per ping-"
              f"iteration, {pings * samples / t / 1e6:.2f} M samples/s; 300 iterations "
              f"= {300 * t / 60:.1f} min; peak RSS {r['rss_mb']:.0f} MB")


def moving_reflectors(n_pings, n_t=400, snr_db=20.0, seed=0):
    """Five reflectors per ping that move one sample later every 8 pings with slowly varying
    amplitudes (neighbouring pings alike, as in a scan), the 20 kHz LFM, white noise at
    ``snr_db``. Returns (noisy [P, T], pulse, truth positions [P, 5])."""
    from recon import deconvolution as dc
    from sonarsim import signals
    rng = np.random.default_rng(seed)
    p = signals.named_pulse("lfm-20k", signals.AIRSAS_FS)
    base = np.sort(rng.choice(np.arange(40, n_t - 60, 12), 5, replace=False))
    amps = rng.uniform(0.4, 1.0, 5)
    w = np.zeros((n_pings, n_t))
    truth = np.array([base + i // 8 for i in range(n_pings)])
    for i in range(n_pings):
        w[i, truth[i]] = amps * (1 + 0.2 * np.sin(i / 15 + np.arange(5)))
    noisy, _ = signals.add_noise(dc.convolve(w, p), snr_db, rng)
    return noisy, p, truth


def _echo_quality(sig, s, p, truth):
    from recon import deconvolution as dc
    widths, offsets = [], []
    for i, ks in enumerate(truth):
        for k in ks:
            offsets.append(int(np.argmax(np.abs(sig[i, k - 5:k + 6]))) - 5)
            widths.append(dc.mainlobe_width(sig[i], k))
    resid = np.linalg.norm(dc.convolve(np.real(sig), p) - s) / np.linalg.norm(s)
    return float(np.median(widths)), float(np.mean(np.abs(offsets) <= 1)), float(resid)


def _fit_batches(s, p, st, warm_iterations=0):
    """INR batches of ``st.pings_per_inr`` pings as recon.deconvolution.inr fits them (one
    new network each), or, with ``warm_iterations``, every batch after the first continuing
    from the previous batch's network for that many iterations. Returns w [N, T]."""
    from dataclasses import replace
    from recon import deconvolution as dc
    scale = float(np.abs(s).max())
    out, field_ = np.empty_like(s), None
    for b in range(0, len(s), st.pings_per_inr):
        rows = slice(b, b + st.pings_per_inr)
        if warm_iterations and field_ is not None:
            batch_st = replace(st, iterations=warm_iterations)
        else:
            batch_st, field_ = st, dc._Field(st, st.seed + b)
        out[rows] = dc.inr_batch(s[rows] / scale, p, batch_st, st.seed + b, field=field_)[0] * scale
    return out


def bench_inr_quality(pings_per_inr, n_batches):
    from recon import deconvolution as dc
    from sonarsim import signals
    s, p, truth = moving_reflectors(pings_per_inr * n_batches)
    mf = signals.matched_filter(s, p, mode="linear")
    print(f"inr quality: {n_batches} batches x {pings_per_inr} pings x {s.shape[1]} samples, "
          "5 moving reflectors per ping, 20 dB; median -6 dB width (samples; an ideal spike "
          "2.41), peaks within 1 sample of the truth, residual |w*p - s|/|s| (noise alone "
          "about 0.1); CPU-s per sample-iteration (fixed per-iteration costs dominate at "
          "this size)")
    for label, sig in (("matched filter", mf), ("wiener", dc.wiener(s, p)[0])):
        w, ok, res = _echo_quality(sig, s, p, truth)
        tail = f"  residual {res:.3f}" if label == "wiener" else ""   # mf: not a reflectivity
        print(f"  {label:34s} width {w:.2f}  peaks {ok:.0%}{tail}")
    configs = [("default (300 iterations)", {}, 0), ("150 iterations", {"iterations": 150}, 0),
               ("100 iterations", {"iterations": 100}, 0), ("60 iterations", {"iterations": 60}, 0),
               ("10 hash levels, 150 it.", {"hash_levels": 10, "iterations": 150}, 0),
               ("MLP 16 x 1, 150 it.", {"mlp_width": 16, "mlp_hidden": 1, "iterations": 150}, 0),
               ("warm start, 60 it. after the 1st", {}, 60),
               ("warm start, 30 it. after the 1st", {}, 30)]
    for label, kw, warm in configs:
        st = dc.INRSettings(pings_per_inr=pings_per_inr, **kw)
        c0 = time.process_time()
        w_all = _fit_batches(s, p, st, warm)
        cpu = time.process_time() - c0
        iters = st.iterations + (n_batches - 1) * (warm or st.iterations)
        later = slice(pings_per_inr, None)       # the batches after the first
        w, ok, res = _echo_quality(dc.analytic(w_all.astype(np.float64))[later], s[later], p,
                                   truth[later])
        print(f"  {label:34s} width {w:.2f}  peaks {ok:.0%}  residual {res:.3f}  "
              f"{cpu / (iters * pings_per_inr * s.shape[1]):.1e} CPU-s", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small sizes (a few seconds)")
    ap.add_argument("--inr-quality", action="store_true",
                    help="only the INR quality/cost sweep (about 2 CPU-min)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_inr_child(json.loads(args.child))))
        return 0
    print("machine: 2 shared cores, loaded by other work; timings are noisy (medians)")
    if args.inr_quality:
        bench_inr_quality(24, 2 if args.quick else 3)
        return 0
    if args.quick:
        bench_wiener(360, 1000, 3)
        bench_inr(36, 1000, 2, 3)
    else:
        bench_wiener(360, 1000, 5)
        bench_wiener(4000, 1000, 3)
        bench_inr(360, 1000, 3, 5)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
