"""From a scene and poses to a sonar dataset: render -> pulse convolution -> decimation -> noise.

The pipeline follows the reference (reference code `airsas/reconstruct_from_numpy.py`), streamed over chunks of poses:

1. **Window.** The crop window of the scene box (reference code `airsas/reconstruct_airsas_scene.py` step 5, pulse length
   min(L, 100) samples): waveform sample k of every ping is at time (start_sample + k)/fs,
   start_sample = the window's ``min_sample``.
2. **Render** energy transients over round-trip path length with bins of
   w = c/(fs·K) (K = ``oversample``). The integrator splats a path of length L between the
   two bins whose *centres* enclose it, so bin j stands for path length
   path_start + (j + ½)·w. We set path_start = min_sample·c/fs − w/2: the centre of bin
   j·K is then exactly the path length c·(start_sample + j)/fs of waveform sample j.
3. **Bounces.** Sum the histograms of the chosen bounces (default: all rendered).
4. **Convolve** with the transmitted pulse resampled ×K by Fourier interpolation
   (``scipy.signal.resample``, as the reference), by FFT over the oversampled histogram,
   zero-padded so the convolution is linear, not circular. An echo at path length L then
   starts at time L/c.
5. **Decimate**: keep every K-th sample (bins 0, K, 2K, ...). No anti-alias filter is
   needed because the resampled pulse is band-limited below fs/2.
6. **Noise** (``snr_db`` given): white Gaussian noise that tops the measured Monte-Carlo
   noise up to the requested *total* SNR, in the unchanged definition of
   :func:`sonarsim.signals.signal_power` over the whole dataset:
   σ² = P_s·10^(−SNR/10) − P_mc (:func:`sonarsim.fidelity.noise_budget`). Ping i's noise
   is σ·z_i with z_i drawn from its own generator seeded by (seed, i), so it does not
   depend on the chunking or on where a run was resumed.

**Fidelity.** Every pose is rendered as two independent half-estimates in one launch
(``sonarsim.render.iter_render(..., halves=True)``, the one render loop); the dataset holds
their mean, and their half
difference gives the Monte-Carlo SNR after matched filtering stored as
``meta['mc_snr_db']`` (:mod:`sonarsim.fidelity`). Without an explicit density a pilot
chooses it for ``mc_snr_db`` (:func:`choose_sampling`). docs/simulation.md "What fidelity
a dataset has".

**Amplitude model** (``amplitude``, stored as ``meta['amplitude_model']``): 'intensity'
(energy histogram ⊗ pulse, the reference's simulation), 'pressure' or 'coherent' (complex
histograms convolved with the analytic pulse, real part kept); docs/simulation.md.

**Streaming and resuming.** Chunks go through :class:`sonarsim.dataset.DatasetStreamWriter`
into ``<out>.partial``; a killed run resumes where it stopped. Without noise that is the
output file. With noise, σ depends on all pings, so the noiseless dataset is streamed into
a hidden scratch file ``.<out name>.noiseless`` first, then the noisy dataset is streamed
from it into ``<out>`` (also resumable) and the scratch file is deleted. Memory is bounded by
one chunk of histograms plus the N×T noiseless waveforms (155 MB for the 54 000-ping scan).

**Determinism.** A pose's random numbers depend on (seed, global pose index, path) only.
Threads add into the histograms in a varying order, but the integrator sums in float64 and
rounds to float32 once, so the same inputs and seed give the same bytes whatever the thread
count, chunking or resume point (measured; docs/simulation.md "Reproducibility"), except
that a float64 sum lying within ~1e-16 of a float32 rounding boundary could in principle
round to the neighbouring float32 (1 ulp). ``threads`` (default None: Dr.Jit's setting, all
cores) only changes the speed.
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import scipy.fft

from . import __version__
from .dataset import DatasetStreamWriter, TransientsLayout, inspect
from .errors import FormatError, InputError
from .geometry import CropWindow, Poses, crop_window
from .render import (DEFAULT_BEAMS, DEFAULT_SOUND_SPEED, PathWindow, RenderSettings,
                     aligned_window, iter_render, make_integrator)
from .scene import SceneSpec
from .signals import REFERENCE_PULSE_SAMPLES, Pulse, analytic, fft_upsample
from .identity import digest
from .fidelity import PingStats, mc_snr_from_energies, noise_budget, snr_db
from .halves import Sampling, default_surface_spacing, half_seed
from .progress import progress_bar
from .threads import dr_threads

NOISE_STREAM = 0x6E6F6973   # spawn key that separates the noise generators from other uses
CONVOLVE_BLOCK = 128        # pings per FFT block (bounds the temporary arrays)


# ----------------------------------------------------------------------------- signal model

def simulation_window(poses: Poses, spec: SceneSpec, pulse: Pulse, sound_speed: float,
                      oversample: int) -> tuple[CropWindow, PathWindow]:
    """The crop window (samples at fs) and the aligned histogram window (see module doc)."""
    crop = crop_window(poses, spec.box, sound_speed, pulse.fs,
                       pulse_samples=min(len(pulse.samples), REFERENCE_PULSE_SAMPLES))
    width = sound_speed / (pulse.fs * oversample)
    return crop, aligned_window(crop, width, oversample)


def preflight(spec: SceneSpec, poses: Poses,
              settings: "SimulationSettings") -> tuple[CropWindow, PathWindow]:
    """Every check of a simulation that needs no rendering, before any work: the settings
    (:meth:`SimulationSettings.validate`), the sample rate and pulse length
    (:mod:`sonarsim.limits`), a pulse that is not all zero, and the memory estimate.
    One-line :class:`InputError` naming the command-line option; ``sonarsim simulate`` and
    ``sonarsim batch`` (each job, while planning) call it alike. Returns the crop window
    and the aligned histogram window."""
    from . import limits
    pulse = settings.pulse
    limits.check_fs(pulse.fs)
    limits.check_pulse_length(len(pulse.samples), pulse.fs, f"pulse {pulse.spec}")
    if not np.any(pulse.samples):
        raise InputError(f"pulse {pulse.spec} is all zero: every waveform would be zero")
    settings.validate()
    crop, window = simulation_window(poses, spec, pulse, settings.sound_speed,
                                     settings.oversample)
    need, detail = limits.simulate_memory(len(poses), settings.bounces, window.n_bins,
                                          crop.num_samples, len(pulse.samples),
                                          settings.oversample, settings.chunk_size,
                                          CONVOLVE_BLOCK)
    limits.check_memory(need, "the simulation", detail,
                        "lower --fs or --oversample, shorten the pulse or simulate fewer poses")
    return crop, window


def oversampled_pulse(pulse: np.ndarray, oversample: int) -> np.ndarray:
    """The pulse at fs·oversample by Fourier interpolation [L·oversample] (reference code `airsas/reconstruct_from_numpy.py`)."""
    return fft_upsample(np.asarray(pulse, float), oversample)


def transients_to_waveforms(hist: np.ndarray, pulse_os: np.ndarray, oversample: int,
                            n_samples: int, bounce_index: Sequence[int] | None = None
                            ) -> np.ndarray:
    """Waveforms float32 [n, n_samples] from histograms [n, B, T_bins] (T_bins >= n_samples·K).

    Sums the bounces ``bounce_index`` (0-based; default all), convolves (linearly, by FFT)
    with ``pulse_os`` (the pulse at fs·K, sample 0 at t = 0) and keeps bins 0, K, 2K, ...
    Complex histograms (amplitude models 'pressure', 'coherent') are convolved with the
    analytic pulse p + i·H{p} and the real part is kept.
    """
    hist = np.asarray(hist)
    if hist.ndim != 3:
        raise InputError(f"transients must be [n, B, T], got shape {hist.shape}")
    k = int(oversample)
    n_bins = hist.shape[2]
    if n_samples * k > n_bins:
        raise InputError(f"{n_samples} samples x oversample {k} exceed the {n_bins} bins")
    index = list(range(hist.shape[1])) if bounce_index is None else list(bounce_index)
    out = np.empty((hist.shape[0], n_samples), np.float32)
    if np.iscomplexobj(hist):
        # Complex amplitudes A·e^{iφ}: Re(A e^{iφ} (p + i·H p)), the pulse shifted in phase by φ.
        n_fft = scipy.fft.next_fast_len(n_bins + len(pulse_os) - 1)
        pulse_spectrum = scipy.fft.fft(analytic(pulse_os), n_fft)
        for a in range(0, hist.shape[0], CONVOLVE_BLOCK):
            block = hist[a:a + CONVOLVE_BLOCK][:, index].sum(axis=1, dtype=np.complex128)
            full = scipy.fft.ifft(scipy.fft.fft(block, n_fft, axis=-1) * pulse_spectrum,
                                  n_fft, axis=-1)
            out[a:a + CONVOLVE_BLOCK] = full[:, :n_samples * k:k].real
        return out
    n_fft = scipy.fft.next_fast_len(n_bins + len(pulse_os) - 1, real=True)
    pulse_spectrum = scipy.fft.rfft(pulse_os, n_fft)
    for a in range(0, hist.shape[0], CONVOLVE_BLOCK):
        block = hist[a:a + CONVOLVE_BLOCK][:, index].sum(axis=1, dtype=np.float64)
        full = scipy.fft.irfft(scipy.fft.rfft(block, n_fft, axis=-1) * pulse_spectrum, n_fft,
                               axis=-1)
        out[a:a + CONVOLVE_BLOCK] = full[:, :n_samples * k:k]
    return out


def ping_noise(seed: int, start: int, stop: int, n_samples: int) -> np.ndarray:
    """Unit-variance Gaussian noise float64 [stop − start, n_samples] for pings start..stop−1.

    Ping i's noise comes from a generator seeded by (seed, i) only.
    """
    out = np.empty((stop - start, n_samples))
    for row, ping in enumerate(range(start, stop)):
        seq = np.random.SeedSequence(int(seed), spawn_key=(NOISE_STREAM, ping))
        out[row] = np.random.default_rng(seq).standard_normal(n_samples)
    return out


# ----------------------------------------------------------------------------- pipeline

DEFAULT_MC_SNR_DB = 30.0          # --mc-snr-db default: Monte-Carlo SNR after matched filtering
DEFAULT_PATHS_PER_POSE = 10_000   # the pilot's base density (and the integrator's paths)
MAX_AUTO_PATHS = 1_000_000        # the most paths per pose the automatic density chooses
MIN_AUTO_SPACING = 2e-4           # m: the finest surface strata the automatic density chooses
PILOT_POSES = 24                  # poses of the pilot runs (evenly spread over the trajectory)
PILOT_SCALES = (0.25, 1.0)        # pilot densities relative to the base density
PILOT_REFINEMENTS = 1             # extra pilot runs at the planned density, to refit
AUTO_MARGIN_DB = 1.5              # aim this much above the target (the pilot is an estimate)
SHORTFALL_DB = 0.5                # a measured SNR this far below the target is reported
# Keys measured during a run and added to the dataset's meta when it is finished.
MEASURED_KEYS = ("mc_snr_db", "mc_noise_power", "effective_snr_db", "mc_snr_raw_db",
                 "noise_sigma")


@dataclass
class SimulationSettings:
    """Everything that determines a simulated dataset besides the scene and the poses.

    Sampling density: ``paths_per_pose`` (TX-cone paths, both half-estimates together) and
    ``surface_spacing`` (the surface estimator of bounce 1, if the integrator has one).
    If both are None the density is chosen by a pilot run to reach ``mc_snr_db``
    (default :data:`DEFAULT_MC_SNR_DB`) Monte-Carlo SNR after matched filtering.
    ``amplitude``: 'intensity' | 'pressure' | 'coherent'; ``speckle_seed`` seeds the
    coherent model's phases; ``bounce1``: the integrator's bounce-1 estimator (None: its
    default). ``log``: where one-line notices go (default: stderr).
    """
    pulse: Pulse
    snr_db: float | None = None
    paths_per_pose: int | None = None
    bounces: int = 1                               # single scattering, as the reference
    bounce_set: tuple[int, ...] | None = None     # 1-based; None = all rendered
    oversample: int = 20
    sound_speed: float = DEFAULT_SOUND_SPEED
    seed: int = 0
    beams: Mapping | None = None
    keep_transients: bool = False
    chunk_size: int | None = None
    threads: int | None = None                    # Dr.Jit threads; None: all (Dr.Jit's default)
    extra_meta: dict = field(default_factory=dict)
    mc_snr_db: float | None = None
    surface_spacing: float | None = None
    amplitude: str = "intensity"
    speckle_seed: int = 0
    bounce1: str | None = None
    log: Callable[[str], None] | None = None

    def validate(self) -> None:
        """Check every setting once (one-line InputError naming the command-line option):
        the render settings by :meth:`sonarsim.render.RenderSettings.validate` and the
        integrator plugin, the rest here."""
        if self.paths_per_pose is not None and (
                isinstance(self.paths_per_pose, bool)
                or not isinstance(self.paths_per_pose, (int, float, np.number))
                or not math.isfinite(self.paths_per_pose)
                or int(self.paths_per_pose) != self.paths_per_pose or self.paths_per_pose < 2):
            raise InputError(f"--paths-per-pose must be an integer >= 2 (two half-estimates), "
                             f"got {self.paths_per_pose}")
        self.render_settings().validate()
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or not 0 <= self.seed < 2**31:
            raise InputError(f"--seed must be an integer in [0, 2^31), got {self.seed}")
        if self.bounce_set is not None:
            if not self.bounce_set or any(b < 1 or b > self.bounces for b in self.bounce_set):
                raise InputError(f"bounce set {list(self.bounce_set)} must be within "
                                 f"1..{self.bounces} (the rendered bounces)")
        for name in ("snr_db", "mc_snr_db"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float, np.number))
                                          and math.isfinite(value)):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number, "
                                 f"got {value}")
        from .threads import check_threads
        check_threads(self.threads)
        if self.keep_transients and self.amplitude == "coherent":
            raise InputError(f"--keep-transients stores energy histograms; amplitude "
                             f"'{self.amplitude}' renders complex ones (not stored)")
        make_integrator(self.render_settings())    # the plugin checks the estimator options

    def render_settings(self, sampling: Sampling | None = None) -> RenderSettings:
        """The :class:`sonarsim.render.RenderSettings` of this simulation at ``sampling``
        (default: the explicit density, else the pilot's base density)."""
        paths = sampling.paths_per_pose if sampling is not None else self.paths_per_pose
        spacing = sampling.surface_spacing if sampling is not None else self.surface_spacing
        return RenderSettings(
            paths_per_pose=paths if paths is not None else DEFAULT_PATHS_PER_POSE,
            bounces=self.bounces, fs=self.pulse.fs, oversample=self.oversample,
            sound_speed=self.sound_speed, seed=self.seed, beams=self.beams,
            bounce1=self.bounce1, amplitude=self.amplitude, surface_spacing=spacing,
            speckle_seed=self.speckle_seed, chunk_size=self.chunk_size)

    @property
    def bounce_index(self) -> list[int]:
        chosen = self.bounce_set or tuple(range(1, self.bounces + 1))
        return sorted({b - 1 for b in chosen})

    @property
    def automatic(self) -> bool:
        """Whether the sampling density is chosen from ``mc_snr_db`` by a pilot run."""
        return self.paths_per_pose is None and self.surface_spacing is None

    @property
    def target_mc_snr_db(self) -> float | None:
        """The Monte-Carlo SNR the run aims at (None: explicit density, no target)."""
        if self.mc_snr_db is not None:
            return float(self.mc_snr_db)
        return DEFAULT_MC_SNR_DB if self.automatic else None

    def say(self, message: str) -> None:
        (self.log or _stderr)(message)


def _stderr(message: str) -> None:
    """The default notice channel: the ``sonarsim.simulate`` logger at INFO (the CLI shows
    it on stderr as ``sonarsim simulate: ...``; ``--quiet`` silences it)."""
    import logging
    logging.getLogger(__name__).info(message)


def scratch_path(out: Path) -> Path:
    """The hidden noiseless intermediate dataset of a noisy simulation to ``out``."""
    return out.with_name(f".{out.name}.noiseless")


def simulate(spec: SceneSpec, poses: Poses, out: str | os.PathLike, settings: SimulationSettings,
             *, resume: bool = True, progress: bool = False,
             on_chunk: Callable[[int, int], None] | None = None) -> Path:
    """Simulate a :class:`sonarsim.dataset.SonarDataset` of ``spec`` seen from ``poses`` into ``out``.

    ``resume``: continue an interrupted run with the same settings (else start over).
    ``on_chunk(stop, n)`` is called after each rendered chunk is stored (for progress
    reports and tests). Returns the output path. The dataset's meta records the sampling
    density used and the measured fidelity (``mc_snr_db``; with noise also
    ``effective_snr_db``; :mod:`sonarsim.fidelity`).
    """
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError(f"{out}: output directory does not exist")
    pulse = settings.pulse
    crop, window = preflight(spec, poses, settings)
    scene = spec.to_mitsuba()
    with dr_threads(settings.threads):
        sampling, choice = choose_sampling(scene, poses, settings, crop, window)
    gt = spec.gt_mesh()
    common = dict(
        n_samples=crop.num_samples, tx=poses.tx, rx=poses.rx, boresight=poses.tx_boresight,
        rx_boresight=None if np.array_equal(poses.tx_boresight, poses.rx_boresight)
        else poses.rx_boresight,
        pulse=pulse.samples, fs=pulse.fs, sound_speed=float(settings.sound_speed),
        source="simulated", start_sample=crop.min_sample,
        gt_vertices=np.asarray(gt.vertices, float) if len(gt.faces) else None,
        gt_faces=np.asarray(gt.faces, np.int64) if len(gt.faces) else None,
        seed=int(settings.seed))
    meta = _meta(spec, settings, crop, window, sampling, choice)
    meta["run_id"] = _run_id(common, meta)
    layout = None
    if settings.keep_transients:
        layout = TransientsLayout(settings.bounces, window.n_bins, window.path_start,
                                  window.bin_width, float(settings.sound_speed), pulse.fs,
                                  int(settings.oversample),
                                  {"paths_per_pose": sampling.paths_per_pose,
                                   "seed": int(settings.seed)})
    noisy = settings.snr_db is not None
    first = scratch_path(out) if noisy else out
    if not resume:
        for path in (out, first):
            with contextlib.suppress(FileNotFoundError):
                Path(os.fspath(path) + ".partial").unlink()
        with contextlib.suppress(FileNotFoundError):
            scratch_path(out).unlink()

    measured = _scratch_measures(first, meta) if noisy else None
    if measured is None:
        writer = _open_writer(first, common, meta, layout, None)
        try:
            _render_into(writer, scene, poses, settings, sampling, crop, window, progress,
                         on_chunk)
            totals = {name: float(np.sum(writer.stats(name))) for name in PingStats.NAMES}
            measured = {"mc_snr_db": mc_snr_from_energies(totals["mf_total"], totals["mf_noise"]),
                        "mc_noise_energy": totals["raw_noise"]}
            if not noisy:
                _report_shortfall(settings, measured["mc_snr_db"], choice)
            writer.finish(measured)
        finally:
            writer.close()
        if not noisy:
            return out

    # Noise pass: noiseless scratch -> noisy output; the added noise tops the MC noise up.
    with inspect(first) as (_, fields):
        clean = np.asarray(fields["waveforms"][()], np.float32)
        budget = noise_budget(clean, float(settings.snr_db), measured["mc_noise_energy"])
        if not budget.reachable:
            settings.say(f"the Monte-Carlo noise alone gives an SNR of {budget.effective_snr_db:.1f} "
                         f"dB (definition of --snr-db), below the requested {settings.snr_db:g} "
                         f"dB: no noise added; raise --mc-snr-db or the sampling density")
        else:
            _report_shortfall(settings, measured["mc_snr_db"], choice)
        final = {"mc_snr_db": measured["mc_snr_db"], "mc_noise_power": budget.mc_power,
                 "noise_sigma": budget.sigma, "effective_snr_db": budget.effective_snr_db,
                 "mc_snr_raw_db": snr_db(budget.signal_power, budget.mc_power)}
        writer = _open_writer(out, common, meta | final, layout, float(settings.snr_db))
        try:
            chunk = max(1, settings.chunk_size or 1024)
            for start, stop in writer.missing_ranges(chunk):
                noise = ping_noise(settings.seed, start, stop, crop.num_samples)
                wf = (clean[start:stop] + budget.sigma * noise).astype(np.float32)
                tr = None
                if layout is not None:
                    tr = fields["transients"]["transients"][start:stop]
                writer.write(start, wf, tr)
            writer.finish()
        finally:
            writer.close()
    scratch_path(out).unlink()
    return out


def _report_shortfall(settings: SimulationSettings, measured: float, choice: dict) -> None:
    """Say once that the run missed its Monte-Carlo SNR target (unless already said)."""
    target = settings.target_mc_snr_db
    if target is None or choice.get("warned") or not measured < target - SHORTFALL_DB:
        return
    settings.say(f"measured Monte-Carlo SNR {measured:.1f} dB after matched filtering, below "
                 f"the requested {target:g} dB ({choice.get('sampling', '')}); raise the "
                 f"sampling density (--paths-per-pose, --surface-spacing)")


# ----------------------------------------------------------------------------- density

def pilot_indices(n: int, count: int = PILOT_POSES) -> np.ndarray:
    """``count`` pose indices spread evenly over 0..n−1 (all of them if n <= count)."""
    if n <= count:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, count)).astype(int))


def _groups(settings: SimulationSettings, sampling: Sampling) -> dict[str, list[int]]:
    """Bounce indices (0-based, summed into the waveforms) per estimator part, for the
    pilot's report: 'surface' (bounce 1 by the surface estimator) and 'paths' (bounces
    >= 2, continued from the surface samples or traced from the TX; with the cone
    estimator bounce 1 too)."""
    chosen = settings.bounce_index
    if sampling.surface_spacing is None:
        return {"paths": chosen}
    out = {"surface": [b for b in chosen if b == 0], "paths": [b for b in chosen if b > 0]}
    return {k: v for k, v in out.items() if v}


def measure_fidelity(scene, poses: Poses, settings: SimulationSettings, sampling: Sampling,
                     crop: CropWindow, window: PathWindow, seed: int | None = None) -> dict:
    """Render ``poses`` at ``sampling`` and measure their Monte-Carlo SNR (no file written).

    Returns {'mc_snr_db', 'mf_total', 'mf_noise', 'groups': {name: noise energy},
    'seconds'}: matched-filter energies summed over the poses, the noise also split by
    sampling control (:func:`_groups`).
    """
    import time
    from .fidelity import mf_energy
    render = settings.render_settings(sampling).replace(
        seed=settings.seed if seed is None else seed)
    pulse_os = oversampled_pulse(settings.pulse.samples, settings.oversample)
    groups = _groups(settings, sampling)
    total = noise = 0.0
    by_group = dict.fromkeys(groups, 0.0)
    t0 = time.perf_counter()
    for _, both in iter_render(scene, poses, render, window=window, halves=True):
        mean, diff = _mean_and_difference(both)
        stats = _chunk_stats(mean, diff, pulse_os, settings, crop)[1]
        total += float(stats.mf_total.sum())
        noise += float(stats.mf_noise.sum())
        for name, index in groups.items():
            d = transients_to_waveforms(diff, pulse_os, settings.oversample, crop.num_samples,
                                        index)
            by_group[name] += float(mf_energy(d, settings.pulse.samples).sum())
    return {"mc_snr_db": mc_snr_from_energies(total, noise), "mf_total": total,
            "mf_noise": noise, "groups": by_group, "seconds": time.perf_counter() - t0}


def choose_sampling(scene, poses: Poses, settings: SimulationSettings, crop: CropWindow,
                    window: PathWindow) -> tuple[Sampling, dict]:
    """The sampling density of a run and a record of how it was chosen.

    Explicit settings are used as given (paths rounded up to an even count). Otherwise a
    pilot renders :data:`PILOT_POSES` poses spread over the trajectory at two densities
    (:data:`PILOT_SCALES` of the base density) and measures the Monte-Carlo noise after
    matched filtering at both. The noise is fitted by a power law in the sampling density
    (:func:`_density`: surface samples per m² with the surface estimator, whose samples
    also start the paths of bounces >= 2, else TX-cone paths per pose), in dB per decade
    clamped to 10..40 (independent samples give 10, stratified quadrature more), and the
    density is set to reach the target plus :data:`AUTO_MARGIN_DB`. Up to
    :data:`PILOT_REFINEMENTS` more pilots at the planned density refit the law. At most
    :data:`MAX_AUTO_PATHS` paths per pose and strata no smaller than
    :data:`MIN_AUTO_SPACING`; if a cap binds the run says so once, with the SNR it expects.
    Never coarser than the base density (the integrator's strata, 10 000 paths): the law
    is not extrapolated below the pilots.
    """
    integrator = make_integrator(settings.render_settings())
    spacing = (settings.surface_spacing if settings.surface_spacing is not None
               else default_surface_spacing(integrator))
    paths = settings.paths_per_pose or DEFAULT_PATHS_PER_POSE
    base = Sampling(int(paths) + int(paths) % 2, spacing)
    if not settings.automatic:
        return base, {"mode": "explicit", "sampling": base.describe()}
    target = settings.target_mc_snr_db
    sub = poses[pilot_indices(len(poses))]
    pilot_seed = half_seed(settings.seed ^ 0x5EED, 0) >> 1
    runs = []
    for scale in PILOT_SCALES:
        s = base.scaled(scale, MAX_AUTO_PATHS)
        if s.surface_spacing is not None:           # paths unused: keep them
            s = Sampling(base.paths_per_pose, s.surface_spacing)
        runs.append((s, measure_fidelity(scene, sub, settings, s, crop, window, pilot_seed)))
    record = {"mode": f"automatic (target {target:g} dB)", "pilot_poses": len(sub)}
    for _ in range(PILOT_REFINEMENTS + 1):
        (s0, r0), (s1, r1) = runs[-2:]
        plan = _plan(base, s0, r0, s1, r1, target)
        if plan is None:                      # no signal or no noise: any density will do
            record["sampling"] = base.describe()
            break
        chosen, want, expected, slopes = plan
        record.update(slopes_db_per_decade={g: round(v, 2) for g, v in slopes.items()},
                      sampling=chosen.describe(), expected_mc_snr_db=round(expected, 2))
        if abs(expected - r1["mc_snr_db"]) < AUTO_MARGIN_DB or chosen in (s0, s1):
            break                             # the last pilot already measured this density
        runs.append((chosen, measure_fidelity(scene, sub, settings, chosen, crop, window,
                                              pilot_seed)))
    record["pilot"] = [{"sampling": s.describe(), "mc_snr_db": round(r["mc_snr_db"], 2)}
                       for s, r in runs]
    if plan is None:
        return base, record
    if want != chosen and expected < target:
        settings.say(f"a Monte-Carlo SNR of {target:g} dB after matched filtering needs about "
                     f"{want.describe()} (pilot on {len(sub)} poses: {r1['mc_snr_db']:.1f} dB at "
                     f"{s1.describe()}); the density is capped at {chosen.describe()}, which "
                     f"should give about {expected:.1f} dB")
        record["warned"] = True
    return chosen, record


def _density(s: Sampling) -> float:
    """The sampling density that a run's noise depends on: surface samples per m² when
    bounce 1 is a surface integral (bounces >= 2 then continue from those samples),
    else TX-cone paths per pose."""
    return s.surface_spacing ** -2 if s.surface_spacing is not None else float(s.paths_per_pose)


def _plan(base: Sampling, s0: Sampling, r0: dict, s1: Sampling, r1: dict, target: float):
    """(chosen, wanted without caps, expected SNR of chosen, slope) from two pilot runs
    (see :func:`choose_sampling`), or None without signal or noise."""
    signal = r1["mf_total"] - r1["mf_noise"]
    n0, n1 = r0["mf_noise"], r1["mf_noise"]
    if not (signal > 0 and n1 > 0):
        return None
    budget = signal * 10.0 ** (-(target + AUTO_MARGIN_DB) / 10.0)
    decades = math.log10(_density(s1) / _density(s0))
    slope = 10.0 * math.log10(n0 / n1) / decades if n0 > 0 and abs(decades) > 0.05 else 10.0
    slope = min(40.0, max(10.0, slope))
    factor = (n1 / budget) ** (10.0 / slope)       # density relative to s1

    # Never coarser than the base density (the integrator's default strata, the base
    # paths): the power law is measured between the pilots, and a coarser density
    # extrapolated from them (e.g. 161 mm strata for centimetre objects, issue 24) misses
    # its target; the base density costs little and measured at least the pilot's SNR.
    def build(max_paths: int, min_spacing: float) -> Sampling:
        if s1.surface_spacing is not None:         # the paths do not matter then
            spacing = min(base.surface_spacing, s1.surface_spacing / math.sqrt(factor))
            return Sampling(base.paths_per_pose, max(min_spacing, spacing))
        p = min(int(max_paths), max(2, base.paths_per_pose, math.ceil(s1.paths_per_pose * factor)))
        return Sampling(p + p % 2, None)

    chosen = build(MAX_AUTO_PATHS, MIN_AUTO_SPACING)
    expected = snr_db(signal, n1 * (_density(chosen) / _density(s1)) ** (-slope / 10.0))
    return chosen, build(2**62, 0.0), expected, {"all": slope}


# ----------------------------------------------------------------------------- rendering

def _mean_and_difference(both: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, half difference) [n, B, T] of two half-estimates [2, n, B, T]."""
    a, b = both[0], both[1]
    dtype = np.result_type(a, np.float32)
    return ((a + b) * 0.5).astype(dtype), ((a - b) * 0.5).astype(dtype)


def _chunk_stats(mean: np.ndarray, diff: np.ndarray, pulse_os: np.ndarray,
                 s: SimulationSettings, crop: CropWindow) -> tuple[np.ndarray, PingStats]:
    """Waveforms of the mean histograms and the Monte-Carlo statistics of the chunk."""
    both = transients_to_waveforms(np.concatenate([mean, diff]), pulse_os, s.oversample,
                                   crop.num_samples, s.bounce_index)
    wf, d = both[:len(mean)], both[len(mean):]
    return wf, PingStats.measure(wf, d, s.pulse.samples)


def _meta(spec: SceneSpec, s: SimulationSettings, crop: CropWindow, window: PathWindow,
          sampling: Sampling, choice: dict) -> dict:
    meta = {"scene": spec.name, "scene_source": spec.source,
            "box": np.stack([spec.box.lo, spec.box.hi], axis=1).tolist(),   # [[x0, x1], ...] m
            "pulse_spec": s.pulse.spec, "paths_per_pose": int(sampling.paths_per_pose),
            "bounces": int(s.bounces), "bounce_set": [b + 1 for b in s.bounce_index],
            "oversample": int(s.oversample), "beams": {**DEFAULT_BEAMS, **dict(s.beams or {})},
            "path_start": window.path_start, "path_bin_width": window.bin_width,
            "crop_min_dist": crop.min_dist, "crop_max_dist": crop.max_dist,
            "amplitude_model": s.amplitude,
            "sampling": {k: v for k, v in choice.items() if k != "warned"},
            "mc_estimate": "two independent half-estimates; mc_snr_db after matched filtering "
                           "(docs/simulation.md)",
            "noise": "white Gaussian; sigma^2 = P_s * 10^(-snr_db/10) - P_mc with P_s, P_mc the "
                     "signal and Monte-Carlo noise power in the signal_power definition; "
                     "ping i seeded by (seed, i)",
            "generator": f"sonarsim {__version__} simulate", **s.extra_meta}
    if sampling.surface_spacing is not None:
        meta["surface_spacing"] = float(sampling.surface_spacing)
    if s.bounce1 is not None:
        meta["bounce1_estimator"] = s.bounce1
    if s.amplitude == "coherent":
        meta["speckle_seed"] = int(s.speckle_seed)
    target = s.target_mc_snr_db
    if target is not None:
        meta["mc_snr_target_db"] = float(target)
    return meta


def _open_writer(path: Path, common: dict, meta: dict, layout, snr_db) -> DatasetStreamWriter:
    try:
        return DatasetStreamWriter(path, **common, meta=meta, snr_db=snr_db,
                                   transients=layout, resume=True)
    except FormatError as exc:
        raise FormatError(f"{exc} (or pass --restart)") from None


def _scratch_measures(path: Path, meta: dict) -> dict | None:
    """The measured values of a finished noiseless scratch file of this very run (None if
    there is none; a stale one is deleted)."""
    if not path.is_file():
        return None
    measured = None
    try:
        with inspect(path) as (_, fields):
            stored = dict(fields["meta"])
            found = {k: stored.pop(k) for k in ("mc_snr_db", "mc_noise_energy") if k in stored}
            if digest(stored) == digest(meta) and len(found) == 2:
                measured = found
    except FormatError:
        measured = None
    if measured is None:
        path.unlink()
    return measured


def _run_id(common: dict, meta: dict) -> str:
    """A digest of everything that determines the noiseless data (detects stale scratch files)."""
    return digest(meta, common)


def _render_into(writer: DatasetStreamWriter, scene, poses: Poses, s: SimulationSettings,
                 sampling: Sampling, crop: CropWindow, window: PathWindow, progress: bool,
                 on_chunk: Callable[[int, int], None] | None) -> None:
    """Render every pose the writer still lacks, chunk by chunk, and store its waveforms
    and per-ping Monte-Carlo statistics.

    A pose's random numbers depend on its global index only, so a resumed run renders
    exactly what an uninterrupted one would.
    """
    spans = writer.missing_ranges(max(1, len(poses)))   # maximal runs of missing poses
    if not spans:
        return
    render = s.render_settings(sampling)
    pulse_os = oversampled_pulse(s.pulse.samples, s.oversample)
    bar = progress_bar(len(poses), progress, unit="ping", desc="simulate",
                       initial=writer.n_done)
    try:
        with dr_threads(s.threads):
            for first, end in spans:
                for sl, both in iter_render(scene, poses, render, window=window, start=first,
                                            stop=end, halves=True):
                    mean, diff = _mean_and_difference(both)
                    del both
                    wf, stats = _chunk_stats(mean, diff, pulse_os, s, crop)
                    del diff
                    writer.write(sl.start, wf, mean if writer.layout is not None else None,
                                 stats={k: getattr(stats, k) for k in PingStats.NAMES})
                    del mean
                    bar.update(sl.stop - sl.start)
                    if on_chunk is not None:
                        on_chunk(sl.stop, len(poses))
    finally:
        bar.close()
