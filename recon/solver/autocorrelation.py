"""Matched-filter model: the rendered impulse response convolved with the pulse's
autocorrelation (``autocorrelation_taps``), for matched-filtered targets."""
from __future__ import annotations

import numpy as np

from .._jit import aligned_upload


def pulse_autocorrelation(dataset, taps: int) -> np.ndarray:
    """The matched filter's response to the dataset's own pulse at lags −taps…taps samples
    [2·taps + 1] complex128, normalised to 1 at lag 0 — computed with the same matched filter
    as the data (:func:`recon.measurements.matched_filtered`), so conventions agree."""
    from sonarsim import signals
    pulse = np.asarray(dataset.pulse, dtype=np.float64)
    c = taps + 1
    w = np.zeros(len(pulse) + 2 * taps + 2)
    w[c:c + len(pulse)] = pulse
    mf = signals.matched_filter(w[None], pulse, mode="linear")[0]
    acf = np.asarray(mf[c - taps:c + taps + 1], dtype=np.complex128)
    return acf / acf[taps]


def expand_bins(bins: np.ndarray, taps: int, n_t: int):
    """Bins to render for the autocorrelation model: per ping the sorted union of
    k − taps … k + taps over the drawn bins k, padded to a fixed length by repeating its last
    bin (a zero along-ray step: no effect on transmittance). Returns (render_bins [P, L],
    positions [P, K, 2·taps + 1]: where bin k − m sits in render_bins, for lags m = −taps…taps)."""
    lags = np.arange(-taps, taps + 1)
    want = np.clip(bins[:, :, None] - lags[None, None, :], 0, n_t - 1)
    length = bins.shape[1] * len(lags)
    render = np.empty((len(bins), length), dtype=np.int64)
    pos = np.empty(want.shape, dtype=np.int64)
    for i in range(len(bins)):
        u = np.unique(want[i])
        render[i, :len(u)] = u
        render[i, len(u):] = u[-1]
        pos[i] = np.searchsorted(u, want[i]) + i * length
    return render, pos


def convolve_rendered(m, y_re, y_im, pos: np.ndarray, acf: np.ndarray):
    """Σ_m acf[m]·ŷ(k − m) for every drawn bin (Float re, im [P·K]) from the rendered ŷ.
    The positions of each lag are uploaded aligned (:func:`aligned_upload`), so every iteration
    reuses one compiled kernel (forward and backward) instead of compiling new ones."""
    import drjit as dr
    P, K, L = pos.shape
    out_re = dr.zeros(m.Float, P * K)
    out_im = dr.zeros(m.Float, P * K)
    for j in range(L):
        idx = aligned_upload(m.UInt32, pos[:, :, j].astype(np.uint32))
        a_re = dr.gather(m.Float, y_re, idx)
        a_im = dr.gather(m.Float, y_im, idx)
        cr, ci = float(acf[j].real), float(acf[j].imag)
        out_re += cr * a_re - ci * a_im
        out_im += cr * a_im + ci * a_re
    return out_re, out_im
