"""Pulse deconvolution of sonar waveforms (step 1 of Reed et al. 2023's method).

Two methods turn the real waveforms s [N, T] of a dataset into deconvolved *analytic*
signals (complex64 [N, T]) that reconstruction solvers use directly, without a matched
filter (``waveform_kind = 'deconvolved_analytic'``, see docs/formats.md):

* ``'wiener'`` (the default): frequency-domain Wiener deconvolution W = S·P*/(|P|² + λ)
  with λ = σ²/σ_w² estimated from the data (white-noise variance σ² from the spectrum
  outside the pulse band, reflectivity variance σ_w² from the spectrum inside it); linear
  (zero-padded), so nothing wraps around. A linear method cannot reach beyond the pulse
  band: its resolution is the matched filter's.
* ``'inr'``: the reference's neural deconvolution (reference code
  ``inr_reconstruction/deconvolve_measurements.py``): per batch of pings, a 2-D hash grid
  + MLP over (range, ping) ∈ [0, 1]² (:mod:`drjit.nn`, tensor/GEMM mode, float32) outputs a
  real reflectivity w; the estimated waveform is ŝ = Re Σ_k w_k·p̂(t − k/fs) = (w ∗ p)(t)
  (p̂ the analytic pulse, p = Re p̂); loss = MSE(ŝ, s/max|s|) + λ_sp·mean|w|
  + λ_ph·(mean|Δ cos φ| + mean|Δ sin φ|) with φ = angle(analytic(ŝ)); Adam, full batch.
  The sparsity prior lets it resolve reflectors closer than the pulse bandwidth allows;
  on extended surfaces it breaks each return into spikes, and NBP on INR-deconvolved
  Table-2 scans is no better than on Wiener's (the cube's much worse), at minutes instead
  of seconds per 1 000 pings — hence Wiener is the default (docs/reconstruction.md, "Which
  deconvolution").

Either way the output sample k is the reflectivity of an echo whose pulse starts at sample k,
the convention of the matched filter, so both kinds of dataset share the time axis
``(start_sample + k)/fs``. Output = analytic(w) (the reference's step before NBP).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from sonarsim.errors import InputError

from .field import NetworkSettings

METHODS = ("wiener", "inr")
DECONVOLVED = "deconvolved_analytic"
OUT_OF_BAND_DB = -40.0      # |P|² below this (re its peak): out of band, noise only
IN_BAND_DB = -6.0           # |P|² above this: in band, used for the reflectivity power
_ROWS_PER_BLOCK = 4096


# ---- shared FFT helpers --------------------------------------------------------------------

def _fft():
    """scipy.fft, imported on first use: importing it costs ~0.2 CPU-s of every ``recon``
    command's start-up, and only a deconvolution needs it."""
    import scipy.fft
    return scipy.fft


def _n_fft(n_t: int, n_p: int) -> int:
    return _fft().next_fast_len(n_t + n_p - 1, real=True)


def _analytic_weights(n: int) -> np.ndarray:
    """rfft-bin weights of the analytic signal: 1 at DC (and Nyquist), 2 elsewhere."""
    w = np.full(n // 2 + 1, 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return w


def _half_to_analytic(half: np.ndarray, n: int, n_keep: int) -> np.ndarray:
    """Analytic signal [.., n_keep] from the rfft ``half`` [.., n//2+1] of a real signal."""
    full = np.zeros(half.shape[:-1] + (n,), dtype=half.dtype)
    full[..., :half.shape[-1]] = half * _analytic_weights(n).astype(half.real.dtype)
    return _fft().ifft(full, axis=-1, workers=-1)[..., :n_keep]


def analytic(x: np.ndarray) -> np.ndarray:
    """Analytic signal of real rows x [.., T] (periodic, like scipy.signal.hilbert)."""
    n = x.shape[-1]
    return _half_to_analytic(_fft().rfft(x, axis=-1), n, n)


def _check_inputs(waveforms, pulse) -> tuple[np.ndarray, np.ndarray]:
    s = np.asarray(waveforms)
    p = np.asarray(pulse, dtype=np.float64)
    if s.ndim != 2 or s.shape[0] == 0 or s.shape[1] == 0:
        raise InputError(f"waveforms: expected [N, T] with N, T >= 1, got shape {s.shape}")
    if np.iscomplexobj(s):
        raise InputError("waveforms are complex: deconvolution needs the real received "
                         "waveforms (is this dataset already deconvolved?)")
    if p.ndim != 1 or p.size == 0 or not np.all(np.isfinite(p)) or not np.any(p):
        raise InputError("pulse: expected a non-zero finite 1-D array")
    if not np.all(np.isfinite(s)):
        raise InputError("waveforms contain NaN or infinity")
    return s, p


# ---- Wiener --------------------------------------------------------------------------------

def noise_and_signal_power(waveforms, pulse) -> tuple[float, float]:
    """(σ², σ_w²): white-noise variance per sample and reflectivity variance per sample.

    With s = w ∗ p + n, n white of variance σ² and w white of variance σ_w², the DFT over
    the T recorded samples has E|S(f)|² = T·(σ_w²·|P(f)|² + σ²). σ² is the mean |S|²/T over
    the bins where |P|² is below OUT_OF_BAND_DB of its peak; σ_w² the mean of
    (|S|²/T − σ²)/|P|² over the bins within IN_BAND_DB of the peak. Without out-of-band bins
    (a pulse as wide as the band), σ² falls back to the median-absolute-deviation estimate
    (median |s| / 0.6745)², which overestimates it where echoes fill the record.
    """
    s, p = _check_inputs(waveforms, pulse)
    n_t = s.shape[1]
    n = _n_fft(n_t, p.size)
    p2 = np.abs(_fft().rfft(p, n=n)) ** 2
    out_band = p2 < p2.max() * 10 ** (OUT_OF_BAND_DB / 10)
    in_band = p2 >= p2.max() * 10 ** (IN_BAND_DB / 10)
    spec = np.zeros(p2.size)
    for b in range(0, s.shape[0], _ROWS_PER_BLOCK):
        block = _fft().rfft(s[b:b + _ROWS_PER_BLOCK], n=n, axis=-1, workers=-1)
        spec += (block.real ** 2 + block.imag ** 2).sum(0, dtype=np.float64)
    spec /= s.shape[0] * n_t
    if out_band.sum() >= max(4, 0.05 * p2.size):
        sigma2 = float(spec[out_band].mean())
    else:
        sigma2 = float((np.median(np.abs(s)) / 0.6745) ** 2)
    sigma_w2 = float(np.mean(np.maximum(spec[in_band] - sigma2, 0.0) / p2[in_band]))
    return sigma2, sigma_w2


def wiener(waveforms, pulse, lam: float | None = None) -> tuple[np.ndarray, dict]:
    """Wiener-deconvolved analytic signals [N, T] complex64 and the settings used.

    W(f) = S(f)·P*(f)/(|P(f)|² + λ) on the zero-padded (linear) spectrum, output the analytic
    signal of w cropped to T samples. λ (units of |P|², i.e. of pulse² per sample) defaults
    to σ²/σ_w² from :func:`noise_and_signal_power` — the MMSE filter for white reflectivity
    in white noise (the reference's ``--wiener_deconvolution`` takes λ by hand).
    """
    s, p = _check_inputs(waveforms, pulse)
    n_pings, n_t = s.shape
    info = {"method": "wiener"}
    if lam is None:
        sigma2, sigma_w2 = noise_and_signal_power(s, p)
        if not sigma_w2 > 0:
            raise InputError("waveforms: no signal above the noise in the pulse band, "
                             "nothing to deconvolve")
        lam = sigma2 / sigma_w2
        info.update(noise_variance=sigma2, reflectivity_variance=sigma_w2,
                    lambda_source="noise/reflectivity power (MMSE)")
    else:
        lam = float(lam)
        if not (math.isfinite(lam) and lam > 0):
            raise InputError(f"wiener lambda: must be positive and finite, got {lam}")
        info["lambda_source"] = "given"
    n = _n_fft(n_t, p.size)
    P = _fft().rfft(p, n=n)
    if not lam > 1e-12 * float(np.max(np.abs(P) ** 2)):
        lam = 1e-12 * float(np.max(np.abs(P) ** 2))
    H = np.conj(P) / (np.abs(P) ** 2 + lam)
    out = np.empty((n_pings, n_t), dtype=np.complex64)
    # single precision (the output is complex64) and all threads
    s32, H32 = s.astype(np.float32, copy=False), H.astype(np.complex64)
    for b in range(0, n_pings, _ROWS_PER_BLOCK):
        half = _fft().rfft(s32[b:b + _ROWS_PER_BLOCK], n=n, axis=-1, workers=-1) * H32
        out[b:b + _ROWS_PER_BLOCK] = _half_to_analytic(half, n, n_t)
    info["lambda"] = float(lam)
    info["lambda_relative_to_peak_P2"] = float(lam / np.max(np.abs(P) ** 2))
    return out, info


# ---- INR: loss and its gradient (NumPy) ---------------------------------------------------

def pulse_band(pulse: np.ndarray, n_t: int, band_db: float) -> np.ndarray | None:
    """rfft-bin mask [n//2+1] (n = the linear-convolution FFT size for T = ``n_t``) of the
    frequencies where |P(f)|² is within ``band_db`` dB of its peak; None if ``band_db`` is
    infinite (the full band)."""
    if math.isinf(band_db):
        return None
    p2 = np.abs(_fft().rfft(pulse, n=_n_fft(n_t, pulse.size))) ** 2
    return (p2 >= p2.max() * 10 ** (-band_db / 10)).astype(np.float64)


def bandpass(x: np.ndarray, band: np.ndarray | None, n_p: int) -> np.ndarray:
    """Rows x [.., T] through the zero-phase FFT band-pass ``band`` (see :func:`pulse_band`;
    ``n_p`` the pulse length that fixed its FFT size), cropped back to T."""
    if band is None:
        return x
    n_t = x.shape[-1]
    n = _n_fft(n_t, n_p)
    return _fft().irfft(_fft().rfft(x, n=n, axis=-1) * band, n=n, axis=-1)[..., :n_t]


def convolve(w: np.ndarray, pulse: np.ndarray, band: np.ndarray | None = None) -> np.ndarray:
    """ŝ = (w ∗ p)[.., :T]: linear convolution of rows w [.., T] with the pulse, cropped;
    with ``band`` (:func:`pulse_band`) the pulse is band-passed first."""
    n_t = w.shape[-1]
    n = _n_fft(n_t, pulse.size)
    spec = _fft().rfft(pulse, n=n) * (1.0 if band is None else band)
    return _fft().irfft(_fft().rfft(w, n=n, axis=-1) * spec, n=n, axis=-1)[..., :n_t]


def correlate(g: np.ndarray, pulse: np.ndarray, band: np.ndarray | None = None) -> np.ndarray:
    """The adjoint of :func:`convolve`: (Σ_j p[j]·g[k + j]) for k < T."""
    n_t = g.shape[-1]
    n = _n_fft(n_t, pulse.size)
    spec = np.conj(_fft().rfft(pulse, n=n)) * (1.0 if band is None else band)
    return _fft().irfft(_fft().rfft(g, n=n, axis=-1) * spec, n=n, axis=-1)[..., :n_t]


def inr_loss(w: np.ndarray, target: np.ndarray, pulse: np.ndarray, sparsity: float,
             phase: float, eps: float = 1e-6, band: np.ndarray | None = None
             ) -> tuple[float, dict, np.ndarray]:
    """Loss of the reference's deconvolution (reference code ``deconvolve_measurements.py``)
    and its gradient with respect to w.

    w, target: [P, T] real (target normalised to max |s| = 1, and band-passed with ``band``
    if that is given). ŝ = convolve(w, p, band);
    L = mean((ŝ − s)²) + sparsity·mean|w| + phase·(mean|Δ_t cos φ| + mean|Δ_t sin φ|),
    φ = angle(analytic(ŝ)), Δ_t the difference of neighbouring samples. The unit phasor
    a/|a| uses |a| regularised to sqrt(|a|² + (eps·max|a|)²).
    Returns (L, {'mse', 'sparsity', 'phase'}, dL/dw [P, T] float64).
    """
    w = np.asarray(w, dtype=np.float64)
    shat = convolve(w, pulse, band)
    r = shat - target
    m = w.size
    mse = float(np.mean(r ** 2))
    sp = float(np.mean(np.abs(w)))
    g_s = 2.0 * r / m
    ph = 0.0
    if phase > 0:
        a = analytic(shat)
        mag = np.sqrt(np.abs(a) ** 2 + (eps * max(float(np.abs(a).max()), 1e-30)) ** 2)
        u = a / mag
        d_re, d_im = np.diff(u.real, axis=-1), np.diff(u.imag, axis=-1)
        m_d = d_re.size
        ph = float(np.mean(np.abs(d_re)) + np.mean(np.abs(d_im)))
        g_u = np.zeros_like(u)
        for d, unit in ((d_re, 1.0), (d_im, 1j)):
            sg = np.sign(d) / m_d
            g_u[..., 1:] += unit * sg
            g_u[..., :-1] -= unit * sg
        # u = a/|a|: the gradient w.r.t. a is the tangential part of g_u over |a|.
        g_a = (g_u - u * np.real(np.conj(u) * g_u)) / mag
        # a = analytic(ŝ) is self-adjoint as a complex operator: dL/dŝ = Re analytic(g_a).
        n_t = g_a.shape[-1]
        full = _fft().fft(g_a, axis=-1)
        h = np.zeros(n_t)
        h[0] = 1.0
        h[1:(n_t + 1) // 2] = 2.0
        if n_t % 2 == 0:
            h[n_t // 2] = 1.0
        g_s = g_s + phase * np.real(_fft().ifft(full * h, axis=-1))
    g_w = correlate(g_s, pulse, band) + sparsity * np.sign(w) / m
    loss = mse + sparsity * sp + phase * ph
    return loss, {"mse": mse, "sparsity": sp, "phase": ph}, g_w


# ---- INR: the network ----------------------------------------------------------------------

@dataclass
class INRSettings(NetworkSettings):
    """Sizes and weights of the INR deconvolution (defaults: see docs/reconstruction.md).

    The network settings (``hash_levels`` … ``mlp_hidden``) are those of
    :class:`recon.field.NetworkSettings`, shared with NBP's field, with the INR's own
    defaults; the names before 2026-11 (``n_levels``, ``width``, …) are in :data:`RENAMED`.

    The reference (AirSAS): 360 pings per INR, 20 hash levels × 2 features, 2^15 entries per
    level, base resolution 16, scale 1.5, MLP 128 × 3 hidden, lr 1e-3, 1000 iterations,
    sparsity 1e-1, phase 1e-4. The CPU defaults keep the encoding and the loss weights and
    use a 32-wide, 2-hidden MLP with a higher learning rate and fewer iterations.
    """

    # the network (recon.field.NetworkSettings), the INR's defaults
    hash_levels: int = 16
    hash_features: int = 2
    hash_log2_size: int = 15
    hash_base_resolution: int = 16
    hash_level_scale: float = 1.5
    mlp_width: int = 32
    mlp_hidden: int = 2
    # the fit
    pings_per_inr: int = 360
    iterations: int = 300
    lr: float = 1e-2
    lr_final: float = 1e-3          # exponential decay from lr to lr_final over the run
    sparsity: float = 1e-1
    phase: float = 1e-4
    seed: int = 0
    band_db: float = 30.0           # data term within this many dB of the pulse's peak

    def validate(self) -> None:
        """Every field in its range (InputError, one line naming the setting), before any
        work. The fit's own settings are checked here; the network's ranges only in
        :meth:`NetworkSettings.validate_network` (the one place recon nbp's field uses too: a
        level count whose finest resolution overflows is refused there rather than failing
        later as a NaN loss); a width or batch that cannot fit is refused by the memory
        check. Every integer setting must be an integer (a manifest's 2.5 is not truncated)."""
        for name in _INTEGER_SETTINGS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise InputError(f"inr {name}: must be an integer, got {v!r}")
        for name, lo, hi in _FIT_RANGES:
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise InputError(f"inr {name}: must be an integer in [{lo}, {hi}], got {v!r}")
        for name in ("lr", "lr_final"):
            v = getattr(self, name)
            if not (_is_number(v) and math.isfinite(v) and 0.0 < v <= 1.0):
                raise InputError(f"inr {name}: must be in (0, 1], got {v!r}")
        for name in ("sparsity", "phase"):
            v = getattr(self, name)
            if not (_is_number(v) and math.isfinite(v) and v >= 0):
                raise InputError(f"inr {name}: must be >= 0, got {v!r}")
        if not (_is_number(self.band_db) and self.band_db > 0):
            raise InputError(f"inr band_db: must be positive (inf = full band), "
                             f"got {self.band_db!r}")
        if not _is_number(self.hash_level_scale):
            raise InputError(f"inr hash_level_scale: must be a number, got "
                             f"{self.hash_level_scale!r}")
        try:
            self.validate_network()
        except InputError as exc:
            raise InputError(f"inr {exc}") from None

    def memory_estimate(self, n_samples: int) -> tuple[int, str]:
        """(peak bytes, how they are made up) of fitting one batch of ``pings_per_inr`` pings
        of ``n_samples`` samples: the hash tables with Adam's two moments and the gradient
        (4 float32 per entry), and per sample the encoding and every MLP activation, kept for
        the backward pass with their gradients (2 float32 each), plus the float64 NumPy loss
        and its FFTs (about 16 float64 per sample)."""
        entries = self.hash_levels * min(2 ** self.hash_log2_size,
                                         int(self.finest_resolution() + 2) ** 2)
        tables = entries * self.hash_features * 4 * 4
        samples = self.pings_per_inr * int(n_samples)
        per_sample = (self.n_features()
                      + self.mlp_width * max(self.mlp_hidden, 1) * 2 + 1) * 4 * 2 + 16 * 8
        return tables + samples * per_sample, (
            f"hash tables {tables / 2**20:.0f} MiB + {self.pings_per_inr} pings x {n_samples} "
            f"samples x {per_sample} bytes")


    def cpu_seconds_estimate(self, n_pings: int, n_samples: int) -> float:
        """Rough CPU time (s, user+sys, within about 2x) of fitting ``n_pings`` pings of
        ``n_samples`` samples: :data:`INR_CPU_S_PER_SAMPLE_ITERATION` (the default network)
        per sample and iteration, scaled by the per-sample activations of this network
        against the default's (the MLP and the encoding dominate the cost). Wall time on k
        idle cores is about this / k."""
        def activations(st):
            return st.n_features() + st.mlp_width * max(st.mlp_hidden, 1) * 2 + 1
        scale = activations(self) / activations(INRSettings())
        return (INR_CPU_S_PER_SAMPLE_ITERATION * scale * int(n_pings) * int(n_samples)
                * self.iterations)


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


# The INR's integer settings (the network's and the fit's), and the ranges of the fit's own
# ones; the network's ranges are NetworkSettings.validate_network's.
_INTEGER_SETTINGS = ("pings_per_inr", "iterations", "seed", "hash_levels", "hash_features",
                     "hash_log2_size", "hash_base_resolution", "mlp_width", "mlp_hidden")
_FIT_RANGES = (("pings_per_inr", 1, 1 << 20), ("iterations", 1, 1_000_000),
               ("seed", 0, 2 ** 32 - 1))


# CPU seconds per sample and Adam iteration of the default network, measured on the
# Table-2 bunny (360 pings x 718 samples, 20 iterations, start-up included: 14.6 s CPU on
# 2 shared cores; benchmarks/bench_deconvolution.py: 3.6 ms wall per ping-iteration at 1000
# samples on 2 loaded cores). A full 54 000-ping scan at 300 iterations:
# 54 000 x 718 x 300 x 2.5e-6 s = 8.1 CPU-hours (about 4 h on 2 idle cores).
INR_CPU_S_PER_SAMPLE_ITERATION = 2.5e-6


# One line of help per INRSettings field (the `recon deconvolve` options are derived from both).
INR_HELP = {
    "pings_per_inr": "pings per network (one AirSAS rotation = 360)",
    "iterations": "Adam iterations per batch of pings",
    "lr": "initial learning rate",
    "lr_final": "final learning rate of the exponential decay",
    "sparsity": "weight of mean|w|",
    "phase": "weight of the phase-smoothness term",
    "hash_levels": "hash-grid levels",
    "hash_features": "features per hash-grid level",
    "hash_log2_size": "log2 of the entries per hash level",
    "hash_base_resolution": "coarsest hash-grid resolution",
    "hash_level_scale": "resolution factor between hash-grid levels",
    "mlp_width": "MLP width",
    "mlp_hidden": "MLP hidden layers",
    "seed": "seed of the initial weights",
    "band_db": "fit the data only where the pulse spectrum is within this many dB of its peak "
               "('inf' = full band)",
}


#: The INR settings' names before they became :class:`recon.field.NetworkSettings`' (old
#: name → new name): ``recon deconvolve --n-levels`` and a batch's ``deconvolve = {n_levels
#: = …}`` are refused in one line naming the new one.
RENAMED = {"n_levels": "hash_levels", "features_per_level": "hash_features",
           "log2_hashmap_size": "hash_log2_size", "base_resolution": "hash_base_resolution",
           "per_level_scale": "hash_level_scale", "width": "mlp_width",
           "hidden_layers": "mlp_hidden"}


def renamed_setting(name: str, option: bool = False) -> str | None:
    """The one-line refusal of an old INR setting name (None for any other name):
    ``option`` words it as command-line options (``--n-levels``), else as keys."""
    new = RENAMED.get(name)
    if new is None:
        return None
    why = "the INR and recon nbp share the network settings' names"
    if option:
        return f"--{name.replace('_', '-')} is now --{new.replace('_', '-')} ({why})"
    return f"{name!r} is now {new!r} ({why})"


class _Field:
    """A 2-D hash grid + MLP w(range, ping) on drjit.nn, with its Adam optimiser."""

    def __init__(self, st: INRSettings, seed: int):
        import drjit as dr
        import drjit.nn as nn
        from drjit.opt import Adam
        from ._jit import jit
        m = jit()
        self.dr, self.m = dr, m
        rng = dr.rng(seed=seed)
        self.enc = nn.HashGridEncoding(m.Float, 2, n_levels=st.hash_levels,
                                       n_features_per_level=st.hash_features,
                                       hashmap_size=2 ** st.hash_log2_size,
                                       base_resolution=st.hash_base_resolution,
                                       per_level_scale=st.hash_level_scale, rng=rng)
        layers = []
        for _ in range(st.mlp_hidden):
            layers += [nn.Linear(-1, st.mlp_width, bias=False), nn.ReLU()]
        layers.append(nn.Linear(-1, 1, bias=False))
        self.net = nn.Sequential(*layers).alloc(m.TensorXf, st.n_features(),
                                                rng=rng)
        # A Python-float learning rate: Adam turns it into an opaque value itself. (An
        # array learning rate is multiplied in place by Adam's debiasing factor in drjit
        # 1.5.0, so it shrinks geometrically.)
        self.opt = Adam(lr=float(st.lr))
        self.opt.update(self.net)
        self.opt["grid"] = self.enc.data

    def __call__(self, coords):
        for k in self.net.keys():
            self.net[k] = self.opt[k]
        self.enc.data = self.opt["grid"]
        feats = self.enc(coords)
        y = self.net(self.m.TensorXf(feats))
        return y.array

    def set_lr(self, lr: float) -> None:
        self.opt.set_learning_rate(float(lr))


def _coords(m, n_pings: int, n_t: int):
    """(range, ping) ∈ [0, 1]² of every sample, ping-major, as a Dr.Jit Array2f."""
    r = np.linspace(0.0, 1.0, n_t, dtype=np.float32)
    q = np.linspace(0.0, 1.0, n_pings, dtype=np.float32) if n_pings > 1 else np.zeros(1, np.float32)
    rr, qq = np.meshgrid(r, q)
    return m.Array2f(m.Float(rr.ravel()), m.Float(qq.ravel()))


def inr_batch(target: np.ndarray, pulse: np.ndarray, st: INRSettings, seed: int,
              on_iteration=None, field: _Field | None = None) -> tuple[np.ndarray, list[float]]:
    """Fit one INR to ``target`` [P, T] (normalised); returns (w [P, T] float32, losses).

    The data term is restricted to the pulse band (``st.band_db``): target and pulse are
    band-passed alike, so energy the pulse cannot have produced (e.g. the strong
    low-frequency content of real recordings) does not pull the fit. ``field``: continue
    training that network (a warm start; benchmarks/bench_deconvolution.py measures it)
    instead of a new one seeded ``seed``."""
    band = pulse_band(pulse, target.shape[1], st.band_db)
    target = bandpass(target, band, pulse.size)
    field_ = field if field is not None else _Field(st, seed)
    dr, m = field_.dr, field_.m
    coords = _coords(m, *target.shape)
    losses = []
    decay = (st.lr_final / st.lr) ** (1.0 / max(st.iterations - 1, 1))
    for it in range(st.iterations):
        field_.set_lr(st.lr * decay ** it)
        w = field_(coords)
        w_np = w.numpy().reshape(target.shape)
        loss, parts, g = inr_loss(w_np, target, pulse, st.sparsity, st.phase, band=band)
        if not math.isfinite(loss):
            raise InputError(f"inr: loss became {loss} at iteration {it}; lower --lr")
        losses.append(loss)
        dr.backward(dr.sum(w * m.Float(g.ravel().astype(np.float32))))
        field_.opt.step()
        if on_iteration is not None:
            on_iteration(loss, parts)
    with dr.suspend_grad():
        w_np = field_(coords).numpy().reshape(target.shape).astype(np.float32)
    return w_np, losses


def inr(waveforms, pulse, settings: INRSettings | None = None, progress: bool = True
        ) -> tuple[np.ndarray, dict]:
    """INR-deconvolved analytic signals [N, T] complex64 and a summary (losses per batch).

    Pings are split into consecutive batches of ``pings_per_inr``; each gets its own network
    and optimiser (seeded ``seed + batch index``). The target is s / max|s| over the whole
    dataset (the reference's global normalisation); the output is analytic(w·max|s|), so
    its amplitude is a reflectivity in the waveform's units per unit pulse amplitude.
    """
    from sonarsim.progress import progress_bar
    st = settings or INRSettings()
    st.validate()
    s, p = _check_inputs(waveforms, pulse)
    n_pings, n_t = s.shape
    check_inr_memory(st, n_pings, n_t)
    scale = float(np.max(np.abs(s)))
    if not scale > 0:
        raise InputError("waveforms: all zero, nothing to deconvolve")
    n_batches = -(-n_pings // st.pings_per_inr)
    out = np.empty((n_pings, n_t), dtype=np.complex64)
    bar = progress_bar(n_batches * st.iterations, progress, unit="it", desc="deconvolve (inr)")
    first_last = []
    t0 = time.perf_counter()

    def tick(loss, parts):
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.3e}", mse=f"{parts['mse']:.2e}", refresh=False)

    try:
        for b in range(n_batches):
            rows = slice(b * st.pings_per_inr, min((b + 1) * st.pings_per_inr, n_pings))
            target = s[rows].astype(np.float64) / scale
            w, losses = inr_batch(target, p, st, st.seed + b, tick)
            out[rows] = analytic(w.astype(np.float64) * scale)
            first_last.append((losses[0], losses[-1]))
    finally:
        bar.close()
    info = {"method": "inr", **asdict(st), "normalisation": scale, "n_batches": n_batches,
            "loss_first": [a for a, _ in first_last], "loss_last": [z for _, z in first_last],
            "seconds": time.perf_counter() - t0}
    return out, info


# ---- datasets ------------------------------------------------------------------------------

def check_inr_memory(st: INRSettings, n_pings: int, n_samples: int) -> None:
    """Refuse (one line) an INR fit whose per-batch memory estimate exceeds the limit."""
    from sonarsim import limits
    need, detail = replace(st, pings_per_inr=min(st.pings_per_inr, n_pings)).memory_estimate(
        n_samples)
    limits.check_memory(need, "INR deconvolution", detail,
                        "use fewer --pings-per-inr, a smaller --mlp-width or fewer --hash-levels")


def check_inr_time(n_pings: int, n_samples: int, settings: INRSettings,
                   max_hours: float | None) -> float:
    """Estimated wall hours of an INR fit on this machine's cores; logged, and refused in one
    line (InputError) above ``max_hours``."""
    import logging
    import os
    cores = max(1, os.cpu_count() or 1)
    hours = settings.cpu_seconds_estimate(n_pings, n_samples) / cores / 3600
    what = (f"{n_pings} pings x {n_samples} samples x {settings.iterations} iterations on "
            f"{cores} core(s)")
    if max_hours is not None and hours > max_hours:
        raise InputError(f"inr: estimated {hours:.2g} h for {what}, above --max-hours "
                         f"{max_hours:g}; use --method wiener (seconds), fewer --pings or "
                         "--iterations, or raise --max-hours")
    logging.getLogger(__name__).info("inr: estimated %.2g min for %s", hours * 60, what)
    return hours


def deconvolve(dataset, method: str = "wiener", *, wiener_lambda: float | None = None,
               inr_settings: INRSettings | None = None, progress: bool = True,
               max_hours: float | None = None):
    """A new :class:`~sonarsim.dataset.SonarDataset` whose waveforms are the deconvolved
    analytic signals [N, T] complex64 (``waveform_kind = 'deconvolved_analytic'``).

    Geometry, pulse, fs, sound speed, start_sample, ground truth and meta are kept (stored
    transients are dropped); meta gains ``deconvolution_method`` and
    ``deconvolution_settings`` (a dict: the settings and what was estimated/measured).

    INR: the estimated wall time (:meth:`INRSettings.cpu_seconds_estimate` over this
    machine's cores) is logged before the fit, and a run above ``max_hours`` (None: no
    bound) is refused (InputError) before any work.
    """
    from sonarsim.dataset import SonarDataset
    if method not in METHODS:
        raise InputError(f"method: choose one of {', '.join(METHODS)}, got {method!r}")
    if getattr(dataset, "waveform_kind", "real") != "real":
        raise InputError(f"dataset waveforms are already '{dataset.waveform_kind}', "
                         "deconvolve the original dataset")
    if method == "inr":       # memory first, then time: the estimate is logged only for a run
        st = inr_settings or INRSettings()     # that goes ahead
        st.validate()
        check_inr_memory(st, dataset.n_pings, dataset.n_samples)
        check_inr_time(dataset.n_pings, dataset.n_samples, st, max_hours)
    if method == "wiener":
        sig, info = wiener(dataset.waveforms, dataset.pulse, wiener_lambda)
    else:
        sig, info = inr(dataset.waveforms, dataset.pulse, inr_settings, progress)
    meta = dict(dataset.meta)
    meta["deconvolution_method"] = method
    meta["deconvolution_settings"] = info
    return SonarDataset(
        waveforms=sig, tx=dataset.tx, rx=dataset.rx, boresight=dataset.boresight,
        pulse=dataset.pulse, fs=dataset.fs, sound_speed=dataset.sound_speed,
        source=dataset.source, start_sample=dataset.start_sample,
        temperatures=dataset.temperatures, gt_vertices=dataset.gt_vertices,
        gt_faces=dataset.gt_faces, snr_db=dataset.snr_db, seed=dataset.seed, transients=None,
        meta=meta, rx_boresight=dataset.rx_boresight, waveform_kind=DECONVOLVED)


# ---- measurement helper used by tests and benchmarks ---------------------------------------

def mainlobe_width(envelope: np.ndarray, peak: int | None = None, level_db: float = -6.0,
                   upsample: int = 16) -> float:
    """Width (samples) of the lobe around ``peak`` (default: the maximum) where the
    band-limited (FFT-upsampled ×``upsample``) |signal| stays above ``level_db`` of the peak.
    ``envelope``: a complex analytic signal [T]."""
    from sonarsim import signals
    x = np.asarray(envelope)
    up = np.abs(signals.fft_upsample(x, upsample))
    k = int(np.argmax(up)) if peak is None else int(round(peak * upsample))
    k = int(np.argmax(up[max(0, k - upsample):k + upsample + 1])) + max(0, k - upsample)
    thr = up[k] * 10 ** (level_db / 20)
    lo = k
    while lo > 0 and up[lo - 1] >= thr:
        lo -= 1
    hi = k
    while hi < len(up) - 1 and up[hi + 1] >= thr:
        hi += 1
    # linear interpolation of the two crossings
    left = lo - (up[lo] - thr) / (up[lo] - up[lo - 1]) if lo > 0 else lo
    right = hi + (up[hi] - thr) / (up[hi] - up[hi + 1]) if hi < len(up) - 1 else hi
    return float(right - left) / upsample
