"""From a scene and poses to a sonar dataset: render -> pulse convolution -> decimation -> noise.

The pipeline follows the reference (REFERENCE_SPEC §6.2), streamed over chunks of poses:

1. **Window.** The crop window of the scene box (REFERENCE_SPEC §1.6 step 5, pulse length
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
6. **Noise** (``snr_db`` given): white Gaussian noise with
   σ² = signal_power(all noiseless waveforms)·10^(−SNR/10) (the SNR definition of
   :func:`sonarsim.signals.signal_power`, over the whole dataset as the reference does).
   Ping i's noise is σ·z_i with z_i drawn from its own generator seeded by (seed, i), so
   it does not depend on the chunking or on where a run was resumed.

**Amplitude model.** The waveforms are intensity-mode, as the reference's simulation: the
energy histogram convolved with the pulse, so an echo's amplitude falls as 1/(r_T² r_R²)
(DESIGN §4), whereas measured AirSAS waveforms are pressure, ∝ 1/(r_T r_R). The dataset
says so in ``meta['amplitude_model'] = 'intensity'``.

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
import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import scipy.fft

from . import __version__
from .dataset import DatasetStreamWriter, TransientsLayout, inspect
from .errors import FormatError, InputError
from .geometry import CropWindow, Poses, crop_window
from .render import DEFAULT_BEAMS, DEFAULT_SOUND_SPEED, PathWindow, aligned_window, iter_render
from .scene import SceneSpec
from .signals import PULSE_HELP, REFERENCE_PULSE_SAMPLES, Pulse, fft_upsample, noise_sigma
from .signals import pulse_from_spec as make_pulse   # the name benchmarks/table2.py uses
from .threads import dr_threads

# Waveforms are energy histograms ⊗ pulse: amplitudes fall as 1/(r_T² r_R²) (the reference's
# intensity mode, DESIGN §4), unlike measured pressure (∝ 1/(r_T r_R)); docs/formats.md.
AMPLITUDE_MODEL = "intensity"
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


def oversampled_pulse(pulse: np.ndarray, oversample: int) -> np.ndarray:
    """The pulse at fs·oversample by Fourier interpolation [L·oversample] (REFERENCE_SPEC §6.2)."""
    return fft_upsample(np.asarray(pulse, float), oversample)


def transients_to_waveforms(hist: np.ndarray, pulse_os: np.ndarray, oversample: int,
                            n_samples: int, bounce_index: Sequence[int] | None = None
                            ) -> np.ndarray:
    """Waveforms float32 [n, n_samples] from histograms [n, B, T_bins] (T_bins >= n_samples·K).

    Sums the bounces ``bounce_index`` (0-based; default all), convolves (linearly, by FFT)
    with ``pulse_os`` (the pulse at fs·K, sample 0 at t = 0) and keeps bins 0, K, 2K, ...
    """
    hist = np.asarray(hist)
    if hist.ndim != 3:
        raise InputError(f"transients must be [n, B, T], got shape {hist.shape}")
    k = int(oversample)
    n_bins = hist.shape[2]
    if n_samples * k > n_bins:
        raise InputError(f"{n_samples} samples x oversample {k} exceed the {n_bins} bins")
    index = list(range(hist.shape[1])) if bounce_index is None else list(bounce_index)
    n_fft = scipy.fft.next_fast_len(n_bins + len(pulse_os) - 1, real=True)
    pulse_spectrum = scipy.fft.rfft(pulse_os, n_fft)
    out = np.empty((hist.shape[0], n_samples), np.float32)
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

@dataclass
class SimulationSettings:
    """Everything that determines a simulated dataset besides the scene and the poses."""
    pulse: Pulse
    snr_db: float | None = None
    paths_per_pose: int = 10_000
    bounces: int = 3
    bounce_set: tuple[int, ...] | None = None     # 1-based; None = all rendered
    oversample: int = 20
    sound_speed: float = DEFAULT_SOUND_SPEED
    seed: int = 0
    beams: Mapping | None = None
    keep_transients: bool = False
    chunk_size: int | None = None
    threads: int | None = None                    # Dr.Jit threads; None: all (Dr.Jit's default)
    extra_meta: dict = field(default_factory=dict)

    def validate(self) -> None:
        for name, lo in (("paths_per_pose", 1), ("bounces", 1), ("oversample", 1), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < lo:
                raise InputError(f"{name} must be an integer >= {lo}, got {value}")
        if self.seed >= 2**32:
            raise InputError(f"seed must be < 2^32, got {self.seed}")
        if self.bounce_set is not None:
            if not self.bounce_set or any(b < 1 or b > self.bounces for b in self.bounce_set):
                raise InputError(f"bounce set {list(self.bounce_set)} must be within "
                                 f"1..{self.bounces} (the rendered bounces)")
        if self.snr_db is not None and not math.isfinite(self.snr_db):
            raise InputError(f"snr_db must be finite, got {self.snr_db}")
        if not (math.isfinite(self.sound_speed) and self.sound_speed > 0):
            raise InputError(f"sound_speed must be positive, got {self.sound_speed}")
        if self.threads is not None and (int(self.threads) != self.threads or self.threads < 1):
            raise InputError(f"threads must be a positive integer, got {self.threads}")

    @property
    def bounce_index(self) -> list[int]:
        chosen = self.bounce_set or tuple(range(1, self.bounces + 1))
        return sorted({b - 1 for b in chosen})


def scratch_path(out: Path) -> Path:
    """The hidden noiseless intermediate dataset of a noisy simulation to ``out``."""
    return out.with_name(f".{out.name}.noiseless")


def simulate(spec: SceneSpec, poses: Poses, out: str | os.PathLike, settings: SimulationSettings,
             *, resume: bool = True, progress: bool = False,
             on_chunk: Callable[[int, int], None] | None = None) -> Path:
    """Simulate a :class:`sonarsim.dataset.SonarDataset` of ``spec`` seen from ``poses`` into ``out``.

    ``resume``: continue an interrupted run with the same settings (else start over).
    ``on_chunk(stop, n)`` is called after each rendered chunk is stored (for progress
    reports and tests). Returns the output path.
    """
    settings.validate()
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError(f"{out}: output directory does not exist")
    pulse = settings.pulse
    crop, window = simulation_window(poses, spec, pulse, settings.sound_speed, settings.oversample)
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
    meta = _meta(spec, settings, crop, window)
    meta["run_id"] = _run_id(common, meta)
    layout = None
    if settings.keep_transients:
        layout = TransientsLayout(settings.bounces, window.n_bins, window.path_start,
                                  window.bin_width, float(settings.sound_speed), pulse.fs,
                                  int(settings.oversample), {"paths_per_pose": settings.paths_per_pose,
                                                             "seed": int(settings.seed)})
    noisy = settings.snr_db is not None
    first = scratch_path(out) if noisy else out
    if not resume:
        for path in (out, first):
            with contextlib.suppress(FileNotFoundError):
                Path(os.fspath(path) + ".partial").unlink()
        with contextlib.suppress(FileNotFoundError):
            scratch_path(out).unlink()

    if not (noisy and _scratch_matches(first, meta)):
        writer = _open_writer(first, common, meta, layout, None)
        try:
            _render_into(writer, spec, poses, settings, crop, window, progress, on_chunk)
            writer.finish()
        finally:
            writer.close()
        if not noisy:
            return out

    # Noise pass: noiseless scratch -> noisy output.
    with inspect(first) as (_, fields):
        clean = np.asarray(fields["waveforms"][()], np.float32)
        sigma = noise_sigma(clean, float(settings.snr_db))
        writer = _open_writer(out, common, meta | {"noise_sigma": sigma},
                              layout, float(settings.snr_db))
        try:
            chunk = max(1, settings.chunk_size or 1024)
            for start, stop in writer.missing_ranges(chunk):
                noise = ping_noise(settings.seed, start, stop, crop.num_samples)
                wf = (clean[start:stop] + sigma * noise).astype(np.float32)
                tr = None
                if layout is not None:
                    tr = fields["transients"]["transients"][start:stop]
                writer.write(start, wf, tr)
            writer.finish()
        finally:
            writer.close()
    scratch_path(out).unlink()
    return out


def _meta(spec: SceneSpec, s: SimulationSettings, crop: CropWindow, window: PathWindow) -> dict:
    return {"scene": spec.name, "scene_source": spec.source,
            "box": np.stack([spec.box.lo, spec.box.hi], axis=1).tolist(),   # [[x0, x1], ...] m
            "pulse_spec": s.pulse.spec, "paths_per_pose": int(s.paths_per_pose),
            "bounces": int(s.bounces), "bounce_set": [b + 1 for b in s.bounce_index],
            "oversample": int(s.oversample), "beams": {**DEFAULT_BEAMS, **dict(s.beams or {})},
            "path_start": window.path_start, "path_bin_width": window.bin_width,
            "crop_min_dist": crop.min_dist, "crop_max_dist": crop.max_dist,
            "amplitude_model": AMPLITUDE_MODEL,
            "noise": "white Gaussian, sigma^2 = signal_power(noiseless) * 10^(-snr_db/10); "
                     "ping i seeded by (seed, i)",
            "generator": f"sonarsim {__version__} simulate", **s.extra_meta}


def _open_writer(path: Path, common: dict, meta: dict, layout, snr_db) -> DatasetStreamWriter:
    try:
        return DatasetStreamWriter(path, **common, meta=meta, snr_db=snr_db,
                                   transients=layout, resume=True)
    except FormatError as exc:
        raise FormatError(f"{exc} (or pass --restart)") from None


def _scratch_matches(path: Path, meta: dict) -> bool:
    """Whether a finished noiseless scratch file of this very run exists (else it is stale)."""
    if not path.is_file():
        return False
    try:
        with inspect(path) as (_, fields):
            same = _digest(fields["meta"]) == _digest(meta)
    except FormatError:
        same = False
    if not same:
        path.unlink()
    return same


def _run_id(common: dict, meta: dict) -> str:
    """A digest of everything that determines the noiseless data (detects stale scratch files)."""
    digest = hashlib.sha256(_digest(meta).encode())
    for key in sorted(common):
        value = common[key]
        digest.update(key.encode())
        if isinstance(value, np.ndarray):
            digest.update(np.ascontiguousarray(value).tobytes())
        else:
            digest.update(repr(value).encode())
    return digest.hexdigest()[:24]


def _digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def _render_into(writer: DatasetStreamWriter, spec: SceneSpec, poses: Poses,
                 s: SimulationSettings, crop: CropWindow, window: PathWindow, progress: bool,
                 on_chunk: Callable[[int, int], None] | None) -> None:
    """Render every pose the writer still lacks, chunk by chunk, and store its waveforms.

    Poses are rendered by :func:`sonarsim.render.iter_render` over each contiguous run of
    missing poses; a pose's random numbers depend on its global index only, so a resumed
    run renders exactly what an uninterrupted one would.
    """
    spans = writer.missing_ranges(max(1, len(poses)))   # maximal runs of missing poses
    if not spans:
        return
    scene = spec.to_mitsuba()
    pulse_os = oversampled_pulse(s.pulse.samples, s.oversample)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(poses), initial=writer.n_done, unit="ping", desc="simulate",
                   dynamic_ncols=True, disable=None)
    try:
        with dr_threads(s.threads):
            for first, end in spans:
                for sl, hist in iter_render(scene, poses, paths_per_pose=s.paths_per_pose,
                                            bounces=s.bounces, seed=s.seed,
                                            chunk_size=s.chunk_size, beams=s.beams,
                                            window=window, start=first, stop=end):
                    wf = transients_to_waveforms(hist, pulse_os, s.oversample, crop.num_samples,
                                                 s.bounce_index)
                    writer.write(sl.start, wf, hist if writer.layout is not None else None)
                    del hist
                    if bar is not None:
                        bar.update(sl.stop - sl.start)
                    if on_chunk is not None:
                        on_chunk(sl.stop, len(poses))
    finally:
        if bar is not None:
            bar.close()
