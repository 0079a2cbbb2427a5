"""simulate: pulse convolution and alignment, SNR, determinism, resume; render/simulate CLIs."""
from __future__ import annotations

import filecmp
from pathlib import Path

import numpy as np
import pytest

from sonarsim import simulate as sim
from sonarsim.cli import main as cli_main
from sonarsim.dataset import SonarDataset, Transients
from sonarsim.errors import InputError
from sonarsim.geometry import crop_window, trajectory
from sonarsim.scene import load_scene
from sonarsim.signals import lfm, matched_filter, named_pulse, pulse_from_spec, signal_power

FS = 100e3


@pytest.fixture(scope="module")
def small_ball(tmp_path_factory) -> Path:
    """A 5 mm sphere floating on the beam axis, no ground: an almost point-like target."""
    path = tmp_path_factory.mktemp("scene") / "ball.toml"
    path.write_text('ground = false\n[[object]]\nshape = "sphere"\nradius = 0.005\n'
                    'center = [0.03, -0.02, 0.15]\n')
    return path


def settings(**kw) -> sim.SimulationSettings:
    base = dict(pulse=pulse_from_spec("lfm-20k", FS), paths_per_pose=4000, bounces=2, seed=5)
    base.update(kw)
    return sim.SimulationSettings(**base)


# ----------------------------------------------------------------------------- signal model

def test_impulse_gives_pulse_at_its_sample_linear_not_circular():
    k, n_samples = 4, 60
    pulse = named_pulse("lfm-20k", FS)[:20]
    pulse_os = sim.oversampled_pulse(pulse, k)
    hist = np.zeros((3, 2, n_samples * k), np.float32)
    hist[0, 0, 10 * k] = 2.0                       # bounce 1, at sample 10
    hist[1, 1, 25 * k] = 1.0                       # bounce 2, at sample 25
    hist[2, 0, 50 * k] = 1.0                       # near the end: the tail must not wrap
    wf = sim.transients_to_waveforms(hist, pulse_os, k, n_samples)
    expected = np.zeros((3, n_samples))
    expected[0, 10:30] = 2 * pulse
    expected[1, 25:45] = pulse
    expected[2, 50:60] = pulse[:10]
    np.testing.assert_allclose(wf, expected, atol=1e-6 * np.abs(pulse).max())
    only_first = sim.transients_to_waveforms(hist, pulse_os, k, n_samples, bounce_index=[0])
    np.testing.assert_allclose(only_first[1], 0.0, atol=1e-12)


def test_pulse_specs(tmp_path):
    assert np.array_equal(pulse_from_spec("LFM-5k", FS).samples, named_pulse("lfm-5k", FS))
    custom = pulse_from_spec("lfm:30e3:10e3:0.5e-3", FS)
    assert np.array_equal(custom.samples, lfm(30e3, 10e3, 0.5e-3, FS, window_ratio=0.1))
    assert np.array_equal(pulse_from_spec("lfm:20e3:15e3:1e-3:0.5", FS).samples,
                          lfm(20e3, 15e3, 1e-3, FS, window_ratio=0.5))
    measured = np.sin(np.arange(300) / 3.0)
    np.save(tmp_path / "p.npy", measured)
    assert np.array_equal(pulse_from_spec(tmp_path / "p.npy", FS, 100).samples, measured[:100])
    for bad in ("chirp", "lfm:1:2", "lfm:a:b:c"):
        with pytest.raises(InputError):
            pulse_from_spec(bad, FS)


def test_ping_noise_independent_of_chunking():
    whole = sim.ping_noise(7, 0, 10, 50)
    np.testing.assert_array_equal(sim.ping_noise(7, 4, 7, 50), whole[4:7])
    assert not np.array_equal(sim.ping_noise(8, 0, 10, 50), whole)
    assert abs(whole.std() - 1) < 0.1


# ----------------------------------------------------------------------------- pipeline

def test_sphere_echo_peaks_at_its_range(small_ball, tmp_path):
    spec = load_scene(small_ball)
    poses = trajectory("cylindrical:6:2", box=spec.box)
    out = sim.simulate(spec, poses, tmp_path / "ball.h5",
                       settings(paths_per_pose=100_000, bounces=1))
    ds = SonarDataset.read(out)
    pulse = named_pulse("lfm-20k", FS)
    crop = crop_window(poses, spec.box, ds.sound_speed, FS, pulse_samples=100)
    assert ds.start_sample == crop.min_sample and ds.waveforms.shape == (12, crop.num_samples)
    np.testing.assert_array_equal(ds.pulse, pulse)
    np.testing.assert_allclose(ds.gt_vertices, spec.gt_mesh().vertices)
    assert ds.snr_db is None and ds.seed == 5

    envelope = np.abs(matched_filter(ds.waveforms, ds.pulse, mode="linear"))
    peak = ds.start_sample + envelope.argmax(axis=1)
    center, radius = np.array([0.03, -0.02, 0.15]), 0.005
    front = (np.linalg.norm(ds.tx - center, axis=1) + np.linalg.norm(ds.rx - center, axis=1)
             - 2 * radius)
    # Lambertian cos^2 weighting over the visible cap: energy density in path length
    # falls as (1 - u)^2 over [front, front + 2R]; its centroid is at u = 1/4.
    expected = (front + 0.25 * 2 * radius) * FS / ds.sound_speed
    assert np.all(np.abs(peak - expected) <= 1.0), peak - expected


def ball_energy_numpy(tx, rx, center, radius, n=40_000):
    """Bounce-1 energy per pose of a Lambertian sphere (albedo 1, beams covering it) by a
    Fibonacci-lattice quadrature of b_T b_R/π cosθ_i cosθ_o/(r_T² r_R²) dA; a convex
    sphere sees a point exactly when both cosines are positive. Also the energy-weighted
    mean path length."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    normal = np.c_[np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z]
    points = center + radius * normal
    area = 4 * np.pi * radius ** 2 / n
    energy, mean_path = [], []
    for t, r in zip(tx, rx):
        dt, dr = t - points, r - points
        lt, lr = np.linalg.norm(dt, axis=1), np.linalg.norm(dr, axis=1)
        ci = np.clip(np.sum(normal * dt, axis=1) / lt, 0, None)
        co = np.clip(np.sum(normal * dr, axis=1) / lr, 0, None)
        w = ci * co / (np.pi * lt ** 2 * lr ** 2) * area
        energy.append(w.sum())
        mean_path.append(np.sum(w * (lt + lr)) / w.sum())
    return np.array(energy), np.array(mean_path)


def test_sphere_energy_and_delay_within_monte_carlo_error(small_ball, tmp_path):
    """Bounce-1 energy and mean path length of the ball against NumPy quadrature, with a
    bound derived from the measured Monte-Carlo error (two seeds), not a loose margin."""
    spec = load_scene(small_ball)
    poses = trajectory("cylindrical:6:2", box=spec.box)
    runs = [SonarDataset.read(sim.simulate(spec, poses, tmp_path / f"b{seed}.h5",
                                           settings(bounces=1, seed=seed, keep_transients=True)))
            for seed in (5, 6)]
    t = runs[0].transients
    lengths = t.path_start + (np.arange(t.n_bins) + 0.5) * t.path_bin_width   # bin centres
    energy = np.array([d.transients.transients[:, 0].sum(axis=1, dtype=float) for d in runs])
    path = np.array([(d.transients.transients[:, 0].astype(float) @ lengths) / e
                     for d, e in zip(runs, energy)])
    ref_energy, ref_path = ball_energy_numpy(runs[0].tx, runs[0].rx,
                                             np.array([0.03, -0.02, 0.15]), 0.005)
    # Monte-Carlo standard error of the mean of the two runs, pooled over the poses.
    se_energy = np.sqrt(np.mean((energy[0] - energy[1]) ** 2 / 2) / 2)
    se_path = np.sqrt(np.mean((path[0] - path[1]) ** 2 / 2) / 2)
    rel = np.abs(energy.mean(axis=0) / ref_energy - 1)
    # 4 standard errors, plus the mesh (an icosphere, 0.2 % less area) and quadrature.
    assert np.all(rel < 4 * se_energy / ref_energy + 3e-3), (rel, se_energy / ref_energy)
    assert np.all(np.abs(path.mean(axis=0) - ref_path) < 4 * se_path + 2e-5)
    assert np.all(se_energy / ref_energy < 0.01)          # the estimate is a precise one


def test_snr_and_same_seed_identical(tmp_path):
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:5:2", box=spec.box)
    clean = sim.simulate(spec, poses, tmp_path / "clean.h5", settings())
    noisy = sim.simulate(spec, poses, tmp_path / "noisy.h5", settings(snr_db=12.0))
    again = sim.simulate(spec, poses, tmp_path / "again.h5", settings(snr_db=12.0))
    assert filecmp.cmp(noisy, again, shallow=False)
    single = sim.simulate(spec, poses, tmp_path / "single.h5", settings(snr_db=12.0, threads=1))
    assert filecmp.cmp(noisy, single, shallow=False)      # default threads: all cores
    assert not (tmp_path / ".noisy.h5.noiseless").exists()
    a, b = SonarDataset.read(clean), SonarDataset.read(noisy)
    noise = b.waveforms.astype(float) - a.waveforms
    # The added noise tops the measured Monte-Carlo noise up to the requested total SNR,
    # in the unchanged definition of signal_power (sonarsim.fidelity.noise_budget).
    p_mc = b.meta["mc_noise_power"]
    p_s = signal_power(a.waveforms) - p_mc
    assert 0 < p_mc < 10 ** -1.2 * p_s                 # reachable at these settings
    assert np.std(noise) == pytest.approx(b.meta["noise_sigma"], rel=0.02)
    assert b.meta["noise_sigma"] ** 2 == pytest.approx(p_s * 10 ** -1.2 - p_mc, rel=1e-6)
    assert b.meta["effective_snr_db"] == pytest.approx(12.0, abs=1e-6)
    assert b.snr_db == 12.0 and b.meta["noise_sigma"] > 0
    other = SonarDataset.read(sim.simulate(spec, poses, tmp_path / "other.h5",
                                           settings(snr_db=12.0, seed=6)))
    assert not np.array_equal(other.waveforms, b.waveforms)


class Kill(Exception):
    pass


def test_resume_after_kill_matches_uninterrupted(tmp_path, monkeypatch):
    spec = load_scene("tabletop")
    poses = trajectory("cylindrical:7:2", box=spec.box)
    kw = dict(snr_db=15.0, chunk_size=3, keep_transients=True)
    assert settings(**kw).threads is None          # resumed with the default: all threads
    reference = sim.simulate(spec, poses, tmp_path / "ref.h5", settings(**kw))

    out = tmp_path / "run.h5"

    def kill_after_two(stop, n):
        if stop >= 6:
            raise Kill

    with pytest.raises(Kill):        # killed while rendering
        sim.simulate(spec, poses, out, settings(**kw), on_chunk=kill_after_two)
    assert not out.exists() and (tmp_path / ".run.h5.noiseless.partial").exists()

    real_noise = sim.ping_noise
    calls = []

    def noise_then_kill(*args):
        calls.append(args)
        if len(calls) > 1:
            raise Kill
        return real_noise(*args)

    monkeypatch.setattr(sim, "ping_noise", noise_then_kill)
    with pytest.raises(Kill):        # killed while adding noise
        sim.simulate(spec, poses, out, settings(**{**kw, "chunk_size": 5}))
    monkeypatch.setattr(sim, "ping_noise", real_noise)
    assert not out.exists() and (tmp_path / "run.h5.partial").exists()

    sim.simulate(spec, poses, out, settings(**kw))
    assert filecmp.cmp(reference, out, shallow=False)
    ds = SonarDataset.read(out)
    # the stored transients reproduce the noiseless waveforms
    clean = sim.transients_to_waveforms(
        ds.transients.transients, sim.oversampled_pulse(ds.pulse, 20), 20, ds.waveforms.shape[1])
    residual = ds.waveforms - clean
    assert np.std(residual) == pytest.approx(ds.meta["noise_sigma"], rel=0.1)


def test_changed_settings_refuse_to_resume(tmp_path):
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:4:1", box=spec.box)
    out = tmp_path / "d.h5"

    def kill(stop, n):
        raise Kill

    with pytest.raises(Kill):
        sim.simulate(spec, poses, out, settings(chunk_size=2), on_chunk=kill)
    with pytest.raises(Exception, match="restart"):
        sim.simulate(spec, poses, out, settings(chunk_size=2, paths_per_pose=300))
    sim.simulate(spec, poses, out, settings(chunk_size=2, paths_per_pose=300), resume=False)
    assert SonarDataset.read(out).meta["paths_per_pose"] == 300


# ----------------------------------------------------------------------------- command line

def test_render_cli_round_trip(tmp_path, capsys):
    out = tmp_path / "t.h5"
    code = cli_main(["render", "sphere", "--poses", "cylindrical:4:1", "--out", str(out),
                     "--paths-per-pose", "300", "--bounces", "2", "--seed", "3",
                     "--no-progress", "--tx-beamwidth", "40"])
    assert code == 0
    t = Transients.read(out)
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:4:1", box=spec.box)
    crop = crop_window(poses, spec.box, t.sound_speed, FS)
    assert t.transients.shape == (4, 2, crop.num_samples * 20)
    assert t.path_start == pytest.approx(crop.min_dist - t.path_bin_width / 2)   # aligned
    np.testing.assert_allclose(t.tx, poses.tx)
    assert t.meta["scene"] == "sphere" and t.meta["beams"]["tx_beamwidth"] == 40.0
    assert t.transients[:, 0].sum() > 0

    out2 = tmp_path / "t2.h5"
    code = cli_main(["render", "sphere", "--poses", "cylindrical:2:1", "--out", str(out2),
                     "--path-range", "1.5", "1.6", "--paths-per-pose", "100", "--no-progress"])
    assert code == 0
    t = Transients.read(out2)
    assert t.path_start == 1.5 and t.n_bins == int(np.ceil(0.1 / t.path_bin_width - 1e-9))


def test_render_and_simulate_share_the_aligned_window(tmp_path):
    """The default render window is simulate's: a render file decimated at bins 0, K, 2K, ...
    gives values at the dataset's sample times; the stored transients (the mean of the two
    half-estimates) are exactly what the waveforms were made from."""
    from sonarsim.render import render_poses as render
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:3:1", box=spec.box)
    ds = SonarDataset.read(sim.simulate(spec, poses, tmp_path / "d.h5",
                                        settings(keep_transients=True)))
    t = render(spec.to_mitsuba(), poses, paths_per_pose=4000, bounces=2, seed=5, box=spec.box,
               progress=False)
    assert t.path_start == ds.transients.path_start and t.n_bins == ds.transients.n_bins
    pulse_os = sim.oversampled_pulse(ds.pulse, 20)
    again = sim.transients_to_waveforms(ds.transients.transients, pulse_os, 20, ds.n_samples)
    np.testing.assert_allclose(again, ds.waveforms, rtol=0, atol=1e-6 * np.abs(again).max())
    # Bounce-1 energy of an independent render agrees (both estimates are unbiased).
    e_render = t.transients[:, 0].sum(axis=1, dtype=float)
    e_sim = ds.transients.transients[:, 0].sum(axis=1, dtype=float)
    np.testing.assert_allclose(e_render, e_sim, rtol=0.03)
    np.testing.assert_allclose(t.path_lengths()[::20], ds.sample_path_lengths(), rtol=0,
                               atol=1e-12)
    assert ds.meta["amplitude_model"] == "intensity"


def test_reference_parity_cli(tmp_path):
    out = tmp_path / "d.h5"
    code = cli_main(["simulate", "sphere", "--poses", "cylindrical:3:1", "--out", str(out),
                     "--paths-per-pose", "300", "--reference-parity", "--no-progress"])
    assert code == 0
    ds = SonarDataset.read(out)
    assert ds.meta["bounce_set"] == [1] and ds.meta["bounces"] == 1
    assert ds.meta["reference_parity"] is True and ds.meta["rx_target"] == [0.0, 0.0, 0.09]
    beams = ds.meta["beams"]
    assert beams["tx_beam"] == "isotropic" and (beams["rx_beam"], beams["rx_beamwidth"]) == ("cone", 25.0)
    aim = np.array([0.0, 0.0, 0.09]) - ds.rx
    np.testing.assert_allclose(ds.receiver_boresight, aim / np.linalg.norm(aim, axis=1)[:, None],
                               atol=1e-12)
    spec = load_scene("sphere")
    np.testing.assert_allclose(ds.boresight, trajectory("cylindrical:3:1", box=spec.box).tx_boresight)

    t_out = tmp_path / "t.h5"
    assert cli_main(["render", "sphere", "--poses", "cylindrical:3:1", "--out", str(t_out),
                     "--paths-per-pose", "300", "--reference-parity", "--no-progress"]) == 0
    t = Transients.read(t_out)
    assert t.n_bounces == 1 and t.meta["reference_parity"] is True
    assert t.meta["beams"]["tx_beam"] == "isotropic"


@pytest.mark.parametrize("argv, message", [
    (["render", "nosuch", "--poses", "sparse:4"], "nosuch"),
    (["render", "sphere", "--poses", "zigzag"], "trajectory"),
    (["simulate", "sphere", "--poses", "cylindrical:2:1", "--pulse", "lfm:1"], "lfm"),
    (["simulate", "sphere", "--poses", "cylindrical:2:1", "--bounce-set", "x"], "bounce-set"),
    (["simulate", "sphere", "--poses", "cylindrical:2:1", "--isotropic", "--tx-beam", "cone"],
     "isotropic"),
    (["simulate", "sphere", "--poses", "cylindrical:2:1", "--reference-parity",
      "--rx-beamwidth", "30"], "--rx-beamwidth"),
    (["simulate", "sphere", "--poses", "cylindrical:2:1", "--reference-parity",
      "--bounce-set", "1,2"], "--bounce-set"),
    (["render", "sphere", "--poses", "cylindrical:2:1", "--reference-parity", "--isotropic"],
     "--isotropic"),
])
def test_cli_errors_are_one_line(tmp_path, capsys, argv, message):
    code = cli_main(argv + ["--out", str(tmp_path / "x.h5"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


def test_simulate_cli(tmp_path, capsys):
    out = tmp_path / "d.h5"
    code = cli_main(["simulate", "cube", "--poses", "cylindrical:3:1", "--out", str(out),
                     "--paths-per-pose", "300", "--snr-db", "20", "--bounce-set", "1",
                     "--pulse", "lfm-5k", "--keep-transients", "--no-progress"])
    assert code == 0
    ds = SonarDataset.read(out)
    assert ds.snr_db == 20.0 and ds.transients.n_bounces == 1
    assert ds.meta["bounce_set"] == [1] and ds.meta["pulse_spec"] == "lfm-5k"
    np.testing.assert_array_equal(ds.pulse, named_pulse("lfm-5k", FS))
