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

Only the parts that both elevation halves of the imaged pings see are added
(:func:`consistent_parts`): a flat face's flash, under-predicted by a refined face that is
right to millimetres but not flat to a fraction of the wavelength, reaches only the look
directions normal to the face, and its image smears along the face's plane beyond its edges
(the Table-2 cube: 9 669 voxels of such ghosts, all imaged by the lowest sensors alone, the
upper half's image there ≤ 0.023 of the data's peak; the bunny's missing ear 0.12–0.33 in
both halves).

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


@dataclasses.dataclass
class UnexplainedImage:
    """What :func:`unexplained_image` finds. Every image is float32 [nx, ny, nz] on the grid,
    divided by the same peak max |BP(z)| of the data over all the imaged pings."""
    image: np.ndarray           # |BP(u)| over all the imaged pings
    lower: np.ndarray | None    # |BP(u)| over the lower elevation half of them (None: one
    upper: np.ndarray | None    # elevation only); and over the upper half
    lower_fraction: float       # the lower half's share of the pings (0.5 up to ties)
    split_deg: float | None     # the elevation (deg) at or below which a ping is 'lower'
    share: float                # Σ|u|² / Σ|z|²: the data's envelope energy left unexplained


ELEVATION_TIE = 1e-6   # rad: elevations closer than this are one (a ring of poses)


def elevation_halves(dataset, pings: np.ndarray, grid) -> tuple[np.ndarray, float] | None:
    """(lower bool [n], split in rad) for the pings ``pings``: those whose TX–RX midpoint is seen
    from the grid's centre at an elevation at or below the median, the rest upper; None when
    every ping has the same elevation (to ``ELEVATION_TIE``: no elevation aperture to split).
    Pings at the median elevation go to the lower half unless that leaves the upper one empty;
    the split returned is the highest elevation in the lower half."""
    tx, rx = (np.asarray(getattr(dataset, k), np.float64)[pings] for k in ("tx", "rx"))
    mid = 0.5 * (tx + rx) - np.asarray(grid.bounds, np.float64).mean(axis=1)
    elevation = np.arctan2(mid[:, 2], np.hypot(mid[:, 0], mid[:, 1]))
    if len(elevation) < 2 or np.ptp(elevation) < ELEVATION_TIE:
        return None
    split = float(np.median(elevation))
    lower = elevation <= split + ELEVATION_TIE
    if lower.all():
        lower = elevation < split - ELEVATION_TIE
    return lower, float(elevation[lower].max())


def unexplained_image(dataset, mesh, albedo: float, grid, index: np.ndarray, settings,
                      ground, seed: int = 0) -> UnexplainedImage:
    """The unexplained image of ``mesh`` (see the module docstring) over the pings
    :func:`residual_pings` of ``index``, with the images of the two elevation halves of those
    pings (:func:`elevation_halves`; their coherent sum is the image) for
    :func:`consistent_parts`, and the share of the data's envelope energy that the mesh leaves
    unexplained."""
    from . import backprojection, measurements
    from .pulse_chain import Envelope
    pings = residual_pings(index)
    if len(pings) == 0:
        raise InputError("no pings to image the unexplained data with")
    z = measurements.matched_filtered(dataset, pings)
    m = model_waveforms(dataset, mesh, albedo, pings, settings, ground, seed)
    u = unexplained_weights(np.abs(z), Envelope(dataset.pulse, dataset.n_samples)(m)[0]) * z
    share = float(np.sum(np.abs(u) ** 2) / max(np.sum(np.abs(z) ** 2), np.finfo(float).tiny))

    def image(signal, rows):
        sub = dataclasses.replace(dataset.select(pings[rows]),
                                  waveforms=signal[rows].astype(np.complex64),
                                  waveform_kind=measurements.DECONVOLVED)
        return backprojection.backproject(sub, grid, progress=False)

    everything = np.ones(len(pings), bool)
    peak = float(np.abs(image(z, everything)).max())
    if not peak > 0:
        raise InputError("the data's backprojection is zero on the grid: nothing to compare with")
    halves = elevation_halves(dataset, pings, grid)
    if halves is None:
        return UnexplainedImage((np.abs(image(u, everything)) / peak).astype(np.float32),
                                None, None, 1.0, None, share)
    lower_rows, split = halves
    lower, upper = image(u, lower_rows), image(u, ~lower_rows)
    return UnexplainedImage(*((np.abs(a) / peak).astype(np.float32)
                              for a in (lower + upper, lower, upper)),
                            float(lower_rows.mean()), float(np.degrees(split)), share)


def consistent_parts(added: np.ndarray, found: UnexplainedImage, level: float) -> np.ndarray:
    """bool [nx, ny, nz]: the parts of ``added`` (26-connected components) that each elevation
    half of the aperture images on its own: somewhere in the part the lower half's image is ≥
    ``level`` × its share of the pings, and so is the upper half's. A surface the start lacks
    echoes toward every elevation it is not hidden from, so each half images it at about its
    share of the full image; a flat face's flash reaches only the few look directions normal to
    the face (a vertical face's: the lowest sensors), and the image of the echo that the
    refined face under-predicts, smeared along the face's plane, comes from one half alone
    (docs/refine.md "Grown from the unexplained data"). Every part is kept when the scan has
    one elevation (no halves)."""
    from scipy import ndimage
    added = np.asarray(added, bool)
    if found.lower is None or not added.any():
        return added
    labels, n = ndimage.label(added, structure=np.ones((3, 3, 3), bool))
    index = np.arange(1, n + 1)
    low = ndimage.maximum(found.lower, labels, index)
    high = ndimage.maximum(found.upper, labels, index)
    keep = ((np.asarray(low) >= level * found.lower_fraction)
            & (np.asarray(high) >= level * (1.0 - found.lower_fraction)))
    return np.concatenate([[False], keep])[labels]


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
