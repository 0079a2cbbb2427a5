"""openSTB interoperability (issue 24, item 7): sonarsim ↔ openSTB's Zarr baseband pressure.

* sonarsim → openSTB → sonarsim keeps waveforms, poses, pulse and timing (exactly at the
  full rate, within the band at a decimated one) and a point target backprojects to its place;
* a result written the way openSTB's ``simple_points`` controller writes it (simulated here
  from openSTB's documented model, independently of the importer) with its configuration
  TOML imports with the right geometry and timing: every echo's matched-filter peak is at the
  round-trip time of the configured geometry, and the point backprojects to its place.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

zarr = pytest.importorskip("zarr")

from recon import synthetic                                   # noqa: E402
from recon.backprojection import backproject                   # noqa: E402
from recon.grid import Grid                                    # noqa: E402
from sonarsim import signals                                   # noqa: E402
from sonarsim.cli import main as sonarsim_main                 # noqa: E402
from sonarsim.errors import FormatError, InputError            # noqa: E402
from sonarsim.importers.openstb import read_openstb, write_openstb   # noqa: E402

POINT = [0.01, -0.02, 0.09]


@pytest.fixture(scope="module")
def point_ds():
    return synthetic.point_dataset([POINT], n_pings=36, heights=(0.05, 0.15),
                                   scene_box=[[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]])


def _peak(volume, grid):
    idx = np.unravel_index(np.argmax(np.abs(volume)), volume.shape)
    return np.array([ax[i] for ax, i in zip(grid.axes(), idx)])


def test_round_trip_at_full_rate_is_exact(point_ds, tmp_path):
    point_ds = synthetic.point_dataset([POINT], n_pings=36, heights=(0.05, 0.15),
                                       scene_box=point_ds.meta["box"])
    point_ds.temperatures = np.linspace(19.0, 21.0, point_ds.n_pings)   # per-ping sound speed
    out = write_openstb(point_ds, tmp_path / "r.zarr")
    root = zarr.open_group(str(out), mode="r")                 # openSTB's documented layout
    n, t = point_ds.waveforms.shape
    assert root["pressure"].shape == (n, 1, t) and root["pressure"].dtype == np.complex64
    times = root["sample_time"][...]
    assert np.allclose(times, (point_ds.start_sample + np.arange(t)) / point_ds.fs)
    assert root["ping_start_time"].shape == (n,) and np.all(np.diff(root["ping_start_time"][...]) > 0)
    f_bb, rate = root.attrs["baseband_frequency"], root.attrs["sample_rate"]
    assert rate == point_ds.fs and 15e3 < f_bb < 25e3         # the 20 kHz LFM's centre
    # openSTB's convention: real pressure = Re(pressure · exp(+j2π f_bb t))
    real = (root["pressure"][:, 0, :] * np.exp(2j * np.pi * f_bb * times)).real
    np.testing.assert_allclose(real, point_ds.waveforms, atol=1e-6 * np.abs(point_ds.waveforms).max())
    back = read_openstb(out)
    np.testing.assert_allclose(back.waveforms, point_ds.waveforms,
                               atol=1e-6 * np.abs(point_ds.waveforms).max())
    for name in ("tx", "rx", "boresight", "pulse", "temperatures"):
        np.testing.assert_array_equal(getattr(back, name), getattr(point_ds, name))
    assert (back.fs, back.start_sample, back.sound_speed) == \
        (point_ds.fs, point_ds.start_sample, point_ds.sound_speed)
    assert back.meta["box"] == point_ds.meta["box"] == [[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]]


def test_decimated_round_trip_keeps_the_band_and_the_point(point_ds, tmp_path):
    out = write_openstb(point_ds, tmp_path / "r.zarr", sample_rate=point_ds.fs / 2)
    assert zarr.open_group(str(out), mode="r")["pressure"].shape[2] == \
        math.ceil(point_ds.waveforms.shape[1] / 2)
    back = read_openstb(out)
    n_t = point_ds.waveforms.shape[1]
    mf = lambda w: np.abs(signals.matched_filter(w[:, :n_t], point_ds.pulse))  # noqa: E731
    a, b = mf(point_ds.waveforms), mf(back.waveforms)
    assert np.abs(a - b).max() < 0.02 * a.max()               # the pulse's band survives
    grid = Grid([[-0.03, 0.05], [-0.06, 0.02], [0.09, 0.09]], (41, 41, 1))
    peak = _peak(backproject(back, grid, progress=False), grid)
    assert np.linalg.norm(peak[:2] - POINT[:2]) <= 0.0021      # one voxel (2 mm)


def test_a_band_that_does_not_fit_the_sample_rate_is_refused(point_ds, tmp_path):
    with pytest.raises(InputError, match="does not fit in"):
        write_openstb(point_ds, tmp_path / "r.zarr", sample_rate=point_ds.fs / 8)
    with pytest.raises(InputError, match="divided by a whole number"):
        write_openstb(point_ds, tmp_path / "r.zarr", sample_rate=0.3 * point_ds.fs)
    assert not (tmp_path / "r.zarr").exists()


# ----------------------------------------------- a result as openSTB writes it, + its config

C = 1500.0
F0, F1, DURATION, ALPHA, SPL = 8e3, 12e3, 2e-3, 0.2, 190.0
F_BB, RATE = 10e3, 6e3
START, END, SPEED, INTERVAL = np.array([0.0, 0.0, 0.0]), np.array([1.6, 1.2, 0.0]), 1.0, 0.02
TX_OFFSET = np.array([0.0, 0.3, 0.1])
RX_OFFSETS = np.array([[-0.05, 0.3, 0.0], [0.05, 0.3, 0.0]])
Q_PORT = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]   # boresight: vehicle +y
TARGET = np.array([0.9, 3.2, 0.1])

CONFIG = f"""
[controller]
plugin = "simple_points"
result_filename = "result.zarr"
points_per_chunk = 100
sample_rate = {RATE}
baseband_frequency = {F_BB}

[system]
plugin = "generic"

[system.transmitter]
plugin = "generic"
position = {TX_OFFSET.tolist()}
orientation = {Q_PORT}

[system.signal]
plugin = "lfm_chirp"
f_start = {F0}
f_stop = {F1}
duration = {DURATION}
rms_spl = {SPL}
window = {{plugin = "tukey", alpha = {ALPHA}}}

[[system.receivers]]
plugin = "generic"
position = {RX_OFFSETS[0].tolist()}
orientation = {Q_PORT}

[[system.receivers]]
plugin = "generic"
position = {RX_OFFSETS[1].tolist()}
orientation = {Q_PORT}

[trajectory]
plugin = "linear"
start_position = {START.tolist()}
end_position = {END.tolist()}
speed = {SPEED}

[ping_times]
plugin = "constant_interval"
interval = {INTERVAL}

[environment]
plugin = "invariant"
sound_speed = {C}
salinity = 35
temperature = 10

[[targets]]
plugin = "single_point"
position = {TARGET.tolist()}
reflectivity = 1

[travel_time]
plugin = "stop_and_hop"
"""


def _geometry(ping_times):
    """Transmitter [P, 3] and receivers [P, 2, 3] by openSTB's definitions, written out:
    the vehicle moves along the track, its x axis turned onto the track (a rotation about z
    here, the track being horizontal), transducers at fixed offsets in the vehicle frame."""
    track = END - START
    heading = math.atan2(track[1], track[0])
    rot = np.array([[math.cos(heading), -math.sin(heading), 0.0],
                    [math.sin(heading), math.cos(heading), 0.0], [0.0, 0.0, 1.0]])
    vehicle = START + ping_times[:, None] * SPEED * track / np.linalg.norm(track)
    return vehicle + TX_OFFSET @ rot.T, vehicle[:, None, :] + RX_OFFSETS @ rot.T, rot


def _baseband_chirp(t):
    """openSTB's Tukey-windowed LFM in the baseband, unit RMS (the level cancels below)."""
    k = (F1 - F0) / DURATION
    s = np.exp(1j * np.pi * t * (2 * (F0 - F_BB) + k * t))
    taper = DURATION * ALPHA / 2
    w = np.where(t < taper, 0.5 * (1 + np.cos(np.pi * (t / taper - 1))), 1.0)
    w = np.where(t > DURATION - taper, 0.5 * (1 + np.cos(np.pi * (t - DURATION + taper) / taper)), w)
    return np.where((t >= 0) & (t <= DURATION), s * w, 0)


@pytest.fixture(scope="module")
def openstb_result(tmp_path_factory):
    """(result dir, config path, ping times, τ [P, 2]): a point target, stop and hop."""
    base = tmp_path_factory.mktemp("openstb")
    (base / "sim.toml").write_text(CONFIG)
    ping_t = np.arange(0.0, np.linalg.norm(END - START) / SPEED + 1e-9, INTERVAL)
    tx, rx, _ = _geometry(ping_t)
    tau = (np.linalg.norm(TARGET - tx, axis=1)[:, None] + np.linalg.norm(TARGET - rx, axis=2)) / C
    n_s = int(math.ceil(1.5 * tau.max() * RATE))
    t = np.arange(n_s) / RATE
    pressure = _baseband_chirp(t[None, None, :] - tau[..., None]) \
        * np.exp(-2j * np.pi * F_BB * tau[..., None])
    root = zarr.open_group(str(base / "result.zarr"), mode="w")
    root.create_array("pressure", data=pressure.astype(np.complex128), chunks=(1, 1, n_s))
    root.create_array("sample_time", data=t)
    root.create_array("ping_start_time", data=ping_t)
    root.attrs["baseband_frequency"] = F_BB
    root.attrs["sample_rate"] = RATE
    return base / "result.zarr", base / "sim.toml", ping_t, tau


def test_openstb_result_imports_with_its_configured_geometry(openstb_result):
    result, config, ping_t, tau = openstb_result
    with pytest.raises(InputError, match="do not store where the sonar was; give the "
                                         "simulation's configuration with --config"):
        read_openstb(result)
    ds = read_openstb(result, config=config)
    n_p = len(ping_t)
    assert ds.waveforms.shape[0] == 2 * n_p and ds.sound_speed == C and ds.source == "openstb"
    assert ds.fs == RATE * math.ceil(2.5 * (F_BB + RATE / 2) / RATE)
    tx, rx, rot = _geometry(ping_t)
    np.testing.assert_allclose(ds.tx, np.repeat(tx, 2, axis=0), atol=1e-12)
    np.testing.assert_allclose(ds.rx, rx.reshape(-1, 3), atol=1e-12)
    np.testing.assert_allclose(ds.boresight, np.tile(rot @ [0.0, 1.0, 0.0], (2 * n_p, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(ds.rx_boresight, ds.boresight, atol=1e-12)
    assert ds.meta["amplitude_model"] == "pressure"
    assert ds.meta["openstb_ping_times"] == pytest.approx({"first": 0.0, "interval": INTERVAL})
    # the pulse: openSTB's chirp at the output rate, in Pa (RMS = the configured SPL)
    assert len(ds.pulse) == int(DURATION * ds.fs) + 1
    assert np.sqrt(2 * np.mean(ds.pulse ** 2)) == pytest.approx(10 ** (SPL / 20) * 1e-6, rel=0.02)
    # every echo's matched-filter peak is at its round-trip time
    mf = np.abs(signals.matched_filter(ds.waveforms, ds.pulse))
    k = np.argmax(mf, axis=1)
    peak_t = (ds.start_sample + k) / ds.fs
    assert np.abs(peak_t - tau.reshape(-1)).max() <= 1.0 / ds.fs


def test_openstb_point_backprojects_to_its_place(openstb_result, tmp_path, capsys):
    result, config, _, _ = openstb_result
    out = tmp_path / "d.h5"
    assert sonarsim_main(["import-openstb", str(result), "--config", str(config),
                          "--out", str(out), "--box", "0.3", "1.5", "2.6", "3.8", "0", "0.2"]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {out}: ")
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(out)
    assert ds.meta["box"] == [[0.3, 1.5], [2.6, 3.8], [0.0, 0.2]]
    grid = Grid([[0.3, 1.5], [2.6, 3.8], [TARGET[2], TARGET[2]]], (49, 49, 1))
    peak = _peak(backproject(ds, grid, progress=False), grid)
    assert np.linalg.norm(peak[:2] - TARGET[:2]) <= 0.025 * math.sqrt(2) + 1e-9   # one voxel


def test_cli_round_trip_and_refusals(point_ds, tmp_path, capsys):
    d = tmp_path / "d.h5"
    point_ds.write(d)
    assert sonarsim_main(["export-openstb", str(d), "--out", str(tmp_path / "r.zarr")]) == 0
    assert "pressure (72, 1, " in capsys.readouterr().out
    assert sonarsim_main(["export-openstb", str(d), "--out", str(tmp_path / "r.zarr")]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert sonarsim_main(["import-openstb", str(tmp_path / "r.zarr"),
                          "--out", str(tmp_path / "back.h5")]) == 0
    from sonarsim.dataset import SonarDataset
    np.testing.assert_allclose(SonarDataset.read(tmp_path / "back.h5").waveforms,
                               point_ds.waveforms, atol=1e-6 * np.abs(point_ds.waveforms).max())
    assert sonarsim_main(["import-openstb", str(d), "--out", str(tmp_path / "x.h5")]) == 2
    assert "not a Zarr group" in capsys.readouterr().err


def test_unsupported_configuration_is_one_line(openstb_result, tmp_path):
    result, _, _, _ = openstb_result
    bad = tmp_path / "bad.toml"
    bad.write_text(CONFIG.replace('plugin = "linear"', 'plugin = "spline"'))
    with pytest.raises(FormatError, match=r"trajectory\.plugin: 'spline' is not supported"):
        read_openstb(result, config=bad)
    bad.write_text(CONFIG.replace("[[system.receivers]]", "[[system.receivers]]", 1)
                   .replace(f"position = {RX_OFFSETS[1].tolist()}\n", "", 1))
    with pytest.raises(FormatError, match=r"system\.receivers\[1\]\.position: expected 3"):
        read_openstb(result, config=bad)


def test_damaged_results_are_one_line(openstb_result, tmp_path):
    result, config, _, _ = openstb_result
    src = zarr.open_group(str(result), mode="r")

    def copy(name, **change):
        root = zarr.open_group(str(tmp_path / name), mode="w")
        for key in ("pressure", "sample_time", "ping_start_time"):
            root.create_array(key, data=change.get(key, src[key][...]))
        root.attrs.update(dict(src.attrs))
        return tmp_path / name

    p = src["pressure"][...]
    p[3, 1, 7] = np.nan
    with pytest.raises(FormatError, match=r"'pressure' has NaN or infinite values \(pings 0\.\.100\)"):
        read_openstb(copy("nan.zarr", pressure=p), config=config)
    with pytest.raises(FormatError, match="'pressure' is float64, expected complex"):
        read_openstb(copy("real.zarr", pressure=src["pressure"][...].real), config=config)
    with pytest.raises(FormatError, match="'sample_time' is not evenly spaced"):
        read_openstb(copy("t.zarr", sample_time=src["sample_time"][...] ** 1.01), config=config)
