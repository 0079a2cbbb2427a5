"""Surface refinement through the sonar renderer: fit a mesh to the measured waveforms.

``solve(dataset, init, settings)`` starts from a triangle mesh (:func:`start_mesh`: the
marching-cubes surface of a reconstructed volume, e.g. NBP's, or a given mesh) and moves its
vertices (and fits the object's albedo relative to the ground's) by gradient descent so that
the rendered waveforms match the dataset's:

* **Model.** The simulator's own renderer through ``mi.render``: a Mitsuba scene of the mesh
  and the known ground (two-sided diffuse), the ``sonar_transient`` integrator with the
  dataset's beams and ``bounces`` bounces, one ``sonar`` sensor holding the batch's poses and a
  ``sonar_film`` on the dataset's time axis (:class:`RenderedScene`). It renders the
  histograms with exact occlusion and the Lambertian terms on the current surface;
  :class:`recon.pulse_chain.PulseChain` turns them into waveforms with the simulator's chain
  (oversampled pulse, decimation). Gradients: the integrator's path-replay adjoint
  (``render_backward``, docs/differentiable.md) fed with the pulse chain's adjoint of the
  loss gradient. Visibility changes are not differentiated (the renderer's documented bias).
* **Objective.** The data's absolute scale is unknown, so a global scale α is fitted in closed
  form each step (loss = ‖α·m − y‖²/‖y‖² = 1 − cos²(m, y), :func:`recon.pulse_chain.scaled_misfit`).
  Stage 1 compares envelopes of the matched-filtered signals (smooth on the range-resolution
  scale: a wide capture range), stage 2 the raw waveforms (the carrier phase: sub-millimetre
  sensitivity).
* **Regulariser.** The vertices are optimised in the differential form of
  ``mi.ad.LargeSteps`` (Nicolet et al. 2021, u = (I + λL)v) with Adam per coordinate
  (UniformAdam, the tutorial's choice, on request); the mesh is remeshed isotropically
  (``gpytoolbox.remesh_botsch``, Botsch & Kobbelt 2004) at the start and, with
  ``remesh_every``, between segments, which keeps the triangles well shaped.
* **Affine stage** (optional, ``affine_steps``): the whole start is scaled per axis about its
  base and shifted horizontally (five parameters, :func:`affine_vertices`) by the envelope
  misfit before any vertex moves alone: a thresholded volume's surface sits a few
  millimetres off the truth by the same amount over a whole face (the τ-cut of the blurred
  echo), which the vertex stages, caught by the start's roughness, do not undo.
* **Support stage** (optional, first): the mesh is cut into patches with one albedo each;
  the albedos are fitted to the envelopes with the geometry fixed and the patches the data
  leave dark (below ``support_keep`` × the median) are removed: floaters and smears of the
  start volume, which moving vertices cannot delete.
* **Grown start** (optional, :func:`grow_occupancy`): the start's occupied set is extended
  by the connected parts of a second volume of the same scan (its backprojection): thin
  parts that NBP misses but the data images; the support stage then prunes what the data
  does not support.
* **Smoothed start** (:func:`smoothed_start`): the start remeshed and smoothed once by
  (I + λL)⁻¹, which takes off roughness below the range resolution that the envelopes do not
  see; ``recon refine`` refines it beside the wrapped starts and the data keep one.
* **Pings.** The chosen pings are split into interleaved batches (each spans the aperture);
  one batch per step.

docs/refine.md has the method, the measured results and their cost.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import typing

import numpy as np

from sonarsim.errors import InputError
from sonarsim.limits import MAX_BOUNCES

from .pulse_chain import Envelope, PulseChain, envelope_misfit, scaled_misfit

if typing.TYPE_CHECKING:
    import trimesh

STAGES = ("envelope", "waveform")
DEFAULT_GROUND = (0.4, 0.4, 1.0)     # m, m, albedo: the simulator's default ground


@dataclass(frozen=True)
class RefineSettings:
    """How :func:`solve` refines a mesh.

    envelope_steps, waveform_steps: optimiser steps of the two stages. lr: Adam step in
    metres of latent displacement (decays ×0.1 over each stage, cosine). large_steps_lambda:
    λ of LargeSteps. edge_length: target edge of the isotropic remeshing (m); remesh_every:
    steps between remeshings (0: only the start mesh is remeshed). pings_per_batch: pings
    per step. fit_albedo: fit the object's albedo (relative to the ground's; needs a ground).
    bounces: bounces rendered (1 = single scattering; 2 or more add the multiple scattering
    between the object and the ground). surface_spacing: the integrator's strata size (m);
    path_samples: its path-length quantiles per stratum. oversample: histogram bins per
    sample (None: the dataset's, else 20). seed: the batch order and the renderer's seeds.
    envelope_blur: coarse to fine: the envelope stage compares the envelopes smoothed by a
    Gaussian of σ = ``envelope_blur`` metres of one-way range at its first step, shrinking
    linearly to 0 at its last (0: no smoothing): a capture range of several range
    resolutions for surface that starts centimetres from the truth. uniform_adam: one
    second-moment scale for all vertices (UniformAdam, Nicolet et al. 2021); False: Adam per
    coordinate, so weakly lit surface (a top seen obliquely) moves as fast as the rest.

    affine_steps: steps of the affine stage that runs before the envelope stage (0: none):
    the start is scaled per axis about its base and shifted horizontally
    (:func:`affine_vertices`), fitted to the envelopes with Adam at step ``lr`` (metres at
    the start's half extent), the albedo with it.

    support_steps: steps of the support stage that runs first (0: none): the mesh is cut
    into patches of about ``patch_size`` (m, k-means of the face centroids), each patch's
    albedo is fitted to the envelopes (log-albedo, Adam step ``support_lr``) with the
    geometry fixed, and the patches whose albedo ends below ``support_keep`` × the
    area-weighted median are removed (surface the data does not support: floaters, smears).
    """

    # The defaults are the command measured from the NBP preset's solids of the full-size
    # Table-2 scans (bunny, cube, cylinder; checked on a held-out box; docs/refine.md
    # "Defaults"): 40 + 20 steps of 32 pings, no remeshing, per-coordinate Adam. No affine
    # stage: measured on eleven scenes it halves the cube but costs four others, and it lets
    # the cube's ghost-grown candidate win (docs/refine.md "The affine stage").
    affine_steps: int = 0
    envelope_steps: int = 40
    waveform_steps: int = 20
    lr: float = 1e-3
    large_steps_lambda: float = 20.0
    edge_length: float = 8e-3
    remesh_every: int = 0
    pings_per_batch: int = 32
    fit_albedo: bool = True
    bounces: int = 1
    surface_spacing: float = 4e-3
    path_samples: int = 4
    oversample: int | None = None
    seed: int = 0
    envelope_blur: float = 0.0
    uniform_adam: bool = False
    support_steps: int = 0
    patch_size: float = 0.025
    support_keep: float = 0.7
    support_lr: float = 0.1

    def validate(self) -> None:
        for name in ("affine_steps", "envelope_steps", "waveform_steps", "remesh_every",
                     "support_steps"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 0:
                raise InputError(f"{name} must be a non-negative integer, got {getattr(self, name)}")
        for name in ("pings_per_batch", "bounces", "path_samples"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise InputError(f"{name} must be a positive integer, got {getattr(self, name)}")
        if self.bounces > MAX_BOUNCES:
            raise InputError(f"bounces must be at most {MAX_BOUNCES}, got {self.bounces}")
        if self.oversample is not None and (int(self.oversample) != self.oversample
                                            or self.oversample < 1):
            raise InputError(f"oversample must be a positive integer, got {self.oversample}")
        for name in ("lr", "large_steps_lambda", "edge_length", "surface_spacing", "patch_size",
                     "support_lr"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number, got {v}")
        if not (np.isfinite(self.envelope_blur) and self.envelope_blur >= 0):
            raise InputError(f"envelope_blur must be a non-negative number (m), got {self.envelope_blur}")
        if not (np.isfinite(self.support_keep) and 0 <= self.support_keep < 1):
            raise InputError(f"support_keep must be in [0, 1), got {self.support_keep}")
        if self.affine_steps + self.envelope_steps + self.waveform_steps + self.support_steps == 0:
            raise InputError("nothing to do: support_steps + affine_steps + envelope_steps + "
                             "waveform_steps is 0")


@dataclass
class RefineResult:
    """The refined mesh (vertices [V, 3] m, faces [F, 3]), the object's albedo relative to the
    ground's (None without a ground), and the record of every step (stage, loss, α, seconds)."""

    vertices: np.ndarray
    faces: np.ndarray
    albedo: float | None
    history: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    affine: dict | None = None      # the affine stage's fit: pivot (m), scale [3], shift [2] (m)

    @property
    def final_misfit(self) -> float:
        """Mean loss of the last stage over its last pass over the batches (all fitted pings
        once; the whole stage when it is shorter): the data's verdict on the refined mesh,
        comparable between refinements of the same pings, stages and settings."""
        return self.stage_misfit(self.history[-1]["stage"])

    def stage_misfit(self, stage: str) -> float | None:
        """Mean loss of ``stage`` ('support', 'affine', 'envelope', 'waveform') over its last
        pass over the batches (the whole stage when shorter); None when the stage did not run."""
        losses = [h["loss"] for h in self.history if h["stage"] == stage]
        if not losses:
            return None
        return float(np.mean(losses[-int(self.settings.get("batches", len(losses))):]))

    @property
    def mesh(self) -> trimesh.Trimesh:
        import trimesh
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


# ------------------------------------------------------------------------ the start mesh

def start_mesh(volume: np.ndarray, bounds, threshold: float = 0.2, z_min: float = 0.005,
               min_component: float = 0.05, wrap_radius: float = 0.0,
               grow: np.ndarray | None = None, grow_threshold: float = 0.2,
               grow_beyond: float = 0.0, add: np.ndarray | None = None,
               shrink_radius: float = 0.0, seal_quorum: float = 0.0,
               sensors: np.ndarray | None = None) -> trimesh.Trimesh:
    """The τ-surface of a volume [nx, ny, nz] (bounds [[x0, x1], ...] m) above the ground.

    With ``grow`` (a second volume of the same scan on the same grid, e.g. its
    backprojection) the occupied set (normalised |volume| > ``threshold``) is first grown by
    :func:`grow_occupancy` (``grow_threshold``, ``z_min``, ``grow_beyond`` m). With
    ``seal_quorum`` q > 0 the empty voxels that it hides from a fraction q of the ``sensors``
    [N, 3] (m, the dataset's frame) are then added (:func:`seal_occupancy`). With
    ``shrink_radius`` > 0 (m) it is then shrunk (:func:`shrink_occupancy`: thick bodies eroded,
    thin parts kept). With ``wrap_radius`` > 0 (m) it is then wrapped (:func:`wrap_occupancy`), which seals the tunnels and pin-holes of a porous
    shell. Voxels below ``z_min`` (the ground's echo) are then cleared, so the object's
    surface closes above the ground; components with fewer than ``min_component`` × the
    largest's faces are dropped (isolated blobs of the volume); with ``min_component`` 0 (a
    solid's parts) the wrap keeps every piece too.
    """
    from .export import mesh_from_volume, normalized_magnitude, voxel_axes
    vol = np.array(volume, copy=True)
    for name, radius in (("wrap", wrap_radius), ("shrink", shrink_radius)):
        if not (np.isfinite(radius) and radius >= 0):
            raise InputError(f"{name} radius: must be >= 0 m, got {radius}")
    if not 0 <= seal_quorum <= 1:
        raise InputError(f"seal quorum: must be in [0, 1], got {seal_quorum}")
    if seal_quorum > 0 and sensors is None:
        raise InputError("sealing a start needs the sensor positions")
    z = voxel_axes(bounds, vol.shape)[2]
    if add is not None and np.shape(add) != vol.shape:
        raise InputError(f"the added voxels' grid {np.shape(add)} differs from the start's {vol.shape}")
    if (grow is not None or wrap_radius > 0 or add is not None or shrink_radius > 0
            or seal_quorum > 0):
        b = np.asarray(bounds, np.float64)
        spacing = (b[:, 1] - b[:, 0]) / np.maximum(np.array(vol.shape) - 1, 1)
        occupied = normalized_magnitude(vol, "minmax") > threshold
        if grow is not None:
            if np.shape(grow) != vol.shape:
                raise InputError(f"the grow volume's grid {np.shape(grow)} differs from the "
                                 f"start's {vol.shape}")
            occupied = grow_occupancy(occupied, normalized_magnitude(grow, "minmax"),
                                      grow_threshold, z >= z_min, spacing, grow_beyond)
        if add is not None:
            occupied = occupied | np.asarray(add, bool)
        if seal_quorum > 0:
            occupied = seal_occupancy(occupied, spacing, np.asarray(sensors) - b[:, 0],
                                      seal_quorum)
        if shrink_radius > 0:
            occupied = shrink_occupancy(occupied, spacing, shrink_radius)
        if wrap_radius > 0:
            # a solid's parts (min_component 0) stay parts when wrapped, as unwrapped
            occupied = wrap_occupancy(occupied, spacing, wrap_radius,
                                      min_fraction=0.1 if min_component > 0 else 0.0)
        vol, threshold = occupied.astype(np.float32), 0.5
    vol[:, :, z < z_min] = 0
    mesh = mesh_from_volume(vol, bounds, threshold)
    if len(mesh.faces) == 0:
        raise InputError(f"the volume has nothing above the threshold {threshold} over z >= {z_min} m")
    return largest_components(mesh, min_component)


def grow_occupancy(occupied: np.ndarray, other: np.ndarray, threshold: float,
                   allowed_z: np.ndarray | None = None, spacing=None,
                   beyond: float = 0.0, touching: bool = True) -> np.ndarray:
    """bool [nx, ny, nz]: ``occupied`` ∪ the parts of {``other`` ≥ ``threshold``} outside it
    that touch it (face-connected; ``other``: a normalised |volume| in [0, 1] on the same grid;
    restricted to the z planes ``allowed_z`` [nz]).

    With ``beyond`` > 0 (m; ``spacing`` [3] m per voxel) only structure that reaches farther
    than ``beyond`` from ``occupied`` is added: the candidate voxels farther than that, and the
    candidate voxels within geodesic distance ``beyond`` of them (through the candidates: the
    bridge to the start); the layer that only hugs the start (the backprojection's blur around
    a surface the start already has) is left out.

    With ``touching`` False the parts so selected are added whether they touch ``occupied`` or
    not (a separate object the start lacks; :func:`recon.unexplained.grown_voxels`); with no
    occupied voxel at all, every candidate then counts as far.

    The use (``recon refine --grow``): a reconstruction with a strong model (NBP) can miss a
    thin part that the data's backprojection still images (the Table-2 bunny's ear tips,
    docs/refine.md); the support stage then keeps the patches that the data supports.
    """
    from scipy import ndimage
    occupied = np.asarray(occupied, bool)
    candidate = (np.asarray(other) >= threshold) & ~occupied
    if allowed_z is not None:
        candidate &= np.asarray(allowed_z, bool)[None, None, :]
    if beyond > 0 and occupied.any():
        spacing = np.asarray(spacing, np.float64)
        far = candidate & (ndimage.distance_transform_edt(~occupied, sampling=spacing) > beyond)
        reach = far
        for _ in range(int(np.ceil(beyond / spacing.min()))):
            reach = ndimage.binary_dilation(reach) & candidate
        candidate = reach
    if not touching:
        return occupied | candidate
    labels, _ = ndimage.label(candidate)
    touching = np.unique(labels[ndimage.binary_dilation(occupied) & candidate])
    return occupied | np.isin(labels, touching[touching > 0])


def wrap_occupancy(occupied: np.ndarray, spacing, radius: float,
                   min_fraction: float = 0.1) -> np.ndarray:
    """bool [nx, ny, nz]: ``occupied`` wrapped at ``radius`` (m).

    ``occupied`` ∪ its morphological closing by a Euclidean ball of ``radius`` metres
    (``spacing`` [3] m per voxel; the array is padded so nothing is lost at the box's faces),
    then the 26-connected parts with < ``min_fraction`` × the largest's voxels dropped and the
    enclosed empty voxels filled, the grid's lowest plane counting as the ground
    (:func:`recon.solid.fill_enclosed`). Gaps narrower than about 2 × ``radius`` (tunnels
    through a porous shell, a missing face of a box) are sealed; concavities wider than that
    stay open (docs/refine.md "Wrapped starts").
    """
    from . import solid
    occupied = np.asarray(occupied, bool)
    if not occupied.any():
        return occupied.copy()
    wrapped = solid.drop_small_components(occupied | ball_closing(occupied, spacing, radius),
                                          min_fraction)
    return solid.fill_enclosed(wrapped, True)


SEAL_SENSORS = 256   # sensor directions of the hidden-voxel test (as the solvers' solid)


def seal_occupancy(occupied: np.ndarray, spacing, sensors: np.ndarray, quorum: float,
                   count: int = SEAL_SENSORS) -> np.ndarray:
    """bool [nx, ny, nz]: ``occupied`` ∪ the empty voxels it hides from at least a fraction
    ``quorum`` of ``count`` sensor directions (:func:`recon.solid.hidden_from`; ``sensors``
    [N, 3] m relative to the grid's lower corner, ``spacing`` [3] m per voxel), then what that
    encloses filled (the grid's lowest plane counting as the ground).

    The use: an NBP solid's shell holds channels and pockets whose walls the scan hardly sees
    (the Table-2 bunny's: a median 7 % of the sensors see them, against 41–48 % for its true
    surface); moving vertices cannot remove such walls, and since no echo comes from them the
    misfit does not penalise them (docs/refine.md "Sealed starts"). A concavity open toward the
    sensors is seen from about half of them and stays open for a quorum above one half.
    """
    from . import solid
    occupied = np.asarray(occupied, bool)
    if not occupied.any():
        return occupied.copy()
    hidden = solid.hidden_from(occupied, spacing, np.asarray(sensors, np.float64), count, quorum)
    return solid.fill_enclosed(occupied | hidden, True)


def shrink_occupancy(occupied: np.ndarray, spacing, radius: float) -> np.ndarray:
    """bool [nx, ny, nz]: ``occupied`` eroded by a Euclidean ball of ``radius`` (m; ``spacing``
    [3] m per voxel), the ground below the grid's lowest plane counting as occupied (an object
    standing on it keeps its base), with its thin parts kept: a part that the opening at the
    same radius removes (thinner than about 2 × ``radius``) and that reaches farther than
    2 × ``radius`` from the eroded body (the Table-2 bunny's ears; not the rim a box's edges
    leave) is added back as it was, with the occupied voxels within ``radius`` of it (its
    foot on the body). The box's faces are not treated as empty.

    The use (``recon refine --shrink``): the NBP solids are fat, their faces 5–8 mm outside the
    object (docs/refine.md "Shrunk starts"), more than the fit pulls back."""
    from scipy import ndimage
    occupied = np.asarray(occupied, bool)
    if radius <= 0 or not occupied.any():
        return occupied.copy()
    spacing = np.asarray(spacing, np.float64)
    below = int(np.ceil(radius / spacing[2])) + 1
    padded = np.concatenate([np.ones(occupied.shape[:2] + (below,), bool), occupied], axis=2)
    eroded = ndimage.distance_transform_edt(padded, sampling=spacing) > radius
    if not eroded[:, :, below:].any():
        return occupied.copy()                   # all of it thin: kept as it is
    from_body = ndimage.distance_transform_edt(~eroded, sampling=spacing)[:, :, below:]
    eroded = eroded[:, :, below:]
    thin = occupied & ~(from_body <= radius)     # what the opening removes
    labels, _ = ndimage.label(thin, structure=np.ones((3, 3, 3)))
    far = np.unique(labels[thin & (from_body > 2 * radius)])
    kept = np.isin(labels, far[far > 0])
    if kept.any():
        kept |= occupied & (ndimage.distance_transform_edt(~kept, sampling=spacing) <= radius)
    return eroded | kept


def ball_closing(occupied: np.ndarray, spacing, radius: float) -> np.ndarray:
    """bool: the morphological closing of ``occupied`` by the Euclidean ball of ``radius`` (m;
    voxel offsets d with |d · spacing| < radius), as ``scipy.ndimage.binary_closing`` with that
    ball on the array padded by the ball's half-width + 1, but by two exact Euclidean distance
    transforms (dilation: distance to the set below r; erosion: distance to the complement not
    below r),
    whose cost does not grow with the ball (binary_closing's grows with its volume: minutes for
    a 6 cm ball on the Table-2 grid)."""
    from scipy import ndimage
    spacing = np.asarray(spacing, np.float64)
    half = np.ceil(radius / spacing).astype(int)
    pad = [(h + 1, h + 1) for h in half]
    grid = np.pad(np.asarray(occupied, bool), pad)
    r = radius * (1 - 1e-9)                      # an offset at exactly the radius is left out
    dilated = ndimage.distance_transform_edt(~grid, sampling=spacing) <= r
    closed = ndimage.distance_transform_edt(dilated, sampling=spacing) > r
    return closed[tuple(slice(p[0], -p[1]) for p in pad)]


def range_resolution(pulse: np.ndarray, fs: float, sound_speed: float) -> float:
    """c / 2B (m): B (Hz) the band where the pulse's amplitude spectrum is ≥ half its peak
    (for the Table-2 'lfm-20k' chirp, 30 → 10 kHz: B ≈ 20 kHz, c / 2B ≈ 8.6 mm in air)."""
    pulse = np.asarray(pulse, np.float64)
    n = 8 * len(pulse)
    spectrum = np.abs(np.fft.rfft(pulse, n=n))
    if not spectrum.max() > 0:
        raise InputError("the dataset's pulse is zero: cannot derive a range resolution")
    freqs = np.fft.rfftfreq(n, 1.0 / float(fs))[spectrum >= 0.5 * spectrum.max()]
    bandwidth = float(freqs.max() - freqs.min())
    return float(sound_speed) / (2.0 * bandwidth)


def affine_frame(vertices: np.ndarray, edge_length: float) -> tuple[np.ndarray, float]:
    """(pivot [3] m, half extent m) of the affine stage for a start's vertices [V, 3]: the
    pivot is the centroid's x, y at the lowest z, so a scale along z keeps the base on the
    ground; the half extent (half the largest side of the bounding box, at least
    ``edge_length``) converts the log-scales to metres at the object's edge."""
    v = np.asarray(vertices, np.float64)
    pivot = np.array([v[:, 0].mean(), v[:, 1].mean(), v[:, 2].min()])
    return pivot, max(0.5 * float(np.ptp(v, axis=0).max()), float(edge_length))


def affine_vertices(vertices: np.ndarray, pivot, half: float, log_scale, shift) -> np.ndarray:
    """float64 [V, 3]: p + diag(exp(q / h))·(v − p) + (t_x, t_y, 0) for vertices v [V, 3] (m),
    pivot p [3] and half extent h (:func:`affine_frame`), q = ``log_scale`` [3] in metres at
    the half extent and (t_x, t_y) = ``shift`` [2] (m): the affine stage's map (:func:`solve`
    differentiates the same expression in Dr.Jit). No vertical shift: the object stays on
    the ground (docs/refine.md "The affine stage")."""
    v, p = np.asarray(vertices, np.float64), np.asarray(pivot, np.float64)
    t = np.append(np.asarray(shift, np.float64), 0.0)
    return p + np.exp(np.asarray(log_scale, np.float64) / half) * (v - p) + t


def _affine_ad(mi, dr, v0, pivot, half: float, log_scale, shift):
    """:func:`affine_vertices` on a flat Dr.Jit vertex buffer [V·3] with differentiable
    ``log_scale`` (Float [3]) and ``shift`` (Float [2])."""
    axis = dr.arange(mi.UInt32, dr.width(v0)) % 3
    p = dr.gather(mi.Float, mi.Float(np.asarray(pivot, np.float32)), axis)
    t = dr.select(axis < 2, dr.gather(mi.Float, shift, dr.minimum(axis, 1)), 0.0)
    return p + dr.exp(dr.gather(mi.Float, log_scale, axis) / half) * (v0 - p) + t


def smooth_vertices(vertices: np.ndarray, faces: np.ndarray, lam: float) -> np.ndarray:
    """float64 [V, 3]: implicit Laplacian smoothing, (I + ``lam`` L)⁻¹ v, with L the
    combinatorial (graph) Laplacian of the mesh's edges — the operator whose differential
    form LargeSteps optimises in, applied once to the positions. A bump of wavelength w on a
    mesh of edge h is damped by about 1 / (1 + lam · (2πh/w)²), so features a few edges wide
    fade and large ones stay; the vertex centroid is kept exactly (L's rows sum to zero), a
    convex body shrinks a little (its surface moves inward by about 3 · lam · h² · H, H the
    mean curvature: 3 · lam · h² / R for a sphere of radius R). ``lam`` = 0: a copy."""
    import trimesh
    from scipy.sparse import coo_matrix, identity
    from scipy.sparse.csgraph import laplacian
    from scipy.sparse.linalg import spsolve
    v = np.asarray(vertices, np.float64)
    if not (np.isfinite(lam) and lam >= 0):
        raise InputError(f"start smoothing: lambda must be >= 0, got {lam}")
    if lam == 0 or len(v) == 0:
        return v.copy()
    edges = trimesh.Trimesh(v, np.asarray(faces, np.int64), process=False).edges_unique
    n = len(v)
    upper = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    graph = laplacian((upper + upper.T).tocsr())
    return np.asarray(spsolve((identity(n) + lam * graph).tocsc(), v), np.float64)


def smoothed_start(mesh: trimesh.Trimesh, lam: float, edge_length: float) -> trimesh.Trimesh:
    """The start ``mesh`` remeshed to ``edge_length`` (:func:`remesh`, as :func:`solve` does)
    and smoothed by :func:`smooth_vertices` with ``lam``: roughness a few edges wide, which the
    envelopes cannot resolve (it is below the range resolution) and the fit therefore does not
    remove, is taken out before the fit (docs/refine.md "Smoothed starts")."""
    import trimesh
    v, f = remesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), edge_length)
    return trimesh.Trimesh(smooth_vertices(v, f, lam), f, process=False)


def seat_on_ground(mesh: trimesh.Trimesh, z_cut: float) -> tuple[trimesh.Trimesh, int]:
    """(mesh, moved): ``mesh`` continued straight down to the ground (z = 0): each of its
    vertices below ``z_cut`` (m) moved vertically onto the ground, ``moved`` of them.

    A volume's start is cut at ``z_min`` (:func:`start_mesh`: the ground's echo hides what is
    lower), so its refinement closes the object by a face a few millimetres above the
    ground, and the fit cannot move that face: no sensor sees it. An object in these scenes
    stands on the ground; its part below the cut is taken as the cut's cross-section
    continued down (the volume solids' convention too: their enclosed voxels are filled down
    to the grid's lowest plane). A vertex that the fit sank below the ground is lifted onto
    it. Nothing moves when the mesh's lowest vertex is above ``z_cut`` (an object the cut
    did not touch). Positions only: the faces, hence a closed mesh's closure, are kept."""
    import trimesh
    v = np.array(mesh.vertices, np.float64)
    low = v[:, 2] < float(z_cut)
    v[low, 2] = 0.0
    return trimesh.Trimesh(v, np.asarray(mesh.faces), process=False), int(low.sum())


def seat_cut(start: trimesh.Trimesh, fitted: trimesh.Trimesh, base: float) -> float | None:
    """The height (m) below which :func:`seat_on_ground` moves ``fitted``'s vertices, for a
    refinement of ``start`` whose closing face lies below ``base`` (a volume's start: the cut
    height plus one voxel): ``base`` raised by as much as the fit lifted the lowest vertex (the
    closing face moves with the walls it joins: the Table-2 bunny's by 3.5 mm); None when the
    start does not reach below ``base`` (it was not cut there: nothing to seat)."""
    start_low = float(np.min(start.vertices[:, 2]))
    if not start_low < base:
        return None
    return float(base) + max(0.0, float(np.min(fitted.vertices[:, 2])) - start_low)


def largest_components(mesh: trimesh.Trimesh, min_fraction: float) -> trimesh.Trimesh:
    """The connected components of ``mesh`` with ≥ ``min_fraction`` × the largest's faces."""
    import trimesh
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    biggest = max(len(p.faces) for p in parts)
    return trimesh.util.concatenate([p for p in parts if len(p.faces) >= min_fraction * biggest])


def split_pinched_vertices(vertices: np.ndarray, faces: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with every vertex where separate fans of faces meet ("bow-tie" vertices, e.g.
    left where faces were removed around it) duplicated once per fan, so that each vertex has
    one fan (edge-connected corners). Positions are unchanged; unused vertices are dropped."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    f = np.asarray(faces, np.int64)
    n_f = len(f)
    if n_f == 0:
        return np.asarray(vertices, np.float64)[:0], f
    # half-edges (a → b) of face i; corner (i, k) is vertex f[i, k]
    a, b, key = _half_edges(f)
    face, k = np.repeat(np.arange(n_f), 3), np.tile(np.arange(3), n_f)
    corner_a, corner_b = 3 * face + k, 3 * face + (k + 1) % 3
    # an edge {a, b} shared by two faces joins their corners at a and at b
    order = np.argsort(key, kind="stable")
    same = np.flatnonzero(key[order][1:] == key[order][:-1])
    i, j = order[same], order[same + 1]
    # corner of half-edge i at vertex a[i], and the corner of j at the same vertex
    ci_a = corner_a[i]
    cj_a = np.where(a[j] == a[i], corner_a[j], corner_b[j])
    ci_b = corner_b[i]
    cj_b = np.where(a[j] == a[i], corner_b[j], corner_a[j])
    rows, cols = np.concatenate([ci_a, ci_b]), np.concatenate([cj_a, cj_b])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_f, 3 * n_f))
    _, label = connected_components(graph, directed=False)     # labels 0..n−1: new vertex ids
    first = np.unique(label, return_index=True)[1]
    return (np.asarray(vertices, np.float64)[f.ravel()[first]],
            label.reshape(-1, 3).astype(np.int64))


def manifold(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without the faces of its non-manifold edges (edges of more than two faces:
    ``remesh_botsch`` can leave a few, and refuses them as input) and with its pinched vertices
    split (:func:`split_pinched_vertices`): an edge-manifold mesh with a few small holes."""
    f = np.asarray(faces, np.int64)
    if len(f):
        _, inverse, count = np.unique(_half_edges(f)[2], return_inverse=True, return_counts=True)
        f = f[~(count[inverse] > 2).reshape(-1, 3).any(axis=1)]
    return split_pinched_vertices(vertices, f)


def repair_slivers(vertices: np.ndarray, faces: np.ndarray, ratio: float = 1e-3
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without slivers: faces whose area is below ``ratio`` × half their longest
    edge squared. A *cap* (its third corner on or near its longest edge) is removed by
    flipping that edge with the face beyond it: the two faces become two that share the
    cap's middle corner and the far corner, covering the same ground (exactly, when the
    cap had zero area). A *needle* (a corner on another: its shortest edge below
    ``sqrt(ratio)`` × the longest), and a cap whose flip would duplicate an edge, has its
    shortest edge collapsed instead (the faces left with a repeated corner go, and so do both
    faces of a coincident pair; unused vertices are dropped).

    Why: ``remesh_botsch`` with feature edges can leave faces of (near) zero area along a
    straight crease, and on such a mesh the renderer's vertex gradient was NaN at some of their
    corners (14 of 4 107 vertices on a smoothed NBP start of the Table-2 cube; which step of
    the renderer makes it is not isolated: a lone zero-area cap on a box gives finite
    gradients); LargeSteps then spreads the NaN over the whole mesh and the next render fails
    (docs/refine.md "Slivers")."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).copy()
    for _ in range(2 * len(f)):
        e = v[f[:, [1, 2, 0]]] - v[f]                             # edges [F, 3, 3]: k → k+1
        length2 = np.einsum("fkc,fkc->fk", e, e)
        area = 0.5 * np.linalg.norm(np.cross(e[:, 0], -e[:, 2]), axis=1)
        bad = np.flatnonzero(area < ratio * 0.5 * length2.max(axis=1))
        if len(bad) == 0:
            break
        face = bad[0]
        k = int(np.argmax(length2[face]))
        a, c, b = f[face, k], f[face, (k + 1) % 3], f[face, (k + 2) % 3]
        beyond = np.flatnonzero(((f == c) & (np.roll(f, -1, axis=1) == a)).any(axis=1))
        needle = length2[face].min() < ratio * length2[face].max()
        if not needle and len(beyond) == 1:
            other = beyond[0]
            x = int(np.setdiff1d(f[other], [a, c])[0])
            edge_bx = (((f == b) & (np.roll(f, -1, axis=1) == x))
                       | ((f == x) & (np.roll(f, -1, axis=1) == b))).any()
            if not edge_bx:
                f[face], f[other] = (a, x, b), (x, c, b)
                continue
        k = int(np.argmin(length2[face]))
        keep, gone = f[face, k], f[face, (k + 1) % 3]
        f[f == gone] = keep
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        _, inverse, count = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True,
                                      return_counts=True)
        f = f[count[inverse.ravel()] == 1]          # a pair of coincident faces: a flat fin
    used, f = np.unique(f.ravel(), return_inverse=True)
    return v[used], f.reshape(-1, 3)


def _half_edges(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, key) [3F] of faces [F, 3]: half-edge k of face i runs a → b = f[i, k] →
    f[i, (k+1) % 3]; ``key`` is the same for both half-edges of an undirected edge."""
    a, b = f.ravel(), np.roll(f, -1, axis=1).ravel()
    return a, b, np.minimum(a, b) * (int(f.max()) + 1) + np.maximum(a, b)


CREASE_ANGLE = 40.0     # degrees between adjacent faces' normals: a crease remeshing keeps
# Above this crease density (crease_density) a mesh's "creases" are the voxel steps of an
# iso-surface, not a model's edges: measured 0–0.22 on the GT meshes of eleven scenes, 0.64
# on a backprojection's and 1.36–1.83 on NBP solids' marching-cubes surfaces (8 mm edges;
# docs/refine.md "Creases").
CREASE_DENSITY_MAX = 0.4


def crease_density(vertices: np.ndarray, faces: np.ndarray, edge_length: float) -> float:
    """The length of the mesh's creases (edges whose faces' normals turn by more than
    :data:`CREASE_ANGLE`) × ``edge_length`` / its area: about the fraction of the surface
    within one edge of a crease (0 for a smooth mesh)."""
    import trimesh
    m = trimesh.Trimesh(vertices, faces, process=False)
    if m.area <= 0 or len(m.face_adjacency) == 0:
        return 0.0
    edges = m.face_adjacency_edges[np.degrees(m.face_adjacency_angles) > CREASE_ANGLE]
    length = np.linalg.norm(m.vertices[edges[:, 0]] - m.vertices[edges[:, 1]], axis=1).sum()
    return float(length * edge_length / m.area)


def remesh(vertices: np.ndarray, faces: np.ndarray, edge_length: float,
           keep_creases: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing to ``edge_length`` (gpytoolbox.remesh_botsch, 5 iterations) of
    the :func:`manifold` part of the mesh (remesh_botsch refuses non-manifold input, and its
    own output, from which later stages start, may have a few non-manifold edges).

    keep_creases: keep the edges where the faces' normals turn by more than
    :data:`CREASE_ANGLE` sharp (remesh_botsch's feature edges: split along the crease, never
    flipped). Without it the remeshing cuts every sharp edge by up to half an edge length; on
    a box the bevels change the echoes more than millimetres of face position do
    (docs/refine.md "Creases"). For a given mesh (``recon refine --init MESH``), not for the
    iso-surface of a volume, whose voxel steps would count as creases: a mesh whose
    :func:`crease_density` exceeds :data:`CREASE_DENSITY_MAX` (an exported iso-surface) is
    remeshed without them."""
    from gpytoolbox import remesh_botsch
    if keep_creases:      # welded, so that a face's neighbours across a crease are known
        import trimesh
        welded = trimesh.Trimesh(vertices, faces, process=True)
        vertices, faces = welded.vertices, welded.faces
        keep_creases = crease_density(vertices, faces, edge_length) <= CREASE_DENSITY_MAX
    vertices, faces = manifold(vertices, faces)
    if len(faces) == 0:
        raise InputError("cannot remesh the surface: no face is left on a manifold part")
    try:
        v, f = remesh_botsch(np.asarray(vertices, np.float64), np.asarray(faces, np.int32),
                             i=5, h=float(edge_length), project=True,
                             detect_feature_edges=bool(keep_creases),
                             feature_dihedral_threshold=CREASE_ANGLE)
    except ValueError as exc:
        raise InputError(f"cannot remesh the surface ({exc}): it has edges shared by more "
                         "than two faces") from None
    return manifold(*repair_slivers(np.asarray(v, np.float64), np.asarray(f, np.int64)))


def _triangles_and_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(corner positions [F, 3, 3], areas [F]) of a mesh's triangles (m, m²)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    return tri, 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def patch_labels(vertices: np.ndarray, faces: np.ndarray, patch_size: float, seed: int = 0,
                 max_patches: int = 400) -> np.ndarray:
    """Patch index per face [F]: k-means (scipy) of the face centroids into about
    area / patch_size² patches (at most ``max_patches``), numbered 0..K−1 without gaps."""
    from scipy.cluster.vq import kmeans2
    tri, area = _triangles_and_areas(vertices, faces)
    area = area.sum()
    k = int(np.clip(round(area / patch_size ** 2), 1, min(max_patches, len(faces))))
    if k == 1:
        return np.zeros(len(faces), np.int64)
    _, labels = kmeans2(tri.mean(axis=1), k, seed=seed, minit="++")
    return np.unique(labels, return_inverse=True)[1].astype(np.int64)


def supported_faces(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    albedo: np.ndarray, keep: float) -> np.ndarray:
    """Mask [F] of the faces whose patch albedo is ≥ ``keep`` × the area-weighted median of
    the patch albedos (the support stage's verdict)."""
    _, area = _triangles_and_areas(vertices, faces)
    patch_area = np.bincount(labels, weights=area, minlength=len(albedo))
    order = np.argsort(albedo)
    cum = np.cumsum(patch_area[order])
    median = albedo[order][np.searchsorted(cum, 0.5 * cum[-1])]
    return albedo[labels] >= keep * median


def _patch_centres(vertices, faces, labels, n_patches) -> np.ndarray:
    """Area-weighted centre [K, 3] (m) of each patch."""
    tri, area = _triangles_and_areas(vertices, faces)
    w = np.bincount(labels, weights=area, minlength=n_patches)
    return np.stack([np.bincount(labels, weights=area * tri.mean(axis=1)[:, a], minlength=n_patches)
                     for a in range(3)], axis=1) / np.maximum(w, 1e-30)[:, None]


def drop_faces(vertices: np.ndarray, faces: np.ndarray, mask: np.ndarray,
               min_component: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """The faces ``mask`` keeps, without unused vertices, and without the connected
    components smaller than ``min_component`` × the largest (faces); made :func:`manifold`
    (removing patches leaves bow-tie vertices where two kept patches touch at a corner, which
    Mitsuba warns about and which would couple two sheets in LargeSteps' Laplacian)."""
    import trimesh
    kept = trimesh.Trimesh(vertices, np.asarray(faces)[mask], process=False)
    kept.remove_unreferenced_vertices()
    kept = largest_components(kept, min_component)
    return manifold(kept.vertices, kept.faces)


# ------------------------------------------------------------------------ the model

def dataset_chain(dataset, settings: RefineSettings) -> tuple[int, tuple[float, float, int],
                                                                PulseChain]:
    """(K, window, chain): the histogram bins per sample (``settings.oversample``, else the
    dataset's, else 20), the :func:`dataset_window` at K and the dataset's pulse chain from
    histograms of that window to its waveforms."""
    k = int(dataset.meta.get("oversample", 20) if settings.oversample is None
            else settings.oversample)
    window = dataset_window(dataset, k)
    return k, window, PulseChain(dataset.pulse, k, dataset.n_samples, window[2])


def dataset_window(dataset, oversample: int) -> tuple[float, float, int]:
    """(start, width, bins) of histograms aligned to a dataset's samples: round-trip path
    (m) of bin 0's lower edge, bin width c/(fs·K), T·K bins; bin j·K is centred on the path
    of sample j (as ``sonarsim simulate``)."""
    c = float(dataset.sound_speed)
    width = c / (float(dataset.fs) * oversample)
    return (dataset.start_sample * c / dataset.fs - width / 2, width,
            dataset.n_samples * oversample)


def dataset_ground(dataset) -> tuple[float, float, float] | None:
    """(size_x, size_y, albedo) of the ground a simulated dataset was rendered with: its
    scene file when it is at hand, else the simulator's default; None for a scene without."""
    from pathlib import Path
    source = dataset.meta.get("scene_source")
    if source and Path(str(source)).is_file():
        import warnings
        from sonarsim.scene import load_scene
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            spec = load_scene(str(source))
        if spec.ground is None:
            return None
        return (float(spec.ground.size[0]), float(spec.ground.size[1]), float(spec.ground.albedo))
    return DEFAULT_GROUND


def _diffuse(mi, albedo: float):
    """A two-sided diffuse BSDF, instantiated on its own: ``mi.load_dict`` shares identical
    plugin instances, so the object and the ground would otherwise share one albedo."""
    return mi.load_dict({"type": "twosided", "material": {
        "type": "diffuse", "reflectance": {"type": "rgb", "value": float(albedo)}}})


class RenderedScene:
    """The mesh, the ground and the sonar as one Mitsuba scene for ``mi.render``.

    ``mesh``: trimesh (m); ``dataset``: its pings and beams; ``window``: (start, width, bins).
    ``labels``: optional patch index per face [F] (0..K−1): each patch becomes its own shape
    with its own albedo (the support stage); the patches share one vertex buffer.
    :meth:`render` returns the histograms [n, bounces, bins] of a batch of pings as a
    Dr.Jit tensor that carries the gradients of the vertex buffer and the albedo(s).
    """

    def __init__(self, mesh: trimesh.Trimesh, dataset, window, ground, settings: RefineSettings,
                 workdir, labels: np.ndarray | None = None):
        from pathlib import Path

        import trimesh
        from sonarsim import runtime
        self.mi = mi = runtime.mitsuba()
        import drjit as dr
        self.dr = dr
        beams = {k: v for k, v in dict(dataset.meta.get("beams") or {}).items()
                 if k in ("tx_beam", "tx_beamwidth", "rx_beam", "rx_beamwidth")}
        v = np.asarray(mesh.vertices, np.float64)
        f = np.asarray(mesh.faces, np.int64)
        labels = np.zeros(len(f), np.int64) if labels is None else np.asarray(labels, np.int64)
        self.n_patches = int(labels.max()) + 1 if len(labels) else 1
        self._v0, self._f0 = v, f
        start, width, bins = window
        items = {"type": "scene",
                 "integrator": {"type": "sonar_transient", "max_bounces": settings.bounces,
                                "surface_spacing": settings.surface_spacing,
                                "path_samples": settings.path_samples, **beams},
                 "sensor": {"type": "sonar", "tx_origin": [0.0, 0.0, 1.0],
                            "tx_boresight": [0.0, 0.0, -1.0],
                            "film": {"type": "sonar_film", "temporal_bins": int(bins),
                                     "start_opl": float(start), "bin_width_opl": float(width)}}}
        patches = []
        for p in range(self.n_patches):
            fp = f[labels == p]
            if len(fp) == 0:
                continue
            used, local = np.unique(fp.ravel(), return_inverse=True)
            path = Path(workdir) / f"patch{p}_{len(fp)}_{id(mesh)}.ply"
            trimesh.Trimesh(v[used], local.reshape(-1, 3), process=False).export(path)
            items[f"target{p}"] = {"type": "ply", "filename": str(path), "bsdf": _diffuse(mi, 1.0)}
            patches.append((p, mi.UInt32((3 * used[:, None] + np.arange(3)).ravel().astype(np.uint32))))
        if ground is not None:
            items["ground"] = {"type": "rectangle", "bsdf": _diffuse(mi, ground[2]),
                               "to_world": mi.ScalarTransform4f().scale(
                                   [ground[0] / 2, ground[1] / 2, 1.0])}
        self.scene = mi.load_dict(items)
        self.params = mi.traverse(self.scene)
        keys = list(self.params.keys())
        self._patches = [(p, f"target{p}.vertex_positions", idx,
                          next(k for k in keys if k.startswith(f"target{p}.bsdf")
                               and k.endswith("reflectance.value"))) for p, idx in patches]
        # every ping's four vectors, float32 once (the renderer's precision); render() slices them
        self._poses = [np.asarray(a, dtype=np.float32) for a in
                       (dataset.tx, dataset.boresight, dataset.rx, dataset.receiver_boresight)]
        from sonarsim.plugins import sonar   # after the variant is set (runtime.mitsuba())
        self._set_poses = sonar.set_poses

    @property
    def vertices(self):
        """The shared vertex buffer (Dr.Jit Float [V·3], m) and faces (UInt32 [F·3])."""
        mi = self.mi
        return (mi.Float(self._v0.ravel().astype(np.float32)),
                mi.UInt32(self._f0.ravel().astype(np.uint32)))

    def render(self, vertices, albedo, index: np.ndarray, seed: int):
        """Histograms [n, bounces, bins] (TensorXf, differentiable) of pings ``index``;
        ``albedo``: Float of width 1 (all patches) or K (one per patch)."""
        mi, dr = self.mi, self.dr
        p = self.params
        self._set_poses(p, *(a[index] for a in self._poses))
        per_patch = dr.width(albedo) > 1
        for patch, key_v, idx, key_albedo in self._patches:
            p[key_v] = dr.gather(mi.Float, vertices, idx)
            p[key_albedo] = dr.gather(mi.Float, albedo, mi.UInt32(patch)) if per_patch else albedo
        p.update()
        out = mi.render(self.scene, p, seed=seed, seed_grad=seed + 0x5EED)
        return out if len(index) > 1 else out[None]


class _Objective:
    """Loss and its gradient with respect to the histograms, per batch of pings."""

    def __init__(self, dataset, chain: PulseChain):
        if dataset.waveform_kind != "real":
            raise InputError("recon refine fits the received waveforms; this dataset holds "
                             f"{dataset.waveform_kind!r} signals (use the dataset before "
                             "`recon deconvolve`)")
        self.chain = chain
        self.data = dataset.waveforms          # float32 [N, T]; batches are converted as used
        self.envelope = Envelope(dataset.pulse, dataset.n_samples)
        self._data_env: dict = {}

    def __call__(self, stage: str, hist: np.ndarray, batch: int, index: np.ndarray,
                 sigma: float = 0.0):
        """(loss, α, ∂loss/∂hist [n, bins]) of histograms [n, bins] (bounces summed);
        sigma: the envelopes' smoothing (samples, :func:`recon.pulse_chain.blur`)."""
        model = self.chain.forward(hist)
        y = np.asarray(self.data[index], np.float64)
        if stage == "waveform":
            loss, alpha, grad = scaled_misfit(model, y)
        else:
            if batch not in self._data_env:
                self._data_env[batch] = self.envelope(y)[0]
            loss, alpha, grad = envelope_misfit(model, self._data_env[batch], self.envelope, sigma)
        return loss, alpha, self.chain.adjoint(grad)


# ------------------------------------------------------------------------ the solver

def finite_gradient(mi, grad) -> tuple:
    """(``grad`` (a Dr.Jit Float) with its non-finite entries set to 0, their count)."""
    g = np.asarray(grad.numpy(), np.float32).ravel()
    bad = ~np.isfinite(g)
    if not bad.any():
        return grad, 0
    g[bad] = 0.0
    return mi.Float(g), int(bad.sum())


def _cosine_rate(lr: float, frac: float) -> float:
    """The step of a stage at ``frac`` ∈ [0, 1] of its steps: ``lr`` decaying to ``lr``/10
    along a half cosine."""
    return lr * (0.1 + 0.45 * (1 + np.cos(np.pi * frac)))


def _fit_affine(model, vertices, log_albedo, settings, fit_albedo, misfit_and_backward,
                history, bar, t0):
    """The affine stage: ``settings.affine_steps`` Adam steps on the five parameters of
    :func:`affine_vertices` (and the log-albedo) against the envelopes. Returns (vertices
    [V, 3], log-albedo, the fit {'pivot', 'half', 'log_scale', 'scale', 'shift'}); one
    record per step is appended to ``history``."""
    mi, dr = model.mi, model.dr
    pivot, half = affine_frame(vertices, settings.edge_length)
    v0 = model.vertices[0]
    opt = mi.ad.Adam(lr=settings.lr)
    opt["log_scale"] = mi.Float(np.zeros(3, np.float32))
    opt["shift"] = mi.Float(np.zeros(2, np.float32))
    opt_rho = mi.ad.Adam(lr=0.02)
    opt_rho["log_albedo"] = mi.Float(log_albedo)
    n = settings.affine_steps
    for j in range(n):
        opt.set_learning_rate(_cosine_rate(settings.lr, j / max(1, n - 1)))
        loss, alpha = misfit_and_backward(
            model, _affine_ad(mi, dr, v0, pivot, half, opt["log_scale"], opt["shift"]),
            dr.exp(opt_rho["log_albedo"]), "envelope")
        opt.step()
        if fit_albedo:
            opt_rho.step()
        history.append({"step": len(history), "stage": "affine", "loss": loss, "alpha": alpha,
                        "albedo": float(dr.exp(opt_rho["log_albedo"])[0]),
                        "seconds": time.perf_counter() - t0})
        bar.update(1)
    q = np.asarray(opt["log_scale"].numpy(), np.float64)
    t = np.asarray(opt["shift"].numpy(), np.float64)
    fit = {"pivot": pivot.tolist(), "half": half, "log_scale": q.tolist(),
           "scale": np.exp(q / half).tolist(), "shift": t.tolist()}
    return affine_vertices(vertices, pivot, half, q, t), float(opt_rho["log_albedo"][0]), fit


def solve(dataset, init: trimesh.Trimesh, settings: RefineSettings = RefineSettings(), *,
          ping_index: np.ndarray | None = None, ground="dataset", progress: bool = False,
          log=None, keep_creases: bool = False) -> RefineResult:
    """Refine ``init`` (a trimesh, metres) against ``dataset`` (real waveforms).

    ping_index: the pings to fit (default all); ground: 'dataset' (:func:`dataset_ground`),
    None (no ground), or (size_x, size_y, albedo). log: callable(str), one line per
    remeshing segment. keep_creases: the remeshings keep ``init``'s sharp edges
    (:func:`remesh`; for a given mesh, not a volume's iso-surface).
    """
    import tempfile

    import trimesh
    from sonarsim import runtime
    from sonarsim.progress import progress_bar
    mi = runtime.mitsuba()
    import drjit as dr

    settings.validate()
    index = np.arange(dataset.n_pings) if ping_index is None else np.asarray(ping_index)
    if len(index) == 0:
        raise InputError("no pings to fit")
    ground = dataset_ground(dataset) if ground == "dataset" else ground
    k, window, chain = dataset_chain(dataset, settings)
    objective = _Objective(dataset, chain)
    vertices, faces = remesh(init.vertices, init.faces, settings.edge_length, keep_creases)

    n_batches = max(1, int(np.ceil(len(index) / settings.pings_per_batch)))
    rng = np.random.default_rng(settings.seed)
    batches = [index[b::n_batches] for b in range(n_batches)]
    fit_albedo = settings.fit_albedo and ground is not None
    log_albedo = 0.0
    plan = [(s, n) for s, n in zip(STAGES, (settings.envelope_steps, settings.waveform_steps)) if n]
    history, order = [], np.arange(n_batches)
    bar = progress_bar(settings.support_steps + settings.affine_steps + sum(n for _, n in plan),
                       progress, unit="step", desc="refine")
    t0 = time.perf_counter()
    support = affine = None

    samples_per_metre = 2.0 * float(dataset.fs) / float(dataset.sound_speed)   # one-way range

    nonfinite = {"steps": 0, "entries": 0}

    def recent_loss(n_steps: int) -> float:
        """Mean loss of the last ``n_steps`` steps, at most two passes over the batches (logs)."""
        return float(np.mean([h["loss"] for h in history[-min(n_steps, 2 * n_batches):]]))

    def misfit_and_backward(model, vertices_ad, albedo_ad, stage, sigma=0.0):
        """One step's misfit (loss, alpha) of the next batch (a new batch order per pass over
        the batches) and its gradient propagated to ``vertices_ad`` and ``albedo_ad``."""
        nonlocal order
        step = len(history)
        if step % n_batches == 0:
            order = rng.permutation(n_batches)
        b = int(order[step % n_batches])
        # The renderer's gradient is taken with respect to detached copies, cleared of
        # non-finite entries (a degenerate triangle's corners, docs/refine.md "Non-finite
        # gradients"), then carried on to the parameters: LargeSteps' solve would otherwise
        # spread one NaN over its whole component, and Adam keep it in its moments.
        v_leaf, a_leaf = dr.detach(vertices_ad), dr.detach(albedo_ad)
        dr.enable_grad(v_leaf, a_leaf)
        hist = model.render(v_leaf, a_leaf, batches[b], settings.seed * 100_003 + 2 * step)
        h = hist.numpy().astype(np.float64).sum(axis=1)
        loss, alpha, grad = objective(stage, h, b, batches[b], sigma)
        g = np.repeat(grad[:, None, :], hist.shape[1], axis=1).astype(np.float32)
        dr.backward(dr.sum(hist * mi.TensorXf(g), axis=None))
        carried, bad = None, 0
        for leaf, param in ((v_leaf, vertices_ad), (a_leaf, albedo_ad)):
            g_leaf, n_bad = finite_gradient(mi, dr.grad(leaf))
            bad += n_bad
            if dr.grad_enabled(param):
                term = dr.sum(param * g_leaf, axis=None)
                carried = term if carried is None else carried + term
        if carried is not None:
            dr.backward(carried)
        if bad:
            nonfinite["steps"] += 1
            nonfinite["entries"] += bad
            if log is not None and nonfinite["steps"] == 1:
                log(f"{stage} step {step}: {bad} non-finite gradient entries set to 0 "
                    "(degenerate triangles)")
        return loss, alpha

    with tempfile.TemporaryDirectory(prefix="refine-") as workdir:
        try:
            if settings.support_steps:
                labels = patch_labels(vertices, faces, settings.patch_size, settings.seed)
                model = RenderedScene(trimesh.Trimesh(vertices, faces, process=False), dataset,
                                      window, ground, settings, workdir, labels)
                opt_rho = mi.ad.Adam(lr=settings.support_lr)
                opt_rho["log_albedo"] = mi.Float(np.zeros(model.n_patches, np.float32))
                v_fixed = model.vertices[0]
                for j in range(settings.support_steps):
                    loss, alpha = misfit_and_backward(model, v_fixed, dr.exp(opt_rho["log_albedo"]),
                                                      "envelope")
                    opt_rho.step()
                    history.append({"step": len(history), "stage": "support", "loss": loss,
                                    "alpha": alpha, "albedo": None,
                                    "seconds": time.perf_counter() - t0})
                    bar.update(1)
                patch_albedo = np.exp(np.asarray(opt_rho["log_albedo"].numpy(), np.float64))
                keep = supported_faces(vertices, faces, labels, patch_albedo, settings.support_keep)
                if not keep.any():
                    raise InputError("the support stage found no patch the data supports")
                n_before = len(faces)
                model_vertices, model_faces = vertices, faces
                vertices, faces = drop_faces(vertices, faces, keep)
                support = {"patches": int(model.n_patches),
                           "patches_kept": int(len(np.unique(labels[keep]))),
                           "faces_before": int(n_before), "faces_after": int(len(faces)),
                           "patch_albedo": patch_albedo.round(4).tolist(),
                           "patch_centres": [np.round(c, 4).tolist() for c in _patch_centres(
                               model_vertices, model_faces, labels, model.n_patches)]}
                del model
                if log is not None:
                    log(f"support steps {settings.support_steps}: loss "
                        f"{recent_loss(settings.support_steps):.4f}, kept "
                        f"{support['patches_kept']}/{support['patches']} patches, "
                        f"{len(faces)}/{n_before} faces, {time.perf_counter() - t0:.0f} s")
            if settings.affine_steps:
                vertices, log_albedo, affine = _fit_affine(
                    RenderedScene(trimesh.Trimesh(vertices, faces, process=False), dataset,
                                  window, ground, settings, workdir),
                    vertices, log_albedo, settings, fit_albedo, misfit_and_backward, history,
                    bar, t0)
                if log is not None:
                    log(f"affine steps {settings.affine_steps}: loss "
                        f"{recent_loss(settings.affine_steps):.4f}, scale "
                        f"{np.round(affine['scale'], 4).tolist()}, shift "
                        f"{np.round(affine['shift'], 4).tolist()} m, {time.perf_counter() - t0:.0f} s")
            for stage, n_steps in plan:
                done = 0
                while done < n_steps:
                    seg = n_steps - done if not settings.remesh_every else min(
                        settings.remesh_every, n_steps - done)
                    if history and history[-1]["stage"] not in ("support", "affine"):
                        vertices, faces = remesh(vertices, faces, settings.edge_length,
                                                 keep_creases)
                    model = RenderedScene(trimesh.Trimesh(vertices, faces, process=False), dataset,
                                          window, ground, settings, workdir)
                    v0, f0 = model.vertices
                    ls = mi.ad.LargeSteps(v0, f0, settings.large_steps_lambda)
                    opt = mi.ad.Adam(lr=settings.lr, uniform=settings.uniform_adam)
                    opt["u"] = ls.to_differential(v0)
                    opt_rho = mi.ad.Adam(lr=0.02)
                    opt_rho["log_albedo"] = mi.Float(log_albedo)
                    for j in range(seg):
                        frac = (done + j) / max(1, n_steps - 1)
                        opt.set_learning_rate(_cosine_rate(settings.lr, frac))
                        blur_m = settings.envelope_blur * (1 - frac) if stage == "envelope" else 0.0
                        loss, alpha = misfit_and_backward(model, ls.from_differential(opt["u"]),
                                                          dr.exp(opt_rho["log_albedo"]), stage,
                                                          blur_m * samples_per_metre)
                        opt.step()
                        if fit_albedo:
                            opt_rho.step()
                        history.append({"step": len(history), "stage": stage, "loss": loss,
                                        "alpha": alpha, "blur_m": blur_m,
                                        "albedo": float(dr.exp(opt_rho["log_albedo"])[0]),
                                        "seconds": time.perf_counter() - t0})
                        bar.update(1)
                    vertices = np.asarray(ls.from_differential(opt["u"]).numpy(),
                                          np.float64).reshape(-1, 3)
                    faces = np.asarray(f0.numpy(), np.int64).reshape(-1, 3)
                    log_albedo = float(opt_rho["log_albedo"][0])
                    done += seg
                    if log is not None:
                        log(f"{stage} steps {done}/{n_steps}: loss {recent_loss(seg):.4f}, "
                            f"{len(faces)} faces, {time.perf_counter() - t0:.0f} s")
        finally:
            bar.close()
    if not (np.isfinite(vertices).all() and np.isfinite(log_albedo)):
        raise InputError("the fit diverged: its vertices or albedo are not finite")
    return RefineResult(vertices, faces, float(np.exp(log_albedo)) if fit_albedo else None,
                        history, {**asdict(settings), "pings": int(len(index)),
                                  "batches": int(n_batches), "nonfinite_gradients": nonfinite,
                                  "ground": ground, "oversample": k, "support": support},
                        affine)
