"""Timing of the real AirSAS scan: where the direct TX→RX arrival sits (docs/importers.md).

The empty-turntable scan, imported without background subtraction, keeps the direct arrival
from the speaker to the microphone 40 mm away. After the DAQ group delay is removed it peaks
about 12–13 µs *before* the geometric prediction |tx − rx|/c: this pins that measured fact,
so a change in the group-delay handling (sign, units, a sample shift) or in the rig
constants shows up here.
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from sonarsim import signals
from sonarsim.importers.airsas import import_airsas

BACKGROUND = "airsas_real/bg_5k"
UPSAMPLE = 50


def direct_arrival_offset_us(ds) -> float:
    """Peak of the mean matched-filter envelope in the first 40 samples minus |tx−rx|/c (µs)."""
    mf = signals.matched_filter(ds.waveforms.astype(np.float64)[:, :256], ds.pulse)
    env = np.abs(signals.fft_upsample(mf, UPSAMPLE, axis=-1)).mean(axis=0)
    peak_s = np.argmax(env[:40 * UPSAMPLE]) / UPSAMPLE / ds.fs
    predicted_s = float(np.mean(np.linalg.norm(ds.tx - ds.rx, axis=1))) / ds.sound_speed
    return (peak_s - predicted_s) * 1e6


@pytest.mark.parametrize("pulse", ["lfm", "commanded"])
def test_direct_arrival_is_13_us_early(shared_data, pulse):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = import_airsas(shared_data / BACKGROUND, None, pulse=pulse, progress=False)
    offset = direct_arrival_offset_us(ds)
    assert -14.0 < offset < -11.0, offset
    # The offset is 1.2 samples: a group delay applied with the wrong sign would be 1.2 ms off.
    assert abs(offset) < 0.2 * float(ds.meta["group_delay_samples"]) / ds.fs * 1e6
