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


def test_echo_image_uses_the_reconstructions_matched_filter(dataset):
    """A picture and a reconstruction of the same data see the same pulse-compressed signal."""
    from recon.measurements import matched_filtered
    from sonarsim.plot import echo_images

    pictured = echo_images(dataset.waveforms, dataset.pulse)["mf"]
    np.testing.assert_allclose(pictured, np.abs(matched_filtered(dataset)), rtol=1e-5,
                               atol=1e-6 * float(pictured.max()))


# ---- transients -------------------------------------------------------------------------

C_AIR = 343.0
TR_PINGS, TR_BINS, TR_OVERSAMPLE = 5, 400, 20   # bins cover path 1.0 .. 1.0686 m
BUMP_PATHS = 1.02 + 0.004 * np.arange(TR_PINGS)     # bounce-1 peak path length per ping (m)


@pytest.fixture(scope="module")
def transients():
    """Gaussian bumps: bounce 1 at BUMP_PATHS, bounce 2 weaker and later, bounce 3 empty."""
    from sonarsim.dataset import Transients

    width = C_AIR / (FS * TR_OVERSAMPLE)
    paths = 1.0 + (np.arange(TR_BINS) + 0.5) * width
    data = np.zeros((TR_PINGS, 3, TR_BINS), np.float32)
    for i, peak in enumerate(BUMP_PATHS):
        data[i, 0] = (1.0 + i) * np.exp(-0.5 * ((paths - peak) / 0.002) ** 2)
        data[i, 1] = 0.01 * np.exp(-0.5 * ((paths - 1.04) / 0.004) ** 2)
    tx = np.tile([0.8, 0.0, 0.1], (TR_PINGS, 1))
    return Transients(data, 1.0, width, C_AIR, FS, TR_OVERSAMPLE, tx, tx - [0, 0, 0.04])


def test_transients_pictures_keep_the_floats(transients, tmp_path):
    from sonarsim.plot_transients import energy_per_bounce, plot_transients

    written = plot_transients(transients, tmp_path, pings=[0, 4])
    assert {p.name for p in written} == {
        "transients.png", "transients_energy.png", "transients_profiles.png",
        "transients_bounce1.exr", "transients_bounce2.exr", "transients_bounce3.exr"}
    for path in written:
        assert path.stat().st_size > (1000 if path.suffix == ".png" else 0)
    for b in range(3):
        y = _exr(tmp_path / f"transients_bounce{b + 1}.exr")["Y"]
        np.testing.assert_array_equal(y, transients.transients[:, b, :])
    y1 = _exr(tmp_path / "transients_bounce1.exr")["Y"]
    peaks = transients.path_lengths()[np.argmax(y1, axis=1)]
    np.testing.assert_allclose(peaks, BUMP_PATHS, atol=transients.path_bin_width)
    # Gaussian area: amplitude * sigma * sqrt(2 pi) / bin width, summed over pings.
    expected_1 = np.sum(1.0 + np.arange(TR_PINGS)) * 0.002 * np.sqrt(2 * np.pi)
    expected_2 = TR_PINGS * 0.01 * 0.004 * np.sqrt(2 * np.pi)
    energy = energy_per_bounce(transients)
    np.testing.assert_allclose(energy * transients.path_bin_width, [expected_1, expected_2, 0.0],
                               rtol=1e-3)
    np.testing.assert_allclose(energy, transients.transients.astype(np.float64).sum(axis=(0, 2)))
    with pytest.raises(InputError, match="0..4"):
        plot_transients(transients, tmp_path, pings=[5])


def test_max_pool_rows_and_power_db():
    from sonarsim.plot import max_pool_rows

    rows = np.arange(14, dtype=np.float32).reshape(7, 2)[::-1]     # strided view, 7 rows
    np.testing.assert_array_equal(max_pool_rows(rows, 3), [[12, 13], [6, 7], [0, 1]])
    np.testing.assert_allclose(to_db(np.array([4.0, 0.4, 0.0]), 20.0, power=True),
                               [0.0, -10.0, -20.0], atol=1e-5)


def test_cli_plot_transients_prints_energies(transients, tmp_path, capsys):
    from sonarsim.cli import main

    path = tmp_path / "t.h5"
    transients.write(path)
    assert main(["plot", str(path), "--out", str(tmp_path / "pics"), "--pings", "1"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("bounce")]
    printed = [float(ln.split()[3]) for ln in lines]
    sums = transients.transients.astype(np.float64).sum(axis=(0, 2))
    np.testing.assert_allclose(printed, sums, rtol=1e-6)
    assert (tmp_path / "pics" / "transients_bounce2.exr").exists()


def test_cli_plot_dataset_with_transients(dataset, transients, tmp_path, capsys):
    from sonarsim.cli import main

    ds = SonarDataset(waveforms=dataset.waveforms[:TR_PINGS], tx=transients.tx,
                      rx=transients.rx, boresight=-transients.tx, pulse=dataset.pulse, fs=FS,
                      sound_speed=C_AIR, source="test", transients=transients)
    path = tmp_path / "d.h5"
    ds.write(path)
    assert main(["plot", str(path), "--out", str(tmp_path / "pics")]) == 0
    assert "bounce 2: energy" in capsys.readouterr().out
    for name in ("echo_mf.exr", "transients.png", "transients_profiles.png"):
        assert (tmp_path / "pics" / name).stat().st_size > 1000
    np.testing.assert_array_equal(_exr(tmp_path / "pics" / "transients_bounce1.exr")["Y"],
                                  transients.transients[:, 0])


def test_cli_plot_refuses_volumes_and_foreign_files(tmp_path, capsys):
    import h5py

    from sonarsim.cli import main
    from sonarsim.dataset import Volume
    from sonarsim.plot_transients import plot_transients

    vol = tmp_path / "v.h5"
    Volume(np.zeros((2, 2, 2), np.complex64), [[0, 1], [0, 1], [0, 1]], "bp", {}).write(vol)
    assert main(["plot", str(vol), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "recon export" in err and "v.h5" in err
    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f["x"] = np.zeros(3)
    assert main(["plot", str(tmp_path / "foreign.h5"), "--out", str(tmp_path / "x")]) == 2
    assert "not a sonarsim file" in capsys.readouterr().err
    with pytest.raises(InputError, match="Transients"):
        plot_transients(np.zeros((2, 3, 4)), tmp_path)


def test_trajectory_box_is_the_one_the_dataset_records(dataset):
    from dataclasses import replace

    from sonarsim.plot import default_box
    box = [[-0.1, 0.1], [-0.15, 0.15], [0.0, 0.25]]
    recorded = default_box(replace(dataset, meta={"box": box}))
    np.testing.assert_array_equal(recorded.lo, [-0.1, -0.15, 0.0])
    np.testing.assert_array_equal(recorded.hi, [0.1, 0.15, 0.25])
    assert default_box(replace(dataset, meta={})).hi[2] == pytest.approx(0.3)  # SIM_BOX


def test_deconvolved_dataset_is_pictured_as_stored(tmp_path):
    """Complex (deconvolved analytic) waveforms are shown as they are, not filtered again."""
    from sonarsim.plot import echo_images

    rng = np.random.default_rng(0)
    w = (rng.standard_normal((5, 64)) + 1j * rng.standard_normal((5, 64))).astype(np.complex64)
    images = echo_images(w, np.ones(8), max_rows=5)
    np.testing.assert_allclose(images["mf"], np.abs(w), rtol=1e-6)
    np.testing.assert_allclose(images["raw_rows"], np.abs(w), rtol=1e-6)


def test_trajectory_views_keep_true_scale(dataset):
    """Top view (x, y) and side view (distance from the z axis, z), both at equal scale: the
    side view shows the real heights of TX/RX and the box (a 3-D view flattened them)."""
    from sonarsim import geometry
    from sonarsim.plot import _trajectory_figure

    box = geometry.SceneBox(lo=(-0.2, -0.2, 0.0), hi=(0.2, 0.2, 0.3))
    fig = _trajectory_figure(dataset, box)
    ax_top, ax_side = fig.axes
    assert ax_top.name == ax_side.name == "rectilinear"
    assert ax_top.get_aspect() == ax_side.get_aspect() == 1.0
    tx_top, tx_side = ax_top.collections[0].get_offsets(), ax_side.collections[0].get_offsets()
    np.testing.assert_allclose(tx_top, dataset.tx[:, :2])
    np.testing.assert_allclose(tx_side, np.c_[np.hypot(*dataset.tx[:, :2].T), dataset.tx[:, 2]])
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    FigureCanvasAgg(fig).draw()
    z_lo, z_hi = ax_side.get_ylim()
    assert z_lo <= 0.0 and z_hi >= 0.3 and z_hi >= dataset.tx[:, 2].max()
    # equal scale: one metre is as long on screen along z as along the radius
    to_px = ax_side.transData.transform
    (x0, y0), (x1, y1) = to_px([0.0, 0.0]), to_px([0.1, 0.1])
    assert abs((x1 - x0) - (y1 - y0)) < 0.01 * abs(x1 - x0)


def test_bounce_energy_bars_are_linear_shares(transients):
    """The bars are each bounce's share of the total energy on a linear axis."""
    from sonarsim.plot_transients import _energy_figure, energy_per_bounce, energy_per_ping

    fig = _energy_figure(transients, energy_per_ping(transients))
    ax_bars = fig.axes[0]
    assert ax_bars.get_yscale() == "linear"
    heights = np.array([p.get_height() for p in ax_bars.patches])
    e = energy_per_bounce(transients)
    np.testing.assert_allclose(heights, 100 * e / e.sum(), rtol=1e-6)
    assert heights.sum() == pytest.approx(100.0)
