"""Sonar signal processing: pulses, analytic signal, matched filter, delays, noise, sound speed.

NumPy/SciPy only. Sample rates ``fs`` are in Hz, times in s, temperatures in °C. For
arrays of signals the time axis is ``axis`` (default the last one).

Sources (docs/references.md): the reference code's air sound speed, LFM pulses
(``sas_utils.gen_real_lfm``), group-delay removal and matched filter (``airsas/reconstruct_airsas_scene.py``), the
simulation's noise (``airsas/reconstruct_from_numpy.py``) and the water sound speed (``svss/``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import FormatError, InputError

AIRSAS_FS = 100e3                          # Hz (AirSAS SysParams.csv)
AIRSAS_GROUP_DELAY_SAMPLES = 62.329317     # samples at AIRSAS_FS (AirSAS SysParams.csv)
REFERENCE_PULSE_SAMPLES = 100              # the reference keeps the first 100 pulse samples

# name -> (f_start, f_stop, duration, tukey ratio); reference code sas_utils.gen_real_lfm.
NAMED_PULSES: dict[str, tuple[float, float, float, float]] = {
    "lfm-20k": (30e3, 10e3, 1e-3, 0.1),
    "lfm-10k": (25e3, 15e3, 1e-3, 0.1),
    "lfm-5k": (22.5e3, 17.5e3, 1e-3, 0.1),
}

# Samples with |s| at or below this fraction of max|s| do not count as signal (signal_power).
SIGNAL_SUPPORT_FRACTION = 1e-6


# --- validation ---------------------------------------------------------------------------

def _check_fs(fs: float, name: str = "fs") -> float:
    try:
        fs = float(fs)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {fs!r}") from None
    if not (math.isfinite(fs) and fs > 0):
        raise InputError(f"{name}: must be positive and finite, got {fs}")
    return fs


def _signal(x, name: str = "signal", axis: int = -1) -> np.ndarray:
    """A finite, non-empty numeric array with a valid time ``axis``."""
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array ({exc})") from None
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise InputError(f"{name}: expected numbers, got dtype {arr.dtype}")
    if arr.ndim == 0:
        raise InputError(f"{name}: expected at least 1 dimension (time), got a scalar")
    if not -arr.ndim <= axis < arr.ndim:
        raise InputError(f"{name}: axis {axis} out of range for {arr.ndim} dimensions")
    if arr.shape[axis] == 0 or arr.size == 0:
        raise InputError(f"{name}: is empty (shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinity")
    return arr


def _pulse(pulse, name: str = "pulse") -> np.ndarray:
    p = _signal(pulse, name)
    if p.ndim != 1:
        raise InputError(f"{name}: expected a 1-D array [L], got shape {p.shape}")
    return p


# --- pulses -------------------------------------------------------------------------------

def lfm(f_start: float, f_stop: float, duration: float, fs: float,
        window_ratio: float = 0.1) -> np.ndarray:
    """Linear FM chirp [L] (float64, peak amplitude 1) with a Tukey window.

    L = round(duration·fs); sample k is at t = k/fs; the instantaneous frequency sweeps
    linearly from ``f_start`` at t = 0 to ``f_stop`` at t = duration (reference code ``sas_utils.gen_real_lfm``:
    cosine phase, window ``tukey(L, window_ratio)``).
    """
    fs = _check_fs(fs)
    for name, value in (("f_start", f_start), ("f_stop", f_stop), ("duration", duration)):
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"{name}: must be finite and >= 0, got {value}")
    if not 0.0 <= window_ratio <= 1.0:
        raise InputError(f"window_ratio: must be in [0, 1], got {window_ratio}")
    n = int(round(duration * fs))
    if n < 2:
        raise InputError(f"LFM of {duration} s at {fs} Hz has {n} samples; need >= 2")
    if max(f_start, f_stop) > fs / 2:
        raise InputError(f"LFM band {f_start}–{f_stop} Hz exceeds the Nyquist frequency {fs / 2} Hz")
    t = np.arange(n) / fs
    import scipy.signal    # lazily: it costs most of a command's start-up and only pulses need it
    chirp = scipy.signal.chirp(t, f0=f_start, t1=duration, f1=f_stop, method="linear", phi=0)
    return chirp * scipy.signal.windows.tukey(n, window_ratio)


def named_pulse(name: str, fs: float = AIRSAS_FS) -> np.ndarray:
    """The reference's analytic LFM called ``name`` ('lfm-20k', 'lfm-10k', 'lfm-5k') at ``fs``."""
    key = str(name).strip().lower()
    if key not in NAMED_PULSES:
        raise InputError(f"unknown pulse '{name}': expected one of {', '.join(NAMED_PULSES)} "
                         f"or a .npy file")
    return lfm(*NAMED_PULSES[key][:3], fs, window_ratio=NAMED_PULSES[key][3])


def load_pulse(path: str | os.PathLike, max_samples: int | None = None) -> np.ndarray:
    """A measured pulse [L] (float64) from a 1-D .npy file, optionally its first ``max_samples``.

    The reference uses the first 100 samples of the measured AirSAS pulses (reference code ``airsas/utils.py::process_folder``).
    """
    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: pulse file not found")
    try:
        arr = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise FormatError(f"{p}: not a readable .npy array ({exc})") from None
    if np.iscomplexobj(arr) or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{p}: pulse must be real numbers, got dtype {arr.dtype}")
    arr = np.squeeze(arr)
    if arr.ndim != 1 or arr.size < 2:
        raise InputError(f"{p}: pulse must be 1-D with >= 2 samples, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{p}: pulse contains NaN or infinity")
    if max_samples is not None:
        if int(max_samples) < 1:
            raise InputError(f"max_samples: must be >= 1, got {max_samples}")
        arr = arr[:int(max_samples)]
    return arr.astype(np.float64)


PULSE_HELP = ("'lfm-20k' (30->10 kHz, 1 ms), 'lfm-10k', 'lfm-5k' (22.5->17.5 kHz), "
              "'lfm:F0:F1:DUR[:TUKEY]' (Hz, Hz, s, window ratio; default 0.1), "
              "or a measured pulse FILE.npy sampled at fs")


@dataclass(frozen=True)
class Pulse:
    """A transmitted pulse ``samples`` [L] at ``fs`` (Hz) and the spec it came from."""
    samples: np.ndarray
    fs: float
    spec: str


def pulse_from_spec(spec: str | os.PathLike, fs: float = AIRSAS_FS,
                    max_samples: int | None = None) -> Pulse:
    """The pulse for a ``--pulse`` spec (see ``PULSE_HELP``), sampled at ``fs`` Hz.

    A named LFM ('lfm-20k', ...), ``lfm:F0:F1:DUR[:TUKEY]`` or a measured ``.npy`` file;
    ``max_samples`` truncates a measured pulse (the reference keeps the first 100 samples
    of the measured AirSAS pulses). ``fs`` and an LFM's duration are checked against
    :mod:`sonarsim.limits` before any sample is made (one-line InputError), so an absurd
    sample rate is refused, not allocated.
    """
    from . import limits
    limits.check_fs(float(fs))
    text = os.fspath(spec).strip()
    low = text.lower()
    if low in NAMED_PULSES:
        limits.check_pulse_length(round(NAMED_PULSES[low][2] * fs), fs, f"pulse {low}")
        return Pulse(named_pulse(low, fs), float(fs), low)
    if low.startswith("lfm:"):
        parts = text.split(":")[1:]
        if len(parts) not in (3, 4):
            raise InputError(f"pulse '{text}': expected lfm:F0:F1:DUR or lfm:F0:F1:DUR:TUKEY")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise InputError(f"pulse '{text}': F0, F1, DUR (and TUKEY) must be numbers") from None
        f0, f1, dur = values[:3]
        ratio = values[3] if len(values) == 4 else 0.1
        if math.isfinite(dur) and dur > 0:
            limits.check_pulse_length(round(dur * fs), fs, f"pulse {text}")
        return Pulse(lfm(f0, f1, dur, fs, window_ratio=ratio), float(fs), text)
    if low.endswith(".npy"):
        return Pulse(load_pulse(text, max_samples), float(fs), text)
    raise InputError(f"unknown pulse '{text}': expected {PULSE_HELP}")


# --- analytic signal and matched filter ---------------------------------------------------

# Rows per FFT block are chosen so a block holds about this many complex samples; this
# bounds the temporary memory for large [N, T] datasets (output excluded).
_BLOCK_SAMPLES = 1 << 22


def _complex_dtype(arr: np.ndarray) -> type:
    """complex64 for float32/float16 input, complex128 otherwise (precision follows input)."""
    return np.complex64 if arr.dtype in (np.float32, np.float16, np.complex64) else np.complex128


def _fft():
    """scipy.fft, imported on first use: every sonarsim and recon command imports this module
    to build its parser, and scipy.fft costs ~0.2 CPU-s of that start-up."""
    import scipy.fft
    return scipy.fft


def _row_blocks(n_rows: int, n_fft: int):
    step = max(1, _BLOCK_SAMPLES // max(n_fft, 1))
    for start in range(0, n_rows, step):
        yield slice(start, min(start + step, n_rows))


def _positive_weights(n: int, squared: bool = False) -> np.ndarray:
    """rfft-bin weights of the analytic signal: 1 at DC (and Nyquist), 2 elsewhere (or squared)."""
    w = np.full(n // 2 + 1, 4.0 if squared else 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return w


def _positive_to_complex(half: np.ndarray, n: int) -> np.ndarray:
    """Inverse FFT of a spectrum that is ``half`` on bins 0 … n//2 and zero on negative bins."""
    full = np.zeros(half.shape[:-1] + (n,), dtype=half.dtype)
    full[..., :half.shape[-1]] = half
    return _fft().ifft(full, axis=-1)


def analytic(x, axis: int = -1) -> np.ndarray:
    """Analytic signal x + j·H{x}, FFT-based over the length of ``axis``.

    Equal to scipy.signal.hilbert (spectrum weight 1 at DC and Nyquist, 2 on positive,
    0 on negative frequencies), so the record is treated as periodic. complex64 for
    float32 input, complex128 otherwise; computed in blocks of rows to bound memory.
    """
    arr = _signal(x, "signal", axis)
    if np.iscomplexobj(arr):
        raise InputError("signal: analytic() expects a real signal")
    moved = np.moveaxis(arr, axis, -1)
    n = moved.shape[-1]
    rows = moved.reshape(-1, n)
    out = np.empty(rows.shape, dtype=_complex_dtype(arr))
    weights = _positive_weights(n)
    for block in _row_blocks(rows.shape[0], n):
        half = _fft().rfft(rows[block], axis=-1) * weights.astype(out.real.dtype)
        out[block] = _positive_to_complex(half, n)
    return np.moveaxis(out.reshape(moved.shape), -1, axis)


def matched_filter(x, pulse, axis: int = -1, mode: str = "linear") -> np.ndarray:
    """Complex analytic cross-correlation of ``x`` with ``pulse`` (the reference code's matched
    filter, `airsas/reconstruct_airsas_scene.py`; sonarsim's default differs: linear, not circular).

    Output sample k is the correlation at lag k (k = 0 … T−1, T = x.shape[axis]), so an
    echo of the pulse starting at sample d peaks at k = d. The default ``'linear'`` is the one
    pulse compression of the project: pictures (``sonarsim plot``) and reconstructions
    (``recon``) of the same data use it, so they agree.

    - ``mode='circular'`` (the reference, for parity checks): K = FFT(analytic(pulse zero-padded to T)),
      result IFFT(FFT(analytic(x))·conj(K)). Lags wrap around: the tail of an echo that
      starts within L−1 samples of the end leaks into the first samples.
    - ``mode='linear'``: both are zero-padded to T + L − 1 before the same product, and
      lags 0 … T−1 are kept. Nothing wraps; echoes are cut at the end of the record.

    Because both factors are analytic, positive frequencies carry weight 4 and the
    real part is twice the real cross-correlation (DC and Nyquist bins: once).
    complex64 for float32 input, complex128 otherwise; computed in blocks of rows.
    """
    arr = _signal(x, "signal", axis)
    p = _pulse(pulse)
    if np.iscomplexobj(arr) or np.iscomplexobj(p):
        raise InputError("matched_filter expects a real signal and a real pulse")
    n_time = arr.shape[axis]
    if mode == "circular":
        if p.size > n_time:
            raise InputError(f"pulse ({p.size} samples) is longer than the signal ({n_time})")
        n_fft = n_time
    elif mode == "linear":
        n_fft = _fft().next_fast_len(n_time + p.size - 1, real=True)
    else:
        raise InputError(f"mode: expected 'circular' or 'linear', got '{mode}'")
    out_dtype = _complex_dtype(arr)
    kernel = np.conj(_fft().rfft(p.astype(np.float64), n=n_fft)) * _positive_weights(n_fft, True)
    kernel = kernel.astype(out_dtype)
    moved = np.moveaxis(arr, axis, -1)
    rows = moved.reshape(-1, n_time)
    out = np.empty(rows.shape, dtype=out_dtype)
    for block in _row_blocks(rows.shape[0], n_fft):
        half = _fft().rfft(rows[block], n=n_fft, axis=-1) * kernel
        out[block] = _positive_to_complex(half, n_fft)[:, :n_time]
    return np.moveaxis(out.reshape(moved.shape), -1, axis)


# --- delays and resampling ----------------------------------------------------------------

def fractional_delay(x, delay_samples, axis: int = -1) -> np.ndarray:
    """Delay ``x`` by ``delay_samples`` (may be fractional) with an FFT phase ramp.

    y = IFFT(FFT(x)·exp(−j·2π·f·delay)) with f = fftfreq(T) in cycles/sample, i.e. a
    *circular* shift: what leaves the end re-enters at the start. Positive delays move
    the signal later; the AirSAS group-delay correction is ``delay = −62.329317``
    (the reference code's group-delay removal). ``delay_samples`` is a scalar or an array broadcastable
    to x's shape without the time axis (one delay per signal). Real input gives real
    output of the same precision; the Nyquist bin of an even-length real signal cannot
    carry a fractional delay and is scaled by cos(π·delay), so keep that bin empty
    (band-limited signals).
    """
    arr = _signal(x, "signal", axis)
    delay = np.asarray(delay_samples, dtype=np.float64)
    if not np.all(np.isfinite(delay)):
        raise InputError("delay_samples: contains NaN or infinity")
    moved = np.moveaxis(arr, axis, -1)
    try:
        delay = np.broadcast_to(delay, moved.shape[:-1])[..., None]
    except ValueError:
        raise InputError(f"delay_samples: shape {delay.shape} does not match signals "
                         f"{moved.shape[:-1]}") from None
    n = moved.shape[-1]
    ramp_dtype = _complex_dtype(arr)
    if np.iscomplexobj(moved):
        ramp = np.exp(-2j * np.pi * _fft().fftfreq(n) * delay).astype(ramp_dtype)
        out = _fft().ifft(_fft().fft(moved, axis=-1) * ramp, axis=-1)
    else:
        if not np.issubdtype(moved.dtype, np.floating):
            moved = moved.astype(np.float64)
        ramp = np.exp(-2j * np.pi * _fft().rfftfreq(n) * delay).astype(ramp_dtype)
        out = _fft().irfft(_fft().rfft(moved, axis=-1) * ramp, n=n, axis=-1)
    return np.moveaxis(out, -1, axis)


def fft_upsample(x, factor: int, axis: int = -1) -> np.ndarray:
    """Fourier interpolation of ``x`` to ``factor`` times as many samples (scipy.signal.resample).

    Periodic, like every FFT operation here: sample k·factor of the output equals input
    sample k for band-limited signals. Real or complex input.
    """
    arr = _signal(x, "signal", axis)
    if int(factor) != factor or factor < 1:
        raise InputError(f"factor: must be a positive integer, got {factor}")
    factor = int(factor)
    if factor == 1:
        return arr.copy()
    import scipy.signal
    return scipy.signal.resample(arr, arr.shape[axis] * factor, axis=axis)


# --- sound speed --------------------------------------------------------------------------

def _temperature(temp_c) -> np.ndarray:
    t = np.asarray(temp_c, dtype=np.float64)
    if t.size == 0 or not np.all(np.isfinite(t)):
        raise InputError(f"temperature: expected finite °C values, got {temp_c!r}")
    return t


def sound_speed_air(temp_c):
    """Speed of sound in air (m/s) at ``temp_c`` (°C): 331.4 + 0.6·T (reference code ``airsas/reconstruct_airsas_scene.py``)."""
    t = _temperature(temp_c)
    if np.any(t < -100) or np.any(t > 200):
        raise InputError(f"temperature {temp_c!r} °C is outside the plausible range for air")
    c = 331.4 + 0.6 * t
    return float(c) if c.ndim == 0 else c


def sound_speed_water(temp_c):
    """Speed of sound in fresh water (m/s) at ``temp_c`` (°C): 1404.3 + 4.7·T − 0.04·T².

    The SVSS formula (reference code ``svss/``); meant for lake temperatures (0–35 °C).
    """
    t = _temperature(temp_c)
    if np.any(t < -5) or np.any(t > 60):
        raise InputError(f"temperature {temp_c!r} °C is outside the range of the water formula")
    c = 1404.3 + 4.7 * t - 0.04 * t ** 2
    return float(c) if c.ndim == 0 else c


# --- noise --------------------------------------------------------------------------------

def signal_power(s) -> float:
    """Mean of s² over the samples where |s| > 1e-6·max|s| (the SNR signal power).

    Silence (e.g. the part of a waveform before the first echo) does not count, and the
    threshold is relative, so the result scales with the units of s (power·a² for s·a).
    The reference (reference code ``airsas/reconstruct_from_numpy.py``) uses the absolute test s > 1e-6: it drops
    negative samples (harmless for zero-mean echoes) and depends on the units — data
    scaled below 1e-6, as raw transient energies can be, would have no signal at all.
    """
    arr = _signal(s, "signal")
    if np.iscomplexobj(arr):
        raise InputError("signal_power expects a real signal")
    flat = arr.reshape(-1)
    peak = float(np.max(np.abs(flat)))
    if peak == 0:
        raise InputError("signal is all zeros: its power (and an SNR) is undefined")
    threshold = SIGNAL_SUPPORT_FRACTION * peak
    total, count = 0.0, 0
    for block in _row_blocks(flat.size, 1):         # bounded temporaries for large datasets
        mag = np.abs(flat[block].astype(np.float64))
        support = mag > threshold
        total += float(np.dot(mag[support], mag[support]))
        count += int(support.sum())
    return total / count


def noise_sigma(s, snr_db: float) -> float:
    """Standard deviation of white noise that gives ``snr_db`` against ``signal_power(s)``."""
    if not math.isfinite(snr_db):
        raise InputError(f"snr_db: must be finite, got {snr_db}")
    return math.sqrt(signal_power(s) * 10.0 ** (-snr_db / 10.0))


def add_noise(s, snr_db: float, rng: np.random.Generator | int) -> tuple[np.ndarray, float]:
    """Add i.i.d. Gaussian noise at ``snr_db`` (dB); returns (noisy s, sigma).

    sigma² = signal_power(s)·10^(−snr_db/10), with the power over all of ``s`` (all pings
    together, as the reference does). ``rng`` is a numpy Generator or an integer seed;
    the same seed gives the same noise. float32 input gets float32 output (and noise
    drawn in float32, so it differs from the float64 draw of the same seed); anything
    else gives float64.
    """
    arr = _signal(s, "signal")
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        rng = np.random.default_rng(int(rng))
    if not isinstance(rng, np.random.Generator):
        raise InputError("rng: expected a numpy Generator or an integer seed")
    sigma = noise_sigma(arr, snr_db)
    dtype = np.float32 if arr.dtype == np.float32 else np.float64
    noisy = rng.standard_normal(arr.shape, dtype=dtype)     # float32 noise for float32 data
    noisy *= sigma
    noisy += arr
    return noisy, sigma
