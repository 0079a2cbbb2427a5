"""sonarsim.importers.airsas on the real AirSAS scan shipped in sonarsim.data (the first 6
flights raw; the whole scan as the dataset this importer made of it).

Expected values are computed here independently with plain NumPy/csv from the raw files
(the reference code's pose model, sound speed, LFM, background and group delay).
"""
from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from sonarsim.errors import FormatError, InputError
from sonarsim.geometry import AIRSAS_REAL_BOX
from sonarsim.importers.airsas import import_airsas

SCAN = "airsas_real/small_features_cutout_5k"
BACKGROUND = "airsas_real/bg_5k"
N_SMALL = 4          # flights in the small copies used for the error cases


@pytest.fixture(scope="module")
def real(shared_data):
    scan, bg = shared_data / SCAN, shared_data / BACKGROUND
    return scan, bg, import_airsas(scan, bg, progress=False)


def _coordinates(folder: Path) -> list[dict]:
    with open(folder / "Coordinates.csv", newline="") as f:
        return list(csv.DictReader(f))


def _sys_param(folder: Path, key: str) -> float:
    with open(folder / "SysParams.csv", newline="") as f:
        return float(dict(csv.reader(f))[key])


def _advance(x: np.ndarray, delay: float) -> np.ndarray:
    """x advanced by ``delay`` samples: IFFT(FFT(x)·e^{+j2πf·delay}) (the reference code's group-delay removal)."""
    n = x.size
    f = np.fft.fftfreq(n)
    f[n // 2] = -0.5      # fold the Nyquist bin to -fs/2 as the reference does
    return np.real(np.fft.ifft(np.fft.fft(x) * np.exp(2j * np.pi * f * delay)))


def test_waveforms_are_background_subtracted_and_advanced(real):
    scan, bg, ds = real
    delay = _sys_param(scan, "Group Delay")
    assert delay == pytest.approx(62.329317)
    assert ds.waveforms.shape == (6, 1000) and ds.start_sample == 0
    for ping in (0, 2, 5):
        raw = np.loadtxt(scan / f"Flight-{ping + 1:06d}.csv", delimiter=",")[:, 0]
        empty = np.loadtxt(bg / f"Flight-{ping + 1:06d}.csv", delimiter=",")[:, 0]
        expect = _advance(raw - empty, delay)
        scale = np.abs(expect).max()
        np.testing.assert_allclose(ds.waveforms[ping], expect, rtol=0, atol=1e-5 * scale)
        # The advance matters: the un-shifted difference is far from the stored ping.
        assert np.abs(ds.waveforms[ping] - (raw - empty)).max() > 0.1 * scale


def test_poses_follow_the_rig_formula(real):
    scan, _, ds = real
    rows = _coordinates(scan)
    tx_rig = np.array([0.0, -0.8485, 0.285])
    rx_rig = np.array([0.0, -0.8615, 0.247])
    center = np.array([0.0, 0.0, 0.1775])
    for ping in (0, 2, 5):
        theta = np.deg2rad(float(rows[ping]["Angle"]))
        height = float(rows[ping]["Height"]) / 1000.0
        rot = np.array([[np.cos(theta), -np.sin(theta), 0],
                        [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
        tx = rot @ tx_rig - center + [0, 0, height]
        rx = rot @ rx_rig - center + [0, 0, height]
        np.testing.assert_allclose(ds.tx[ping], tx, atol=1e-12)
        np.testing.assert_allclose(ds.rx[ping], rx, atol=1e-12)
        aim = np.array([0.0, 0.0, 0.1]) - tx          # AIRSAS_REAL_BOX centre
        np.testing.assert_allclose(ds.boresight[ping], aim / np.linalg.norm(aim), atol=1e-12)
    # At angle 0 the speaker sits on the -y axis, 0.8485 m from the rotation axis.
    np.testing.assert_allclose(ds.tx[0], [0.0, -0.8485, 0.285 - 0.1775 + 0.150], atol=1e-12)


def test_the_shipped_whole_scan_follows_the_rig_formula(real_scan):
    """The whole scan (360 flights at 1 degree steps, height 150 mm) as shipped: ping k at
    angle k degrees."""
    assert real_scan.n_pings == 360
    tx_rig, center = np.array([0.0, -0.8485, 0.285]), np.array([0.0, 0.0, 0.1775])
    for k in (45, 200, 359):
        theta = np.deg2rad(k)
        rot = np.array([[np.cos(theta), -np.sin(theta), 0],
                        [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
        np.testing.assert_allclose(real_scan.tx[k], rot @ tx_rig - center + [0, 0, 0.150],
                                   atol=1e-9)


def test_temperatures_and_sound_speed(real):
    scan, _, ds = real
    temps = np.array([float(r["Temp"]) for r in _coordinates(scan)])
    np.testing.assert_array_equal(ds.temperatures, temps)
    assert ds.sound_speed == pytest.approx(331.4 + 0.6 * temps.mean(), rel=1e-12)
    assert 340 < ds.sound_speed < 350


def test_pulse_is_the_waveform_params_lfm(real):
    _, _, ds = real
    t = np.arange(100) / 100e3       # LFM_2.25E+4Hz_1.75E+4Hz_1.00E-3s_..._tukeywin_1.00E-1
    expect = scipy.signal.chirp(t, 22.5e3, 1e-3, 17.5e3) * scipy.signal.windows.tukey(100, 0.1)
    np.testing.assert_allclose(ds.pulse, expect, atol=1e-12)
    assert ds.fs == 100e3 and ds.source == "airsas:small_features_cutout_5k"


# ---------------------------------------------------------------- small copies, fast cases
def _small_copy(src: Path, dst: Path, n: int = N_SMALL, waveforms=None) -> Path:
    dst.mkdir()
    for name in ("SysParams.csv", "WaveformParams.csv", "Waveforms.csv"):
        shutil.copy(src / name, dst / name)
    lines = (src / "Coordinates.csv").read_text().splitlines()[: n + 1]
    if waveforms is not None:
        lines = [lines[0]] + [ln.rsplit(",", 1)[0] + f",{w:.3f}"
                              for ln, w in zip(lines[1:], waveforms)]
    (dst / "Coordinates.csv").write_text("\n".join(lines) + "\n")
    for i in range(1, n + 1):
        shutil.copy(src / f"Flight-{i:06d}.csv", dst / f"Flight-{i:06d}.csv")
    return dst


@pytest.fixture()
def small(shared_data, tmp_path):
    return (_small_copy(shared_data / SCAN, tmp_path / "scan"),
            _small_copy(shared_data / BACKGROUND, tmp_path / "bg"))


def test_truncated_flight_names_file_and_line(small):
    scan, bg = small
    path = scan / "Flight-000003.csv"
    text = path.read_text()
    cut = text[: len(text) * 2 // 5]
    path.write_text(cut)
    lines = cut.count("\n") + (0 if cut.endswith("\n") else 1)
    with pytest.raises(FormatError) as err:
        import_airsas(scan, bg, progress=False)
    msg = str(err.value)
    assert "Flight-000003.csv: line " in msg
    line = int(msg.split("line ")[1].split(":")[0])
    assert line in (lines, lines + 1)


def test_missing_coordinates(small):
    scan, bg = small
    (scan / "Coordinates.csv").unlink()
    with pytest.raises(FormatError, match=r"Coordinates\.csv: file not found"):
        import_airsas(scan, bg, progress=False)


def test_garbled_lines_name_file_and_line(small):
    scan, bg = small
    coords = (scan / "Coordinates.csv").read_text().splitlines()
    coords[3] = coords[3].replace(",", ",x", 1)
    (scan / "Coordinates.csv").write_text("\n".join(coords) + "\n")
    with pytest.raises(FormatError, match=r"Coordinates\.csv: line 4: "):
        import_airsas(scan, bg, progress=False)

    _small_copy(bg, scan.parent / "scan2")  # fresh scan copy from the (intact) background
    flight = bg / "Flight-000002.csv"
    rows = flight.read_text().splitlines()
    rows[499] = "0.001,garbage"
    flight.write_text("\n".join(rows) + "\n")
    with pytest.raises(FormatError, match=r"bg/Flight-000002\.csv: line 500: value 'garbage'"):
        import_airsas(scan.parent / "scan2", bg, progress=False)


def test_missing_flight_file_and_mismatched_background(small, shared_data, tmp_path):
    scan, bg = small
    (scan / "Flight-000004.csv").unlink()
    with pytest.raises(FormatError, match=r"Flight-000004\.csv: file not found"):
        import_airsas(scan, bg, progress=False)
    full = _small_copy(shared_data / SCAN, tmp_path / "scan6", n=6)
    with pytest.raises(FormatError, match=r"background lacks 2 of the 6 flights"):
        import_airsas(full, bg, progress=False)


def test_interleaved_waveforms_need_an_index(shared_data, tmp_path):
    scan = _small_copy(shared_data / SCAN, tmp_path / "mixed", waveforms=[0, 1, 0, 1])
    with open(scan / "WaveformParams.csv", "a") as f:
        f.write("\nLFM_3.00E+4Hz_1.00E+4Hz_1.00E-3s_5.00E-1V_tukeywin_1.00E-1\n")
    with pytest.raises(InputError, match="interleaves waveforms"):
        import_airsas(scan, progress=False)
    ds = import_airsas(scan, waveform_index=1, progress=False)
    assert ds.waveforms.shape[0] == 2
    rows = _coordinates(scan)
    theta = np.deg2rad(float(rows[3]["Angle"]))       # second selected flight = flight 4
    np.testing.assert_allclose(ds.tx[1, :2], [0.8485 * np.sin(theta), -0.8485 * np.cos(theta)],
                               atol=1e-12)
    t = np.arange(100) / 100e3
    expect = scipy.signal.chirp(t, 30e3, 1e-3, 10e3) * scipy.signal.windows.tukey(100, 0.1)
    np.testing.assert_allclose(ds.pulse, expect, atol=1e-12)


def test_rig_constants_from_sysparams_else_geometry(small):
    scan, _ = small
    params = (scan / "SysParams.csv").read_text().replace("Speaker y,-848.500000E-3",
                                                         "Speaker y,-900.000000E-3")
    (scan / "SysParams.csv").write_text(params)
    ds = import_airsas(scan, progress=False)
    assert np.linalg.norm(ds.tx[0, :2]) == pytest.approx(0.9)
    assert ds.meta["rig_constants_from"] == "SysParams.csv"
    kept = [ln for ln in params.splitlines()
            if not ln.startswith(("Speaker", "Mic", "Center"))]
    (scan / "SysParams.csv").write_text("\n".join(kept) + "\n")
    ds = import_airsas(scan, progress=False)
    assert np.linalg.norm(ds.tx[0, :2]) == pytest.approx(0.8485)
    assert ds.meta["rig_constants_from"] == "sonarsim.geometry"


def test_measured_pulse_file_and_box(small, shared_data):
    scan, bg = small
    pulse_file = shared_data / "pulses" / "airsas_5khz_measured.npy"
    ds = import_airsas(scan, bg, pulse=pulse_file, box=AIRSAS_REAL_BOX, progress=False)
    np.testing.assert_array_equal(ds.pulse, np.load(pulse_file)[:100])
    ds = import_airsas(scan, bg, pulse=pulse_file, pulse_samples=0, progress=False)
    assert ds.pulse.size == np.load(pulse_file).size


def test_cli_writes_dataset_and_reports_errors(small, tmp_path, capsys):
    from sonarsim.cli import main
    from sonarsim.dataset import SonarDataset

    scan, bg = small
    out = tmp_path / "d.h5"
    assert main(["import-airsas", str(scan), "--background", str(bg), "--out", str(out),
                 "--box", "-0.1", "0.1", "-0.1", "0.1", "0", "0.2", "--no-progress"]) == 0
    ds = SonarDataset.read(out)
    assert ds.waveforms.shape == (N_SMALL, 1000) and ds.temperatures.shape == (N_SMALL,)
    assert ds.meta["box"] == [[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]]
    aim = np.array([0.0, 0.0, 0.1]) - ds.tx[0]
    np.testing.assert_allclose(ds.boresight[0], aim / np.linalg.norm(aim), atol=1e-12)
    (scan / "Coordinates.csv").unlink()
    capsys.readouterr()
    assert main(["import-airsas", str(scan), "--out", str(tmp_path / "e.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert "Coordinates.csv" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "e.h5").exists()


def test_commanded_and_named_pulses(small):
    scan, _ = small
    ds = import_airsas(scan, pulse="commanded", progress=False)
    expect = np.loadtxt(scan / "Waveforms.csv", delimiter=",", ndmin=2)[:, 0]
    np.testing.assert_array_equal(ds.pulse, expect)
    assert ds.pulse.size == 100 and np.abs(ds.pulse).max() == pytest.approx(0.5, abs=0.01)
    ds = import_airsas(scan, pulse="lfm-5k", progress=False)
    t = np.arange(100) / 100e3
    np.testing.assert_allclose(ds.pulse, scipy.signal.chirp(t, 22.5e3, 1e-3, 17.5e3)
                               * scipy.signal.windows.tukey(100, 0.1), atol=1e-12)


def test_binary_garbage_and_blank_lines_name_the_line(small):
    scan, bg = small
    path = scan / "Flight-000001.csv"
    rows = path.read_bytes().split(b"\n")
    rows[9] = b"\xff\xfe\x00"
    path.write_bytes(b"\n".join(rows))
    with pytest.raises(FormatError, match=r"Flight-000001\.csv: line 10: not UTF-8"):
        import_airsas(scan, bg, progress=False)
    rows[9] = b""
    path.write_bytes(b"\n".join(rows))
    with pytest.raises(FormatError, match=r"Flight-000001\.csv: line 10: empty line"):
        import_airsas(scan, bg, progress=False)


def test_reading_flights_shows_progress_in_logs_and_quiet_silences_it(shared_data, tmp_path,
                                                                       capsys, monkeypatch):
    """Progress goes through sonarsim.progress: timed lines when stderr is a log, nothing
    under -q (it was a bare tqdm bar: a log saw carriage returns, -q did not silence it)."""
    from sonarsim.cli import main
    monkeypatch.setenv("SONARSIM_PROGRESS_INTERVAL", "0.000001")
    argv = ["import-airsas", str(shared_data / SCAN), "--background",
            str(shared_data / BACKGROUND)]
    assert main([*argv, "--out", str(tmp_path / "a.h5")]) == 0
    err = capsys.readouterr().err
    assert "reading small_features_cutout_5k" in err and "flight" in err and "\r" not in err
    assert main(["-q", *argv, "--out", str(tmp_path / "b.h5")]) == 0
    assert capsys.readouterr().err == ""
