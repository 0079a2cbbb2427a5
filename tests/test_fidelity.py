"""Measured fidelity: the Monte-Carlo SNR a dataset reports against the spread between two
seeds, the total effective SNR of --snr-db, the unchanged additive-noise definition, the
automatic density and its one-line shortfall notice."""
from __future__ import annotations

import numpy as np
import pytest

from sonarsim import simulate as sim
from sonarsim.commands.info import describe
from sonarsim.dataset import SonarDataset
from sonarsim.fidelity import mf_energy, noise_budget
from sonarsim.geometry import trajectory
from sonarsim.halves import Sampling, half_seed
from sonarsim.scene import load_scene
from sonarsim.signals import matched_filter, noise_sigma, pulse_from_spec, signal_power

FS = 100e3


# Coarse surface strata (3 cm) leave clear Monte-Carlo noise (about 23 dB) at little cost.
def settings(**kw) -> sim.SimulationSettings:
    base = dict(pulse=pulse_from_spec("lfm-20k", FS), bounces=2, seed=1, paths_per_pose=4000,
                surface_spacing=0.03)
    base.update(kw)
    return sim.SimulationSettings(**base)


def mf_total(w: np.ndarray, pulse: np.ndarray) -> float:
    """Σ|MF(w)|² by the library's linear matched filter (not the Parseval shortcut)."""
    return float(np.sum(np.abs(matched_filter(w.astype(float), pulse, mode="linear")) ** 2))


@pytest.fixture(scope="module")
def sphere_scan():
    spec = load_scene("sphere")
    return spec, trajectory("cylindrical:12:2", box=spec.box)


def test_mf_energy_is_the_linear_correlation_energy():
    rng = np.random.default_rng(3)
    w, p = rng.standard_normal((4, 57)), rng.standard_normal(9)
    direct = [np.sum(np.correlate(row, p, mode="full") ** 2) for row in w]
    np.testing.assert_allclose(mf_energy(w, p), direct, rtol=1e-10)


def test_additive_noise_definition_unchanged_and_topped_up():
    rng = np.random.default_rng(0)
    clean = np.zeros((5, 200))
    clean[:, 40:120] = rng.standard_normal((5, 80))
    # Without Monte-Carlo noise: exactly the signal_power / noise_sigma definition.
    b = noise_budget(clean, 20.0, 0.0)
    assert b.sigma == pytest.approx(noise_sigma(clean, 20.0), rel=1e-12)
    assert b.effective_snr_db == pytest.approx(20.0, abs=1e-9) and b.reachable
    # With MC noise power P_mc over the 400 support samples: sigma^2 = P_s 10^-2 - P_mc.
    p_mc = 1e-3 * signal_power(clean)
    b = noise_budget(clean, 20.0, p_mc * 400)
    p_s = signal_power(clean) - p_mc
    assert b.sigma ** 2 == pytest.approx(p_s * 1e-2 - p_mc, rel=1e-9)
    assert b.effective_snr_db == pytest.approx(20.0, abs=1e-9)
    # MC noise above the budget: nothing added, the shortfall is reported.
    b = noise_budget(clean, 40.0, p_mc * 400)
    assert b.sigma == 0.0 and not b.reachable and b.effective_snr_db == pytest.approx(30.0, abs=0.01)


def test_half_seeds_are_distinct():
    seeds = {half_seed(s, h) for s in range(2000) for h in (0, 1)}
    assert len(seeds) == 4000


def _spread_snr(w1: np.ndarray, w2: np.ndarray, pulse: np.ndarray) -> float:
    """MC SNR of one dataset after matched filtering from two independent seeds."""
    noise = mf_total(w1 - w2, pulse) / 2                 # one dataset's MC noise energy
    signal = (mf_total(w1, pulse) + mf_total(w2, pulse)) / 2 - noise
    return 10 * np.log10(signal / noise)


def test_mc_snr_matches_the_spread_between_two_seeds(sphere_scan, tmp_path):
    spec, poses = sphere_scan
    ds = [SonarDataset.read(sim.simulate(spec, poses, tmp_path / f"s{seed}.h5",
                                         settings(seed=seed)))
          for seed in (1, 2, 3, 4)]
    spread = np.mean([_spread_snr(ds[i].waveforms, ds[j].waveforms, ds[0].pulse)
                      for i, j in ((0, 1), (2, 3))])
    assert 5 < spread < 27                              # MC noise clearly present
    reported = [d.meta["mc_snr_db"] for d in ds]
    assert np.mean(reported) == pytest.approx(spread, abs=0.75)
    assert max(abs(r - spread) for r in reported) < 1.5


def test_snr_db_20_gives_total_effective_snr_20(sphere_scan, tmp_path):
    """Measured from two seeds: the added noise accounts for the MC noise already there."""
    spec, poses = sphere_scan
    kw = dict(snr_db=20.0)
    ds = [SonarDataset.read(sim.simulate(spec, poses, tmp_path / f"n{seed}.h5",
                                         settings(seed=seed, **kw)))
          for seed in (1, 2)]
    clean = SonarDataset.read(sim.simulate(spec, poses, tmp_path / "c.h5",
                                           settings(seed=1)))
    # Strong enough MC noise that ignoring it would miss 20 dB by more than 0.5 dB.
    assert ds[0].meta["mc_snr_raw_db"] < 26
    support = np.abs(clean.waveforms) > 1e-6 * np.abs(clean.waveforms).max()
    w1, w2 = (d.waveforms.astype(float) for d in ds)
    noise = np.mean(((w1 - w2)[support]) ** 2) / 2       # MC + added, one dataset
    signal = np.mean((((w1 + w2) / 2)[support]) ** 2) - noise / 2
    assert 10 * np.log10(signal / noise) == pytest.approx(20.0, abs=0.5)
    assert ds[0].meta["effective_snr_db"] == pytest.approx(20.0, abs=1e-6)


def test_automatic_density_reaches_its_target_and_says_so_once(tmp_path, monkeypatch):
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:4:2", box=spec.box)
    messages: list[str] = []
    s = settings(paths_per_pose=None, surface_spacing=None, mc_snr_db=22.0, log=messages.append)
    ds = SonarDataset.read(sim.simulate(spec, poses, tmp_path / "auto.h5", s))
    assert ds.meta["mc_snr_db"] >= 22.0 - sim.SHORTFALL_DB and messages == []
    assert ds.meta["sampling"]["mode"].startswith("automatic")
    lines = "\n".join(describe(tmp_path / "auto.h5"))
    assert "Monte-Carlo SNR" in lines and "target 22 dB" in lines
    # Capped density: one notice before the run, none after it.
    monkeypatch.setattr(sim, "MIN_AUTO_SPACING", 0.02)
    s = settings(paths_per_pose=None, surface_spacing=None, mc_snr_db=40.0, log=messages.append)
    ds = SonarDataset.read(sim.simulate(spec, poses, tmp_path / "capped.h5", s))
    assert len(messages) == 1 and "capped" in messages[0] and ds.meta["surface_spacing"] == 0.02
    assert ds.meta["mc_snr_db"] < 40.0


def test_complex_histograms_take_the_real_part_of_the_analytic_pulse():
    from sonarsim.signals import analytic
    k, n = 4, 60
    pulse = pulse_from_spec("lfm-20k", FS).samples[:20]
    pulse_os = sim.oversampled_pulse(pulse, k)
    hist = np.zeros((2, 1, n * k), np.complex64)
    hist[0, 0, 10 * k] = 1.0                       # phase 0: the pulse itself
    hist[1, 0, 10 * k] = 1j                        # phase 90°: minus its Hilbert transform
    wf = sim.transients_to_waveforms(hist, pulse_os, k, n)
    a = analytic(pulse_os)[::k]
    np.testing.assert_allclose(wf[0, 10:30], a.real[:20], atol=1e-5 * np.abs(a).max())
    np.testing.assert_allclose(wf[1, 10:30], -a.imag[:20], atol=1e-5 * np.abs(a).max())
    real = sim.transients_to_waveforms(hist[:1].real, pulse_os, k, n)
    np.testing.assert_allclose(wf[0], real[0], atol=1e-5 * np.abs(a).max())


def test_coherent_speckle_follows_its_own_seed(tmp_path):
    """--seed changes only the sampling noise; --speckle-seed changes the speckle."""
    spec = load_scene("sphere")
    poses = trajectory("cylindrical:4:1", box=spec.box)

    def run(name, **kw):
        s = settings(bounces=1, amplitude="coherent", surface_spacing=0.008, **kw)
        return SonarDataset.read(sim.simulate(spec, poses, tmp_path / name, s))

    a, b, c = run("a.h5", seed=1), run("b.h5", seed=2), run("c.h5", seed=1, speckle_seed=9)
    assert a.meta["amplitude_model"] == "coherent" and c.meta["speckle_seed"] == 9

    def corr(x, y):
        return float(np.sum(x * y) / np.sqrt(np.sum(x * x) * np.sum(y * y)))

    assert corr(a.waveforms, b.waveforms) > 0.99          # same speckle, other MC noise
    assert corr(a.waveforms, c.waveforms) < 0.8           # another speckle realisation


def test_automatic_density_is_never_coarser_than_the_base():
    """Issue 24: a target far below what the pilots measured must not extrapolate the
    power law to strata coarser than the integrator's (it gave 161 mm strata for centimetre
    objects, which then missed the target); nor fewer paths than the base."""
    base = Sampling(10_000, 8e-3)
    s0, s1 = base.scaled(0.25, sim.MAX_AUTO_PATHS), base
    s0 = Sampling(base.paths_per_pose, s0.surface_spacing)
    r0 = {"mf_total": 1.0, "mf_noise": 1e-5}          # 50 dB at 16 mm
    r1 = {"mf_total": 1.0, "mf_noise": 2.5e-6}        # 56 dB at 8 mm
    chosen, want, expected, _ = sim._plan(base, s0, r0, s1, r1, target=20.0)
    assert chosen.surface_spacing == base.surface_spacing and want == chosen
    assert expected == pytest.approx(56.0, abs=0.1)
    paths = Sampling(10_000, None)
    chosen = sim._plan(paths, Sampling(2_500, None), r0, paths, r1, target=20.0)[0]
    assert chosen.paths_per_pose == 10_000
    # A target above the pilots still refines (finer strata).
    finer = sim._plan(base, s0, r0, s1, r1, target=70.0)[0]
    assert finer.surface_spacing < base.surface_spacing
