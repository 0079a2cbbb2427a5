"""Pulse deconvolution (recon.deconvolution, recon deconvolve) and deconvolved datasets."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from recon import deconvolution as dc
from recon import measurements
from sonarsim import signals
from sonarsim.dataset import SonarDataset
from sonarsim.errors import FormatError, InputError

FS = 100e3
TRUE_POS = (100, 180, 260)
AMPS = (1.0, 0.7, 0.5)


def reflector_train(n_pings=8, n_t=400, snr_db=20.0, seed=0):
    """Sparse reflectors (integer sample positions, one sample later every 10 pings) convolved
    with the reference's 20 kHz LFM, plus white noise at ``snr_db``.
    Returns (noisy [P, T], pulse, truth [P, 3], noise sigma)."""
    p = signals.named_pulse("lfm-20k", FS)
    w = np.zeros((n_pings, n_t))
    truth = np.array([[k + i // 10 for k in TRUE_POS] for i in range(n_pings)])
    for i in range(n_pings):
        w[i, truth[i]] = AMPS
    clean = dc.convolve(w, p)
    noisy, sigma = signals.add_noise(clean, snr_db, np.random.default_rng(seed))
    # the label is a measurement: signal power over noise power
    measured = 10 * np.log10(signals.signal_power(clean) / np.mean((noisy - clean) ** 2))
    assert abs(measured - snr_db) < 0.3
    return noisy, p, truth, sigma


def _widths_and_offsets(sig, truth):
    widths, offsets = [], []
    for i in range(len(truth)):
        for k in truth[i]:
            seg = np.abs(sig[i, k - 5:k + 6])
            offsets.append(int(np.argmax(seg)) - 5)
            widths.append(dc.mainlobe_width(sig[i], k))
    return np.array(widths), np.array(offsets)


# ---- operators and loss ---------------------------------------------------------------------

def test_convolve_and_correlate_are_adjoint_and_match_numpy():
    rng = np.random.default_rng(0)
    p = rng.normal(size=37)
    w, g = rng.normal(size=(3, 120)), rng.normal(size=(3, 120))
    np.testing.assert_allclose(dc.convolve(w, p),
                               [np.convolve(row, p)[:120] for row in w], atol=1e-10)
    assert np.isclose(np.sum(dc.convolve(w, p) * g), np.sum(w * dc.correlate(g, p)))
    band = dc.pulse_band(p, 120, 10.0)
    assert 0 < band.sum() < band.size
    assert np.isclose(np.sum(dc.convolve(w, p, band) * g), np.sum(w * dc.correlate(g, p, band)))
    assert dc.pulse_band(p, 120, np.inf) is None


def test_inr_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    p = signals.named_pulse("lfm-20k", FS)[:40]
    w, tgt = rng.normal(size=(2, 90)) * 0.1, rng.normal(size=(2, 90)) * 0.1
    for band in (None, dc.pulse_band(p, 90, 20.0)):
        loss, parts, g = dc.inr_loss(w, tgt, p, sparsity=0.1, phase=0.05, band=band)
        assert np.isclose(loss, parts["mse"] + 0.1 * parts["sparsity"] + 0.05 * parts["phase"])
        for seed in range(3):
            d = np.random.default_rng(10 + seed).normal(size=w.shape)
            eps = 1e-6
            fd = (dc.inr_loss(w + eps * d, tgt, p, 0.1, 0.05, band=band)[0]
                  - dc.inr_loss(w - eps * d, tgt, p, 0.1, 0.05, band=band)[0]) / (2 * eps)
            assert np.isclose(fd, np.sum(g * d), rtol=1e-5)


def test_analytic_matches_scipy_hilbert():
    import scipy.signal
    x = np.random.default_rng(2).normal(size=(2, 101))
    np.testing.assert_allclose(dc.analytic(x), scipy.signal.hilbert(x, axis=-1), atol=1e-12)


# ---- Wiener ---------------------------------------------------------------------------------

def test_noise_estimate_is_close_to_the_added_noise():
    s, p, _, sigma = reflector_train(n_pings=16)
    sigma2, _ = dc.noise_and_signal_power(s, p)
    assert 0.8 < sigma2 / sigma ** 2 < 1.3


def test_noise_and_reflectivity_power_and_the_mmse_lambda_of_a_white_scene():
    """s = w ∗ p + n with white w (variance 1) and white n (variance σ² = half the pulse's peak
    |P|²), a stationary 300-sample record: σ², σ_w² and λ = σ²/σ_w² come out within the
    ~10 % that a short record's spectral leakage costs (measured 1.10, 0.90, 1.22)."""
    p = signals.named_pulse("lfm-20k", FS)
    rng = np.random.default_rng(0)
    n_t = 300
    w = rng.normal(size=(64, n_t + 2 * p.size))
    sigma2 = 0.5 * np.max(np.abs(np.fft.rfft(p, 4096)) ** 2)
    s = dc.convolve(w, p)[:, p.size:p.size + n_t]      # no start-up: echoes before the record
    s = s + rng.normal(scale=np.sqrt(sigma2), size=s.shape)
    est_sigma2, est_sigma_w2 = dc.noise_and_signal_power(s, p)
    assert 0.9 < est_sigma2 / sigma2 < 1.25
    assert 0.8 < est_sigma_w2 / 1.0 < 1.1
    _, info = dc.wiener(s, p)
    assert info["lambda"] == pytest.approx(est_sigma2 / est_sigma_w2, rel=1e-12)
    assert 0.8 < info["lambda"] / sigma2 < 1.35


def test_wiener_sharpens_a_reflector_train_at_20db():
    s, p, truth, _ = reflector_train()
    mf = signals.matched_filter(s, p, mode="linear")
    out, info = dc.wiener(s, p)
    assert out.dtype == np.complex64 and out.shape == s.shape and info["lambda"] > 0
    w_mf, off_mf = _widths_and_offsets(mf, truth)
    w_wi, off_wi = _widths_and_offsets(out, truth)
    assert np.all(off_mf == 0) and np.all(np.abs(off_wi) == 0)
    # A linear filter cannot go beyond the pulse band: about 0.53x the matched filter here.
    assert np.all(w_wi <= 0.6 * w_mf), (w_wi, w_mf)


# ---- INR ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def inr_result():
    s, p, truth, _ = reflector_train()
    st = dc.INRSettings(iterations=150, lr=1e-2, lr_final=1e-3, sparsity=0.1, phase=1e-4)
    out, info = dc.inr(s, p, st, progress=False)
    return s, p, truth, out, info


def test_inr_halves_the_matched_filter_mainlobe_at_20db(inr_result):
    s, p, truth, out, info = inr_result
    mf = signals.matched_filter(s, p, mode="linear")
    w_mf, _ = _widths_and_offsets(mf, truth)
    w_inr, off = _widths_and_offsets(out, truth)
    assert np.all(np.abs(off) <= 1), off
    assert np.median(w_inr) <= 0.5 * np.median(w_mf), (w_inr, w_mf)
    assert np.mean(w_inr <= 0.5 * w_mf) >= 0.75
    assert info["loss_last"][0] < 0.05 * info["loss_first"][0]


def test_inr_output_fits_the_data_to_the_noise_level(inr_result):
    s, p, truth, out, info = inr_result
    w = np.real(out).astype(np.float64)
    resid = np.linalg.norm(dc.convolve(w, p) - s) / np.linalg.norm(s)
    assert resid < 0.2        # noise alone is 0.15 of the data norm here
    # sparse: little energy away from the reflectors
    mask = np.ones(s.shape, bool)
    for i, ks in enumerate(truth):
        for k in ks:
            mask[i, k - 3:k + 4] = False
    assert np.sum(np.abs(out[mask]) ** 2) < 0.15 * np.sum(np.abs(out) ** 2)


def test_inr_settings_are_validated():
    with pytest.raises(InputError, match="iterations"):
        dc.INRSettings(iterations=0).validate()
    with pytest.raises(InputError, match="sparsity"):
        dc.INRSettings(sparsity=-1.0).validate()
    with pytest.raises(InputError, match="band_db"):
        dc.INRSettings(band_db=0.0).validate()


# ---- datasets -------------------------------------------------------------------------------

def _point_dataset(tmp_path, n_pings=24):
    from recon import synthetic
    ds = synthetic.point_dataset([[0.0, 0.0, 0.1]], 1.0, n_pings=n_pings)
    ds.waveforms = signals.add_noise(ds.waveforms, 20.0, 0)[0].astype(np.float32)
    path = tmp_path / "pt.h5"
    ds.write(path)
    return ds, path


def test_deconvolved_dataset_round_trip_and_measurements_pass_through(tmp_path):
    ds, _ = _point_dataset(tmp_path, 8)
    out = dc.deconvolve(ds, "wiener")
    assert out.waveform_kind == "deconvolved_analytic" and out.waveforms.dtype == np.complex64
    path = tmp_path / "pd.h5"
    out.write(path)
    with h5py.File(path) as f:
        assert f.attrs["waveform_kind"] == "deconvolved_analytic"
        assert f["waveforms"].dtype == np.complex64
    back = SonarDataset.read(path)
    np.testing.assert_array_equal(back.waveforms, out.waveforms)
    assert back.meta["deconvolution_method"] == "wiener"
    assert back.meta["deconvolution_settings"]["lambda"] > 0
    assert back.select([1, 2]).waveform_kind == "deconvolved_analytic"
    np.testing.assert_array_equal(measurements.matched_filtered(back, [3]), out.waveforms[[3]])
    np.testing.assert_array_equal(measurements.analytic_waveforms(back), out.waveforms)
    assert measurements.is_deconvolved(back) and not measurements.is_deconvolved(ds)
    # a real dataset still gets the matched filter
    assert not np.allclose(measurements.complex_signals(ds), ds.waveforms)
    with pytest.raises(InputError, match="already"):
        dc.deconvolve(back, "wiener")


def test_waveform_kind_is_validated(tmp_path):
    ds, path = _point_dataset(tmp_path, 4)
    with h5py.File(path) as f:
        assert f.attrs["waveform_kind"] == "real"
    assert SonarDataset.read(path).waveform_kind == "real"
    with pytest.raises(InputError, match="expected complex"):
        SonarDataset(ds.waveforms, ds.tx, ds.rx, ds.boresight, ds.pulse, ds.fs,
                     ds.sound_speed, "x", waveform_kind="deconvolved_analytic")
    with pytest.raises(InputError, match="waveform_kind"):
        SonarDataset(ds.waveforms, ds.tx, ds.rx, ds.boresight, ds.pulse, ds.fs,
                     ds.sound_speed, "x", waveform_kind="bogus")
    with h5py.File(path, "r+") as f:
        f.attrs["waveform_kind"] = "deconvolved_analytic"      # but float32 data
    with pytest.raises(FormatError, match="expected complex64"):
        SonarDataset.read(path)
    with h5py.File(path, "r+") as f:
        f.attrs["waveform_kind"] = "nonsense"
    with pytest.raises(FormatError, match="waveform_kind"):
        SonarDataset.read(path)


def test_backprojection_of_a_deconvolved_dataset_is_sharper(tmp_path):
    from recon import backprojection
    from recon.grid import Grid
    ds, _ = _point_dataset(tmp_path, 24)
    grid = Grid(np.array([[-0.03, 0.03], [-0.03, 0.03], [0.1, 0.1]]), (61, 61, 1))
    areas, peaks = [], []
    for d in (ds, dc.deconvolve(ds, "wiener")):
        a = np.abs(backprojection.backproject(d, grid, progress=False)[:, :, 0])
        areas.append(int(np.sum(a >= a.max() / 2)))
        peaks.append(np.unravel_index(np.argmax(a), a.shape))
    assert peaks[0] == peaks[1] == (30, 30)
    assert areas[1] < 0.95 * areas[0], areas


# ---- CLI ------------------------------------------------------------------------------------

def _recon(capsys, *args):
    from recon.cli import main
    rc = main([str(a) for a in args])
    return rc, capsys.readouterr().err


def test_cli_inr_two_iterations_end_to_end(tmp_path, capsys):
    _, path = _point_dataset(tmp_path, 12)
    out = tmp_path / "pd.h5"
    rc, err = _recon(capsys, "deconvolve", path, "--out", out, "--iterations", "2",
                     "--pings-per-inr", "5", "--no-progress")
    assert rc == 0, err
    back = SonarDataset.read(out)
    info = back.meta["deconvolution_settings"]
    assert back.waveform_kind == "deconvolved_analytic" and back.n_pings == 12
    assert info["method"] == "inr" and info["iterations"] == 2
    assert info["n_batches"] == 3 and len(info["loss_first"]) == 3    # 5 + 5 + 2 pings
    for first, last in zip(info["loss_first"], info["loss_last"]):
        assert np.isfinite(first) and last < first
    assert np.all(np.isfinite(back.waveforms)) and np.all(np.abs(back.waveforms).max(1) > 0)


def test_cli_bad_input_gives_one_line_errors(tmp_path, capsys):
    _, path = _point_dataset(tmp_path, 4)
    pd = tmp_path / "pd.h5"
    assert _recon(capsys, "deconvolve", path, "--out", pd, "--method", "wiener")[0] == 0
    for args, text in [((tmp_path / "none.h5",), "no such file"),
                       ((pd,), "already"),
                       ((path, "--lr", "-1"), "lr"),
                       ((path, "--method", "wiener", "--wiener-lambda", "0"), "lambda")]:
        rc, err = _recon(capsys, "deconvolve", *args, "--out", tmp_path / "x.h5")
        assert rc == 2, (args, err)
        assert text in err and len(err.strip().splitlines()) == 1, err


def test_cli_options_are_the_inr_settings():
    """Every INRSettings field is a `recon deconvolve` option (derived, not declared by hand),
    None unless given, its help naming the INRSettings default."""
    import argparse
    import dataclasses
    from recon.commands import deconvolve as cmd
    parser = argparse.ArgumentParser()
    cmd.add_arguments(parser)
    args = parser.parse_args(["d.h5", "--out", "o.h5", "--hash-levels", "3",
                              "--hash-level-scale", "2"])
    assert cmd.inr_settings_given(args) == {"hash_levels": 3, "hash_level_scale": 2.0}
    d = dc.INRSettings()
    helps = {a.dest: a.help for a in parser._actions}
    for f in dataclasses.fields(dc.INRSettings):
        assert f"(default {getattr(d, f.name)})" in helps[f.name], f.name


def test_cli_default_method_is_wiener_and_the_other_methods_settings_are_refused(tmp_path,
                                                                                capsys):
    """Wiener is the default (docs/reconstruction.md: NBP on Wiener- vs INR-deconvolved
    scans); INR settings select the INR; a setting of the method not run is refused in one
    line, not silently ignored."""
    _, path = _point_dataset(tmp_path, 4)
    out = tmp_path / "pd.h5"
    rc, err = _recon(capsys, "deconvolve", path, "--out", out)
    assert rc == 0, err
    assert SonarDataset.read(out).meta["deconvolution_method"] == "wiener"
    for args, text in [(("--method", "wiener", "--iterations", "5", "--mlp-width", "8"),
                        "INR settings (--mlp-width, --iterations) apply to --method inr only"),
                       (("--method", "inr", "--wiener-lambda", "1"),
                        "--wiener-lambda applies to --method wiener only"),
                       (("--iterations", "5", "--wiener-lambda", "1"),
                        "--wiener-lambda applies to --method wiener only")]:
        rc, err = _recon(capsys, "deconvolve", path, "--out", tmp_path / "x.h5", *args)
        assert rc == 2 and text in err and len(err.strip().splitlines()) == 1, (args, err)
    assert not (tmp_path / "x.h5").exists()


def test_inr_network_settings_are_the_fields_network_settings():
    """One settings object (#22): the INR's network is described by recon.field's
    NetworkSettings fields (same names, same range checks as recon nbp's field), with the
    INR's own defaults; the old names are gone."""
    import dataclasses
    from recon.field import NetworkSettings
    assert issubclass(dc.INRSettings, NetworkSettings)
    names = {f.name for f in dataclasses.fields(dc.INRSettings)}
    assert {f.name for f in dataclasses.fields(NetworkSettings)} <= names
    assert not names & set(dc.RENAMED)
    assert set(dc.RENAMED.values()) == {f.name for f in dataclasses.fields(NetworkSettings)}
    st = dc.INRSettings()
    assert (st.hash_levels, st.mlp_width, st.mlp_hidden) == (16, 32, 2)   # the INR's defaults
    assert st.n_features() == 32
    # the field's finest-resolution rule (2^24 cells per axis) refuses what overflows
    with pytest.raises(InputError, match="inr hash_levels: the finest level"):
        dc.INRSettings(hash_levels=40, hash_level_scale=2.0).validate()
    with pytest.raises(InputError, match="inr mlp_width"):
        dc.INRSettings(mlp_width=4096).validate()


def test_inr_network_ranges_live_in_network_settings_only(monkeypatch):
    """The network's ranges are checked in one place, NetworkSettings.validate_network: moving
    its width bound moves the INR's; the INR adds only that integers are integers."""
    import recon.field
    monkeypatch.setattr(recon.field, "MAX_MLP_WIDTH", 2048)
    dc.INRSettings(mlp_width=1500).validate()
    monkeypatch.setattr(recon.field, "MAX_MLP_WIDTH", 16)
    with pytest.raises(InputError, match="inr mlp_width: must be <= 16"):
        dc.INRSettings(mlp_width=32).validate()
    for name, bad in (("hash_levels", 2.5), ("mlp_width", "8"), ("iterations", True)):
        with pytest.raises(InputError, match=f"inr {name}: must be an integer"):
            dc.INRSettings(**{name: bad}).validate()


@pytest.mark.parametrize("old, new", [("--n-levels", "--hash-levels"), ("--width", "--mlp-width"),
                                      ("--hidden-layers", "--mlp-hidden"),
                                      ("--per-level-scale", "--hash-level-scale"),
                                      ("--features-per-level", "--hash-features"),
                                      ("--log2-hashmap-size", "--hash-log2-size"),
                                      ("--base-resolution", "--hash-base-resolution")])
def test_old_inr_option_names_are_refused_naming_the_new_one(tmp_path, capsys, old, new):
    from recon.cli import main
    with pytest.raises(SystemExit) as stop:     # a usage error: argparse's exit
        main(["deconvolve", str(tmp_path / "d.h5"), "--out", str(tmp_path / "o.h5"), old, "3"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and f"{old} is now {new}" in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert dc.renamed_setting(old[2:].replace("-", "_")).startswith(
        f"{old[2:].replace('-', '_')!r} is now {new[2:].replace('-', '_')!r}")
    assert dc.renamed_setting("lr") is None


def test_inr_cost_is_estimated_and_a_long_run_refused_before_any_work(tmp_path, capsys):
    """The INR's cost grows with pings x samples x iterations: a run estimated above
    --max-hours is refused in one line naming the alternative, before any fitting (no output
    file); within the bound the estimate is printed."""
    st = dc.INRSettings()
    one = st.cpu_seconds_estimate(360, 718)
    assert one == pytest.approx(dc.INR_CPU_S_PER_SAMPLE_ITERATION * 360 * 718 * 300)
    assert st.cpu_seconds_estimate(720, 718) == pytest.approx(2 * one)
    assert dc.INRSettings(mlp_width=128, mlp_hidden=3).cpu_seconds_estimate(360, 718) > 3 * one
    _, path = _point_dataset(tmp_path, 12)
    out = tmp_path / "pd.h5"
    rc, err = _recon(capsys, "deconvolve", path, "--out", out, "--method", "inr",
                     "--max-hours", "1e-9")
    assert rc == 2 and "estimated" in err and "--method wiener" in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()
    rc, err = _recon(capsys, "deconvolve", path, "--out", out, "--iterations", "2",
                     "--pings-per-inr", "6", "--no-progress")
    assert rc == 0 and "inr: estimated" in err, err
