"""Loss of one chunk: the data term and the priors of §4.4 (sparsity, smoothness, phase,
TV along rays), and the scene units in which the priors see σ."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .settings import SolverSettings


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
    cache = getattr(field, "cache", None)
    if settings.surface_tv > 0 and cache:
        # total variation of the occupancy (its surface area): |o(x) − o(x')| over a random
        # step of √2·mean pitch; a solid costs one edge per line through it, a hollow shell
        # two, a floater a pair: filled interiors and clean exteriors are cheapest
        vbar = math.sqrt(2.0) * float(np.mean(h))
        o_near, _, _ = field.occupancy_and_amplitude(samples.points + u_vec * (settings.smooth_delta * vbar))
        jump = dr.abs(cache["occupancy"] - o_near)
        terms["surface_tv"] = weight * settings.surface_tv * dr.sum(valid * jump) / n_valid
    if settings.sh_sparsity > 0 and cache and "sh" in cache:
        # SH-SAS's L1 prior on the direction-dependent coefficients (recon.scattering)
        l1 = sum(dr.sqrt(re * re + im * im + 1e-20) for re, im in cache["sh"])
        terms["sh_sparsity"] = weight * settings.sh_sparsity * dr.sum(valid * l1) / n_valid
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


def in_scene_units(settings: SolverSettings, scale: float, energy: float = 1.0) -> SolverSettings:
    """The settings with every weight that multiplies |σ| (sparsity, smoothness, TV, the
    occlusion scale) divided by the scene unit: ``scale`` (the scaled backprojection's peak)
    when ``lr_units`` is 'relative', else 1. The priors and the transmittance then see σ in
    units of the scene's own scale, so one set of weights means the same for voxels (σ ~ 1e-3
    here) and the network (σ ~ 1); the phase prior is scale-free.

    ``energy``: the targets' mean energy E = mean |s|² over the reachable samples (the data
    term of an empty scene; :func:`recon.solver.sampling.target_energy`). With
    ``prior_units`` 'energy' (and relative units) the prior weights (not the occlusion
    scale) are also multiplied by E: the loss is then E·(data/E + λ·prior), so a weight λ
    trades the same *fraction* of the data term against the prior in every scene. Targets
    are normalised to their peak, so E depends on how the echo energy is spread: the cube's
    few specular echoes give E = 0.042 where the bunny gives 0.51 (5×3 pose subsets of the
    Table-2 scans), and a weight that suits the bunny wipes the cube out."""
    unit = scale if settings.lr_units == "relative" and scale > 0 else 1.0
    if unit == 1.0:
        return settings
    e = float(energy) if settings.prior_units == "energy" and energy > 0 else 1.0
    return dataclasses.replace(settings, sparsity=settings.sparsity * e / unit,
                               smoothness=settings.smoothness * e / unit,
                               tv=settings.tv * e / unit,
                               sh_sparsity=settings.sh_sparsity * e / unit,
                               occlusion_scale=settings.occlusion_scale / unit)
