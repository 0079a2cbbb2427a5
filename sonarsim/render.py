"""Chunked transient rendering: many sonar poses through the ``sonar_transient`` integrator.

:func:`render_poses` returns a :class:`sonarsim.dataset.Transients` (float32 [N, B, T] energy
histograms over round-trip path length, one per bounce) in memory; :func:`render_to_file`
writes the same histograms to a transients file chunk by chunk (memory bounded by one
chunk, whatever N; what ``sonarsim render`` does); :func:`iter_render` yields them
chunk by chunk, optionally as two independent
half-estimates (``halves=True``: [2, n, B, T], their mean is the estimate) and, for the
'coherent' amplitude model, complex64 (docs/transient_rendering.md). Poses are split into chunks whose histogram
buffers fit a memory budget and whose lane count (poses × paths) stays below 2³²; each
chunk is one Dr.Jit kernel launch, and every chunk reuses the same compiled kernel.

The path-length window is ``path_range`` if given, else the reference's crop window
(:func:`sonarsim.geometry.crop_window`) over the scene box (``box``, by default the
bounding box of the Mitsuba scene) and the poses, **aligned to the sample grid**
(:func:`aligned_window`): path_start = min_dist − w/2, so the centre of bin j·K
(K = oversample) is the path length c·(min_sample + j)/fs of waveform sample j, and
decimating to bins 0, K, 2K, ... gives values at the sample times (what ``simulate``
does). Bin width w = sound_speed / (fs · oversample); bin j covers
[path_start + j·w, path_start + (j+1)·w) and stands for its centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .dataset import Transients, atomic_write_h5
from .errors import InputError
from .geometry import CropWindow, Poses, SceneBox, crop_window
from .progress import progress_bar

DEFAULT_BEAMS = {"tx_beam": "cone", "tx_beamwidth": 30.0, "rx_beam": "cone", "rx_beamwidth": 30.0}
# The reference renderer (its airsas/create_render_commands.py): isotropic point light; a 25° perspective
# camera aimed at a fixed point, approximated here by a 25° cone (docs/simulation.md).
REFERENCE_PARITY_BEAMS = {"tx_beam": "isotropic", "rx_beam": "cone", "rx_beamwidth": 25.0}
REFERENCE_RX_TARGET = (0.0, 0.0, 0.09)   # m, the reference camera's look-at point
REFERENCE_BOUNCES = (1,)                 # its max_bounce 2 = columns 0 (empty) and 1
BEAM_KEYS = tuple(DEFAULT_BEAMS) + ("shading_normals",)
DEFAULT_SOUND_SPEED = 344.973      # m/s, the reference's simulated system file (derived from the reference renderer's tMin/tMax/nBin)
DEFAULT_MEMORY_BUDGET = 768 * 2**20  # bytes for one chunk's histogram buffers
_LANE_LIMIT = 2**32 - 1
AMPLITUDES = ("intensity", "pressure", "coherent")       # the integrator's 'amplitude'
BOUNCE1_ESTIMATORS = ("surface", "cone")                 # the integrator's 'bounce1'
# Bytes per histogram bin while a chunk is rendered: float64 Dr.Jit buffer, its float32
# rounding and NumPy copy, plus headroom for Dr.Jit's allocator cache.
_BYTES_PER_BIN = 20


@dataclass(frozen=True)
class PathWindow:
    """Histogram window: ``n_bins`` bins of ``bin_width`` metres of round-trip path from ``path_start``."""

    path_start: float
    bin_width: float
    n_bins: int

    @property
    def path_end(self) -> float:
        return self.path_start + self.n_bins * self.bin_width


def scene_box(scene) -> SceneBox:
    """Axis-aligned bounding box of a Mitsuba scene (m)."""
    bbox = scene.bbox()
    lo, hi = np.array(bbox.min, dtype=np.float64), np.array(bbox.max, dtype=np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
        raise InputError("the scene is empty: nothing to render")
    flat = hi - lo < 1e-6            # e.g. a scene that is only a ground plane
    return SceneBox(np.where(flat, lo - 5e-7, lo), np.where(flat, hi + 5e-7, hi))


def aligned_window(crop: CropWindow, bin_width: float, oversample: int) -> PathWindow:
    """The histogram window of a crop window whose bin centres j·K fall on the sample times.

    The integrator's tent splat makes bin j stand for its centre path_start + (j + ½)·w;
    with path_start = min_dist − w/2 the centre of bin j·oversample is
    min_dist + j·oversample·w = c·(min_sample + j)/fs. ``crop.num_samples·oversample`` bins.
    """
    return PathWindow(crop.min_dist - bin_width / 2, bin_width, crop.num_samples * int(oversample))


def path_window(scene, poses: Poses, *, fs: float = 100e3, oversample: int = 20,
                sound_speed: float = DEFAULT_SOUND_SPEED, path_range=None,
                box: SceneBox | None = None) -> PathWindow:
    """The histogram window :func:`render` uses for these arguments (see the module doc).

    ``path_range`` (LMIN, LMAX) is used as given: path_start = LMIN, ⌈(LMAX − LMIN)/w⌉ bins.
    Otherwise the crop window of ``box`` (default: the scene's bounding box) over ``poses``,
    aligned to the sample grid by :func:`aligned_window`.
    """
    _check_positive("fs", fs)
    _check_positive("sound_speed", sound_speed)
    if int(oversample) != oversample or oversample < 1:
        raise InputError(f"oversample must be an integer >= 1, got {oversample}")
    width = sound_speed / (fs * int(oversample))
    if path_range is not None:
        lo, hi = (float(v) for v in path_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise InputError(f"path_range must be two finite lengths LMIN < LMAX, got {path_range}")
        return PathWindow(lo, width, max(1, math.ceil((hi - lo) / width - 1e-9)))
    crop = crop_window(poses, box if box is not None else scene_box(scene), sound_speed, fs)
    return aligned_window(crop, width, int(oversample))


def reference_parity_poses(poses: Poses, target=REFERENCE_RX_TARGET) -> Poses:
    """``poses`` with every RX boresight aimed at ``target`` [3] m (TX boresights kept)."""
    rx_dir = np.asarray(target, np.float64).reshape(1, 3) - poses.rx
    if np.any(np.linalg.norm(rx_dir, axis=1) == 0):
        raise InputError(f"a receiver sits on the RX target {tuple(target)}")
    return Poses(poses.tx, poses.rx, poses.tx_boresight, rx_dir)


def choose_chunk_size(paths_per_pose: int, bounces: int, n_bins: int,
                      memory_budget: int = DEFAULT_MEMORY_BUDGET, *, buffers: int = 1) -> int:
    """Poses per chunk: histogram buffers within ``memory_budget`` bytes, lanes < 2³².

    ``buffers``: histogram buffers per pose (2 for halves, 2 for complex, 4 for both).
    """
    per_pose = _BYTES_PER_BIN * bounces * n_bins * int(buffers)
    by_memory = max(1, memory_budget // per_pose)
    by_lanes = _LANE_LIMIT // paths_per_pose
    by_bins = _LANE_LIMIT // (bounces * n_bins * int(buffers))
    return int(max(1, min(by_memory, by_lanes, by_bins)))


def chunk_poses(n_poses: int, paths_per_pose: int, bounces: int, n_bins: int,
                chunk_size: int | None = None, memory_budget: int = DEFAULT_MEMORY_BUDGET,
                buffers: int = 1) -> int:
    """Poses per kernel launch of :func:`iter_render` for ``n_poses`` poses: ``chunk_size``
    if given (checked against the 2³² lane and bin limits), else equal chunks within
    ``memory_budget`` (Dr.Jit's allocator then reuses the same buffers)."""
    if chunk_size is None:
        limit = choose_chunk_size(paths_per_pose, bounces, n_bins, memory_budget, buffers=buffers)
        return math.ceil(n_poses / math.ceil(n_poses / limit)) if n_poses else limit
    if int(chunk_size) != chunk_size or chunk_size < 1:
        raise InputError(f"chunk_size must be a positive integer, got {chunk_size}")
    if (chunk_size * paths_per_pose > _LANE_LIMIT
            or chunk_size * bounces * n_bins * buffers > _LANE_LIMIT):
        most = choose_chunk_size(paths_per_pose, bounces, n_bins, 2**62, buffers=buffers)
        raise InputError(f"chunk_size {chunk_size} exceeds 2^32 lanes or bins per launch; "
                         f"use at most {most}")
    return int(chunk_size)


def chunk_memory(n_poses: int, paths_per_pose: int, bounces: int, n_bins: int,
                 chunk_size: int | None = None,
                 memory_budget: int = DEFAULT_MEMORY_BUDGET) -> tuple[int, int]:
    """(poses per chunk, bytes of its histogram buffers while it is rendered) for a render
    of ``n_poses`` poses: what :func:`iter_render` holds at once, whatever ``n_poses``."""
    chunk = min(chunk_poses(n_poses, paths_per_pose, bounces, n_bins, chunk_size,
                            memory_budget), max(n_poses, 1))
    return chunk, chunk * _BYTES_PER_BIN * bounces * n_bins


def estimator_props(bounce1: str | None = None, amplitude: str = "intensity",
                    surface_spacing: float | None = None, speckle_seed: int = 0) -> dict:
    """Integrator properties of the estimator settings (None: the integrator's default)."""
    if amplitude not in AMPLITUDES:
        raise InputError(f"amplitude must be one of {', '.join(AMPLITUDES)}, got {amplitude!r}")
    if bounce1 is not None and bounce1 not in BOUNCE1_ESTIMATORS:
        raise InputError(f"bounce1 must be one of {', '.join(BOUNCE1_ESTIMATORS)}, got {bounce1!r}")
    props: dict = {"amplitude": amplitude}
    if bounce1 is not None:
        props["bounce1"] = bounce1
    if surface_spacing is not None:
        props["surface_spacing"] = float(surface_spacing)
    if isinstance(speckle_seed, bool) or int(speckle_seed) != speckle_seed \
            or not 0 <= speckle_seed < 2**32:
        raise InputError(f"speckle_seed must be an integer in [0, 2^32), got {speckle_seed}")
    props["speckle_seed"] = int(speckle_seed)
    return props


def make_integrator(bounces: int = 3, beams: Mapping | None = None, *,
                    bounce1: str | None = None, amplitude: str = "intensity",
                    surface_spacing: float | None = None, speckle_seed: int = 0):
    """A ``sonar_transient`` integrator for ``bounces`` bounces, the given beam settings and
    estimator settings (:func:`estimator_props`; docs/transient_rendering.md)."""
    from . import runtime
    mi = runtime.mitsuba()
    props = {"type": "sonar_transient", "max_bounces": int(bounces), **_beam_settings(beams),
             **estimator_props(bounce1, amplitude, surface_spacing, speckle_seed)}
    try:
        return mi.load_dict(props)
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"bad integrator settings {props}: {exc}") from None


def iter_render(scene, poses: Poses, *, paths_per_pose: int = 10_000, bounces: int = 3,
                fs: float = 100e3, oversample: int = 20, sound_speed: float = DEFAULT_SOUND_SPEED,
                path_range=None, seed: int = 0, chunk_size: int | None = None,
                beams: Mapping | None = None, box: SceneBox | None = None,
                memory_budget: int = DEFAULT_MEMORY_BUDGET, progress: bool = False,
                window: PathWindow | None = None, start: int = 0, stop: int | None = None,
                bounce1: str | None = None, amplitude: str = "intensity",
                surface_spacing: float | None = None, speckle_seed: int = 0,
                halves: bool = False) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(pose_slice, hist)`` per chunk, ``hist`` [n, bounces, T] for ``poses[pose_slice]``
    (float32; complex64 for amplitude 'coherent'), or [2, n, bounces, T] with ``halves``:
    two independent half-estimates whose mean is the estimate.

    Arguments as in :func:`render`; ``window`` (from :func:`path_window`) overrides the
    window arguments. ``start``, ``stop``: render only poses start..stop−1 (default all);
    slices are global indices into ``poses``. A pose's histogram depends only on its
    global index, the seed and the settings, not on the chunking or on ``start``; the
    default window is still computed over all of ``poses``.
    """
    paths_per_pose, bounces, seed = _check_settings(poses, paths_per_pose, bounces, seed)
    props = estimator_props(bounce1, amplitude, surface_spacing, speckle_seed)
    buffers = (2 if halves else 1) * (2 if amplitude == "coherent" else 1)
    first, end = _check_range(start, stop, len(poses))
    if window is None:
        window = path_window(scene, poses, fs=fs, oversample=oversample,
                             sound_speed=sound_speed, path_range=path_range, box=box)
    n = end - first
    if n == 0:
        return
    chunk_size = chunk_poses(n, paths_per_pose, bounces, window.n_bins, chunk_size,
                             memory_budget, buffers)
    if halves and paths_per_pose < 2 and props.get("bounce1") == "cone":
        raise InputError("two half-estimates need paths_per_pose >= 2")
    integrator = make_integrator(bounces, beams, bounce1=bounce1, amplitude=amplitude,
                                 surface_spacing=surface_spacing, speckle_seed=speckle_seed)
    bar = progress_bar(n, progress, unit="pose", desc="render")
    try:
        for a in range(first, end, chunk_size):
            sl = slice(a, min(end, a + chunk_size))
            hist = integrator.render_transients(
                scene, poses.tx[sl], poses.rx[sl], poses.tx_boresight[sl], poses.rx_boresight[sl],
                window.path_start, window.bin_width, window.n_bins, paths_per_pose, seed,
                pose_offset=a, halves=halves)
            bar.update(sl.stop - sl.start)
            yield sl, hist
    finally:
        bar.close()


def render_poses(scene, poses: Poses, *, paths_per_pose: int = 10_000, bounces: int = 3,
           fs: float = 100e3, oversample: int = 20, sound_speed: float = DEFAULT_SOUND_SPEED,
           path_range=None, seed: int = 0, chunk_size: int | None = None,
           beams: Mapping | None = None, box: SceneBox | None = None,
           memory_budget: int = DEFAULT_MEMORY_BUDGET, progress: bool = True,
           bounce1: str | None = None, amplitude: str = "intensity",
           surface_spacing: float | None = None, speckle_seed: int = 0) -> Transients:
    """Render energy transients [N, bounces, T] for every pose of ``poses``, in memory.

    scene: a Mitsuba scene (two-sided diffuse surfaces; the ground is one of its shapes).
    paths_per_pose: TX-cone Monte-Carlo paths per pose (only with bounce1="cone"; the
    surface estimator samples every bounce from its facets). bounces: histograms for bounces 1…B.
    fs (Hz), oversample, sound_speed (m/s): bin width sound_speed / (fs · oversample) m.
    path_range: (LMIN, LMAX) round-trip metres (path_start = LMIN), else the crop window of
    ``box`` (default: the scene's bounding box) and the poses, aligned so that bin centres
    j·oversample fall on the sample times (:func:`aligned_window`). seed: 0 ≤ seed < 2³². chunk_size: poses per
    kernel launch (default from ``memory_budget`` bytes). beams: overrides of
    :data:`DEFAULT_BEAMS` ('cone' | 'isotropic' | 'piston'; full beamwidths in degrees).
    Values are the energy received from a unit-intensity TX: ∫ b_R L dω at the RX.
    bounce1: 'surface' (stratified surface quadrature, the integrator's default) or 'cone'
    (TX-cone path tracing); surface_spacing: its facet size in m (default: the
    integrator's). amplitude: 'intensity' (energy) or 'pressure' (the seed's Eq. (1)); the
    complex 'coherent' model cannot be stored in a float32 transients file (use
    :func:`iter_render` or ``simulate``). speckle_seed: unused here.

    The result holds N·bounces·T float32 values (9.3 GB for the 54 000-pose scan at 3
    bounces); :func:`render_to_file` streams the same values to a file instead.
    """
    plan = _plan(scene, poses, paths_per_pose, bounces, fs, oversample, sound_speed,
                 path_range, seed, beams, box, bounce1, amplitude, surface_spacing,
                 speckle_seed)
    out = np.empty((len(poses), plan.bounces, plan.window.n_bins), np.float32)
    for sl, hist in _plan_chunks(scene, poses, plan, chunk_size, memory_budget, progress):
        out[sl] = hist
    return plan.transients(out, poses)


def render_to_file(scene, poses: Poses, out, *, meta: Mapping | None = None,
                   paths_per_pose: int = 10_000, bounces: int = 3, fs: float = 100e3,
                   oversample: int = 20, sound_speed: float = DEFAULT_SOUND_SPEED,
                   path_range=None, seed: int = 0, chunk_size: int | None = None,
                   beams: Mapping | None = None, box: SceneBox | None = None,
                   memory_budget: int = DEFAULT_MEMORY_BUDGET, progress: bool = True,
                   bounce1: str | None = None, amplitude: str = "intensity",
                   surface_spacing: float | None = None,
                   speckle_seed: int = 0) -> tuple[Path, tuple[int, int, int], PathWindow]:
    """Render like :func:`render_poses` and write the transients file ``out`` chunk by chunk.

    Each chunk of poses is written to the file's ``transients`` dataset [N, bounces, T]
    (float32) as soon as it is rendered, so memory holds one chunk (``memory_budget``
    bytes of histogram buffers, default 768 MiB), whatever the number of poses. The file
    is written under a temporary name in ``out``'s directory with root attribute
    ``complete = False`` and renamed to ``out`` only when every pose is in
    (:func:`sonarsim.dataset.atomic_write_h5`); an interrupted run leaves no file at
    ``out``. The file equals ``render_poses(...).write(out)`` with the same arguments and
    ``meta`` merged into the transients' meta (the bytes of ``transients`` are the same
    for the same ``chunk_size``; across chunk sizes up to a rare 1-ulp difference,
    see the integrator's doc). Returns (out, (N, bounces, T), window).
    """
    plan = _plan(scene, poses, paths_per_pose, bounces, fs, oversample, sound_speed,
                 path_range, seed, beams, box, bounce1, amplitude, surface_spacing,
                 speckle_seed)
    shape = (len(poses), plan.bounces, plan.window.n_bins)
    # A validated header: the real one but for a one-bin stand-in of the histograms.
    header = plan.transients(np.zeros(shape[:2] + (1,), np.float32), poses, meta)

    def fill(f) -> None:
        header._write_group(f, data=False)      # attributes, pings/tx, pings/rx, meta
        f.attrs["complete"] = False             # until the last chunk is in
        # Contiguous, no fill value: every pose is written exactly once.
        data = f.create_dataset("transients", shape=shape, dtype=np.float32)
        for sl, hist in _plan_chunks(scene, poses, plan, chunk_size, memory_budget, progress):
            data[sl.start:sl.stop] = hist
            del hist
        f.attrs["complete"] = True

    return atomic_write_h5(out, fill), shape, plan.window


@dataclass(frozen=True)
class _Plan:
    """Checked settings of one render: window, estimator properties and file metadata."""

    paths_per_pose: int
    bounces: int
    seed: int
    window: PathWindow
    beams: Mapping | None
    bounce1: str | None
    amplitude: str
    surface_spacing: float | None
    speckle_seed: int
    sound_speed: float
    fs: float
    oversample: int
    meta: dict

    def transients(self, data: np.ndarray, poses: Poses,
                   meta: Mapping | None = None) -> Transients:
        """The validated :class:`Transients` of ``data`` [N, bounces, T], ``meta`` added."""
        return Transients(data, self.window.path_start, self.window.bin_width,
                          self.sound_speed, self.fs, self.oversample, poses.tx, poses.rx,
                          {**self.meta, **dict(meta or {})})


def _plan(scene, poses, paths_per_pose, bounces, fs, oversample, sound_speed, path_range,
          seed, beams, box, bounce1, amplitude, surface_spacing, speckle_seed) -> _Plan:
    """Check the settings of :func:`render_poses`/:func:`render_to_file`; window and meta."""
    paths_per_pose, bounces, seed = _check_settings(poses, paths_per_pose, bounces, seed)
    props = estimator_props(bounce1, amplitude, surface_spacing, speckle_seed)
    if amplitude == "coherent":
        raise InputError("amplitude 'coherent' gives complex histograms, which a transients "
                         "file (float32) cannot hold; simulate a dataset instead")
    if path_range is None and box is None:
        box = scene_box(scene)
    window = path_window(scene, poses, fs=fs, oversample=oversample, sound_speed=sound_speed,
                         path_range=path_range, box=box)
    meta = {"integrator": "sonar_transient", "mode": amplitude, "amplitude_model": amplitude,
            "bounce1": props.get("bounce1", "surface"),
            **{k: v for k, v in props.items() if k == "surface_spacing"},
            "paths_per_pose": paths_per_pose, "bounces": bounces, "seed": seed,
            "beams": _beam_settings(beams),
            "window": "path_range" if path_range is not None else "crop_window"}
    if path_range is None:
        meta["window_box"] = np.stack([box.lo, box.hi], axis=1).tolist()   # [[x0,x1],[y0,y1],[z0,z1]] m
    return _Plan(paths_per_pose, bounces, seed, window, beams, bounce1, amplitude,
                 surface_spacing, speckle_seed, float(sound_speed), float(fs), int(oversample),
                 meta)


def _plan_chunks(scene, poses, plan: _Plan, chunk_size, memory_budget, progress):
    return iter_render(scene, poses, paths_per_pose=plan.paths_per_pose, bounces=plan.bounces,
                       seed=plan.seed, chunk_size=chunk_size, beams=plan.beams,
                       memory_budget=memory_budget, progress=progress, window=plan.window,
                       bounce1=plan.bounce1, amplitude=plan.amplitude,
                       surface_spacing=plan.surface_spacing)


# ---------------------------------------------------------------------------- helpers
def _beam_settings(beams: Mapping | None) -> dict:
    settings = dict(DEFAULT_BEAMS)
    for key, value in (beams or {}).items():
        if key not in BEAM_KEYS:
            raise InputError(f"unknown beam setting {key!r}; use {', '.join(BEAM_KEYS)}")
        if key.endswith("_beamwidth"):
            value = float(value)
        elif key == "shading_normals":
            value = bool(value)
        else:
            value = str(value)
        settings[key] = value
    return settings


def _check_settings(poses, paths_per_pose, bounces, seed) -> tuple[int, int, int]:
    if not isinstance(poses, Poses):
        raise InputError(f"poses must be a sonarsim.geometry.Poses, got {type(poses).__name__}")
    for name, value, lo, hi in (("paths_per_pose", paths_per_pose, 1, _LANE_LIMIT),
                                ("bounces", bounces, 1, 64), ("seed", seed, 0, _LANE_LIMIT)):
        if isinstance(value, bool) or int(value) != value or not lo <= value <= hi:
            raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {value}")
    if len(poses) > _LANE_LIMIT:
        raise InputError(f"at most {_LANE_LIMIT} poses per render")
    return int(paths_per_pose), int(bounces), int(seed)


def _check_range(start, stop, n: int) -> tuple[int, int]:
    """(start, stop) as ints with 0 <= start <= stop <= n (stop None: n)."""
    stop = n if stop is None else stop
    for name, value in (("start", start), ("stop", stop)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"{name} must be an integer pose index, got {value!r}")
    if not 0 <= start <= stop <= n:
        raise InputError(f"pose range must satisfy 0 <= start <= stop <= {n}, got {start}..{stop}")
    return int(start), int(stop)


def _check_positive(name: str, value) -> None:
    if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive number, got {value}")
