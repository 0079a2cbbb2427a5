"""What a refined mesh leaves unexplained: the part of the data its echoes miss, imaged.

A mesh fitted by ``recon refine`` cannot grow a part its start lacks (the Table-2 bunny's ear
that the NBP solid lost): moving vertices changes no topology. The data still hold that part's
echoes, and the fitted model says which echoes it does not explain. Per ping, with z = MF(y)
the matched-filtered analytic signal of the measured waveform (:func:`recon.measurements.
matched_filtered`) and m the mesh's rendered waveform (same renderer, albedo and ground as the
fit; :class:`recon.refine.RenderedScene`), the **unexplained signal** is

    u(t) = w(t)·z(t),   w(t) = clip(1 − α·|MF(m)|(t) / |z(t)|, 0, 1)

with α the one global scale of the model's envelopes to the data's (closed form, as the
envelope misfit's). u keeps the data's phase where the model predicts less echo than there
is and is zero where the model accounts for it. Its coherent backprojection (:mod:`recon.
backprojection` on u as an already compressed signal), divided by the peak of the
backprojection of z over the same pings, is the **unexplained image** (0 … ~1): a missing
part focuses in it as it does in the data's image, while the sidelobes and smears of the
surfaces the mesh already has do not, since their echoes are explained.

Why not the raw residual y − α·m: where the surface is right to a few millimetres but not to
the carrier's phase (flat faces), the raw residual is nearly all of the data (measured on the
Table-2 cube: 99 % of the energy) and its image is the data's. The envelope ratio does not
care about the phase (docs/refine.md "Grown from the unexplained data").
"""
from __future__ import annotations

import dataclasses

import numpy as np

from sonarsim.errors import InputError

RESIDUAL_PINGS = 2160     # pings imaged (evenly strided over the fitted ones: every 25th of
                          # a 54 000-ping scan; all of a 2 160-ping one)
RENDER_BATCH = 64         # pings rendered at once


def residual_pings(index: np.ndarray, count: int = RESIDUAL_PINGS) -> np.ndarray:
    """At most ``count`` pings of ``index``, evenly strided from its first."""
    index = np.asarray(index)
    return index[::max(1, int(np.ceil(len(index) / count)))]


def model_waveforms(dataset, mesh, albedo: float, index: np.ndarray, settings, ground,
                    seed: int = 0) -> np.ndarray:
    """float64 [n, T]: the rendered waveforms of ``mesh`` (trimesh, m) for the pings ``index``
    with the object's ``albedo`` (relative to the ground's), through the dataset's pulse chain
    (:class:`recon.pulse_chain.PulseChain`), bounces summed; no gradients are recorded."""
    import tempfile

    from sonarsim import runtime

    from .refine import RenderedScene, dataset_chain
    mi = runtime.mitsuba()
    import drjit as dr
    _, window, chain = dataset_chain(dataset, settings)
    out = np.zeros((len(index), dataset.n_samples))
    with tempfile.TemporaryDirectory(prefix="unexplained-") as workdir:
        model = RenderedScene(mesh, dataset, window, ground, settings, workdir)
        vertices = model.vertices[0]
        with dr.suspend_grad():
            for b in range(0, len(index), RENDER_BATCH):
                pings = np.asarray(index[b:b + RENDER_BATCH])
                hist = model.render(vertices, mi.Float(float(albedo)), pings,
                                    seed * 100_003 + b)
                out[b:b + len(pings)] = chain.forward(
                    hist.numpy().astype(np.float64).sum(axis=1))
    return out


def unexplained_weights(data_envelope: np.ndarray, model_envelope: np.ndarray) -> np.ndarray:
    """w [n, T] in [0, 1]: 1 − α·e_m / e_y clipped, α = ⟨e_m, e_y⟩ / ⟨e_m, e_m⟩ (the best
    global scale); 1 where the model is silent, 0 where it predicts at least the data's
    envelope. A silent model (all zero) explains nothing: w = 1."""
    ey = np.asarray(data_envelope, np.float64)
    em = np.asarray(model_envelope, np.float64)
    mm = float(np.vdot(em, em).real)
    alpha = float(np.vdot(em, ey).real) / mm if mm > 0 else 0.0
    return np.clip(1.0 - alpha * em / np.maximum(ey, np.finfo(float).tiny), 0.0, 1.0)


def unexplained_image(dataset, mesh, albedo: float, grid, index: np.ndarray, settings,
                      ground, seed: int = 0) -> tuple[np.ndarray, float]:
    """(image float32 [nx, ny, nz], share): |BP(u)| / max |BP(z)| on ``grid`` over the pings
    :func:`residual_pings` of ``index`` (see the module docstring), and the share of the data's
    envelope energy Σ|u|² / Σ|z|² that the mesh leaves unexplained."""
    from . import backprojection, measurements
    from .pulse_chain import Envelope
    pings = residual_pings(index)
    if len(pings) == 0:
        raise InputError("no pings to image the unexplained data with")
    z = measurements.matched_filtered(dataset, pings)
    m = model_waveforms(dataset, mesh, albedo, pings, settings, ground, seed)
    u = unexplained_weights(np.abs(z), Envelope(dataset.pulse, dataset.n_samples)(m)[0]) * z
    share = float(np.sum(np.abs(u) ** 2) / max(np.sum(np.abs(z) ** 2), np.finfo(float).tiny))
    sub = dataset.select(pings)
    images = []
    for signal in (z, u):
        compressed = dataclasses.replace(sub, waveforms=signal.astype(np.complex64),
                                         waveform_kind=measurements.DECONVOLVED)
        images.append(np.abs(backprojection.backproject(compressed, grid, progress=False)))
    peak = float(images[0].max())
    if not peak > 0:
        raise InputError("the data's backprojection is zero on the grid: nothing to compare with")
    return (images[1] / peak).astype(np.float32), share


UNEXPLAINED_BEYOND = 1.0  # × the range resolution c/2B: the layer of an imperfect fit's
                          # residual around the surfaces it has is not added


def grown_voxels(volume: np.ndarray, bounds, threshold: float, z_min: float,
                 image: np.ndarray, level: float, beyond: float) -> np.ndarray:
    """bool [nx, ny, nz]: the voxels that the unexplained ``image`` (same grid) adds to the
    start's occupied set (normalised |``volume``| > ``threshold``): of the voxels ≥ ``level``
    at z ≥ ``z_min`` outside the set, those farther than ``beyond`` (m) from it, and those
    within geodesic distance ``beyond`` of them through such voxels (their bridge towards the
    set) — :func:`recon.refine.grow_occupancy` without its touching rule. The layer of an
    imperfect fit's residual that only hugs the start is left out; a part detached from the
    start is added (a separate object the start lacks)."""
    from .export import normalized_magnitude, voxel_axes
    from .refine import grow_occupancy
    if np.shape(image) != np.shape(volume):
        raise InputError(f"the unexplained image's grid {np.shape(image)} differs from the "
                         f"start's {np.shape(volume)}")
    occupied = normalized_magnitude(volume, "minmax") > threshold
    b = np.asarray(bounds, np.float64)
    spacing = (b[:, 1] - b[:, 0]) / np.maximum(np.array(occupied.shape) - 1, 1)
    z = voxel_axes(bounds, occupied.shape)[2]
    return grow_occupancy(occupied, np.asarray(image), level, z >= z_min, spacing, beyond,
                          touching=False) & ~occupied
