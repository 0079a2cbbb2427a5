"""Settings of the solver: :class:`SolverSettings` (one field per option of ``recon gd`` /
``recon nbp``), their help texts, the network's defaults and the named presets."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from sonarsim.errors import InputError

from ..field import NetworkSettings
from ..solid import THRESHOLD_MODES


@dataclass
class SolverSettings(NetworkSettings):
    """Settings of a neural-backprojection or gradient-descent run (see :data:`HELP`).

    The defaults are gradient descent's (voxels, scaled-backprojection start, learning rate
    relative to the voxel scale); :data:`NETWORK_DEFAULTS` overrides them for the network
    and :data:`PRESETS` holds the named size/prior sets.
    """

    iterations: int = 1000
    seed: int = 0
    ensemble: int = 1
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
    ping_sampling: str = "uniform"
    scale_factor: float = 10.0
    data: str = "auto"
    incoherent: bool = False
    lambertian: bool = False       # voxels: the linear model + sparsity (measured,
    occlusion_scale: float = 0.0   # docs/reconstruction.md); NETWORK_DEFAULTS: the full model
    sparsity: float = 2.0
    prior_units: str = "energy"    # voxels: prior weights × the targets' mean energy (scale-free)
    smoothness: float = 0.0
    phase: float = 0.0
    tv: float = 0.0
    smooth_delta: float = 1.0
    reg_start: int = 200
    init_scale: float = 1e-8
    init: str = "bp"
    ray_jitter: bool = True
    deterministic: bool = True     # a seed fixes the run (issue: reproducible by default)
    # network (NBP only; the hash grid and MLP fields come from NetworkSettings)
    occupancy: bool = False
    surface_tv: float = 0.0
    solid_floor: bool = True
    warm_start_iterations: int = 0
    warm_start_lr: float = 1e-2
    autocorrelation_taps: int = 0
    scattering: str = "isotropic"
    sh_sparsity: float = 0.0
    sh_start: int = 0
    # the exported volume (both representations): the fitted field, or its solid (recon.solid)
    output: str = "solid"
    solid_threshold: float = 1.7       # × the Otsu level of |σ| smoothed by solid_blur voxels
    solid_min_fraction: float = 0.1
    solid_close: int = 3
    solid_ground: bool = True
    solid_hidden: int = 256
    solid_hidden_quorum: float = 1.0
    solid_cavity_floor: float = 0.02
    solid_blur: float = 0.7
    solid_threshold_mode: str = "otsu"
    solid_smooth: float = 1.0          # voxels: Gaussian on the solid's indicator, re-cut at 1/2
    solid_part_volume: float = 1.5e-6  # m³: a separate part this large and ...
    solid_part_height: float = 0.05    # m: ... reaching this high is kept (not a floater)

    def validate(self):
        if not (isinstance(self.ensemble, (int, np.integer)) and not isinstance(self.ensemble, bool)
                and 1 <= self.ensemble <= MAX_ENSEMBLE):
            raise InputError(f"ensemble: must be an integer in [1, {MAX_ENSEMBLE}], got {self.ensemble!r}")
        for name in ("iterations", "pings_per_iteration", "bins_per_ping", "n_rays"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("pings_per_chunk", "warm_start_iterations", "reg_start", "autocorrelation_taps",
                     "sh_start"):
            if int(getattr(self, name)) < 0:
                raise InputError(f"{name}: must be >= 0, got {getattr(self, name)}")
        self.validate_network()
        if self.lr_final is not None and not self.lr_final > 0:
            raise InputError(f"lr_final: must be positive, got {self.lr_final}")
        for name in ("lr", "scale_factor", "warm_start_lr"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("sparsity", "smoothness", "phase", "tv", "surface_tv", "occlusion_scale",
                     "adam_epsilon", "sh_sparsity",
                     "sampling_uniformity", "init_scale", "smooth_delta"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name}: must be a finite number >= 0, got {v}")
        for name, options in CHOICES.items():
            if getattr(self, name) not in options:
                raise InputError(f"{name}: choose one of {', '.join(options)}, got {getattr(self, name)!r}")
        from ..solid import check_parameters
        check_parameters(self.solid_threshold, self.solid_min_fraction, self.solid_close,
                         names=("solid_threshold", "solid_min_fraction", "solid_close"),
                         max_close=10, mode=self.solid_threshold_mode)
        if int(self.solid_hidden) != self.solid_hidden or not 0 <= self.solid_hidden <= 4096:
            raise InputError(f"solid_hidden: must be an integer in [0, 4096], got {self.solid_hidden}")
        from ..solid import check_blur, check_cavity_floor, check_quorum
        check_blur(self.solid_blur, "solid_blur")
        check_blur(self.solid_smooth, "solid_smooth")
        check_quorum(self.solid_hidden_quorum, "solid_hidden_quorum")
        check_cavity_floor(self.solid_cavity_floor, "solid_cavity_floor")
        from ..solid import check_part
        check_part(self.solid_part_volume, self.solid_part_height,
                   ("solid_part_volume", "solid_part_height"))
        if not 0 < self.beamwidth_deg <= 360:
            raise InputError(f"beamwidth_deg: must be in (0, 360], got {self.beamwidth_deg}")
        from ..scattering import check_settings
        check_settings(self)


# Most ensemble members of one run (each is a whole fit).
MAX_ENSEMBLE = 16

# Iterations between checkpoints: one default for recon gd/nbp, their Python API and the CLI.
CHECKPOINT_EVERY = 100

# Fields that only the network reads (neither an option of recon gd nor a parameter of its
# volumes).
NETWORK_ONLY = ("hash_", "mlp_", "warm_start", "occupancy", "surface_tv", "solid_floor",
                "scattering", "sh_")


def applies_to(name: str, network: bool) -> bool:
    """Whether the setting ``name`` means something for this representation."""
    return network or not name.startswith(NETWORK_ONLY)


CHOICES = {"lr_units": ("relative", "absolute"), "init": ("bp", "random"),
           "ping_sampling": ("uniform", "stratified"),
           "prior_units": ("energy", "peak"),
           "data": ("auto", "matched", "analytic", "deconvolved"), "output": ("field", "solid"),
           "solid_threshold_mode": THRESHOLD_MODES}

HELP = {
    "iterations": "optimiser steps",
    "seed": "random seed (pings, bins, rays, initialisation)",
    "ensemble": "fit the scene this many times, with the seeds seed, seed+1, …, and combine: "
                "the solid keeps the voxels more than half of the members' solids hold, the "
                "field output is the members' mean field (each member costs a whole fit; "
                "deterministic CPU fits run side by side, as many at once as --threads and "
                "the memory allow, each in its own process on one core)",
    "lr": "Adam learning rate (× the voxel scale max|scaled BP| if lr_units is relative)",
    "lr_final": "learning rate at the last step, exponential decay from lr (none = constant)",
    "lr_units": "'relative': lr in units of max|scaled backprojection|; 'absolute': parameter units",
    "prior_units": "with relative lr units: 'energy' multiplies the weights of the priors on |σ| by "
                   "the targets' mean energy E (the data term of an empty scene), so they weigh "
                   "the same against the data in every scene; 'peak': not (targets are "
                   "normalised to their peak only)",
    "adam_epsilon": "Adam's epsilon",
    "pings_per_iteration": "pings per optimiser step (reference accum_grad)",
    "pings_per_chunk": "pings rendered per backward pass (0 = all at once); bounds memory",
    "bins_per_ping": "range bins drawn per ping (reference max_weights)",
    "n_rays": "rays in the TX cone per ping",
    "beamwidth_deg": "TX cone full angle, degrees",
    "sampling_uniformity": "bins are drawn with p ∝ |target|^u",
    "ping_sampling": "'uniform': each step draws its pings at random from the whole scan; "
                     "'stratified': the run's pings are spread evenly over the scan order "
                     "(every ping once per pass; fewer draws than pings: one per equal "
                     "contiguous stratum), then shuffled; the schedule is for exactly "
                     "'iterations' steps, so a checkpoint resumes only with the same count",
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
    "occupancy": "NBP (experimental): the network outputs an occupancy o ∈ [0, 1] and a "
                 "complex surface amplitude a; the first occupied point along a ray scatters, "
                 "what lies behind it is hidden, and the exported volume is o",
    "surface_tv": "occupancy: weight of the total variation of o over a random step (its "
                  "surface area; favours filled interiors and no floaters)",
    "solid_floor": "occupancy: o = 1 below the grid's lowest voxel plane (the rig's ground), "
                   "so the ground's echo is o's rise there and no slab of voxels",
    "scattering": "NBP: 'isotropic' (σ(x)) or 'sh:L' (L = 0..4): the network outputs complex "
                  "spherical-harmonic coefficients and σ depends on the look direction "
                  "(SH-SAS, docs/scattering.md); the exported volume is c_00, the direction average",
    "sh_sparsity": "NBP sh:L: weight of an L1 prior on the direction-dependent coefficients, "
                   "mean over the samples of Σ_{l≥1}|c_lm| (keeps the field near isotropic; "
                   "applies from reg_start, as the other priors)",
    "sh_start": "NBP sh:L: iteration from which the l ≥ 1 coefficients enter the model; before "
                "it the field is isotropic (c_00 only; SH-SAS raises the degree during training)",
    "output": "exported volume: 'field' (the fitted complex field) or 'solid' (its solid "
              "occupancy, 1 inside and 0 outside: recon.solid.solidify, docs/reconstruction.md)",
    "solid_threshold": "solid: occupied where |σ|/max|σ| exceeds this (threshold mode 'peak'), "
                       "or this factor × the Otsu level of |σ|/max|σ| (mode 'otsu')",
    "solid_threshold_mode": "solid: 'peak' (a fixed fraction of the peak) or 'otsu' (a factor "
                            "on the field's own Otsu level: recon.solid step 1)",
    "solid_blur": "solid: smooth |σ| with a Gaussian of this many voxels before the threshold "
                  "(0 = off; recon.solid step 1)",
    "solid_smooth": "solid: smooth the solid's boundary with a Gaussian of this many voxels on "
                    "its indicator, cut again at one half (0 = off; recon.solid step 7)",
    "solid_min_fraction": "solid: drop connected parts smaller than this fraction of the largest "
                          "(floaters)",
    "solid_close": "solid: close gaps of the occupied set by this many voxels",
    "solid_part_volume": "solid: keep a connected part of at least this many cubic metres "
                         "whose top reaches solid_part_height above the grid's lowest plane, "
                         "however small against the largest part (a separate object, not a "
                         "floater; 0 = off; recon.solid step 2)",
    "solid_part_height": "solid: the height in metres above the grid's lowest plane that such "
                         "a part must reach (floaters lie on the ground)",
    "solid_hidden": "solid: fill the voxels that the occupied set hides from this many sensor "
                    "positions spread over the scan (0 = off; recon.solid step 5)",
    "solid_hidden_quorum": "solid: a voxel counts as hidden when the occupied set hides it from "
                           "at least this fraction of those sensors (1 = every one)",
    "solid_cavity_floor": "solid: fill an upward-open cavity when fewer than half of its floor "
                          "voxels have a voxel of the thresholded field (or the ground) within "
                          "this many metres below them (0 = off; recon.solid step 6)",
    "solid_ground": "solid: the grid's lowest z plane is the ground, so a shell standing on it "
                    "is filled",
    "warm_start_lr": "NBP: Adam learning rate of the warm start (absolute; the fit is to the "
                     "backprojection normalised to max 1)",
    "warm_start_iterations": "NBP: first fit the network to the scaled backprojection for this many "
                             "steps (0 = reference's cold start)",
}

# Start values of the network (overriding the voxel defaults above): the configuration
# measured on the bunny (docs/reconstruction.md); no Lambertian factor since 2026-11-28 (it
# put a lid over shallow cavities; docs "The Lambertian factor and the lid"); occlusion scale
# 100 since 2026-11-28 (500 before: it raised a cap over the cylinder's top; docs "The
# occlusion scale"); pings stratified over the scan since 2026-11-28 (a uniform draw of
# 1 500 of 54 000 pings let a full-size seed fail; docs "Stratified pings"). Adam's step on
# the network's weights is absolute; the reference uses lr 1e-4 from a cold start and 26 000
# single-ping steps, far too many for a CPU, so the network is first fitted to the scaled
# backprojection.
NETWORK_DEFAULTS = dict(lr=5e-3, lr_final=5e-4, lr_units="absolute", init="bp",
                        warm_start_iterations=300, pings_per_chunk=1, lambertian=False,
                        occlusion_scale=100.0, sparsity=0.0, reg_start=500,
                        solid_threshold=0.3, solid_threshold_mode="peak", solid_blur=0.0,
                        solid_hidden_quorum=0.8,
                        ping_sampling="stratified")

# Named sets. 'gd' / 'nbp': the frozen defaults of recon gd / recon nbp (every value that
# matters written out, so a change of a field's default above cannot move them; which scenes
# and measurements chose each value: docs/reconstruction.md, "Presets"). 'cpu'/'reference':
# sampling and network sizes; 'sim'/'airsas': the reference's per-scene priors (scripts of
# the paper's code, §4.8 of the method description).
# The exported volume of both frozen presets: the solid occupancy (recon.solid), with a
# threshold per representation (docs/reconstruction.md, "Solid output"); gaps closed by 3
# voxels (≈ the range resolution c/2B = 8.6 mm of the Table-2 LFM on 3.2 mm voxels; measured on
# the Table-2 shapes and held-out torus / two-object / bowl, docs "Solid output").
# Open cavities whose floor no data voxel within 2 cm supports are filled (step 6, 2026-11-28:
# the cube's missing top; docs "Open cavities without a floor", GD's solids measured there).
# The boundary is smoothed last by a Gaussian of 1 voxel (step 7, 2026-11-28): flat faces
# flat, the normals and depth maps better on every Table-2 and held-out field; 1.5 voxels and
# more erase a 1.4 cm rod and a 1.2 cm wall of a held-out scene (docs "Smoothed solid boundary").
# Separate parts of at least 1.5 cm³ reaching 5 cm above the ground are kept beside the
# largest (step 2, 2026-11-29: the thin scene's rod, the bunny's ear tips; no floater of 36
# full-size fields qualified; docs "Small separate objects").
SOLID = dict(output="solid", solid_min_fraction=0.1, solid_close=3, solid_ground=True,
             solid_hidden=256, solid_cavity_floor=0.02, solid_smooth=1.0,
             solid_part_volume=1.5e-6, solid_part_height=0.05)

PRESETS = {
    "gd": dict(iterations=1000, lr=2e-2, lr_final=2e-3, lr_units="relative", init="bp",
               pings_per_iteration=5, pings_per_chunk=0, ping_sampling="uniform",
               bins_per_ping=110, n_rays=2000,
               beamwidth_deg=30.0, scale_factor=10.0, lambertian=False, occlusion_scale=0.0,
               sparsity=2.0, prior_units="energy", smoothness=0.0, phase=0.0, tv=0.0,
               reg_start=200, **SOLID, solid_hidden_quorum=1.0,
               # three fits whose solids vote, as NBP's: the cube fails with seed 2 (Chamfer²
               # × 5.7); the vote beats the seeds' mean on all six scenes measured (2026-11-29,
               # docs/reconstruction.md "Ensemble of three fits")
               ensemble=3,
               # voxels are independent, so |σ| is speckled voxel by voxel: smooth it within
               # the range resolution, then cut at 1.7 × the field's Otsu level (2026-11-28;
               # a fixed 0.5 of the peak until then; docs "Smoothed magnitude, Otsu level")
               solid_blur=0.7, solid_threshold_mode="otsu", solid_threshold=1.7),
    # 300 steps after the 300-step BP warm start (1 000 until 2026-11-27: longer fits thin the
    # field and the solid loses; docs/reconstruction.md "Fit length")
    "nbp": dict(NETWORK_DEFAULTS, iterations=300, pings_per_iteration=5, pings_per_chunk=5,
                bins_per_ping=64, n_rays=600, beamwidth_deg=30.0, scale_factor=10.0,
                hash_levels=12, hash_features=2, hash_log2_size=15, hash_base_resolution=16,
                hash_level_scale=1.5, mlp_width=32, mlp_hidden=1, occupancy=False,
                # three fits (seeds seed..seed+2), majority vote of their solids: a seed's failed
                # solid (cube, cylinder, sphere: Chamfer² × 2–3) is outvoted (2026-11-28,
                # docs/reconstruction.md "Ensemble of three fits")
                ensemble=3,
                # hidden from 80 % of the sensors fills porous shells (2026-11-28; GD keeps 1:
                # 0.8 closed a held-out arch's tunnel in its solid; docs "hidden-voxel quorum")
                **SOLID, solid_threshold=0.3, solid_hidden_quorum=0.8,
                # the network's field is smooth already; a blur thickened its walls and the
                # Otsu cut moved seeds both ways (docs "Smoothed magnitude, Otsu level")
                solid_blur=0.0, solid_threshold_mode="peak"),
    "cpu": dict(pings_per_iteration=5, pings_per_chunk=5, bins_per_ping=64, n_rays=600,
                hash_levels=12, mlp_width=32, mlp_hidden=1, iterations=1000),
    "reference": dict(pings_per_iteration=5, bins_per_ping=200, n_rays=4777, hash_levels=14,
                      hash_log2_size=15, mlp_width=128, mlp_hidden=3),
    "sim": dict(bins_per_ping=110, scale_factor=10.0, lambertian=True, occlusion_scale=500.0,
                sparsity=1.0, prior_units="peak", smoothness=0.0, phase=0.0, reg_start=500,
                init="random"),
    "airsas": dict(bins_per_ping=200, scale_factor=30.0, lambertian=True, occlusion_scale=1000.0,
                   sparsity=10.0, prior_units="peak", smoothness=50.0, phase=0.1, reg_start=500,
                   beamwidth_deg=30.0, init="random"),
}

# The preset each entry point uses when none is named: recon gd / recon nbp, the Python
# API (recon.gradient_descent.solve, recon.nbp.solve), sonarsim batch and benchmarks/table2.
DEFAULT_PRESET = {False: "gd", True: "nbp"}


def default_preset(network: bool) -> str:
    """The frozen preset of the voxels (False) or the network (True)."""
    return DEFAULT_PRESET[bool(network)]


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
