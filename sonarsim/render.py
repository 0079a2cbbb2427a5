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

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .dataset import Transients, TransientsStreamWriter
from .errors import InputError
from .limits import MAX_BOUNCES
from .geometry import CropWindow, Poses, SceneBox, crop_window
from .progress import progress_bar
from .signals import AIRSAS_FS

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


def path_window(scene, poses: Poses, *, fs: float = AIRSAS_FS, oversample: int = 20,
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


@dataclass(frozen=True)
class RenderSettings:
    """Everything that determines a render besides the scene, the poses and the window box.

    paths_per_pose: TX-cone Monte-Carlo paths per pose (used with bounce1='cone'; the
    surface estimator samples every bounce from its strata). bounces: histograms for
    bounces 1…B. fs (Hz), oversample, sound_speed (m/s): bin width sound_speed / (fs ·
    oversample) m. path_range: (LMIN, LMAX) round-trip metres (path_start = LMIN), else the
    crop window of the scene box and the poses (:func:`path_window`). seed: 0 ≤ seed < 2³².
    beams: overrides of :data:`DEFAULT_BEAMS` ('cone' | 'isotropic' | 'piston'; full
    beamwidths in degrees; 'shading_normals'). bounce1: 'surface' | 'cone' (None: the
    integrator's default, 'surface'); amplitude: 'intensity' | 'pressure' | 'coherent';
    surface_spacing: strata size of the surface estimator in m (None: the integrator's);
    speckle_seed: the coherent model's phases. chunk_size: poses per kernel launch (None:
    from ``memory_budget`` bytes of histogram buffers).

    :meth:`validate` is sonarsim's one check of every value (one-line :class:`InputError`
    naming the command-line option), used by the Python API, the CLI and the batch alike;
    the beam patterns and widths are checked by the integrator plugin
    (:func:`make_integrator`), which also guards its own properties for users of
    ``mi.load_dict``.
    """

    paths_per_pose: int = 10_000
    bounces: int = 3
    fs: float = AIRSAS_FS
    oversample: int = 20
    sound_speed: float = DEFAULT_SOUND_SPEED
    path_range: tuple | None = None
    seed: int = 0
    beams: Mapping | None = None
    bounce1: str | None = None
    amplitude: str = "intensity"
    surface_spacing: float | None = None
    speckle_seed: int = 0
    chunk_size: int | None = None
    memory_budget: int = DEFAULT_MEMORY_BUDGET

    def replace(self, **changes) -> "RenderSettings":
        """A copy with ``changes`` (field names; an unknown one is an InputError)."""
        unknown = sorted(set(changes) - set(self.__dataclass_fields__))
        if unknown:
            raise InputError(f"unknown render setting(s) {', '.join(unknown)}; use "
                             f"{', '.join(self.__dataclass_fields__)}")
        return dataclasses.replace(self, **changes)

    def validate(self) -> "RenderSettings":
        """Check every setting; returns the settings with integers as ints, beams complete."""
        for name, lo, hi in (("paths_per_pose", 1, _LANE_LIMIT), ("bounces", 1, MAX_BOUNCES),
                             ("seed", 0, _LANE_LIMIT), ("oversample", 1, 10_000),
                             ("speckle_seed", 0, _LANE_LIMIT)):
            _check_int(name, getattr(self, name), lo, hi)
        if self.chunk_size is not None:
            _check_int("chunk_size", self.chunk_size, 1, _LANE_LIMIT)
        _check_positive("fs", self.fs)
        _check_positive("sound_speed", self.sound_speed)
        _check_positive("memory_budget", self.memory_budget)
        if self.path_range is not None:
            try:
                lo, hi = (float(v) for v in self.path_range)
            except (TypeError, ValueError):
                raise InputError(f"--path-range must be two lengths LMIN LMAX, got "
                                 f"{self.path_range!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise InputError(f"--path-range must be two finite lengths LMIN < LMAX, got "
                                 f"{self.path_range}")
        if self.amplitude not in AMPLITUDES:
            raise InputError(f"--amplitude must be one of {', '.join(AMPLITUDES)}, "
                             f"got {self.amplitude!r}")
        if self.bounce1 is not None and self.bounce1 not in BOUNCE1_ESTIMATORS:
            raise InputError(f"--bounce1-estimator must be one of "
                             f"{', '.join(BOUNCE1_ESTIMATORS)}, got {self.bounce1!r}")
        if self.surface_spacing is not None:
            if not (isinstance(self.surface_spacing, (int, float, np.number))
                    and not isinstance(self.surface_spacing, bool)
                    and math.isfinite(self.surface_spacing)
                    and 1e-5 <= self.surface_spacing <= 10):
                raise InputError(f"--surface-spacing must be in [1e-5, 10] m, got "
                                 f"{self.surface_spacing}")
            if self.bounce1 == "cone":
                raise InputError("--surface-spacing needs --bounce1-estimator surface")
        return dataclasses.replace(
            self, paths_per_pose=int(self.paths_per_pose), bounces=int(self.bounces),
            seed=int(self.seed), oversample=int(self.oversample),
            speckle_seed=int(self.speckle_seed), beams=_beam_settings(self.beams),
            chunk_size=None if self.chunk_size is None else int(self.chunk_size))

    def integrator_props(self) -> dict:
        """The ``sonar_transient`` properties of these settings."""
        props = {"type": "sonar_transient", "max_bounces": int(self.bounces),
                 **_beam_settings(self.beams), "amplitude": self.amplitude,
                 "speckle_seed": int(self.speckle_seed)}
        if self.bounce1 is not None:
            props["bounce1"] = self.bounce1
        if self.surface_spacing is not None:
            props["surface_spacing"] = float(self.surface_spacing)
        return props

    @property
    def buffers(self) -> int:
        """Histogram buffers per pose and half: 2 for the complex 'coherent' model."""
        return 2 if self.amplitude == "coherent" else 1


def make_integrator(bounces: int | RenderSettings = 3, beams: Mapping | None = None, *,
                    bounce1: str | None = None, amplitude: str = "intensity",
                    surface_spacing: float | None = None, speckle_seed: int = 0):
    """A ``sonar_transient`` integrator of a :class:`RenderSettings` (or of these keyword
    settings). Its plugin validates the estimator options; a refusal is one InputError line."""
    from . import runtime
    settings = bounces if isinstance(bounces, RenderSettings) else RenderSettings(
        bounces=bounces, beams=beams, bounce1=bounce1, amplitude=amplitude,
        surface_spacing=surface_spacing, speckle_seed=speckle_seed)
    props = settings.integrator_props()
    mi = runtime.mitsuba()
    try:
        return mi.load_dict(props)
    except (RuntimeError, ValueError) as exc:   # Mitsuba quotes the plugin's traceback
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        reason = lines[-1] if lines else type(exc).__name__
        if "sonar_transient:" in reason:
            reason = reason[reason.index("sonar_transient:"):]
        raise InputError(f"integrator settings: {reason}") from None


def _settings(settings: RenderSettings | None, overrides: Mapping) -> RenderSettings:
    """``settings`` (default: RenderSettings()) with keyword ``overrides``, validated."""
    base = settings if settings is not None else RenderSettings()
    if not isinstance(base, RenderSettings):
        raise InputError(f"settings must be a sonarsim.render.RenderSettings, got "
                         f"{type(base).__name__}")
    return base.replace(**overrides).validate()


def iter_render(scene, poses: Poses, settings: RenderSettings | None = None, *,
                window: PathWindow | None = None, box: SceneBox | None = None,
                start: int = 0, stop: int | None = None, halves: bool = False,
                progress: bool = False, **overrides) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(pose_slice, hist)`` per chunk, ``hist`` [n, bounces, T] for ``poses[pose_slice]``
    (float32; complex64 for amplitude 'coherent'), or [2, n, bounces, T] with ``halves``:
    two independent half-estimates whose mean is the estimate (paths of even and odd
    index; the surface estimator's two jittered points per stratum).

    ``settings`` (:class:`RenderSettings`) with keyword ``overrides`` of its fields (e.g.
    ``bounces=1``). ``window`` (from :func:`path_window`) overrides the window settings;
    ``box``: the scene box of the default window (default: the scene's bounding box).
    ``start``, ``stop``: render only poses start..stop−1 (default all); slices are global
    indices into ``poses``. A pose's histogram depends only on its global index, the seed
    and the settings, not on the chunking or on ``start``; the default window is still
    computed over all of ``poses``. The one render loop: ``render_poses``,
    ``render_to_file`` and ``sonarsim.simulate`` all render through it.
    """
    s = _settings(settings, overrides)
    _check_poses(poses)
    first, end = _check_range(start, stop, len(poses))
    if window is None:
        window = path_window(scene, poses, fs=s.fs, oversample=s.oversample,
                             sound_speed=s.sound_speed, path_range=s.path_range, box=box)
    n = end - first
    if n == 0:
        return
    buffers = (2 if halves else 1) * s.buffers
    chunk_size = chunk_poses(n, s.paths_per_pose, s.bounces, window.n_bins, s.chunk_size,
                             s.memory_budget, buffers)
    if halves and s.paths_per_pose < 2 and s.bounce1 == "cone":
        raise InputError("two half-estimates need --paths-per-pose >= 2")
    integrator = make_integrator(s)
    bar = progress_bar(n, progress, unit="pose", desc="render")
    try:
        for a in range(first, end, chunk_size):
            sl = slice(a, min(end, a + chunk_size))
            hist = integrator.render_transients(
                scene, poses.tx[sl], poses.rx[sl], poses.tx_boresight[sl], poses.rx_boresight[sl],
                window.path_start, window.bin_width, window.n_bins, s.paths_per_pose, s.seed,
                pose_offset=a, halves=halves)
            bar.update(sl.stop - sl.start)
            yield sl, hist
    finally:
        bar.close()


def render_poses(scene, poses: Poses, settings: RenderSettings | None = None, *,
                 box: SceneBox | None = None, progress: bool = True,
                 **overrides) -> Transients:
    """Render energy transients [N, bounces, T] for every pose of ``poses``, in memory.

    scene: a Mitsuba scene (two-sided diffuse surfaces; the ground is one of its shapes).
    ``settings`` (:class:`RenderSettings`) with keyword ``overrides`` of its fields; the
    window is ``path_range`` or the crop window of ``box`` (default: the scene's bounding
    box) and the poses, aligned so that bin centres j·oversample fall on the sample times
    (:func:`aligned_window`). Values are the energy received from a unit-intensity TX:
    ∫ b_R L dω at the RX ('intensity'), or the pressure of the seed's Eq. (1)
    ('pressure'); the complex 'coherent' model cannot be stored in a float32 transients
    file (use :func:`iter_render` or ``simulate``).

    The result holds N·bounces·T float32 values (9.3 GB for the 54 000-pose scan at 3
    bounces); :func:`render_to_file` streams the same values to a file instead.
    """
    plan = _plan(scene, poses, _settings(settings, overrides), box)
    out = np.empty((len(poses), plan.settings.bounces, plan.window.n_bins), np.float32)
    for sl, hist in _plan_chunks(scene, poses, plan, progress):
        out[sl] = hist
    return plan.transients(out, poses)


def render_to_file(scene, poses: Poses, out, settings: RenderSettings | None = None, *,
                   meta: Mapping | None = None, box: SceneBox | None = None,
                   progress: bool = True,
                   **overrides) -> tuple[Path, tuple[int, int, int], PathWindow]:
    """Render like :func:`render_poses` and write the transients file ``out`` chunk by chunk.

    Each chunk of poses is written to the file's ``transients`` dataset [N, bounces, T]
    (float32) as soon as it is rendered, so memory holds one chunk (``memory_budget``
    bytes of histogram buffers, default 768 MiB), whatever the number of poses. The file
    is written under a temporary name in ``out``'s directory with root attribute
    ``complete = False`` and renamed to ``out`` only when every pose is in
    (:class:`sonarsim.dataset.TransientsStreamWriter`: free space checked first, histograms
    compressed); an interrupted run leaves no file at ``out``. The file equals ``render_poses(...).write(out)`` with the
    same arguments and ``meta`` merged into the transients' meta (the bytes of
    ``transients`` are the same for the same ``chunk_size``; across chunk sizes up to a
    rare 1-ulp difference, see the integrator's doc). Returns (out, (N, bounces, T), window).
    """
    plan = _plan(scene, poses, _settings(settings, overrides), box)
    shape = (len(poses), plan.settings.bounces, plan.window.n_bins)
    # A validated header: the real one but for a one-bin stand-in of the histograms.
    header = plan.transients(np.zeros(shape[:2] + (1,), np.float32), poses, meta)

    with TransientsStreamWriter(out, header, n_bins=shape[2]) as writer:
        for sl, hist in _plan_chunks(scene, poses, plan, progress):
            writer.write(sl.start, hist)
            del hist
    return Path(out), shape, plan.window


@dataclass(frozen=True)
class _Plan:
    """Checked settings of one render: the settings, the window and the file metadata."""

    settings: RenderSettings
    window: PathWindow
    meta: dict

    def transients(self, data: np.ndarray, poses: Poses,
                   meta: Mapping | None = None) -> Transients:
        """The validated :class:`Transients` of ``data`` [N, bounces, T], ``meta`` added."""
        s = self.settings
        return Transients(data, self.window.path_start, self.window.bin_width,
                          float(s.sound_speed), float(s.fs), s.oversample, poses.tx, poses.rx,
                          {**self.meta, **dict(meta or {})})


def _plan(scene, poses, s: RenderSettings, box) -> _Plan:
    """The window and meta of :func:`render_poses`/:func:`render_to_file` (settings checked)."""
    _check_poses(poses)
    if s.amplitude == "coherent":
        raise InputError("amplitude 'coherent' gives complex histograms, which a transients "
                         "file (float32) cannot hold; simulate a dataset instead")
    make_integrator(s)                   # the estimator options, checked by the plugin
    if s.path_range is None and box is None:
        box = scene_box(scene)
    window = path_window(scene, poses, fs=s.fs, oversample=s.oversample,
                         sound_speed=s.sound_speed, path_range=s.path_range, box=box)
    meta = {"integrator": "sonar_transient", "amplitude_model": s.amplitude,
            "bounce1": s.bounce1 or "surface",
            **({"surface_spacing": float(s.surface_spacing)}
               if s.surface_spacing is not None else {}),
            "paths_per_pose": s.paths_per_pose, "bounces": s.bounces, "seed": s.seed,
            "beams": _beam_settings(s.beams),
            "window": "path_range" if s.path_range is not None else "crop_window"}
    if s.path_range is None:
        meta["window_box"] = np.stack([box.lo, box.hi], axis=1).tolist()   # [[x0,x1],[y0,y1],[z0,z1]] m
    return _Plan(s, window, meta)


def _plan_chunks(scene, poses, plan: _Plan, progress):
    return iter_render(scene, poses, plan.settings, window=plan.window, progress=progress)


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


def _check_int(name: str, value, lo: int, hi: int) -> None:
    """An integer in [lo, hi] (hi = 2³² − 1 is written [lo, 2^32)), else a one-line
    InputError naming the command-line option."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or int(value) != value or not lo <= value <= hi:
        bounds = f"[{lo}, 2^32)" if hi == _LANE_LIMIT else f"[{lo}, {hi}]"
        raise InputError(f"--{name.replace('_', '-')} must be an integer in {bounds}, "
                         f"got {value!r}")


def _check_poses(poses) -> None:
    if not isinstance(poses, Poses):
        raise InputError(f"poses must be a sonarsim.geometry.Poses, got {type(poses).__name__}")
    if len(poses) > _LANE_LIMIT:
        raise InputError(f"at most {_LANE_LIMIT} poses per render")


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
    if isinstance(value, bool) or not (isinstance(value, (int, float, np.number))
                                       and math.isfinite(value) and value > 0):
        raise InputError(f"--{name.replace('_', '-')} must be a positive number, got {value}")
