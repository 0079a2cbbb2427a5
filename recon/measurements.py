"""Per-ping quantities shared by the reconstructors: complex measurements and sound speeds.

The complex measurement of a ping is the matched-filtered analytic signal (reference code
``sas_utils.match_filter_all``), computed with :func:`sonarsim.signals.matched_filter` — the one
implementation in the project. Sample k of a dataset waveform is at time
``(start_sample + k) / fs`` after transmission, i.e. at round-trip path ``c·t``.

A dataset written by ``recon deconvolve`` (``waveform_kind == 'deconvolved_analytic'``)
already holds complex, pulse-compressed analytic signals: :func:`matched_filtered`,
:func:`analytic_waveforms` and :func:`complex_signals` return them unchanged (no second
matched filter), so every solver reads both kinds of dataset.
"""
from __future__ import annotations

import numpy as np

from sonarsim.errors import InputError


def check_dataset(dataset) -> None:
    """Raise :class:`InputError` if a dataset cannot be reconstructed (no pings, bad values)."""
    w = np.asarray(dataset.waveforms)
    if w.ndim != 2 or w.shape[0] == 0 or w.shape[1] == 0:
        raise InputError(f"dataset waveforms: need at least one ping and one sample, got shape {w.shape}")
    for name in ("tx", "rx"):
        a = np.asarray(getattr(dataset, name))
        if a.shape != (w.shape[0], 3):
            raise InputError(f"dataset pings/{name}: expected shape {(w.shape[0], 3)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"dataset pings/{name}: contains NaN or infinity")
    if not (np.isfinite(dataset.fs) and dataset.fs > 0):
        raise InputError(f"dataset fs: must be positive, got {dataset.fs}")
    if not (np.isfinite(dataset.sound_speed) and dataset.sound_speed > 0):
        raise InputError(f"dataset sound_speed: must be positive, got {dataset.sound_speed}")


def sound_speeds(dataset, per_ping: bool = True) -> np.ndarray:
    """Sound speed per ping [N] (m/s).

    With ``per_ping`` and per-ping temperatures in the dataset, each ping gets
    ``sonarsim.signals.sound_speed_air(T_i)``; otherwise every ping gets ``dataset.sound_speed``.
    """
    n = len(dataset.waveforms)
    temps = getattr(dataset, "temperatures", None)
    if per_ping and temps is not None and len(temps) == n and np.all(np.isfinite(temps)):
        from sonarsim import signals
        return np.asarray(signals.sound_speed_air(np.asarray(temps, dtype=np.float64)),
                          dtype=np.float64).reshape(n)
    return np.full(n, float(dataset.sound_speed))


DECONVOLVED = "deconvolved_analytic"


def is_deconvolved(dataset) -> bool:
    """True if the dataset's waveforms are deconvolved analytic signals (``recon deconvolve``)."""
    return getattr(dataset, "waveform_kind", "real") == DECONVOLVED


def _stored(dataset, pings) -> np.ndarray:
    w = dataset.waveforms if pings is None else dataset.waveforms[pings]
    return np.asarray(w, dtype=np.complex64)


def complex_signals(dataset, pings=None) -> np.ndarray:
    """The complex measurement [n, T] complex64 a solver fits: the stored deconvolved analytic
    signal for a deconvolved dataset, else the matched-filtered analytic signal."""
    return matched_filtered(dataset, pings)


def matched_filtered(dataset, pings=None) -> np.ndarray:
    """Matched-filtered analytic signal [n, T] complex64 of the selected pings (all by default).

    Uses the *linear* (zero-padded) correlation rather than the reference's circular one,
    so echoes near the end of the cropped window do not wrap onto its start. A deconvolved
    dataset's waveforms are already pulse-compressed and are returned as stored.
    """
    from sonarsim import signals
    if is_deconvolved(dataset):
        return _stored(dataset, pings)
    w = np.asarray(dataset.waveforms if pings is None else dataset.waveforms[pings],
                   dtype=np.float64)
    mf = signals.matched_filter(w, np.asarray(dataset.pulse, dtype=np.float64), axis=-1,
                                mode="linear")
    return np.asarray(mf, dtype=np.complex64)


def analytic_waveforms(dataset, pings=None) -> np.ndarray:
    """Analytic signal of the raw waveforms [n, T] complex64 (no pulse compression); a
    deconvolved dataset's waveforms are already analytic and are returned as stored."""
    from sonarsim import signals
    if is_deconvolved(dataset):
        return _stored(dataset, pings)
    w = np.asarray(dataset.waveforms if pings is None else dataset.waveforms[pings],
                   dtype=np.float64)
    return np.asarray(signals.analytic(w, axis=-1), dtype=np.complex64)
