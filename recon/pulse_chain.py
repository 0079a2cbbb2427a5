"""From histograms to waveforms and back: the simulator's pulse chain as a linear operator.

``A`` maps bounce-1 histograms [n, T_bins] (bins of c/(fs·K) metres of path, K the
oversampling) to waveforms [n, T] exactly as :func:`sonarsim.simulate.transients_to_waveforms`
does (linear convolution with the pulse resampled ×K, then every K-th bin): that function is
the forward operator. :meth:`PulseChain.adjoint` is Aᵀ (zero-insertion ×K, then correlation
with the oversampled pulse), so ⟨A h, r⟩ = ⟨h, Aᵀ r⟩ (tested).

The losses compare a model with the measured waveforms up to an unknown global scale,
fitted in closed form (the data's absolute level is unknown: transducer gains, albedo):
:func:`scaled_misfit` on the raw waveforms, and :func:`envelope_misfit` on the envelope of
the matched-filtered analytic signal (|MF(w)|, :func:`sonarsim.signals.matched_filter`), which
is smooth on the scale of the range resolution and so has a wider capture range.
"""
from __future__ import annotations

import numpy as np

from sonarsim.errors import InputError


def _fft():
    """scipy.fft, imported on first use (it costs a command's start-up)."""
    import scipy.fft
    return scipy.fft


class PulseChain:
    """The linear map histograms [n, n_bins] → waveforms [n, n_samples] of a dataset.

    pulse: float [L] at fs; oversample: K (bins per sample); n_samples: T; n_bins ≥ T·K.
    """

    def __init__(self, pulse: np.ndarray, oversample: int, n_samples: int, n_bins: int):
        if int(oversample) != oversample or oversample < 1:
            raise InputError(f"oversample must be a positive integer, got {oversample}")
        if n_bins < n_samples * oversample:
            raise InputError(f"{n_bins} bins cannot hold {n_samples} samples x {oversample}")
        self.k, self.n_samples, self.n_bins = int(oversample), int(n_samples), int(n_bins)
        from sonarsim.simulate import oversampled_pulse
        self.pulse_os = oversampled_pulse(np.asarray(pulse, float), self.k)
        self._n_fft = _fft().next_fast_len(self.n_bins + len(self.pulse_os) - 1, real=True)
        self._spectrum = _fft().rfft(self.pulse_os, self._n_fft)

    def forward(self, hist: np.ndarray) -> np.ndarray:
        """Waveforms float32 [n, T] of histograms [n, n_bins]."""
        hist = np.asarray(hist)
        from sonarsim.simulate import transients_to_waveforms
        return transients_to_waveforms(hist[:, None, :], self.pulse_os, self.k, self.n_samples)

    def adjoint(self, residual: np.ndarray) -> np.ndarray:
        """Aᵀ r: float64 [n, n_bins] of waveform-domain values r [n, T]."""
        r = np.asarray(residual, np.float64)
        up = np.zeros((r.shape[0], self._n_fft))
        up[:, :self.n_samples * self.k:self.k] = r
        corr = _fft().irfft(_fft().rfft(up, axis=-1) * np.conj(self._spectrum),
                               self._n_fft, axis=-1)
        return corr[:, :self.n_bins]


def scaled_misfit(model: np.ndarray, data: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(loss, α, ∂loss/∂model) of loss = ‖α·m − y‖² / ‖y‖² with α = ⟨m, y⟩/⟨m, m⟩.

    The best global scale in closed form; loss = 1 − cos²(m, y) ∈ [0, 1]. By the envelope
    theorem the gradient is that of the loss at fixed α: 2α(α·m − y)/‖y‖².
    """
    m, y = np.asarray(model, np.float64), np.asarray(data, np.float64)
    yy, mm = float(np.vdot(y, y).real), float(np.vdot(m, m).real)
    if yy == 0:
        raise InputError("the measured waveforms are all zero")
    if mm == 0:
        return 1.0, 0.0, np.zeros_like(m)
    alpha = float(np.vdot(m, y).real) / mm
    resid = alpha * m - y
    loss = float(np.vdot(resid, resid).real) / yy
    return loss, alpha, (2.0 * alpha / yy) * resid


class Envelope:
    """e = |MF(w)|: the envelope of the matched-filtered analytic signal of waveforms [n, T]
    (:func:`sonarsim.signals.matched_filter`, linear mode), with its vector-Jacobian product."""

    def __init__(self, pulse: np.ndarray, n_samples: int):
        self.pulse = np.asarray(pulse, np.float64)
        self.n_samples = int(n_samples)
        self._n_fft = _fft().next_fast_len(self.n_samples + self.pulse.size - 1, real=True)
        n = self._n_fft
        weights = np.zeros(n)              # the matched filter's spectrum weights, full FFT
        weights[0] = 1.0
        half = n // 2
        weights[1:(n + 1) // 2] = 4.0
        if n % 2 == 0:
            weights[half] = 1.0
        self._kernel = np.conj(_fft().fft(self.pulse, n)) * weights

    def __call__(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(e [n, T], z [n, T] complex): the envelope and the matched-filtered signal."""
        from sonarsim.signals import matched_filter
        z = matched_filter(np.asarray(w, np.float64), self.pulse)
        return np.abs(z), z

    def vjp(self, z: np.ndarray, grad_e: np.ndarray) -> np.ndarray:
        """∂loss/∂w [n, T] from ∂loss/∂e [n, T] at the signal z = MF(w)."""
        g = grad_e * z / np.maximum(np.abs(z), 1e-30)
        full = np.zeros((g.shape[0], self._n_fft), complex)
        full[:, :self.n_samples] = g
        back = _fft().ifft(_fft().fft(full, axis=-1) * np.conj(self._kernel), axis=-1)
        return back.real[:, :self.n_samples]


def blur(signals: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of signals [n, T] along time, σ in samples (0: unchanged).

    Zero-padded correlation with a symmetric kernel (``scipy.ndimage.gaussian_filter1d``,
    mode 'constant', truncated at 4σ): a symmetric linear map, so it is its own adjoint and
    serves as the vector-Jacobian product too (tested).
    """
    if sigma <= 0:
        return np.asarray(signals)
    from scipy.ndimage import gaussian_filter1d
    return gaussian_filter1d(np.asarray(signals, np.float64), float(sigma), axis=-1,
                             mode="constant", truncate=4.0)


def envelope_misfit(model: np.ndarray, data_envelope: np.ndarray, envelope: Envelope,
                    sigma: float = 0.0) -> tuple[float, float, np.ndarray]:
    """(loss, α, ∂loss/∂model) of :func:`scaled_misfit` between the envelopes |MF(model)|
    and ``data_envelope``, both smoothed by :func:`blur` with σ = ``sigma`` samples (the
    coarse-to-fine schedule of ``recon refine --envelope-blur``); the gradient is with
    respect to the model waveforms."""
    e, z = envelope(model)
    loss, alpha, grad_e = scaled_misfit(blur(e, sigma), blur(data_envelope, sigma))
    return loss, alpha, envelope.vjp(z, blur(grad_e, sigma))
