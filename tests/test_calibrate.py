"""recon calibrate: autofocus by gradient (recon.calibrate).

A small simulated circular scan of point scatterers, written in NumPy here (echo of each
point = the pulse delayed by the round-trip path / c + the time offset, amplitude 1/(r_t r_r)),
is recorded with a known timing or rig error; the fit must find it. The AD gradient of the
focus must equal central differences of the focus itself.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sonarsim import signals
from sonarsim.dataset import SonarDataset

from recon import backprojection, calibrate, measurements
from recon.grid import Grid

FS = 100e3
C = 343.0
POINTS = np.array([[0.06, 0.02, 0.1], [-0.05, 0.07, 0.1], [0.0, -0.08, 0.1], [-0.07, -0.03, 0.1]])
# 5 mm voxels with the points on voxel centres (the focus of a point between voxel centres
# can peak slightly away from the true delays).
GRID = Grid([[-0.12, 0.12], [-0.12, 0.12], [0.1, 0.1]], (49, 49, 1))


def scan(time_offset: float = 0.0, rig_forward: float = 0.0, n: int = 48,
         true_c: float = C) -> SonarDataset:
    """Circular scan (radius 0.85 m, TX 13 mm behind and 38 mm above RX, as AirSAS) whose
    echoes arrive at path/true_c + time_offset (the file says C) and whose true rig sits
    ``rig_forward`` metres closer to the centre than the stored positions say."""
    ang = np.arange(n) * 2 * math.pi / n
    radial = np.stack([np.sin(ang), -np.cos(ang), np.zeros(n)], axis=1)   # centre -> sonar
    tx = 0.8485 * radial + [0, 0, 0.2575]
    rx = 0.8615 * radial + [0, 0, 0.2195]
    fwd = -radial                                   # horizontal boresight: towards the centre
    pulse = signals.lfm(30e3, 10e3, 1e-3, FS)
    start, n_t = 380, 320
    padded = np.zeros((n, n_t))
    for p in POINTS:
        rt = np.linalg.norm(p - (tx + rig_forward * fwd), axis=1)
        rr = np.linalg.norm(p - (rx + rig_forward * fwd), axis=1)
        delay = ((rt + rr) / true_c + time_offset) * FS - start
        echo = np.zeros((n, n_t))
        echo[:, :len(pulse)] = pulse
        padded += signals.fractional_delay(echo, delay, axis=-1) / (rt * rr)[:, None]
    bore = fwd * math.cos(math.radians(10)) + [0, 0, -math.sin(math.radians(10))]
    return SonarDataset(waveforms=padded.astype(np.float32), tx=tx, rx=rx, boresight=bore,
                        pulse=pulse, fs=FS, sound_speed=C, source="simulated",
                        start_sample=start)


@pytest.fixture(scope="module")
def offset_scan():
    return scan(time_offset=-13e-6)


def test_image_is_the_product_backprojection(offset_scan):
    problem = calibrate.FocusProblem(offset_scan, GRID, upsample=4)
    ours = problem.image()
    # The product interpolates linearly (error ~1 % at R = 4 for this 30 kHz pulse), the
    # calibration with a Catmull-Rom cubic: compare with the product at R = 32.
    product = backprojection.backproject(offset_scan, GRID, upsample=32, progress=False)
    linear4 = backprojection.backproject(offset_scan, GRID, upsample=4, progress=False)
    err = np.linalg.norm(ours - product) / np.linalg.norm(product)
    assert err < 2e-3 and err < 0.3 * np.linalg.norm(linear4 - product) / np.linalg.norm(product)


def numpy_focus(dataset, grid: Grid, theta, upsample: int = 4) -> float:
    """The focus S of the calibrated backprojection in plain float64 NumPy (independent of
    the Dr.Jit kernel): s_i(k) Catmull-Rom interpolated at k = (path/(c + dc) + dt)*fs*R - start*R,
    TX/RX moved by the rig offset along (towards the centre, left, up)."""
    dc, dt, fwd_off, left_off, up_off = theta
    s = signals.fft_upsample(measurements.matched_filtered(dataset).astype(np.complex128),
                             upsample, axis=-1)
    fwd = -np.asarray(dataset.tx, dtype=np.float64) * [1, 1, 0]
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    left = np.cross([0.0, 0.0, 1.0], fwd)
    off = fwd_off * fwd + left_off * left + up_off * np.array([0.0, 0.0, 1.0])
    v = grid.points()[None, :, :]
    path = (np.linalg.norm(v - (dataset.tx + off)[:, None], axis=-1)
            + np.linalg.norm(v - (dataset.rx + off)[:, None], axis=-1))
    k = (path / (C + dc) + dt) * FS * upsample - dataset.start_sample * upsample
    k0 = np.floor(k).astype(int)
    ok = (k0 >= 1) & (k0 < s.shape[1] - 2)
    k0 = np.where(ok, k0, 1)
    rows = np.arange(len(s))[:, None]
    w = k - k0
    # Catmull-Rom: the Hermite cubic whose end slopes are the central differences.
    p0, p1, p2, p3 = (s[rows, k0 + j] for j in (-1, 0, 1, 2))
    m1, m2 = (p2 - p0) / 2, (p3 - p1) / 2
    h00, h10, h01, h11 = (2 * w**3 - 3 * w**2 + 1, w**3 - 2 * w**2 + w, -2 * w**3 + 3 * w**2,
                          w**3 - w**2)
    val = np.where(ok, h00 * p1 + h10 * m1 + h01 * p2 + h11 * m2, 0)
    image = val.sum(axis=0)
    a2 = np.abs(image) ** 2
    return len(a2) * (a2 ** 2).sum() / a2.sum() ** 2


def test_gradient_equals_central_differences(offset_scan):
    problem = calibrate.FocusProblem(offset_scan, GRID, upsample=4)
    at = calibrate.Calibration(0.4, -6e-6, (0.002, -0.003, 0.004))
    s, grad = problem.focus_and_gradient(at)
    assert s == pytest.approx(numpy_focus(offset_scan, GRID, at.vector()), rel=1e-4)
    # float64 differences with steps far below the 2.5 us upsampled sample.
    steps = (1e-5, 1e-11, 1e-8, 1e-8, 1e-8)
    for j, h in enumerate(steps):
        plus, minus = at.vector(), at.vector()
        plus[j] += h
        minus[j] -= h
        fd = (numpy_focus(offset_scan, GRID, plus) - numpy_focus(offset_scan, GRID, minus)) / (2 * h)
        assert grad[j] == pytest.approx(fd, rel=0.01), calibrate.PARAMETERS[j]


def test_fit_recovers_a_rig_offset():
    res = calibrate.fit(scan(rig_forward=0.004), GRID, free="rig_forward", curvature=True)
    assert res.calibration.rig_offset[0] == pytest.approx(0.004, abs=0.0002)
    assert res.focus_after > 1.2 * res.focus_before
    assert res.curvature.shape == (1, 1) and res.curvature[0, 0] > 0      # a maximum


def test_fit_recovers_the_sound_speed():
    res = calibrate.fit(scan(true_c=C + 1.5), GRID, free="sound_speed", curvature=False)
    assert res.calibration.sound_speed == pytest.approx(1.5, abs=0.1)


@pytest.mark.parametrize("budget", [2, 3, 5])
def test_max_evaluations_is_a_hard_limit(budget):
    """Once: --max-evaluations 2 ran 8 evaluations (scipy's maxfun lets line searches run
    over). The search stops at the budget and keeps the best focus it evaluated."""
    res = calibrate.fit(scan(rig_forward=0.004), GRID, free="rig_forward", curvature=False,
                        max_evaluations=budget)
    assert 1 <= len(res.history) <= budget
    assert res.focus_after == pytest.approx(max(h[1] for h in res.history), rel=1e-6)


def test_apply_moves_the_scan_onto_the_truth(offset_scan):
    fixed = calibrate.apply(offset_scan, calibrate.Calibration(time_offset=-13e-6))
    truth = scan()
    assert np.abs(fixed.waveforms - truth.waveforms).max() < 1e-3 * np.abs(truth.waveforms).max()
    moved = calibrate.apply(truth, calibrate.Calibration(rig_offset=(0.004, 0.0, 0.0)))
    assert np.allclose(moved.tx - truth.tx, 0.004 * -(truth.tx * [1, 1, 0])
                       / np.linalg.norm(truth.tx[:, :2], axis=1)[:, None], atol=1e-12)


def test_command_recovers_the_time_offset_and_refuses_bad_options(offset_scan, tmp_path,
                                                                     capsys):
    from recon.cli import main
    data = tmp_path / "d.h5"
    offset_scan.write(data)
    out = tmp_path / "cal.json"
    args = [str(data), "--out", str(out), "--fit", "time_offset",
            "--bounds", "-0.12", "0.12", "-0.12", "0.12", "0.1", "0.1", "--shape", "49", "49", "1",
            "--no-curvature", "--no-progress", "--corrected", str(tmp_path / "fixed.h5")]
    assert main(["calibrate", *args]) == 0
    assert "time offset -12.8" in capsys.readouterr().out
    rec = json.loads(out.read_text())
    assert rec["calibration"]["time_offset_s"] == pytest.approx(-13e-6, abs=0.3e-6)
    assert rec["calibration"]["rig_offset_m"] == {"forward": 0.0, "left": 0.0, "up": 0.0}
    assert rec["focus_after"] > 1.2 * rec["focus_before"]
    assert SonarDataset.read(tmp_path / "fixed.h5").meta["calibration"].startswith("sound speed")
    for bad, words in ((args, "file exists"),
                       ([str(data), "--out", str(tmp_path / "x.json"), "--fit", "temperature"],
                        "--fit: unknown parameter 'temperature'"),
                       ([str(data), "--out", str(tmp_path / "x.txt")], "written as .json")):
        assert main(["calibrate", *bad]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_parameter_on_its_bound_is_reported(offset_scan, monkeypatch):
    monkeypatch.setitem(calibrate.BOUNDS, "time_offset", 5e-6)     # the truth (-13 us) is outside
    res = calibrate.fit(offset_scan, GRID, free="time_offset", curvature=False)
    assert res.calibration.time_offset == pytest.approx(-5e-6, abs=1e-9)
    assert res.at_bounds == ("time_offset",)


@pytest.mark.parametrize("free", ["time_offset", ("time_offset", "rig_forward")])
def test_first_step_moves_the_steepest_parameter_by_one_display_unit(offset_scan, free):
    """L-BFGS-B's first trial step within bounds is the gradient itself; the objective is
    normalised so that it moves the parameter of the largest gradient by one display unit
    (1 µs, 1 mm), whatever the gradient's size (a flat start, the real scan at z = 0.2 m, took
    steps of 0.0004 µs and stopped there on a GPU). Fails when the normalisation is dropped."""
    res = calibrate.fit(offset_scan, GRID, free=free, curvature=False, max_evaluations=3)
    names = (free,) if isinstance(free, str) else free
    idx = [calibrate.PARAMETERS.index(n) for n in names]
    units = np.array([calibrate.UNITS[n][1] for n in names])
    step = (np.asarray(res.history[1][2])[idx] - np.asarray(res.history[0][2])[idx]) * units
    assert np.abs(step).max() == pytest.approx(1.0, rel=1e-6)
