"""Solid extraction: from a reconstructed scattering field to a solid occupancy.

Sonar sees surfaces, and a field fitted to sonar data (NBP, GD) is bright on the surfaces it
saw and dark elsewhere, with a few isolated bright specks (floaters) where noise or sidelobes
were fitted. The evaluation of Reed et al. 2023 (IoU against the GT's *volume* samples,
Chamfer of the thresholded occupancy's surface; docs/evaluation.md) rewards a solid
occupancy whose boundary is the surface. :func:`solidify` makes one from the field alone
(no knowledge of the scene), in documented steps applied identically to every scene:

1. **threshold**: occupied = m > ``threshold`` with m = |σ| / max|σ| (the evaluation's
   min–max τ). Two options, both scale-free: ``blur`` > 0 smooths |σ| first with a Gaussian of
   that many voxels (σ of the kernel; m is then the smoothed magnitude over its maximum), and
   ``threshold_mode="otsu"`` reads ``threshold`` as a factor on the Otsu level of m (Otsu's
   two-class split, ``skimage.filters.threshold_otsu``, of the voxels with m > 0.02), so the
   cut follows the field's own background/surface split instead of a fixed fraction of its
   brightest voxel (:func:`threshold_level`);
2. **drop floaters**: keep the 26-connected components holding at least ``min_fraction`` of
   the largest one's voxels, and (with ``part_volume`` > 0, m³) every component of at least
   that volume whose top reaches ``part_height`` (m) above the box's lowest plane: a
   separate object far smaller than the largest one (a rod beside a box, a bunny's ear tip cut
   off by the threshold) is not a floater. Floaters are blobs of a few resolution cells, and
   the large ones lie on the ground, where its echo leaves them (measured on 36 full-size NBP
   and GD fields of six scenes: no floater of 1.5 cm³ rose above 3.5 cm;
   docs/reconstruction.md "Small separate objects");
3. **close gaps**: a morphological closing by ``close`` voxels (a 6-connected ball), so a shell
   with pin-holes becomes watertight; only voxels are added, never removed;
4. **fill enclosed interiors**: voxels that no 6-connected path of empty voxels joins to the
   box's boundary become occupied (``scipy.ndimage.binary_fill_holes``). With ``floor=True``
   the grid's lowest z plane counts as closed (the rig's ground, on which scanned objects
   stand), so a shell open only at its base is filled down to the ground.
5. **fill what no sensor saw** (with ``sensors`` and ``hidden`` > 0): an empty voxel from which
   the straight line toward each of ``hidden`` sensor positions (spread over the scan) meets
   an occupied voxel is hidden from the whole scan; the data say nothing about it, and for an
   object it is interior (a cavity reached only through a narrow or oblique opening, a base
   under an overhang). Such voxels become occupied, then step 4 runs again
   (:func:`hidden_from`). With ``quorum`` q < 1, hidden from at least a fraction q of the
   sensors is enough: a cavity glimpsed only through the pores of a porous shell by a few
   sensors is filled too.
6. **fill open cavities without a floor** (with ``cavity_floor`` > 0, metres): an *open
   cavity* is a connected set of empty voxels that the solid encloses within their
   horizontal slice (a box without its top, a cup): open upward. Its floor voxels are the
   cavity voxels resting on an occupied one. A floor voxel is *supported* when a voxel of the
   thresholded field (steps 1–3, the data) or, with ``floor``, the ground lies within
   ``cavity_floor`` below it. A cavity with fewer than half of its floor voxels supported is
   filled (:func:`floorless_cavities`): its floor is the level down to which step 5 filled,
   not a surface the scan saw, so the field holds no evidence of an opening there; a real
   container shows its floor. Made for the cube, whose top face the field barely holds
   (docs/reconstruction.md "Open cavities without a floor").
7. **smooth the boundary** (with ``smooth`` > 0, voxels): the solid's indicator (1 inside, 0
   outside) is smoothed by a Gaussian of ``smooth`` voxels and cut again at one half. Bumps,
   dents and stair steps narrower than the kernel go, flat faces become flat, the volume of
   a body much thicker than the kernel barely changes (a convex edge is rounded to a radius
   of about ``smooth`` voxels). Outside the box the solid continues as its outermost plane
   (so the base of an object on the ground is not eaten away). Thin parts of a body go: at
   ``smooth`` = 2 a wall 4 voxels thick stays, one 2 voxels thick (or a rod 5 voxels across)
   vanishes; a separate part of which nothing would remain (a small object, a point target)
   is kept as it was (:func:`smooth_boundary`; docs/reconstruction.md "Smoothed solid
   boundary").

What it does to other objects: an open object (a bowl open upward, an arch, a tube open at an
end) keeps its opening, because its inside is joined to the boundary through it, and is not
filled; a thin plate or a single surface stays what it is (it encloses nothing); an object
whose *base* is open and stands on the ground (a dome, a cup upside down) is filled, as
``floor=True`` says it is closed by the ground; an object smaller than ``min_fraction`` of the
largest one in the box is dropped with the floaters unless it passes step 2's ``part_volume``
and ``part_height`` (an object lying flat on the ground, under ``part_height``, does not).
With step 5 and ``quorum`` q < 1, an opening seen by fewer than a fraction 1 − q of the
sensors is closed too (the lower hole of a torus lying on the ground, for the Table-2 scan
and q = 0.8). Tests: tests/test_solid.py.
"""
from __future__ import annotations

import numpy as np

from sonarsim.errors import InputError

DEFAULTS = dict(threshold=0.2, min_fraction=0.1, close=1, floor=True, hidden=0, quorum=1.0,
                cavity_floor=0.0, blur=0.0, threshold_mode="peak", smooth=0.0,
                part_volume=0.0, part_height=0.0)
THRESHOLD_MODES = ("peak", "otsu")
# The Otsu level is taken over the voxels above this fraction of the peak: the empty box
# (most of the grid, |σ| ≈ 0) would otherwise be one of the two classes.
OTSU_FLOOR = 0.02


def _ndimage():
    """scipy.ndimage, imported on first use (every ``recon`` command imports this module
    while its parser is built; the import costs ~0.1 CPU-s)."""
    from scipy import ndimage
    return ndimage


def occupancy(volume: np.ndarray, threshold: float) -> np.ndarray:
    """bool [nx, ny, nz]: |volume| / max|volume| > ``threshold`` (all False if the volume is 0)."""
    mag = np.abs(np.asarray(volume))
    peak = float(mag.max()) if mag.size else 0.0
    if not peak > 0:
        return np.zeros(mag.shape, dtype=bool)
    return mag > threshold * peak


def thresholded(volume: np.ndarray, threshold: float, blur: float = 0.0,
                mode: str = "peak") -> np.ndarray:
    """bool [nx, ny, nz]: step 1, the relative magnitude (:func:`relative_magnitude`) above
    its cut (:func:`threshold_level`)."""
    return step_one(volume, threshold, blur, mode)[0]


def step_one(volume: np.ndarray, threshold: float, blur: float = 0.0,
             mode: str = "peak") -> tuple[np.ndarray, float]:
    """(step 1's bool [nx, ny, nz], its cut as a fraction of the (smoothed) peak)."""
    if not blur > 0 and mode == "peak":
        return occupancy(volume, threshold), float(threshold)   # the plain rule, bit for bit
    relative = relative_magnitude(volume, blur)
    level = threshold_level(relative, threshold, mode)
    return relative > level, level


def relative_magnitude(volume: np.ndarray, blur: float = 0.0) -> np.ndarray:
    """float32 [nx, ny, nz]: |volume| (smoothed by a Gaussian of ``blur`` voxels when > 0)
    over its maximum; all 0 for a zero volume."""
    mag = np.abs(np.asarray(volume)).astype(np.float32)
    if blur > 0:
        mag = _ndimage().gaussian_filter(mag, float(blur))   # mirrored at the box faces
    peak = float(mag.max()) if mag.size else 0.0
    return mag / peak if peak > 0 else np.zeros_like(mag)


def threshold_level(relative: np.ndarray, threshold: float, mode: str = "peak") -> float:
    """The cut on the relative magnitude ``relative`` (max 1) of step 1: ``threshold`` itself
    (mode 'peak'), or ``threshold`` × the Otsu level of the voxels above
    :data:`OTSU_FLOOR` (mode 'otsu'; 1.0, i.e. nothing occupied, when fewer than two
    distinct values lie above the floor)."""
    if mode == "peak":
        return float(threshold)
    from skimage.filters import threshold_otsu
    values = relative[relative > OTSU_FLOOR]
    if values.size < 2 or float(values.min()) == float(values.max()):
        return 1.0
    return float(threshold) * float(threshold_otsu(values))


def parts(occupied: np.ndarray) -> tuple[np.ndarray, int]:
    """(int labels like ``occupied``, count): its 26-connected parts, numbered from 1 (the
    connectivity every step of this module means by a part)."""
    return _ndimage().label(occupied, structure=np.ones((3, 3, 3), dtype=bool))


def drop_small_components(occupied: np.ndarray, min_fraction: float, min_voxels: int = 0,
                          min_top: int = 0) -> np.ndarray:
    """Keep the 26-connected components of at least ``min_fraction`` × the largest's size,
    and (``min_voxels`` > 0) those of at least ``min_voxels`` voxels whose highest voxel has
    a z index ≥ ``min_top``."""
    labels, n = parts(occupied)
    if n <= 1:
        return occupied.copy()
    sizes = np.bincount(labels.ravel())[1:]
    keep = sizes >= min_fraction * sizes.max()
    if min_voxels > 0:
        z = np.broadcast_to(np.arange(occupied.shape[2]), occupied.shape)
        top = np.asarray(_ndimage().maximum(z, labels, np.arange(1, n + 1)))
        keep |= (sizes >= min_voxels) & (top >= min_top)
    return np.isin(labels, np.flatnonzero(keep) + 1)


def part_rule(part_volume: float, part_height: float, spacing) -> tuple[int, int]:
    """Step 2's (min_voxels, min_top) for parts of ``part_volume`` m³ reaching ``part_height``
    m above the lowest plane, on voxels of ``spacing`` [3] m (0, 0: off, also on a grid one
    voxel thick along an axis, whose voxels have no volume)."""
    if not part_volume > 0:
        return 0, 0
    voxel = float(np.prod(spacing))
    if not voxel > 0:
        return 0, 0
    return (max(1, int(np.ceil(part_volume / voxel - 1e-9))),
            int(np.ceil(part_height / spacing[2] - 1e-9)))


def close_gaps(occupied: np.ndarray, radius: int) -> np.ndarray:
    """``occupied`` ∪ its morphological closing by a ``radius``-voxel 6-connected ball (the
    array is padded first so nothing is lost at the box's faces)."""
    if radius <= 0:
        return occupied.copy()
    pad = radius + 1
    closed = _ndimage().binary_closing(np.pad(occupied, pad), iterations=radius)
    return occupied | closed[pad:-pad, pad:-pad, pad:-pad]


def smooth_boundary(occupied: np.ndarray, sigma: float) -> np.ndarray:
    """bool like ``occupied``: step 7, the indicator smoothed by a Gaussian of ``sigma`` voxels
    and cut at 0.5 (``sigma`` = 0: a copy). Beyond the box the indicator repeats its outermost
    plane (``mode='nearest'``): an object standing on the lowest plane, or leaving the box, is
    not rounded off where the box cuts it. A 26-connected part of ``occupied`` of which nothing
    would remain is kept unchanged (a small object or a point target is not erased)."""
    occupied = np.asarray(occupied, dtype=bool)
    if not sigma > 0 or not occupied.any():
        return occupied.copy()
    smoothed = _ndimage().gaussian_filter(occupied.astype(np.float32), float(sigma),
                                          mode="nearest") > 0.5
    # a whole part the smoothing would erase (a small object, a point target) is kept as it was
    labels, count = parts(occupied)
    kept = np.bincount(labels[smoothed], minlength=count + 1)
    lost = np.flatnonzero(kept[1:] == 0) + 1
    if lost.size:
        smoothed |= np.isin(labels, lost)
    return smoothed


def fill_enclosed(occupied: np.ndarray, floor: bool) -> np.ndarray:
    """Fill every empty voxel not joined to the box's boundary by empty voxels (6-connected);
    with ``floor`` the lowest z plane is treated as closed (an occupied plane below it)."""
    if not floor:
        return _ndimage().binary_fill_holes(occupied)
    padded = np.pad(occupied, ((0, 0), (0, 0), (1, 0)), constant_values=True)
    return _ndimage().binary_fill_holes(padded)[:, :, 1:]


def sensor_directions(sensors: np.ndarray, count: int, centre: np.ndarray) -> np.ndarray:
    """float [K, 3] unit vectors from ``centre`` toward ``count`` sensor positions taken evenly
    along the scan's ping order (K = min(count, N); ``sensors`` [N, 3] in metres)."""
    sensors = np.asarray(sensors, dtype=np.float64).reshape(-1, 3)
    picks = np.unique(np.linspace(0, len(sensors) - 1, min(int(count), len(sensors))).round())
    toward = sensors[picks.astype(np.int64)] - np.asarray(centre, dtype=np.float64)
    norms = np.linalg.norm(toward, axis=1, keepdims=True)
    return toward[norms[:, 0] > 0] / norms[norms[:, 0] > 0]


def _blocked_along(sub: np.ndarray, step: np.ndarray) -> np.ndarray:
    """bool like ``sub``: voxels whose ray along ``step`` (voxels per unit step, [3]) meets a
    True voxel of ``sub`` beyond itself (one shifted OR per distinct rounded offset)."""
    shape = np.array(sub.shape)
    blocked = np.zeros_like(sub)
    last = None
    for t in range(1, int(np.ceil(np.linalg.norm(shape))) + 2):
        o = np.round(t * step).astype(np.int64)
        if np.any(np.abs(o) >= shape):
            break
        if last is not None and np.array_equal(o, last):
            continue
        last = o
        src = tuple(slice(max(o[a], 0), shape[a] + min(o[a], 0)) for a in range(3))
        dst = tuple(slice(max(-o[a], 0), shape[a] + min(-o[a], 0)) for a in range(3))
        blocked[dst] |= sub[src]
    return blocked


def hidden_from(occupied: np.ndarray, spacing, sensors: np.ndarray, count: int,
                quorum: float = 1.0) -> np.ndarray:
    """bool like ``occupied``: the empty voxels hidden from ``count`` sensor positions, i.e. the
    straight line from the voxel toward at least a fraction ``quorum`` (in (0, 1]; 1 = every
    one) of them meets an occupied voxel.

    Lines are parallel per sensor (the direction from the occupied set's centre to the sensor:
    the far-field approximation, exact for sensors far compared with the object) and stepped
    one voxel at a time with rounding; only the occupied set's bounding box (+1 voxel) can be
    hidden. spacing: [3] voxel size (m); sensors: [N, 3] positions (m) in the grid's frame,
    relative to the grid's lower corner (the caller subtracts it). Cost: ``count`` × (the box's
    diagonal in voxels) shifted ORs of the box (about 1 s for 144 sensors and a 60³ box).
    """
    occupied = np.asarray(occupied, dtype=bool)
    out = np.zeros_like(occupied)
    if not occupied.any() or count <= 0:
        return out
    spacing = np.asarray(spacing, dtype=np.float64)
    if not np.any(spacing > 0):
        return out
    # an axis one voxel thick (a 2-D grid) has zero spacing: any step along it leaves the box
    spacing = np.where(spacing > 0, spacing, spacing[spacing > 0].min())
    idx = np.argwhere(occupied)
    lo = np.maximum(idx.min(0) - 1, 0)
    hi = np.minimum(idx.max(0) + 2, occupied.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    sub = occupied[box]
    centre = idx.mean(0) * spacing
    directions = sensor_directions(sensors, count, centre)
    # blocked toward at least `need` of the K directions; a voxel may miss K - need of them
    need = int(np.ceil(quorum * len(directions) - 1e-9))
    misses = np.zeros(sub.shape, dtype=np.int32)
    allowed = len(directions) - need
    for direction in directions:
        misses += ~_blocked_along(sub, direction * spacing.min() / spacing)
        if np.all(sub | (misses > allowed)):
            break
    out[box] = ~sub & (misses <= allowed)
    return out


def check_parameters(threshold: float, min_fraction: float, close, *,
                     names=("solid threshold", "solid min_fraction", "solid close"),
                     max_close: int | None = None, mode: str = "peak") -> None:
    """The ranges of :func:`solidify`'s parameters (one-line InputError naming ``names``):
    threshold in [0, 1) (mode 'peak') or a factor in (0, 1/OTSU_FLOOR) (mode 'otsu'),
    min_fraction in [0, 1], close an integer ≥ 0 (≤ ``max_close``)."""
    if mode not in THRESHOLD_MODES:
        raise InputError(f"{names[0]} mode: choose one of {', '.join(THRESHOLD_MODES)}, got {mode!r}")
    if mode == "peak" and not 0 <= threshold < 1:
        raise InputError(f"{names[0]}: must be in [0, 1), got {threshold}")
    if mode == "otsu" and not 0 < threshold < 1 / OTSU_FLOOR:
        raise InputError(f"{names[0]}: with the Otsu mode a factor in (0, {1 / OTSU_FLOOR:g}), "
                         f"got {threshold}")
    if not 0 <= min_fraction <= 1:
        raise InputError(f"{names[1]}: must be in [0, 1], got {min_fraction}")
    if int(close) != close or close < 0 or (max_close is not None and close > max_close):
        bound = ">= 0" if max_close is None else f"in [0, {max_close}]"
        raise InputError(f"{names[2]}: must be an integer {bound}, got {close}")


def check_blur(blur: float, name: str = "solid blur") -> None:
    """The Gaussian's width is a finite number of voxels >= 0 (one-line InputError)."""
    if not (np.isfinite(blur) and 0 <= blur <= 10):
        raise InputError(f"{name}: must be a number of voxels in [0, 10], got {blur}")


def check_cavity_floor(cavity_floor: float, name: str = "solid cavity_floor") -> None:
    """Step 6's support distance is a finite number of metres >= 0 (one-line InputError)."""
    if not (np.isfinite(cavity_floor) and cavity_floor >= 0):
        raise InputError(f"{name}: must be a finite number of metres >= 0, got {cavity_floor}")


def check_part(part_volume: float, part_height: float,
               names=("solid part_volume", "solid part_height")) -> None:
    """Step 2's separate-object volume (m³) and height (m): finite, >= 0 (one-line InputError)."""
    if not (np.isfinite(part_volume) and part_volume >= 0):
        raise InputError(f"{names[0]}: must be a finite number of cubic metres >= 0, "
                         f"got {part_volume}")
    if not (np.isfinite(part_height) and part_height >= 0):
        raise InputError(f"{names[1]}: must be a finite number of metres >= 0, got {part_height}")


def check_quorum(quorum: float, name: str = "solid quorum") -> None:
    """The hidden-voxel quorum is a fraction in (0, 1] (one-line InputError otherwise)."""
    if not (np.isfinite(quorum) and 0 < quorum <= 1):
        raise InputError(f"{name}: must be in (0, 1], got {quorum}")


def solidify(volume: np.ndarray, threshold: float = DEFAULTS["threshold"],
             min_fraction: float = DEFAULTS["min_fraction"], close: int = DEFAULTS["close"],
             floor: bool = DEFAULTS["floor"], hidden: int = DEFAULTS["hidden"],
             sensors: np.ndarray | None = None, bounds=None,
             quorum: float = DEFAULTS["quorum"],
             cavity_floor: float = DEFAULTS["cavity_floor"],
             blur: float = DEFAULTS["blur"],
             threshold_mode: str = DEFAULTS["threshold_mode"],
             smooth: float = DEFAULTS["smooth"],
             part_volume: float = DEFAULTS["part_volume"],
             part_height: float = DEFAULTS["part_height"]) -> np.ndarray:
    """bool [nx, ny, nz]: the solid occupancy of a reconstructed field (module docstring).

    volume: complex or real [nx, ny, nz] (z the vertical axis, index 0 the lowest plane).
    hidden: sensor positions to test visibility from (0 = step 5 off); sensors: [N, 3] the
    scan's sensor positions (m) and bounds [3, 2] the volume's box (m), both needed with
    ``hidden`` > 0; quorum: the fraction of those sensors a voxel must be hidden from;
    cavity_floor: step 6's support distance in metres (0 = step 6 off; needs ``bounds``);
    blur (voxels) and threshold_mode ('peak' | 'otsu'): step 1's magnitude and cut;
    smooth: step 7's Gaussian in voxels (0 = off); part_volume (m³, 0 = off) and part_height
    (m): step 2's separate objects kept whatever their size against the largest (needs
    ``bounds``).
    """
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise InputError(f"solid extraction: expected a 3-D volume, got shape {volume.shape}")
    check_parameters(threshold, min_fraction, close, mode=threshold_mode)
    check_blur(blur)
    check_blur(smooth, "solid smooth")
    if int(hidden) != hidden or hidden < 0:
        raise InputError(f"solid hidden: must be an integer >= 0, got {hidden}")
    check_quorum(quorum)
    check_cavity_floor(cavity_floor)
    if int(hidden) > 0 and (sensors is None or bounds is None):
        raise InputError("solid extraction: hidden > 0 needs the sensor positions and the bounds")
    if cavity_floor > 0 and bounds is None:
        raise InputError("solid extraction: cavity_floor > 0 needs the bounds")
    check_part(part_volume, part_height)
    if part_volume > 0 and bounds is None:
        raise InputError("solid extraction: part_volume > 0 needs the bounds")
    spacing = None
    if bounds is not None:
        bounds = np.asarray(bounds, dtype=np.float64)
        n = np.array(volume.shape)
        spacing = (bounds[:, 1] - bounds[:, 0]) / np.maximum(n - 1, 1)
    occupied = thresholded(volume, threshold, blur, threshold_mode)
    occupied = drop_small_components(occupied, min_fraction,
                                     *part_rule(part_volume, part_height, spacing))
    data = close_gaps(occupied, int(close))
    occupied = fill_enclosed(data, bool(floor))
    if int(hidden) <= 0 and not cavity_floor > 0:
        return smooth_boundary(occupied, float(smooth))
    if int(hidden) > 0:
        relative = np.asarray(sensors, dtype=np.float64) - bounds[:, 0]
        occupied = occupied | hidden_from(occupied, spacing, relative, int(hidden), float(quorum))
        occupied = fill_enclosed(occupied, bool(floor))
    if cavity_floor > 0:
        reach = int(round(cavity_floor / spacing[2])) if spacing[2] > 0 else 0
        occupied = fill_enclosed(occupied | floorless_cavities(occupied, data, reach, bool(floor)),
                                 bool(floor))
    return smooth_boundary(occupied, float(smooth))


def floorless_cavities(occupied: np.ndarray, data: np.ndarray, reach: int,
                       ground: bool = True) -> np.ndarray:
    """bool like ``occupied``: the open cavities of step 6 whose floor the data do not show.

    Open cavity: a 6-connected set of empty voxels each enclosed by ``occupied`` within its own
    z slice (2-D hole filling slice by slice). Floor voxels: its voxels whose lower neighbour
    is occupied; supported where a voxel of ``data`` (the thresholded field) lies 1..``reach``
    voxels below, or, with ``ground``, where the grid's lowest plane does (the ground). A
    cavity is returned when fewer than half of its floor voxels are supported (one without
    floor voxels stays open)."""
    ndimage = _ndimage()
    occupied = np.asarray(occupied, dtype=bool)
    data = np.asarray(data, dtype=bool)
    cavity = np.zeros_like(occupied)
    for k in range(occupied.shape[2]):
        cavity[:, :, k] = ndimage.binary_fill_holes(occupied[:, :, k]) & ~occupied[:, :, k]
    labels, count = ndimage.label(cavity)
    if count == 0:
        return cavity
    floor_voxels = np.zeros_like(cavity)
    floor_voxels[:, :, 1:] = cavity[:, :, 1:] & occupied[:, :, :-1]
    reach = max(int(reach), 0)
    supported = np.zeros_like(cavity)
    for d in range(1, min(reach, occupied.shape[2] - 1) + 1):
        supported[:, :, d:] |= data[:, :, :-d]
    if ground:      # the lowest plane (the ground) lies 1..reach below planes 1..reach
        supported[:, :, :reach + 1] = True
    total = np.bincount(labels[floor_voxels], minlength=count + 1)
    held = np.bincount(labels[floor_voxels & supported], minlength=count + 1)
    floorless = np.flatnonzero((total > 0) & (held < 0.5 * total))
    return np.isin(labels, floorless[floorless > 0])
