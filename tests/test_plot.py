"""sonarsim.plot / ``sonarsim plot``: files are written and the EXR floats are the data."""
from __future__ import annotations

import numpy as np
import OpenEXR
import pytest
import scipy.signal

from sonarsim.dataset import SonarDataset
from sonarsim.errors import InputError
from sonarsim.plot import plot_dataset, to_db

FS = 100e3
N_PINGS, N_SAMPLES = 8, 300
DELAYS = 40 + 17 * np.arange(N_PINGS)       # echo start sample of each ping


def _pulse() -> np.ndarray:
    t = np.arange(100) / FS
    return scipy.signal.chirp(t, 30e3, 1e-3, 10e3) * scipy.signal.windows.tukey(100, 0.1)


@pytest.fixture(scope="module")
def dataset() -> SonarDataset:
    pulse = _pulse()
    waveforms = np.zeros((N_PINGS, N_SAMPLES))
    for i, d in enumerate(DELAYS):
        waveforms[i, d:d + pulse.size] = (1.0 + 0.1 * i) * pulse
    angles = np.deg2rad(np.arange(N_PINGS) * 45.0)
    tx = np.stack([0.85 * np.cos(angles), 0.85 * np.sin(angles), np.full(N_PINGS, 0.1)], 1)
    rx = tx - [0, 0, 0.04]
    return SonarDataset(waveforms=waveforms, tx=tx, rx=rx, boresight=-tx, pulse=pulse, fs=FS,
                        sound_speed=343.0, source="test", start_sample=100)


def _exr(path) -> dict[str, np.ndarray]:
    with OpenEXR.File(str(path)) as f:
        return {name: np.array(ch.pixels) for name, ch in f.channels().items()}


def test_writes_png_and_exr_with_the_data(dataset, tmp_path):
    written = plot_dataset(dataset, tmp_path / "out", complex_exr=True)
    names = {p.name for p in written}
    assert names == {"echo_raw.png", "echo_raw.exr", "echo_mf.png", "echo_mf.exr",
                     "pulse.png", "trajectory.png"}
    for path in written:
        assert path.stat().st_size > 1000
        if path.suffix == ".png":
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    raw = _exr(tmp_path / "out" / "echo_raw.exr")
    np.testing.assert_array_equal(raw["Y"], dataset.waveforms)
    mf = _exr(tmp_path / "out" / "echo_mf.exr")
    assert mf["Y"].shape == (N_PINGS, N_SAMPLES)
    np.testing.assert_allclose(mf["Y"], np.hypot(mf["re"], mf["im"]), rtol=1e-5)
    # An echo starting at sample d correlates best with the pulse at lag d.
    np.testing.assert_array_equal(np.argmax(mf["Y"], axis=1), DELAYS)
    # Echo energy: the matched-filter peak is 2·(scale)·Σp² (both factors analytic, §1.6).
    energy = np.sum(_pulse() ** 2)
    np.testing.assert_allclose(mf["Y"].max(axis=1), 2 * (1 + 0.1 * np.arange(N_PINGS)) * energy,
                               rtol=0.02)


def test_to_db_closed_form():
    np.testing.assert_allclose(to_db(np.array([2.0, 0.2, 0.002, 0.0]), 40.0),
                               [0.0, -20.0, -40.0, -40.0], atol=1e-5)
    with pytest.raises(InputError):
        plot_dataset(None, "unused", dynamic_range_db=0.0)


def test_cli_plot(dataset, tmp_path, capsys):
    from sonarsim.cli import main

    path = tmp_path / "d.h5"
    dataset.write(path)
    assert main(["plot", str(path), "--out", str(tmp_path / "pics"), "--dynamic-range", "40",
                 "--box", "-0.2", "0.2", "-0.2", "0.2", "0", "0.3"]) == 0
    assert (tmp_path / "pics" / "trajectory.png").stat().st_size > 1000
    assert set(_exr(tmp_path / "pics" / "echo_mf.exr")) == {"Y"}
    assert main(["plot", str(tmp_path / "absent.h5"), "--out", str(tmp_path / "x")]) == 2
    assert "absent.h5" in capsys.readouterr().err


def test_png_rows_are_max_pooled_over_ping_groups(dataset):
    from sonarsim.plot import echo_images

    full = echo_images(dataset.waveforms, dataset.pulse, max_rows=N_PINGS)
    pooled = echo_images(dataset.waveforms, dataset.pulse, max_rows=3)
    assert pooled["group"] == 3 and pooled["mf_rows"].shape == (3, N_SAMPLES)
    for r, rows in enumerate((slice(0, 3), slice(3, 6), slice(6, 8))):
        np.testing.assert_array_equal(pooled["mf_rows"][r], full["mf"][rows].max(axis=0))
        np.testing.assert_array_equal(pooled["raw_rows"][r], full["raw_rows"][rows].max(axis=0))
