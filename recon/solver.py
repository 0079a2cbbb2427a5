"""One solver, two scene representations: neural backprojection (Reed et al. 2023, §4) and
gradient descent on voxels (its ``--no_network`` special case, reference
``inr_reconstruction/reconstruct_scene.py``).

Per iteration (§4.2 of the paper's method, supplement Eq. 10–12):

1. draw ``pings_per_iteration`` pings and, per ping, ``bins_per_ping`` range bins without
   replacement with p_k ∝ |w_k|^u over the bins whose ellipsoids can reach the grid;
2. intersect a cone of ``n_rays`` rays leaving the TX around its boresight with each bin's
   ellipsoid (:class:`recon.forward.EllipsoidSamples`);
3. render ŵ(r_k) = Σ_j σ(x_kj)·L_kj·T_kj with :func:`recon.forward.render` (the one forward
   model: transmittance, Lambertian factor from ∇|σ|) for the *scene* — complex voxels
   (:class:`VoxelScene`) or a hash-grid + MLP field (:class:`recon.field.NetworkScene`);
4. L = mean|ŵ − w|² + [from ``reg_start``] sparsity, smoothness, phase and TV priors;
5. one Adam step (:class:`Adam`, state in plain arrays so checkpoints own it).

Pings are rendered ``pings_per_chunk`` at a time and their gradients accumulated before the
step (the reference's ``accum_grad``), which bounds memory for the network.

Checkpoints (``.npz``, atomic) carry the parameters, Adam moments, the host generator's
state, the loss history and the run's identity (dataset digest, grid, settings); resuming
with another identity is refused with a one-line error.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.errors import FormatError, InputError
from sonarsim.progress import progress_bar

from . import forward, measurements
from ._jit import jit
from .adam import Adam  # noqa: F401  (re-exported: recon.solver.Adam)
from .grid import Grid


@dataclass
class SolverSettings:
    """Settings of a neural-backprojection or gradient-descent run (see :data:`HELP`).

    The defaults are gradient descent's (voxels, scaled-backprojection start, learning rate
    relative to the voxel scale); :data:`NETWORK_DEFAULTS` overrides them for the network
    and :data:`PRESETS` holds the named size/prior sets.
    """

    iterations: int = 1000
    seed: int = 0
    lr: float = 2e-2
    lr_final: float | None = 2e-3
    lr_units: str = "relative"
    adam_epsilon: float = 1e-8
    pings_per_iteration: int = 5
    pings_per_chunk: int = 0
    bins_per_ping: int = 110
    n_rays: int = 2000
    beamwidth_deg: float = 30.0
    sampling_uniformity: float = 1.0
    scale_factor: float = 10.0
    data: str = "auto"
    incoherent: bool = False
    lambertian: bool = False       # voxels: the linear model + sparsity (measured,
    occlusion_scale: float = 0.0   # docs/reconstruction.md); NETWORK_DEFAULTS: the full model
    sparsity: float = 3.0
    smoothness: float = 0.0
    phase: float = 0.0
    tv: float = 0.0
    smooth_delta: float = 1.0
    reg_start: int = 200
    init_scale: float = 1e-8
    init: str = "bp"
    ray_jitter: bool = True
    deterministic: bool = True     # a seed fixes the run (issue: reproducible by default)
    # network (NBP only)
    hash_levels: int = 14
    hash_features: int = 2
    hash_log2_size: int = 15
    hash_base_resolution: int = 16
    hash_level_scale: float = 1.5
    mlp_width: int = 128
    mlp_hidden: int = 3
    warm_start_iterations: int = 0
    autocorrelation_taps: int = 0

    def validate(self):
        for name in ("iterations", "pings_per_iteration", "bins_per_ping", "n_rays", "hash_levels",
                     "hash_features", "hash_base_resolution", "mlp_width", "mlp_hidden"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("pings_per_chunk", "warm_start_iterations", "reg_start", "autocorrelation_taps"):
            if int(getattr(self, name)) < 0:
                raise InputError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not 8 <= self.hash_log2_size <= 26:
            raise InputError(f"hash_log2_size: must be in [8, 26], got {self.hash_log2_size}")
        if not self.hash_level_scale >= 1:
            raise InputError(f"hash_level_scale: must be >= 1, got {self.hash_level_scale}")
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
        for name, options in CHOICES.items():
            if getattr(self, name) not in options:
                raise InputError(f"{name}: choose one of {', '.join(options)}, got {getattr(self, name)!r}")
        if not 0 < self.beamwidth_deg <= 360:
            raise InputError(f"beamwidth_deg: must be in (0, 360], got {self.beamwidth_deg}")


CHOICES = {"lr_units": ("relative", "absolute"), "init": ("bp", "random"),
           "data": ("auto", "matched", "analytic", "deconvolved")}

HELP = {
    "iterations": "optimiser steps",
    "seed": "random seed (pings, bins, rays, initialisation)",
    "lr": "Adam learning rate (× the voxel scale max|scaled BP| if lr_units is relative)",
    "lr_final": "learning rate at the last step, exponential decay from lr (none = constant)",
    "lr_units": "'relative': lr in units of max|scaled backprojection|; 'absolute': parameter units",
    "adam_epsilon": "Adam's epsilon",
    "pings_per_iteration": "pings per optimiser step (reference accum_grad)",
    "pings_per_chunk": "pings rendered per backward pass (0 = all at once); bounds memory",
    "bins_per_ping": "range bins drawn per ping (reference max_weights)",
    "n_rays": "rays in the TX cone per ping",
    "beamwidth_deg": "TX cone full angle, degrees",
    "sampling_uniformity": "bins are drawn with p ∝ |target|^u",
    "scale_factor": "targets are normalised to max 1, then multiplied by this",
    "data": "targets: 'auto' (deconvolved if the dataset is, else matched), 'matched' "
            "(matched-filtered analytic signal), 'deconvolved', 'analytic' (raw analytic signal)",
    "incoherent": "ablation: fit |target| with a real, non-negative scene",
    "lambertian": "Lambertian factor from the scene's normals (-∇|σ|)",
    "occlusion_scale": "transmittance scale s_occ, 0 = no occlusion (per unit of σ as sparsity)",
    "sparsity": "sparsity prior weight λ_sp (mean|σ|; σ in units of the voxel scale if lr_units "
                "is relative)",
    "smoothness": "smoothness prior weight λ_sm",
    "phase": "phase-smoothness prior weight λ_ph",
    "tv": "total variation along rays weight",
    "smooth_delta": "smoothness offset in units of √2 × mean voxel pitch",
    "reg_start": "iteration from which the priors apply",
    "init_scale": "std of the random initial voxels",
    "init": "initial scene: 'bp' (backprojection scaled through the model) or 'random'",
    "ray_jitter": "rotate the ray pattern randomly about the boresight per ping",
    "deterministic": "run on one thread so float32 gradient sums have a fixed order: the same "
                     "seed gives bit-identical results on any machine; --no-deterministic uses "
                     "every thread (about 2x faster on 2 cores, last bits vary with threads)",
    "hash_levels": "hash-grid levels", "hash_features": "features per level",
    "hash_log2_size": "log2 of the hash-table entries per level",
    "hash_base_resolution": "coarsest level resolution over the grid box",
    "hash_level_scale": "resolution factor between levels",
    "mlp_width": "MLP hidden width", "mlp_hidden": "MLP hidden layers",
    "autocorrelation_taps": "model the matched filter: convolve the rendered impulse response with "
                            "the pulse's autocorrelation over ±taps samples (0 = off; for "
                            "matched-filtered targets)",
    "warm_start_iterations": "NBP: first fit the network to the scaled backprojection for this many "
                             "steps (0 = reference's cold start)",
}

# Start values of the network (overriding the voxel defaults above): the configuration
# measured on the bunny (docs/reconstruction.md). Adam's step on the network's weights is
# absolute; the reference uses lr 1e-4 from a cold start and 26 000 single-ping steps, far
# too many for a CPU, so the network is first fitted to the scaled backprojection.
NETWORK_DEFAULTS = dict(lr=5e-3, lr_final=5e-4, lr_units="absolute", init="bp",
                        warm_start_iterations=300, pings_per_chunk=1, lambertian=True,
                        occlusion_scale=500.0, sparsity=0.0, reg_start=500)

# Named sets. 'cpu'/'reference': sampling and network sizes; 'sim'/'airsas': the reference's
# per-scene priors (scripts of the paper's code, §4.8 of the method description).
PRESETS = {
    "cpu": dict(pings_per_iteration=5, pings_per_chunk=5, bins_per_ping=64, n_rays=600,
                hash_levels=12, mlp_width=32, mlp_hidden=1, iterations=1000),
    "reference": dict(pings_per_iteration=5, bins_per_ping=200, n_rays=4777, hash_levels=14,
                      hash_log2_size=15, mlp_width=128, mlp_hidden=3),
    "sim": dict(bins_per_ping=110, scale_factor=10.0, lambertian=True, occlusion_scale=500.0,
                sparsity=1.0, smoothness=0.0, phase=0.0, reg_start=500, init="random"),
    "airsas": dict(bins_per_ping=200, scale_factor=30.0, lambertian=True, occlusion_scale=1000.0,
                   sparsity=10.0, smoothness=50.0, phase=0.1, reg_start=500, beamwidth_deg=30.0,
                   init="random"),
}


def settings_for(preset: str | None = None, network: bool = False, **overrides) -> SolverSettings:
    """Settings from the representation's defaults, a named preset (or several joined by
    '+', e.g. 'cpu+sim'), then explicit overrides."""
    values = dict(NETWORK_DEFAULTS) if network else {}
    for name in (preset.split("+") if preset else []):
        if name not in PRESETS:
            raise InputError(f"preset: choose from {', '.join(PRESETS)}, got {name!r}")
        values.update(PRESETS[name])
    values.update(overrides)
    unknown = set(values) - {f.name for f in dataclasses.fields(SolverSettings)}
    if unknown:
        raise InputError(f"unknown solver setting(s): {', '.join(sorted(unknown))}")
    settings = SolverSettings(**values)
    settings.validate()
    return settings


# ---------------------------------------------------------------------------------------
# Targets and sampling

def target_kind(dataset, settings: SolverSettings) -> str:
    """The kind of data fitted: 'auto' resolves to 'deconvolved' for a deconvolved dataset
    (``recon deconvolve``), else 'matched'. 'matched' and 'analytic' of a deconvolved dataset
    are its stored signals: the matched-filter ablation runs on the original dataset."""
    deconvolved = measurements.is_deconvolved(dataset)
    if settings.data == "auto":
        return "deconvolved" if deconvolved else "matched"
    if settings.data == "deconvolved" and not deconvolved:
        raise InputError("data 'deconvolved': the dataset is not deconvolved (run recon deconvolve)")
    return settings.data


def targets(dataset, settings: SolverSettings) -> np.ndarray:
    """Complex targets [N, T] complex64: the chosen analytic data normalised to max 1, times
    ``scale_factor`` (|·| for the incoherent ablation)."""
    kind = target_kind(dataset, settings)
    if kind == "matched":
        s = measurements.matched_filtered(dataset)
    elif kind == "deconvolved":
        s = measurements.complex_signals(dataset)
    else:
        s = measurements.analytic_waveforms(dataset)
    peak = float(np.abs(s).max())
    if not peak > 0:
        raise InputError("dataset waveforms: all zero, nothing to fit")
    s = s * (settings.scale_factor / peak)
    if settings.incoherent:
        s = np.abs(s)
    return s.astype(np.complex64)


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


class Sampler:
    """Host-side random choices of one run (NumPy generator; fully determined by the seed)."""

    def __init__(self, tgt: np.ndarray, first: np.ndarray, last: np.ndarray,
                 settings: SolverSettings, rng: np.random.Generator):
        self.tgt, self.first, self.last, self.s, self.rng = tgt, first, last, settings, rng
        self.active = np.flatnonzero(last >= first)
        if len(self.active) == 0:
            raise InputError("no ping's echo window overlaps the grid: check bounds and dataset")

    def draw(self):
        """(pings [P], bins [P, K] sorted per ping, roll [P] radians)."""
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


def rolled_frames(boresight: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Per-ping local→world matrices [P, 3, 3]: boresight frames rolled by ``roll`` (rad)."""
    f = forward.boresight_frames(boresight)
    c, s = np.cos(roll), np.sin(roll)
    rot = np.zeros((len(roll), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    return f @ rot


# ---------------------------------------------------------------------------------------
# Scene representations

class VoxelScene:
    """Complex voxels on the grid (trilinear, zero outside): parameters 're', 'im' [nx*ny*nz]."""

    kind = "voxels"

    def __init__(self, grid: Grid, settings: SolverSettings, incoherent: bool = False):
        self.grid, self.vf, self.incoherent = grid, forward.VoxelField(grid), incoherent
        self.h = self.vf.h

    def initial(self, rng: np.random.Generator, x0: np.ndarray | None) -> dict:
        n = self.grid.size
        return {"re": np.zeros(n, np.float32), "im": np.zeros(n, np.float32)}

    def with_start(self, params: dict, x0: np.ndarray) -> dict:
        """Parameters that represent the complex volume ``x0`` [nx, ny, nz] (added)."""
        return {"re": params["re"] + x0.real.ravel().astype(np.float32),
                "im": params["im"] + x0.imag.ravel().astype(np.float32)}

    def bind(self, params) -> forward.BoundVoxels:
        im = params["im"] * 0.0 if self.incoherent else params["im"]
        return self.vf.field(params["re"], im)

    def volume(self, params, grid: Grid | None = None) -> np.ndarray:
        """The complex volume [nx, ny, nz] (on ``grid``: trilinear resampling)."""
        import drjit as dr
        re, im = np.asarray(dr.detach(params["re"])), np.asarray(dr.detach(params["im"]))
        if self.incoherent:
            im = im * 0
        if grid is None or grid == self.grid:
            return (re + 1j * im).astype(np.complex64).reshape(self.grid.shape)
        m = self.vf.m
        pts = grid.points().T.astype(np.float32)
        a, b = self.vf.sample(m.Float(re), m.Float(im), m.Array3f(*(m.Float(p) for p in pts)))
        return (np.asarray(a) + 1j * np.asarray(b)).astype(np.complex64).reshape(grid.shape)


# ---------------------------------------------------------------------------------------
# Adam with explicit state


def random_directions(m, n: int, seed: int):
    """``n`` unit vectors (Array3f) uniform on the sphere, from a PCG32 stream per lane seeded
    by ``seed`` (an opaque value: one compiled kernel for every seed): the directions u of
    the smoothness priors, drawn on the device instead of as 3·n host normals."""
    import drjit as dr
    rng = m.PCG32(n, initstate=dr.opaque(m.UInt64, int(seed) & (2 ** 64 - 1)))
    z = 1.0 - 2.0 * rng.next_float32()
    phi = (2.0 * math.pi) * rng.next_float32()
    r = dr.sqrt(dr.maximum(1.0 - z * z, 0.0))
    s, c = dr.sincos(phi)
    return m.Array3f(r * c, r * s, z)


def loss_terms(m, field, samples, s_re, s_im, y_re, y_im, t_re, t_im, settings, h,
               reg_on: bool, u_vec, weight: float = 1.0, n_total: int | None = None):
    """Data term and priors (Dr.Jit scalars) of one chunk, weighted by ``weight`` (the
    chunk's share of the iteration's pings, so chunk sums equal the iteration means)."""
    import drjit as dr
    data = weight * (dr.mean(dr.square(y_re - t_re)) + dr.mean(dr.square(y_im - t_im)))
    terms = {"data": data}
    if not reg_on:
        return terms
    valid = m.Float(dr.select(samples.valid, 1.0, 0.0))
    n_valid = dr.maximum(dr.sum(valid), 1.0)
    mag = dr.sqrt(s_re * s_re + s_im * s_im + 1e-20)
    if settings.sparsity > 0:
        terms["sparsity"] = weight * settings.sparsity * dr.sum(valid * mag) / n_valid
    if settings.smoothness > 0 or settings.phase > 0:
        vbar = math.sqrt(2.0) * float(np.mean(h))
        shifted = samples.points + u_vec * (settings.smooth_delta * vbar)
        p_re, p_im = field(shifted)
        if settings.smoothness > 0:
            terms["smoothness"] = weight * settings.smoothness * dr.sum(
                valid * (dr.abs(s_re - p_re) + dr.abs(s_im - p_im))) / n_valid
        if settings.phase > 0:
            p_mag = dr.sqrt(p_re * p_re + p_im * p_im + 1e-20)
            terms["phase"] = weight * settings.phase * dr.sum(
                valid * dr.abs(s_re / mag - p_re / p_mag)) / n_valid
    if settings.tv > 0:
        P, J, K = samples.shape
        lane = dr.arange(m.UInt32, P * J * K)
        has_next = (lane % K) != K - 1
        n_re = dr.gather(m.Float, s_re, dr.select(has_next, lane + 1, lane))
        n_im = dr.gather(m.Float, s_im, dr.select(has_next, lane + 1, lane))
        tv = dr.sqrt(dr.square(n_re - s_re) + dr.square(n_im - s_im) + 1e-20)
        w = valid * m.Float(dr.select(has_next, 1.0, 0.0))
        terms["tv"] = weight * settings.tv * dr.sum(w * tv) / dr.maximum(dr.sum(w), 1.0)
    return terms


def in_scene_units(settings: SolverSettings, scale: float) -> SolverSettings:
    """The settings with every weight that multiplies |σ| (sparsity, smoothness, TV, the
    occlusion scale) divided by the scene unit: ``scale`` (the scaled backprojection's peak)
    when ``lr_units`` is 'relative', else 1. The priors and the transmittance then see σ in
    units of the scene's own scale, so one set of weights means the same for voxels (σ ~ 1e-3
    here) and the network (σ ~ 1); the phase prior is scale-free."""
    unit = scale if settings.lr_units == "relative" and scale > 0 else 1.0
    if unit == 1.0:
        return settings
    return dataclasses.replace(settings, sparsity=settings.sparsity / unit,
                               smoothness=settings.smoothness / unit, tv=settings.tv / unit,
                               occlusion_scale=settings.occlusion_scale / unit)


def render_chunk(scene, params, samples, settings: SolverSettings, eps: float, field=None):
    """The forward model of one chunk (shared by both representations): (ŷ_re, ŷ_im, σ_re,
    σ_im) at every lane, through :func:`recon.forward.render`. ``field``: ``scene.bind(params)``
    if the caller already has it (the voxels' packed buffer is then made once per chunk)."""
    return forward.render(scene.bind(params) if field is None else field, samples,
                          lambertian_eps=eps if settings.lambertian else None,
                          occlusion_scale=settings.occlusion_scale, with_sigma=True)


# ---------------------------------------------------------------------------------------
# Matched-filter model: the pulse autocorrelation

def pulse_autocorrelation(dataset, taps: int) -> np.ndarray:
    """The matched filter's response to the dataset's own pulse at lags −taps…taps samples
    [2·taps + 1] complex128, normalised to 1 at lag 0 — computed with the same matched filter
    as the data (:func:`recon.measurements.matched_filtered`), so conventions agree."""
    from sonarsim import signals
    pulse = np.asarray(dataset.pulse, dtype=np.float64)
    c = taps + 1
    w = np.zeros(len(pulse) + 2 * taps + 2)
    w[c:c + len(pulse)] = pulse
    mf = signals.matched_filter(w[None], pulse, mode="linear")[0]
    acf = np.asarray(mf[c - taps:c + taps + 1], dtype=np.complex128)
    return acf / acf[taps]


def expand_bins(bins: np.ndarray, taps: int, n_t: int):
    """Bins to render for the autocorrelation model: per ping the sorted union of
    k − taps … k + taps over the drawn bins k, padded to a fixed length by repeating its last
    bin (a zero along-ray step: no effect on transmittance). Returns (render_bins [P, L],
    positions [P, K, 2·taps + 1]: where bin k − m sits in render_bins, for lags m = −taps…taps)."""
    lags = np.arange(-taps, taps + 1)
    want = np.clip(bins[:, :, None] - lags[None, None, :], 0, n_t - 1)
    length = bins.shape[1] * len(lags)
    render = np.empty((len(bins), length), dtype=np.int64)
    pos = np.empty(want.shape, dtype=np.int64)
    for i in range(len(bins)):
        u = np.unique(want[i])
        render[i, :len(u)] = u
        render[i, len(u):] = u[-1]
        pos[i] = np.searchsorted(u, want[i]) + i * length
    return render, pos


def convolve_rendered(m, y_re, y_im, pos: np.ndarray, acf: np.ndarray):
    """Σ_m acf[m]·ŷ(k − m) for every drawn bin (Float re, im [P·K]) from the rendered ŷ."""
    import drjit as dr
    P, K, L = pos.shape
    out_re = dr.zeros(m.Float, P * K)
    out_im = dr.zeros(m.Float, P * K)
    for j in range(L):
        idx = m.UInt32(pos[:, :, j].ravel().astype(np.uint32))
        a_re = dr.gather(m.Float, y_re, idx)
        a_im = dr.gather(m.Float, y_im, idx)
        cr, ci = float(acf[j].real), float(acf[j].imag)
        out_re += cr * a_re - ci * a_im
        out_im += cr * a_im + ci * a_re
    return out_re, out_im


# ---------------------------------------------------------------------------------------
# Profiling

def _no_timer(phase, *arrays, iteration_end=False):
    pass


class PhaseTimer:
    """Profile of the solver's iterations by phase (``fit(..., timer=PhaseTimer())``).

    The loop calls ``timer(phase, *arrays)`` after each phase ('sampling': pings, bins,
    sample points and targets; 'forward': the forward model; 'loss': data term and priors;
    'backward': AD to the parameters; 'adam': the optimiser step; 'host': reading the loss
    values, history, callback). The timer evaluates the phase's arrays, waits for the device
    and charges the wall time since the previous call to the phase, with the Dr.Jit kernels
    launched meanwhile (their count, execution time and how many were compiled, i.e. missed
    the in-memory kernel cache). Forcing evaluation at phase ends changes kernel fusion a
    little: the profiled iteration is slightly slower than a free-running one.

    ``rows()`` → per phase (name, wall seconds, kernel seconds, kernel launches, compiled
    kernels, process CPU seconds — each per iteration) over the iterations after ``skip``.
    On a shared machine the CPU seconds of a one-thread run are the steadier figure.
    """

    PHASES = ("sampling", "forward", "loss", "backward", "adam", "host")

    def __init__(self, skip: int = 2):
        import time
        import drjit as dr
        self._clock, self._cpu = time.perf_counter, time.process_time
        self.skip, self.iteration = int(skip), 0
        self.totals = {}
        self._last = self._last_cpu = None
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                      # drop what ran before

    def __call__(self, phase, *arrays, iteration_end=False):
        import drjit as dr
        dr.eval(*(a for a in arrays if a is not None))
        dr.sync_thread()
        now, cpu = self._clock(), self._cpu()
        hist = dr.kernel_history()
        if self._last is not None and phase != "setup" and self.iteration >= self.skip:
            t = self.totals.setdefault(phase, [0.0, 0.0, 0, 0, 0.0])
            t[0] += now - self._last
            t[4] += cpu - self._last_cpu
            for k in hist:
                t[1] += float(k.get("execution_time", 0.0)) * 1e-3
                if k["type"] == dr.KernelType.JIT:
                    t[2] += 1
                    t[3] += 0 if k.get("cache_hit") else 1
        self._last, self._last_cpu = now, cpu
        if iteration_end:
            self.iteration += 1

    def close(self):
        import drjit as dr
        dr.set_flag(dr.JitFlag.KernelHistory, False)

    def rows(self):
        n = max(self.iteration - self.skip, 1)
        return [(p, *(v / n for v in self.totals[p])) for p in self.PHASES if p in self.totals]


# ---------------------------------------------------------------------------------------
# The loop

def dataset_digest(dataset) -> str:
    """SHA-256 (hex, 16 chars) of a dataset's waveforms, poses, pulse and sampling."""
    h = hashlib.sha256()
    for a in (dataset.waveforms, dataset.tx, dataset.rx, dataset.pulse):
        h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
    h.update(repr((float(dataset.fs), float(dataset.sound_speed),
                   int(dataset.start_sample))).encode())
    return h.hexdigest()[:16]


def scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings) -> np.ndarray:
    """Backprojection times the complex factor α that best fits the targets through the
    linear model on a fixed batch of pings (α = ⟨A x, s⟩/‖A x‖²)."""
    from . import backprojection
    x = backprojection.backproject(dataset, grid, progress=False)
    if settings.incoherent:
        x = np.abs(x).astype(np.complex64)
    rng = np.random.default_rng([settings.seed, 1])
    batch = dataclasses.replace(settings, pings_per_iteration=4 * settings.pings_per_iteration)
    pings, bins, _ = Sampler(tgt, first, last, batch, rng).draw()
    op = forward.EllipsoidOperator(grid, forward.ping_geometry(dataset, pings, bins, speeds),
                                   n_rays=settings.n_rays, beamwidth_deg=settings.beamwidth_deg)
    ax = op.forward(x)
    s = tgt[pings[:, None], bins]
    denom = np.vdot(ax, ax)
    alpha = np.vdot(ax, s) / denom if denom > 0 else 0.0
    if settings.incoherent:
        alpha = abs(alpha)
    return (x * alpha).astype(np.complex64)


def fit(dataset, grid: Grid, settings: SolverSettings, scene, *, checkpoint=None,
        checkpoint_every=500, resume=False, progress=True, callback=None, desc="fit",
        timer=None):
    """Optimise ``scene`` (a :class:`VoxelScene` or :class:`recon.field.NetworkScene`);
    returns (Adam parameters dict, history list of dicts, info dict). ``timer``: a
    :class:`PhaseTimer` to profile the iterations (it forces evaluation between phases)."""
    import drjit as dr
    if not isinstance(grid, Grid):
        raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
    measurements.check_dataset(dataset)
    threads = int(dr.thread_count())
    if settings.deterministic:
        dr.set_thread_count(1)
    try:
        return _fit(dataset, grid, settings, scene, checkpoint, checkpoint_every, resume,
                    progress, callback, desc, timer)
    finally:
        if settings.deterministic:
            dr.set_thread_count(threads)


def _fit(dataset, grid, settings, scene, checkpoint, checkpoint_every, resume, progress,
         callback, desc, timer=None):
    import drjit as dr
    m = jit()
    speeds = measurements.sound_speeds(dataset)
    tgt = targets(dataset, settings)
    first, last = reachable_bins(dataset, grid, speeds)
    identity = {"dataset": dataset_digest(dataset), "grid": {"bounds": grid.bounds.tolist(),
                "shape": list(grid.shape)}, "scene": scene.kind,
                "settings": {k: v for k, v in asdict(settings).items() if k != "iterations"}}
    rng = np.random.default_rng(settings.seed)
    params = scene.initial(rng, None)
    for k in params:
        if settings.init_scale > 0 and scene.kind == "voxels":
            params[k] = params[k] + (rng.standard_normal(params[k].shape)
                                     * settings.init_scale).astype(np.float32)
    scale = 1.0
    x0 = None
    if settings.init == "bp" or settings.lr_units == "relative" or settings.warm_start_iterations:
        x0 = scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings)
        peak = float(np.abs(x0).max())
        if not peak > 0:
            import warnings
            warnings.warn("the backprojection could not be scaled through the model (no ray met "
                          "it); voxel scale set to scale_factor/n_rays", RuntimeWarning, stacklevel=3)
            peak = settings.scale_factor / settings.n_rays
        if settings.lr_units == "relative":
            scale = peak
    if x0 is not None and settings.init == "bp" and scene.kind == "voxels":
        params = scene.with_start(params, x0)
    lr0 = settings.lr * scale
    lr1 = None if settings.lr_final is None else settings.lr_final * scale
    info = {"voxel_scale": scale, "lr_absolute": lr0, "dataset_digest": identity["dataset"],
            "target_kind": target_kind(dataset, settings)}
    model = in_scene_units(settings, scale)
    if x0 is not None and scene.kind == "network" and (settings.init == "bp"
                                                        or settings.warm_start_iterations):
        params = scene.warm_start(params, x0, max(settings.warm_start_iterations, 1), rng)
    opt = Adam(params, lr0, epsilon=settings.adam_epsilon)
    start, history = 0, []
    if resume:
        if checkpoint is None:
            raise InputError("resume: needs a checkpoint path")
        if Path(checkpoint).exists():
            start, history = load_checkpoint(checkpoint, opt, rng, identity, settings)
    sampler = Sampler(tgt, first, last, settings, rng)
    directions = forward.cone_directions(settings.n_rays, settings.beamwidth_deg)
    eps = 0.5 * float(np.min(scene.h))
    chunk = settings.pings_per_chunk or settings.pings_per_iteration
    taps = int(settings.autocorrelation_taps)
    if taps and info["target_kind"] != "matched":
        raise InputError("autocorrelation_taps: the pulse-autocorrelation model is for "
                         f"matched-filtered targets, this run fits {info['target_kind']} data")
    acf = pulse_autocorrelation(dataset, taps) if taps else None
    n_t = tgt.shape[1]
    bar = progress_bar(settings.iterations, progress, unit="it", desc=desc, initial=start,
                       leave=False)
    tick = timer if timer is not None else _no_timer
    tick("setup")
    for it in range(start, settings.iterations):
        pings, bins, roll = sampler.draw()
        reg_on = it >= settings.reg_start
        need_u = reg_on and (settings.smoothness > 0 or settings.phase > 0)
        n_chunks = -(-len(pings) // chunk)
        u_seeds = rng.integers(0, 2 ** 63, n_chunks) if need_u else None
        frames = rolled_frames(np.asarray(dataset.boresight)[pings], roll)
        record = {}
        for c0 in range(0, len(pings), chunk):
            sl = slice(c0, c0 + chunk)
            render_bins, pos = (expand_bins(bins[sl], taps, n_t) if taps
                                else (bins[sl], None))
            geo = forward.ping_geometry(dataset, pings[sl], render_bins, speeds)
            samples = forward.EllipsoidSamples(geo, directions, frames=frames[sl])
            u_vec = None
            if need_u:
                u_vec = random_directions(m, dr.width(samples.points), int(u_seeds[c0 // chunk]))
            t = tgt[pings[sl, None], bins[sl]].ravel()
            t_re, t_im = m.Float(t.real.copy()), m.Float(t.imag.copy())
            tick("sampling", t_re, t_im, u_vec)
            field = scene.bind(opt.params)
            y_re, y_im, s_re, s_im = render_chunk(scene, opt.params, samples, model, eps,
                                                  field=field)
            if taps:
                y_re, y_im = convolve_rendered(m, y_re, y_im, pos, acf)
            tick("forward", y_re, y_im, s_re, s_im)
            terms = loss_terms(m, field, samples, s_re, s_im, y_re, y_im, t_re, t_im, model,
                               scene.h, reg_on, u_vec, weight=len(pings[sl]) / len(pings))
            loss = sum(terms.values())
            tick("loss", loss, *terms.values())
            dr.backward(loss)
            tick("backward", *(dr.grad(v) for v in opt.params.values()))
            for k, v in terms.items():
                record[k] = record.get(k, 0.0) + float(v[0])
            record["loss"] = record.get("loss", 0.0) + float(loss[0])
            tick("host")
        if lr1 is not None:
            frac = it / max(settings.iterations - 1, 1)
            opt.lr = float(lr0 * (lr1 / lr0) ** frac)
        opt.step()
        tick("adam")
        record["iteration"] = it + 1
        history.append(record)
        if callback is not None:
            callback(it + 1, record)
        bar.set_postfix(loss=f"{record['loss']:.3g}", refresh=False)
        bar.update(1)
        if checkpoint is not None and ((it + 1) % checkpoint_every == 0
                                       or it + 1 == settings.iterations):
            save_checkpoint(checkpoint, opt, rng, it + 1, history, identity, settings)
        tick("host", iteration_end=True)
    bar.close()
    return opt.params, history, info


# ---------------------------------------------------------------------------------------
# Checkpoints

def save_checkpoint(path, opt: Adam, rng, iteration, history, identity, settings):
    arrays = dict(opt.state())
    arrays["iteration"] = np.array(iteration, dtype=np.int64)
    arrays["rng_state"] = np.array(json.dumps(rng.bit_generator.state))
    arrays["history"] = np.array(json.dumps(history))
    arrays["identity"] = np.array(json.dumps(identity))
    arrays["iterations"] = np.array(settings.iterations, dtype=np.int64)
    with atomic_path(Path(path), keep_suffix=False) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def load_checkpoint(path, opt: Adam, rng, identity, settings):
    """Restore ``opt`` and ``rng`` from ``path``; returns (iteration, history). A file that
    is not a complete checkpoint → FormatError; another run's checkpoint → InputError."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        saved = json.loads(str(data["identity"]))
        iteration = int(data["iteration"])
        history = json.loads(str(data["history"]))
        rng_state = json.loads(str(data["rng_state"]))
        saved_iterations = int(data["iterations"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable solver checkpoint "
                          f"({type(exc).__name__}: {str(exc)[:80]})") from None
    for key in ("dataset", "scene", "grid"):
        if saved.get(key) != identity[key]:
            raise InputError(f"{path}: checkpoint is of another run ({key} {saved.get(key)} "
                             f"!= {identity[key]})")
    a, b = saved.get("settings", {}), identity["settings"]
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if diff:
        k = diff[0]
        raise InputError(f"{path}: checkpoint has {k}={a.get(k)!r}, this run {b.get(k)!r}")
    if settings.lr_final is not None and saved_iterations != settings.iterations:
        raise InputError(f"{path}: checkpoint's learning-rate schedule is for {saved_iterations} "
                         f"iterations, this run has {settings.iterations}")
    if iteration > settings.iterations:
        raise InputError(f"{path}: checkpoint is at iteration {iteration}, past --iterations "
                         f"{settings.iterations}")
    opt.load(data)
    rng.bit_generator.state = rng_state
    return iteration, history


def make_scene(grid: Grid, settings: SolverSettings, network: bool):
    """The scene representation: :class:`recon.field.NetworkScene` or :class:`VoxelScene`."""
    if network:
        from .field import NetworkScene
        return NetworkScene(grid, settings, incoherent=settings.incoherent)
    return VoxelScene(grid, settings, incoherent=settings.incoherent)


def loss_by_tenth(history: list[dict], key: str) -> list[float]:
    """Mean of ``key`` over each tenth of the run's iterations (at most 10 values, first to
    last): the convergence record a volume carries (a single step's loss is noisy: every step
    draws other pings, bins and rays)."""
    values = np.array([h[key] for h in history if key in h], dtype=np.float64)
    if values.size == 0:
        return []
    return [float(c.mean()) for c in np.array_split(values, min(10, values.size))]


def solve(dataset, grid: Grid, *, network: bool, method: str, preset: str | None = None,
          checkpoint=None, checkpoint_every: int = 500, resume: bool = False,
          progress: bool = True, callback=None, export_grid: Grid | None = None, timer=None,
          **overrides):
    """Run the solver and return a :class:`~sonarsim.dataset.Volume` (``method``) on ``grid``
    (or the scene sampled on ``export_grid``), with the settings, final loss and info in
    ``params``. ``callback(iteration, record)`` gets each iteration's loss terms."""
    from sonarsim.dataset import Volume
    settings = settings_for(preset, network=network, **overrides)
    scene = make_scene(grid, settings, network)
    params, history, info = fit(dataset, grid, settings, scene, checkpoint=checkpoint,
                                checkpoint_every=checkpoint_every, resume=resume,
                                progress=progress, callback=callback, desc=method, timer=timer)
    out_grid = grid if export_grid is None else export_grid
    vol = scene.volume(params, out_grid)
    p = dict(asdict(settings))
    p["preset"] = preset or "none"
    p["scene"] = scene.kind
    p["final_loss"] = float(history[-1]["loss"]) if history else float("nan")
    p["final_data_loss"] = float(history[-1]["data"]) if history else float("nan")
    p["data_loss_by_tenth"] = loss_by_tenth(history, "data")
    p["loss_by_tenth"] = loss_by_tenth(history, "loss")
    p["n_pings"] = int(len(dataset.waveforms))
    p.update(info)
    return Volume(volume=vol, bounds=np.asarray(out_grid.bounds, dtype=np.float64), method=method,
                  params=p)
