"""Pictures of transients files: per-bounce images, EXR floats, energy bookkeeping."""
from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from sonarsim.cli import main
from sonarsim.dataset import Transients, Volume
from sonarsim.plot_transients import energy_per_bounce, plot_transients

FS, OVERSAMPLE, C = 100e3, 20, 343.0
W = C / (FS * OVERSAMPLE)


def read_exr(path) -> dict[str, np.ndarray]:
    with OpenEXR.File(str(path)) as f:
        return {name: np.array(ch.pixels) for name, ch in f.channels().items()}


def bump_transients(n_pings=6, n_bins=400, path_start=1.0) -> Transients:
    """Gaussian bumps at a known path length per ping; energy only in bounces 1 and 2."""
    j = np.arange(n_bins)
    data = np.zeros((n_pings, 3, n_bins), dtype=np.float32)
    for i in range(n_pings):
        centre = 100 + 20 * i
        data[i, 0] = np.exp(-0.5 * ((j - centre) / 3.0) ** 2)
        data[i, 1] = 0.1 * np.exp(-0.5 * ((j - centre - 60) / 8.0) ** 2)
    tx = np.tile([0.0, -0.85, 0.1], (n_pings, 1))
    rx = np.tile([0.0, -0.86, 0.07], (n_pings, 1))
    return Transients(transients=data, path_start=path_start, path_bin_width=W,
                      sound_speed=C, fs=FS, oversample=OVERSAMPLE, tx=tx, rx=rx, meta={})


def test_plot_transients_writes_pictures_and_exact_floats(tmp_path):
    tr = bump_transients()
    written = plot_transients(tr, tmp_path)
    names = {p.name for p in written}
    assert {"transients.png", "transients_energy.png", "transients_profiles.png",
            "transients_bounce1.exr", "transients_bounce2.exr",
            "transients_bounce3.exr"} <= names
    for p in written:
        assert p.stat().st_size > 0
    for b in range(3):
        channels = read_exr(tmp_path / f"transients_bounce{b + 1}.exr")
        (values,) = channels.values()
        np.testing.assert_array_equal(values, tr.transients[:, b, :])


def test_energy_per_bounce_matches_the_sums():
    tr = bump_transients()
    energy = energy_per_bounce(tr)
    expected = tr.transients.astype(np.float64).sum(axis=(0, 2))
    np.testing.assert_allclose(energy, expected, rtol=1e-12)
    # Closed form of the Gaussian sums: sqrt(2 pi) sigma per ping (tails are inside the window).
    np.testing.assert_allclose(energy[:2], [6 * np.sqrt(2 * np.pi) * 3.0,
                                            6 * 0.1 * np.sqrt(2 * np.pi) * 8.0], rtol=1e-6)
    assert energy[2] == 0.0


def test_cli_plots_a_transients_file_and_reports_energy(tmp_path, capsys):
    tr = bump_transients()
    tr.write(tmp_path / "t.h5")
    assert main(["plot", str(tmp_path / "t.h5"), "--out", str(tmp_path / "pics")]) == 0
    out = capsys.readouterr().out
    energy = energy_per_bounce(tr)
    share = 100 * energy / energy.sum()
    assert f"bounce 1: energy {energy[0]:.6e} ({share[0]:.2f} %)" in out
    assert "bounce 3: energy 0.000000e+00 (0.00 %)" in out
    assert (tmp_path / "pics" / "transients.png").stat().st_size > 0


def test_cli_refuses_a_volume_with_a_pointer_to_recon_export(tmp_path, capsys):
    vol = Volume(volume=np.ones((2, 2, 2), np.complex64),
                 bounds=np.array([[0, 1], [0, 1], [0, 1]], float), method="test", params={})
    vol.write(tmp_path / "v.h5")
    assert main(["plot", str(tmp_path / "v.h5"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "recon export" in err


def test_bad_profile_pings_are_an_input_error(tmp_path):
    from sonarsim.errors import InputError
    with pytest.raises(InputError, match="profile pings"):
        plot_transients(bump_transients(), tmp_path, pings=[99])
