"""Monte-Carlo fidelity of a simulated dataset, measured from two independent half-estimates.

Every simulation renders each pose twice with independent random numbers (two *halves*,
each an unbiased estimate with half the samples) and stores their mean. Their half
difference d = (w_a − w_b)/2 has the same variance as the error of the mean
(w_a + w_b)/2 whenever the halves are independent and equally noisy, so it is a direct
sample of the Monte-Carlo noise that the dataset carries. Bias (a wrong estimator) is
not noise and is not seen here; the closed-form and independent-computation tests cover it.

Two measures are derived from it (docs/simulation.md "What fidelity a dataset has"):

* ``mc_snr_db`` — after matched filtering, the quantity reconstruction sees:
  10·log10(E_s / E_mc) with E_mc = Σ|MF(d)|² and E_s = Σ|MF(w)|² − E_mc (the signal
  energy, the noise energy removed) over every ping and sample of the dataset;
  MF is the linear correlation with the transmitted pulse (energies by Parseval).
* the raw per-sample Monte-Carlo power P_mc = Σd² / n_support, in the definition of
  the additive-noise SNR (:func:`sonarsim.signals.signal_power`: mean square over the
  samples where |w| > 1e-6·max|w|). The MC noise lives where the echoes are, so Σd² is
  taken over all samples.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from .errors import InputError
from .signals import SIGNAL_SUPPORT_FRACTION, signal_power

_BLOCK = 256   # pings per FFT block


def mf_energy(waveforms: np.ndarray, pulse: np.ndarray) -> np.ndarray:
    """Σ_t |(w ⋆ p)[t]|² per ping, float64 [n], for waveforms [n, T] and a pulse [L].

    The full linear cross-correlation (T + L − 1 lags), computed by Parseval from the
    spectra: no correlation output is formed.
    """
    w = np.asarray(waveforms)
    if w.ndim != 2:
        raise InputError(f"waveforms must be [n, T], got shape {w.shape}")
    p = np.asarray(pulse, np.float64)
    n_fft = scipy.fft.next_fast_len(w.shape[1] + len(p) - 1, real=True)
    gain = np.abs(scipy.fft.rfft(p, n_fft)) ** 2
    weight = np.full(gain.shape, 2.0)             # one-sided spectrum: count ±f twice
    weight[0] = 1.0
    if n_fft % 2 == 0:
        weight[-1] = 1.0
    gain *= weight / n_fft
    out = np.empty(w.shape[0])
    for a in range(0, w.shape[0], _BLOCK):
        spec = scipy.fft.rfft(np.asarray(w[a:a + _BLOCK], np.float64), n_fft, axis=-1)
        out[a:a + _BLOCK] = (spec.real ** 2 + spec.imag ** 2) @ gain
    return out


@dataclass
class PingStats:
    """Per-ping Monte-Carlo statistics, float64 [n] each."""
    mf_total: np.ndarray      # Σ|MF(w)|²  (w = mean of the halves)
    mf_noise: np.ndarray      # Σ|MF(d)|²  (d = half difference)
    raw_noise: np.ndarray     # Σ d²

    NAMES = ("mf_total", "mf_noise", "raw_noise")

    @classmethod
    def measure(cls, mean: np.ndarray, half_diff: np.ndarray, pulse: np.ndarray) -> "PingStats":
        """Statistics of waveforms ``mean`` [n, T] and their half difference [n, T]."""
        return cls(mf_energy(mean, pulse), mf_energy(half_diff, pulse),
                   np.square(np.asarray(half_diff, np.float64)).sum(axis=1))


def snr_db(signal: float, noise: float) -> float:
    """10·log10(signal/noise); +inf without noise, nan without signal."""
    if not signal > 0:
        return math.nan
    if noise <= 0:
        return math.inf
    return 10.0 * math.log10(signal / noise)


def mc_snr_from_energies(mf_total: float, mf_noise: float) -> float:
    """``mc_snr_db`` from the summed matched-filter energies (module doc)."""
    return snr_db(mf_total - mf_noise, mf_noise)


def support_count(clean: np.ndarray) -> int:
    """Number of samples in the support of :func:`sonarsim.signals.signal_power`."""
    clean = np.asarray(clean)
    peak = float(np.max(np.abs(clean))) if clean.size else 0.0
    if peak == 0:
        return 0
    threshold = SIGNAL_SUPPORT_FRACTION * peak
    return int(sum(int(np.count_nonzero(np.abs(clean[a:a + 4096]) > threshold))
                   for a in range(0, len(clean), 4096)))


@dataclass(frozen=True)
class NoiseBudget:
    """How much white noise to add so that the *total* effective SNR is the requested one.

    In the definition of :func:`sonarsim.signals.signal_power` (raw waveforms, mean
    square over the signal support): the noiseless waveforms already carry Monte-Carlo
    noise of power ``mc_power``, so the signal power is ``signal_power(clean) − mc_power``
    and the added noise gets the rest of the noise budget:
    σ² = P_s·10^(−SNR/10) − P_mc (zero, and ``reachable`` False, if the MC noise alone
    exceeds the budget). ``effective_snr_db`` = 10·log10(P_s / (P_mc + σ²)).
    """
    sigma: float
    signal_power: float
    mc_power: float
    effective_snr_db: float
    reachable: bool


def noise_budget(clean: np.ndarray, snr: float, raw_noise_sum: float) -> NoiseBudget:
    """The :class:`NoiseBudget` for noiseless waveforms ``clean`` [N, T] whose summed
    squared half difference is ``raw_noise_sum`` (Σd² over the dataset)."""
    if not math.isfinite(snr):
        raise InputError(f"snr_db: must be finite, got {snr}")
    total = signal_power(clean)
    count = support_count(clean)
    mc = float(raw_noise_sum) / max(1, count)
    p_s = max(total - mc, 0.0)
    budget = p_s * 10.0 ** (-snr / 10.0)
    var = budget - mc
    reachable = var >= 0
    sigma = math.sqrt(var) if reachable else 0.0
    return NoiseBudget(sigma, p_s, mc, snr_db(p_s, mc + sigma * sigma), reachable)
