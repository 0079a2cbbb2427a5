"""Gradient descent on complex voxels through the ellipsoidal forward model (the reference's
``--no_network`` baseline, REFERENCE_SPEC §5.2, with the loss and sampling of §4.2–§4.5).

Each iteration draws ``pings_per_iteration`` pings (seeded NumPy generator), draws
``bins_per_ping`` range bins per ping without replacement with probability ∝ |target|^u over
the bins whose ellipsoids can reach the grid (the reference's aggressive crop, per ping),
renders them with :func:`recon.forward.render` (Lambertian normals and occlusion optional),
and takes one :class:`drjit.opt.Adam` step on the loss

    L = mean|ŝ − s|² + [after reg_start] λ_sp·mean|σ| + λ_sm·mean(|Re Δσ| + |Im Δσ|)
        + λ_ph·mean|cos∠σ(x) − cos∠σ(x')| + λ_tv·mean|σ_{k+1} − σ_k| (along rays)

over all sampled points x; x' = x + δ·v̄·u with u a random unit vector and
v̄ = √2·(mean voxel pitch), as the reference's smoothness/phase priors (§4.4).

Targets s: the matched-filtered analytic signal (default) or the analytic signal of the raw
waveform, divided by the dataset's maximum magnitude and multiplied by ``scale_factor``
(the reference multiplies its deconvolved targets by 10–30).

Grid mapping (the §5.2 quirk fixed): the reference's voxel grid has len(arange(lo, hi, Δ))
cells looked up with align-corners semantics over [lo, hi], which shifts voxel centres by up
to one cell relative to its own BP grid. Here the optimised voxels are exactly the
:class:`~recon.grid.Grid` centres (linspace, endpoints included), trilinear in between and
zero outside, so GD and BP volumes are directly comparable voxel by voxel.

Every iteration runs the same compiled kernels: per-iteration values (pings, ranges, random
vectors) are arrays, not literals. Checkpoints (``.npz``, written atomically) hold the
voxels, the Adam moments, the iteration and the generator state; ``resume`` continues a run
where it stopped (same samples; float32 rounding may differ in the last digits).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.errors import FormatError, InputError
from sonarsim.progress import progress_bar

from . import forward, measurements
from ._jit import jit
from .grid import Grid


@dataclass
class GDSettings:
    """Settings of a gradient-descent run.

    Defaults (docs/reconstruction.md, "Gradient descent", has the measurements behind them):
    start from the backprojection scaled by its least-squares factor through the linear
    model (``init='bp'``); the reference's forward model (Lambertian factor, occlusion with
    s_occ 500) without priors; and a learning rate *relative* to the voxel scale
    max |scaled BP| (``lr_units='relative'``): Adam moves every voxel by about ``lr`` × that
    scale per step whatever the gradient's size, so an absolute rate means nothing until the
    data's units are fixed. The rate decays exponentially from ``lr`` to ``lr_final``;
    resuming reproduces a run only with the same ``iterations``. For point-like scenes the
    linear model (``lambertian=False, occlusion_scale=0``) fits better.

    Sampling follows the reference's simulated-scene script (REFERENCE_SPEC §4.2–§4.5: 5
    pings per step, 110 bins per ping, targets scaled to max 10). ``preset='sim'`` or
    ``'airsas'`` restores the reference's priors (sparsity after iteration 500, …) and its
    tiny random initialisation.
    """

    iterations: int = 1000
    lr: float = 2e-2
    lr_final: float | None = 2e-3         # exponential decay from lr to lr_final (None = constant)
    lr_units: str = "relative"            # 'relative': × voxel scale (max |scaled BP|) | 'absolute'
    adam_epsilon: float = 1e-8
    pings_per_iteration: int = 5          # reference accum_grad
    bins_per_ping: int = 110              # reference max_weights (sim)
    n_rays: int = 2000
    beamwidth_deg: float = 30.0
    sampling_uniformity: float = 1.0      # p_k ∝ |s_k|^u
    scale_factor: float = 10.0
    data: str = "matched"                 # 'matched' | 'analytic'
    lambertian: bool = True
    occlusion_scale: float = 500.0
    sparsity: float = 0.0
    smoothness: float = 0.0
    phase: float = 0.0
    tv: float = 0.0
    smooth_delta: float = 1.0
    reg_start: int = 500
    init_scale: float = 1e-8              # std of the random complex initial voxels (absolute)
    init: str = "bp"                      # 'bp' (scaled backprojection) | 'random'
    ray_jitter: bool = True               # random roll of the ray pattern per ping
    seed: int = 0

    def validate(self):
        for name in ("iterations", "pings_per_iteration", "bins_per_ping", "n_rays"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if self.lr_final is not None and not self.lr_final > 0:
            raise InputError(f"lr_final: must be positive, got {self.lr_final}")
        for name in ("lr", "scale_factor"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("sparsity", "smoothness", "phase", "tv", "occlusion_scale", "adam_epsilon",
                     "sampling_uniformity", "init_scale", "smooth_delta"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name}: must be a finite number >= 0, got {v}")
        if self.lr_units not in ("relative", "absolute"):
            raise InputError(f"lr_units: choose 'relative' or 'absolute', got {self.lr_units!r}")
        if self.init not in ("random", "bp"):
            raise InputError(f"init: choose 'random' or 'bp', got {self.init!r}")
        if self.data not in ("matched", "analytic"):
            raise InputError(f"data: choose 'matched' or 'analytic', got {self.data!r}")
        if not 0 < self.beamwidth_deg <= 360:
            raise InputError(f"beamwidth_deg: must be in (0, 360], got {self.beamwidth_deg}")


# The reference's per-scene settings (REFERENCE_SPEC §4.2–§4.5, §4.8) that carry over to
# this implementation (its lr, iteration count and ray count do not: see GDSettings).
# On simulated scenes they fit worse than the defaults (docs/reconstruction.md).
PRESETS = {
    "sim": dict(bins_per_ping=110, scale_factor=10.0, lambertian=True, occlusion_scale=500.0,
                sparsity=1.0, smoothness=0.0, phase=0.0, reg_start=500, init="random"),
    "airsas": dict(bins_per_ping=200, scale_factor=30.0, lambertian=True, occlusion_scale=1000.0,
                   sparsity=10.0, smoothness=50.0, phase=0.1, reg_start=500, beamwidth_deg=30.0,
                   init="random"),
}


def settings_for(preset: str | None = None, **overrides) -> GDSettings:
    """GDSettings from a named preset ('sim', 'airsas': the reference's values) and explicit
    overrides (None = the defaults)."""
    if preset is not None and preset not in PRESETS:
        raise InputError(f"preset: choose one of {', '.join(PRESETS)}, got {preset!r}")
    values = dict(PRESETS.get(preset, {}))
    values.update(overrides)
    unknown = set(values) - set(GDSettings.__dataclass_fields__)
    if unknown:
        raise InputError(f"unknown gradient-descent setting(s): {', '.join(sorted(unknown))}")
    settings = GDSettings(**values)
    settings.validate()
    return settings


def targets(dataset, settings: GDSettings) -> np.ndarray:
    """Complex targets [N, T] complex64: the chosen analytic data, normalised to max 1,
    times ``scale_factor``."""
    s = (measurements.matched_filtered(dataset) if settings.data == "matched"
         else measurements.analytic_waveforms(dataset))
    peak = float(np.abs(s).max())
    if not peak > 0:
        raise InputError("dataset waveforms: all zero, nothing to fit")
    return (s * (settings.scale_factor / peak)).astype(np.complex64)


def reachable_bins(dataset, grid: Grid, speeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ping the first and last waveform sample [N] whose ellipsoid can meet the grid box."""
    corners = np.array(np.meshgrid(*grid.bounds, indexing="ij")).reshape(3, -1).T
    tx, rx = np.asarray(dataset.tx), np.asarray(dataset.rx)
    paths = (np.linalg.norm(corners[None] - tx[:, None], axis=2)
             + np.linalg.norm(corners[None] - rx[:, None], axis=2))
    # Closest point of the box may be nearer than every corner (sensor inside the box's span).
    near = np.linalg.norm(np.clip(tx, grid.bounds[:, 0], grid.bounds[:, 1]) - tx, axis=1) \
        + np.linalg.norm(np.clip(rx, grid.bounds[:, 0], grid.bounds[:, 1]) - rx, axis=1)
    lo = np.minimum(paths.min(axis=1), near)
    hi = paths.max(axis=1)
    n_t = np.asarray(dataset.waveforms).shape[1]
    first = np.floor(lo / speeds * dataset.fs - dataset.start_sample).astype(int)
    last = np.ceil(hi / speeds * dataset.fs - dataset.start_sample).astype(int)
    return np.clip(first, 0, n_t - 1), np.clip(last, 0, n_t - 1)


class _Sampler:
    """Host-side random choices of one run (NumPy generator; fully determined by the seed)."""

    def __init__(self, tgt: np.ndarray, first: np.ndarray, last: np.ndarray, settings: GDSettings,
                 rng: np.random.Generator):
        self.tgt, self.first, self.last, self.s, self.rng = tgt, first, last, settings, rng
        self.active = np.flatnonzero(last >= first)
        if len(self.active) == 0:
            raise InputError("no ping's echo window overlaps the grid: check bounds and dataset")

    def draw(self):
        s, rng = self.s, self.rng
        pings = rng.choice(self.active, size=s.pings_per_iteration,
                           replace=len(self.active) < s.pings_per_iteration)
        bins = np.empty((len(pings), s.bins_per_ping), dtype=np.int64)
        for i, p in enumerate(pings):
            cand = np.arange(self.first[p], self.last[p] + 1)
            w = np.abs(self.tgt[p, cand]).astype(np.float64) ** s.sampling_uniformity + 1e-12
            if len(cand) <= s.bins_per_ping:
                # Every candidate once; the remaining slots repeat bins drawn by magnitude.
                extra = rng.choice(cand, size=s.bins_per_ping - len(cand), p=w / w.sum())
                bins[i] = np.sort(np.concatenate([cand, extra]))
            else:
                bins[i] = np.sort(rng.choice(cand, size=s.bins_per_ping, replace=False,
                                             p=w / w.sum()))
        roll = rng.uniform(0, 2 * np.pi, len(pings)) if s.ray_jitter else np.zeros(len(pings))
        return pings, bins, roll


def _scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings) -> np.ndarray:
    """Backprojection of the dataset times the complex factor α that best fits the targets
    through the linear model on a fixed batch of pings (α = ⟨A x, s⟩/‖A x‖²)."""
    from . import backprojection
    x = backprojection.backproject(dataset, grid, progress=False)
    rng = np.random.default_rng([settings.seed, 1])
    batch = GDSettings(**{**asdict(settings), "pings_per_iteration": 4 * settings.pings_per_iteration})
    pings, bins, _ = _Sampler(tgt, first, last, batch, rng).draw()
    op = forward.EllipsoidOperator(grid, forward.ping_geometry(dataset, pings, bins, speeds),
                                   n_rays=settings.n_rays, beamwidth_deg=settings.beamwidth_deg)
    ax = op.forward(x)
    s = tgt[pings[:, None], bins]
    denom = np.vdot(ax, ax)
    return (x * (np.vdot(ax, s) / denom)).astype(np.complex64) if denom > 0 else x * 0


def _rolled(boresight: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Boresight frames rolled about the boresight by ``roll`` (radians), as a direction set
    rotation: returns per-ping local→world matrices [P, 3, 3]."""
    f = forward.boresight_frames(boresight)
    c, s = np.cos(roll), np.sin(roll)
    rot = np.zeros((len(roll), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    return f @ rot


def _loss_terms(m, field, samples, s_re, s_im, y_re, y_im, t_re, t_im, settings, grid,
                reg_on: bool, u_vec):
    """Data term and regularisers (Dr.Jit scalars)."""
    import drjit as dr
    data = dr.mean(dr.square(y_re - t_re)) + dr.mean(dr.square(y_im - t_im))
    terms = {"data": data}
    if not reg_on:
        return terms
    valid = m.Float(dr.select(samples.valid, 1.0, 0.0))
    n_valid = dr.maximum(dr.sum(valid), 1.0)
    mag = dr.sqrt(s_re * s_re + s_im * s_im + 1e-20)
    if settings.sparsity > 0:
        terms["sparsity"] = settings.sparsity * dr.sum(valid * mag) / n_valid
    if settings.smoothness > 0 or settings.phase > 0:
        vbar = math.sqrt(2.0) * float(np.mean(field.h))
        shifted = samples.points + u_vec * (settings.smooth_delta * vbar)
        p_re, p_im = field.sample_fn(shifted)
        if settings.smoothness > 0:
            terms["smoothness"] = settings.smoothness * dr.sum(
                valid * (dr.abs(s_re - p_re) + dr.abs(s_im - p_im))) / n_valid
        if settings.phase > 0:
            p_mag = dr.sqrt(p_re * p_re + p_im * p_im + 1e-20)
            terms["phase"] = settings.phase * dr.sum(valid * dr.abs(s_re / mag - p_re / p_mag)) / n_valid
    if settings.tv > 0:
        P, J, K = samples.shape
        lane = dr.arange(m.UInt32, P * J * K)
        has_next = (lane % K) != K - 1
        n_re = dr.gather(m.Float, s_re, dr.select(has_next, lane + 1, lane))
        n_im = dr.gather(m.Float, s_im, dr.select(has_next, lane + 1, lane))
        tv = dr.sqrt(dr.square(n_re - s_re) + dr.square(n_im - s_im) + 1e-20)
        w = valid * m.Float(dr.select(has_next, 1.0, 0.0))
        terms["tv"] = settings.tv * dr.sum(w * tv) / dr.maximum(dr.sum(w), 1.0)
    return terms


class _BoundField:
    """A voxel field whose sample function reads the optimiser's current parameters."""

    def __init__(self, vf: forward.VoxelField, opt):
        self.vf, self.opt, self.h = vf, opt, vf.h

    def sample_fn(self, points):
        return self.vf.sample(self.opt["re"], self.opt["im"], points)

    def bound(self) -> forward.BoundVoxels:
        return self.vf.field(self.opt["re"], self.opt["im"])


def solve(dataset, grid: Grid, *, iterations: int = 1000, seed: int = 0,
          checkpoint: str | os.PathLike | None = None, checkpoint_every: int = 500,
          resume: bool = False, progress: bool = True, callback=None, preset: str | None = None,
          **overrides):
    """Fit complex voxels on ``grid`` to ``dataset``; returns a :class:`~sonarsim.dataset.Volume`
    (method 'gd') with the final voxels and the settings and final losses in ``params``.

    Any :class:`GDSettings` field can be given as a keyword; ``preset`` ('sim', 'airsas')
    starts from the reference's per-scene values. ``callback(iteration, terms)`` (terms:
    dict of floats) is called every iteration if given.
    """
    from sonarsim.dataset import Volume
    settings = settings_for(preset, iterations=iterations, seed=seed, **overrides)
    volume, history, info = fit(dataset, grid, settings, checkpoint=checkpoint,
                                checkpoint_every=checkpoint_every, resume=resume,
                                progress=progress, callback=callback)
    params = {k: v for k, v in asdict(settings).items()}
    params["preset"] = preset or "none"
    params["final_loss"] = float(history[-1]["loss"]) if history else float("nan")
    params["n_pings"] = int(len(dataset.waveforms))
    params.update(info)
    return Volume(volume=volume, bounds=np.asarray(grid.bounds, dtype=np.float64), method="gd",
                  params=params)


def fit(dataset, grid: Grid, settings: GDSettings, *, checkpoint=None, checkpoint_every=500,
        resume=False, progress=True, callback=None):
    """The optimisation loop; returns (volume complex64 [nx, ny, nz], history list of dicts,
    info dict: ``voxel_scale`` (max |scaled BP|, 1 with absolute lr and random init) and
    ``lr_absolute`` (the initial Adam learning rate in voxel units))."""
    import drjit as dr
    from drjit.opt import Adam
    if not isinstance(grid, Grid):
        raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
    measurements.check_dataset(dataset)
    m = jit()
    speeds = measurements.sound_speeds(dataset)
    tgt = targets(dataset, settings)
    first, last = reachable_bins(dataset, grid, speeds)
    rng = np.random.default_rng(settings.seed)
    init = (rng.standard_normal((2, grid.size)) * settings.init_scale).astype(np.float32)
    scale = 1.0
    if settings.init == "bp" or settings.lr_units == "relative":
        x0 = _scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings)
        peak = float(np.abs(x0).max())
        if not peak > 0:
            # No ray of the fitting batch met a non-zero voxel (e.g. a thin 2-D slab and few
            # rays): no least-squares scale. Fall back to the value a voxel needs to give the
            # target peak if every ray saw it, and start from tiny random values.
            import warnings
            warnings.warn("gradient descent: the backprojection could not be scaled through the "
                          "model (no ray met it); starting from random values with voxel scale "
                          "scale_factor/n_rays", RuntimeWarning, stacklevel=2)
            peak = settings.scale_factor / settings.n_rays
        if settings.lr_units == "relative":
            scale = peak
        if settings.init == "bp":
            init += np.stack([x0.real.ravel(), x0.imag.ravel()]).astype(np.float32)
    lr0 = settings.lr * scale
    lr1 = None if settings.lr_final is None else settings.lr_final * scale
    info = {"voxel_scale": scale, "lr_absolute": lr0}
    opt = Adam(lr=lr0, epsilon=settings.adam_epsilon)
    opt["re"] = m.Float(init[0])
    opt["im"] = m.Float(init[1])
    start = 0
    history: list[dict] = []
    if resume:
        if checkpoint is None:
            raise InputError("resume: needs a checkpoint path")
        if Path(checkpoint).exists():
            start, history = _load_checkpoint(checkpoint, opt, rng, grid, settings, m)
    sampler = _Sampler(tgt, first, last, settings, rng)
    vf = forward.VoxelField(grid)
    bound = _BoundField(vf, opt)
    directions = forward.cone_directions(settings.n_rays, settings.beamwidth_deg)
    eps = 0.5 * float(np.min(vf.h))
    bar = progress_bar(settings.iterations, progress, unit="it", desc="gd", initial=start,
                       leave=False)
    for it in range(start, settings.iterations):
        pings, bins, roll = sampler.draw()
        geo = forward.ping_geometry(dataset, pings, bins, speeds)
        samples = forward.EllipsoidSamples(geo, directions, frames=_rolled(geo.boresight, roll))
        P, J, K = samples.shape
        u_vec = None
        if it >= settings.reg_start and (settings.smoothness > 0 or settings.phase > 0):
            u = rng.standard_normal((3, P * J * K), dtype=np.float32)
            u /= np.linalg.norm(u, axis=0, keepdims=True) + 1e-12
            u_vec = m.Array3f(*(m.Float(u[a]) for a in range(3)))
        t = tgt[pings[:, None], bins].ravel()
        t_re, t_im = m.Float(t.real.copy()), m.Float(t.imag.copy())
        y_re, y_im, s_re, s_im = forward.render(
            bound.bound(), samples, lambertian_eps=eps if settings.lambertian else None,
            occlusion_scale=settings.occlusion_scale, with_sigma=True)
        terms = _loss_terms(m, bound, samples, s_re, s_im, y_re, y_im, t_re, t_im, settings,
                            grid, it >= settings.reg_start, u_vec)
        loss = sum(terms.values())
        dr.backward(loss)
        if lr1 is not None:
            frac = it / max(settings.iterations - 1, 1)
            opt.set_learning_rate(float(lr0 * (lr1 / lr0) ** frac))
        opt.step()
        record = {k: float(v[0]) for k, v in terms.items()}
        record["loss"] = float(loss[0])
        record["iteration"] = it + 1
        history.append(record)
        if callback is not None:
            callback(it + 1, record)
        bar.set_postfix(loss=f"{record['loss']:.3g}", refresh=False)
        bar.update(1)
        if checkpoint is not None and ((it + 1) % checkpoint_every == 0
                                       or it + 1 == settings.iterations):
            _save_checkpoint(checkpoint, opt, rng, it + 1, history, grid, settings)
    bar.close()
    vol = (np.asarray(opt["re"]) + 1j * np.asarray(opt["im"])).astype(np.complex64)
    return vol.reshape(grid.shape), history, info


# ---------------------------------------------------------------------------------------
# Checkpoints

def _adam_state(opt, key):
    value, promoted, lr, extra = opt.state[key]
    return extra


def _save_checkpoint(path, opt, rng, iteration, history, grid, settings):
    path = Path(path)
    arrays = {"iteration": np.array(iteration), "bounds": grid.bounds, "shape": np.array(grid.shape)}
    for key in ("re", "im"):
        arrays[f"{key}"] = np.asarray(opt[key])
        t, m1, v1, _ = _adam_state(opt, key)
        arrays[f"{key}_t"] = np.asarray(t).reshape(-1)[:1].astype(np.int64)
        arrays[f"{key}_m"] = np.asarray(m1)
        arrays[f"{key}_v"] = np.asarray(v1)
    arrays["rng_state"] = np.array(json.dumps(rng.bit_generator.state))
    arrays["history"] = np.array(json.dumps(history))
    arrays["settings"] = np.array(json.dumps(asdict(settings)))
    with atomic_path(path, keep_suffix=False) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def _load_checkpoint(path, opt, rng, grid, settings, m):
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable GD checkpoint ({exc})") from None
    if tuple(data["shape"]) != grid.shape or not np.allclose(data["bounds"], grid.bounds):
        raise InputError(f"{path}: checkpoint grid {tuple(data['shape'])} does not match {grid.shape}")
    saved = json.loads(str(data["settings"]))
    for key in ("seed", "pings_per_iteration", "bins_per_ping", "n_rays"):
        if saved.get(key) != getattr(settings, key):
            raise InputError(f"{path}: checkpoint has {key}={saved.get(key)}, this run {getattr(settings, key)}")
    for key in ("re", "im"):
        opt[key] = m.Float(data[key])
        value, promoted, lr, extra = opt.state[key]
        t = int(np.asarray(data[f"{key}_t"]).reshape(-1)[0])
        t = type(extra[0])(t) if not isinstance(extra[0], int) else t
        opt.state[key] = (value, promoted, lr,
                          (t, m.Float(data[f"{key}_m"]),
                           m.Float(data[f"{key}_v"]), extra[3]))
    rng.bit_generator.state = json.loads(str(data["rng_state"]))
    return int(data["iteration"]), json.loads(str(data["history"]))
