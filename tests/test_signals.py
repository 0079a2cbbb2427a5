"""Closed-form checks of sonarsim.signals (pulses, analytic signal, matched filter, noise)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from sonarsim import signals
from sonarsim.errors import FormatError, InputError

FS = 100e3


def instantaneous_frequency(pulse: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, Hz) from the unwrapped phase of the analytic signal (pulse zero-padded)."""
    a = signals.analytic(np.concatenate([pulse, np.zeros(pulse.size)]))[:pulse.size]
    freq = np.diff(np.unwrap(np.angle(a))) * fs / (2 * np.pi)
    return (np.arange(freq.size) + 0.5) / fs, freq


def tukey_continuous(t: np.ndarray, duration: float, ratio: float) -> np.ndarray:
    """Tukey window evaluated at continuous times t (0 outside [0, duration])."""
    taper = ratio * duration / 2
    w = np.ones_like(t)
    rise, fall = t < taper, t > duration - taper
    w[rise] = 0.5 * (1 - np.cos(np.pi * t[rise] / taper))
    w[fall] = 0.5 * (1 - np.cos(np.pi * (duration - t[fall]) / taper))
    w[(t < 0) | (t > duration)] = 0
    return w


def test_long_lfm_sweeps_linearly():
    dur = 10e-3                       # time-bandwidth 200: the analytic phase is clean
    t, f = instantaneous_frequency(signals.lfm(30e3, 10e3, dur, FS), FS)
    mid = slice(int(0.1 * f.size), int(0.9 * f.size))
    expected = 30e3 + (10e3 - 30e3) * t / dur
    assert np.max(np.abs(f[mid] - expected[mid])) < 5.0


@pytest.mark.parametrize("name,f0,f1", [("lfm-20k", 30e3, 10e3), ("lfm-10k", 25e3, 15e3),
                                        ("lfm-5k", 22.5e3, 17.5e3)])
def test_named_pulses_match_reference_sweeps(name, f0, f1):
    pulse = signals.named_pulse(name, FS)
    assert pulse.shape == (100,)
    t, f = instantaneous_frequency(pulse, FS)
    mid = slice(int(0.15 * f.size), int(0.85 * f.size))
    slope, intercept = np.polyfit(t[mid], f[mid], 1)
    # A 1 ms pulse has a short time-bandwidth product: allow 2 % of the band for ringing.
    tol = 0.02 * abs(f1 - f0) + 100.0
    assert abs(intercept - f0) < tol
    assert abs(intercept + slope * 1e-3 - f1) < tol


def test_lfm_equals_reference_construction():
    # reference code sas_utils.gen_real_lfm: chirp on t = linspace(0, T - 1/fs, T·fs), times tukey(L, 0.1).
    n = 100
    t = np.linspace(0, 1e-3 - 1 / FS, n)
    expected = scipy.signal.chirp(t, 30e3, 1e-3, 10e3) * scipy.signal.windows.tukey(n, 0.1)
    np.testing.assert_allclose(signals.named_pulse("lfm-20k", FS), expected, atol=1e-12)


def test_analytic_of_cosine_is_complex_exponential():
    n, m = 512, 37
    omega = 2 * np.pi * m / n
    k = np.arange(n)
    np.testing.assert_allclose(signals.analytic(np.cos(omega * k + 0.3)),
                               np.exp(1j * (omega * k + 0.3)), atol=1e-12)


def test_matched_filter_peaks_at_fractional_delay():
    delay = 123.37                                  # samples
    n, dur = 1000, 1e-3
    pulse = signals.named_pulse("lfm-20k", FS)
    t = np.arange(n) / FS - delay / FS              # continuous-time echo, no resampling code
    echo = scipy.signal.chirp(t, 30e3, dur, 10e3) * tukey_continuous(t, dur, 0.1)
    for mode in ("circular", "linear"):
        mf = signals.matched_filter(echo, pulse, mode=mode)
        assert mf.dtype == np.complex128 and mf.shape == (n,)
        fine = signals.fft_upsample(mf, 20)
        assert abs(np.argmax(np.abs(fine)) / 20 - delay) <= 0.1


def test_matched_filter_real_part_is_twice_circular_correlation():
    rng = np.random.default_rng(1)
    n = 301                                         # odd: no Nyquist bin
    x, p = rng.standard_normal(n), rng.standard_normal(40)
    padded = np.zeros(n)
    padded[:40] = p
    corr = np.array([np.dot(np.roll(x, -k), padded) for k in range(n)])
    expected = 2 * corr - x.sum() * p.sum() / n     # DC bin carries weight 1, not 2
    np.testing.assert_allclose(signals.matched_filter(x, p, mode="circular").real, expected,
                               atol=1e-10)


def test_matched_filter_default_is_the_linear_one_used_everywhere():
    rng = np.random.default_rng(3)
    x, p = rng.standard_normal((3, 200)), rng.standard_normal(30)
    np.testing.assert_array_equal(signals.matched_filter(x, p), signals.matched_filter(x, p, mode="linear"))
    assert not np.allclose(signals.matched_filter(x, p), signals.matched_filter(x, p, mode="circular"))


def test_matched_filter_linear_mode_does_not_wrap():
    pulse = signals.named_pulse("lfm-20k", FS)
    x = np.zeros(600)
    x[:100] = pulse                                  # echo at lag 0
    circ = np.abs(signals.matched_filter(x, pulse, mode="circular"))
    lin = np.abs(signals.matched_filter(x, pulse, mode="linear"))
    assert circ[0] == pytest.approx(lin[0], rel=1e-3)
    # Negative lags wrap to the end of the circular result only.
    assert circ[-3] > 0.3 * circ[0]
    assert lin[-50:].max() < 0.02 * lin[0]


def test_matched_filter_axis_and_batches():
    pulse = signals.named_pulse("lfm-5k", FS)
    rng = np.random.default_rng(2)
    x = rng.standard_normal((3, 400))
    batched = signals.matched_filter(x.T, pulse, axis=0)
    for i in range(3):
        np.testing.assert_allclose(batched[:, i], signals.matched_filter(x[i], pulse), atol=1e-9)


def test_fractional_delay_of_cosine():
    n, m, d = 256, 11, 7.3
    k = np.arange(n)
    x = np.cos(2 * np.pi * m * k / n)
    np.testing.assert_allclose(signals.fractional_delay(x, d),
                               np.cos(2 * np.pi * m * (k - d) / n), atol=1e-12)
    z = np.exp(2j * np.pi * m * k / n)
    np.testing.assert_allclose(signals.fractional_delay(z, d),
                               np.exp(2j * np.pi * m * (k - d) / n), atol=1e-12)


def test_group_delay_round_trip_and_per_ping_delays():
    rng = np.random.default_rng(3)
    # Band-limited pings (Nyquist bin empty): delaying then un-delaying is exact.
    pings = signals.fft_upsample(rng.standard_normal((4, 250)), 4)
    gd = signals.AIRSAS_GROUP_DELAY_SAMPLES
    corrected = signals.fractional_delay(pings, -gd)
    np.testing.assert_allclose(signals.fractional_delay(corrected, gd), pings, atol=1e-10)
    delays = np.array([0.0, 1.0, 2.5, -3.25])
    shifted = signals.fractional_delay(pings, delays)
    np.testing.assert_allclose(shifted[1], np.roll(pings[1], 1), atol=1e-10)
    np.testing.assert_allclose(shifted[3], signals.fractional_delay(pings[3], -3.25), atol=1e-12)


def test_fft_upsample_keeps_samples_of_bandlimited_signal():
    n = 128
    k = np.arange(n)
    x = np.sin(2 * np.pi * 5 * k / n) + 0.5 * np.cos(2 * np.pi * 9 * k / n)
    up = signals.fft_upsample(x, 5)
    fine = np.arange(5 * n) / 5
    np.testing.assert_allclose(up, np.sin(2 * np.pi * 5 * fine / n)
                               + 0.5 * np.cos(2 * np.pi * 9 * fine / n), atol=1e-12)


def test_sound_speeds():
    assert signals.sound_speed_air(0.0) == pytest.approx(331.4)
    assert signals.sound_speed_air(21.6) == pytest.approx(344.36)
    np.testing.assert_allclose(signals.sound_speed_air(np.array([10.0, 20.0])), [337.4, 343.4])
    assert signals.sound_speed_water(10.0) == pytest.approx(1404.3 + 47 - 4)
    t_f55 = (55 - 32) * 0.5556                        # SVSS default, reference code svss/
    assert 1450 < signals.sound_speed_water(t_f55) < 1460
    with pytest.raises(InputError):
        signals.sound_speed_air(float("nan"))


def bursts(n: int = 200_000) -> np.ndarray:
    """A zero-mean tone burst train with silent gaps (whole periods, no sample at a zero)."""
    k = np.arange(n)
    s = np.sin(2 * np.pi * (k + 0.25) / 50)
    s[(k // 10_000) % 2 == 1] = 0                     # every other 10 000 samples silent
    return s


def test_signal_power_ignores_silence_and_units():
    s = bursts()
    assert signals.signal_power(s) == pytest.approx(0.5, rel=1e-9)    # sin² over the bursts
    tiny = 1e-9 * s                                    # the reference's s > 1e-6 finds nothing here
    assert signals.signal_power(tiny) == pytest.approx(0.5e-18, rel=1e-9)


@pytest.mark.parametrize("snr_db", [-5.0, 0.0, 10.0, 20.0, 40.0])
def test_noise_has_requested_snr(snr_db):
    s = bursts()
    noisy, sigma = signals.add_noise(s, snr_db, np.random.default_rng(int(snr_db) + 10))
    noise = noisy - s
    measured = 10 * np.log10(signals.signal_power(s) / np.mean(noise ** 2))
    assert measured == pytest.approx(snr_db, abs=0.3)
    assert sigma ** 2 == pytest.approx(0.5 * 10 ** (-snr_db / 10), rel=1e-9)


def test_noise_is_reproducible_and_keeps_dtype():
    s = bursts(10_000).astype(np.float32)
    a, _ = signals.add_noise(s, 10.0, 7)
    b, _ = signals.add_noise(s, 10.0, np.random.default_rng(7))
    c, _ = signals.add_noise(s, 10.0, 8)
    assert a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_load_pulse(tmp_path, shared_data):
    path = shared_data / "pulses" / "airsas_20khz_measured.npy"
    full = signals.load_pulse(path)
    first = signals.load_pulse(path, max_samples=100)
    assert full.ndim == 1 and full.size > 100 and first.shape == (100,)
    np.testing.assert_array_equal(first, full[:100])
    assert np.all(np.isfinite(full))


def test_pulse_file_errors(tmp_path):
    with pytest.raises(FormatError, match="nope.npy"):
        signals.load_pulse(tmp_path / "nope.npy")
    bad = tmp_path / "bad.npy"
    np.save(bad, np.ones((3, 4)))
    with pytest.raises(InputError, match="bad.npy"):
        signals.load_pulse(bad)
    nan = tmp_path / "nan.npy"
    np.save(nan, np.array([0.0, np.nan, 1.0]))
    with pytest.raises(InputError, match="nan.npy"):
        signals.load_pulse(nan)
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not numpy")
    with pytest.raises(FormatError, match="junk.npy"):
        signals.load_pulse(junk)
    with pytest.raises(InputError, match="unknown pulse"):
        signals.named_pulse("lfm-7k")


@pytest.mark.parametrize("call", [
    lambda: signals.analytic(np.array([])),
    lambda: signals.analytic(np.array([1.0, np.nan])),
    lambda: signals.analytic(np.float64(1.0)),
    lambda: signals.matched_filter(np.ones(10), np.ones((2, 3))),
    lambda: signals.matched_filter(np.ones(10), np.ones(20), mode="circular"),
    lambda: signals.matched_filter(np.ones(10), np.ones(3), mode="fast"),
    lambda: signals.lfm(30e3, 10e3, 1e-3, 0.0),
    lambda: signals.lfm(30e3, 10e3, 1e-3, float("nan")),
    lambda: signals.lfm(60e3, 10e3, 1e-3, 100e3),
    lambda: signals.fractional_delay(np.ones((2, 8)), [1.0, 2.0, 3.0]),
    lambda: signals.fft_upsample(np.ones(8), 0),
    lambda: signals.add_noise(np.zeros(8), 10.0, 0),
    lambda: signals.add_noise(np.ones(8), float("nan"), 0),
    lambda: signals.add_noise(np.ones(8), 10.0, None),
])
def test_bad_inputs_raise_input_error(call):
    with pytest.raises(InputError):
        call()


@pytest.mark.parametrize("n", [255, 256])
def test_analytic_equals_scipy_hilbert_and_keeps_precision(n):
    rng = np.random.default_rng(4)
    x = rng.standard_normal((n, 3))
    np.testing.assert_allclose(signals.analytic(x, axis=0), scipy.signal.hilbert(x, axis=0),
                               atol=1e-12)
    single = signals.analytic(x.astype(np.float32), axis=0)
    assert single.dtype == np.complex64
    np.testing.assert_allclose(single, scipy.signal.hilbert(x, axis=0), atol=1e-4)


def test_blocked_processing_matches_single_block(monkeypatch):
    rng = np.random.default_rng(5)
    x = rng.standard_normal((37, 300)).astype(np.float32)
    pulse = signals.named_pulse("lfm-20k", FS)
    whole = signals.matched_filter(x, pulse)
    whole_power = signals.signal_power(x)
    monkeypatch.setattr(signals, "_BLOCK_SAMPLES", 1000)   # forces blocks of 3 rows
    blocked = signals.matched_filter(x, pulse)
    assert blocked.dtype == np.complex64
    np.testing.assert_allclose(blocked, whole, atol=1e-5)
    np.testing.assert_allclose(signals.analytic(x), signals.analytic(x.astype(np.float64)),
                               atol=1e-4)
    assert signals.signal_power(x) == pytest.approx(whole_power, rel=1e-12)
