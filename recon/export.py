"""Export of reconstructed volumes: normalised magnitude, MIPs, slices, iso-surface mesh.

A volume is a complex array ``[nx, ny, nz]`` whose voxel centres are
``linspace(lo, hi, n)`` per axis (``bounds`` = ``[[x0, x1], [y0, y1], [z0, z1]]``, metres).

Decisions (see docs/evaluation.md):

* **Normalisation.** ``|v|`` min-max normalised to [0, 1] by default, as the reference
  does, so that a threshold (default 0.2) means the same thing as in the paper. ``max``
  (divide by the maximum only) is available. A constant volume (max == min, e.g. all
  zeros) normalises to all zeros: it contains no structure and nothing lies above any
  threshold.
* **Mesh.** Marching cubes (scikit-image, Lewiner) on the normalised magnitude padded
  by one voxel of 0 (so surfaces touching the box are closed), at ``level = threshold``.
  Vertices are mapped to world coordinates as ``lo + (p - 1) * spacing`` with
  ``spacing = (hi - lo) / (n - 1)`` and ``p`` the padded index. The reference maps with
  ``/n`` instead of ``/(n - 1)``, keeps the padding offset and swaps x/y
  (reference code evaluate/); those shift and stretch its meshes by one to two voxels.
* **Single voxel along an axis.** Its spacing is undefined; the smallest spacing of the
  other axes is used (the voxel is treated as a cube). A 1x1x1 volume has no spacing at
  all and raises :class:`InputError`.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.dataset.volume import voxel_axes as volume_voxel_axes
from sonarsim.dataset.volume import voxel_spacing as _spacing
from sonarsim.errors import InputError

if TYPE_CHECKING:     # trimesh (networkx, scipy.spatial) is imported where a mesh is made:
    import trimesh    # it is most of a recon command's start-up (``recon --help``)

NORMALIZATIONS = ("minmax", "max")
DEFAULT_THRESHOLD = 0.2
AXIS_NAMES = "xyz"


# --------------------------------------------------------------------------- geometry

def check_volume_array(volume: np.ndarray, name: str = "volume") -> np.ndarray:
    """Validate a volume array ``[nx, ny, nz]`` (complex or real) and return it."""
    arr = np.asarray(volume)
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise InputError(f"{name}: expected a 3-D array [nx, ny, nz], got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinite values")
    return arr


def check_bounds(bounds, shape: tuple[int, int, int]) -> np.ndarray:
    """Validate ``bounds`` [3, 2] (metres) against a volume shape and return float64 bounds."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (3, 2) or not np.all(np.isfinite(b)):
        raise InputError(f"bounds: expected finite [[x0,x1],[y0,y1],[z0,z1]], got {b.tolist()}")
    for a in range(3):
        if shape[a] > 1 and not b[a, 1] > b[a, 0]:
            raise InputError(f"bounds: {AXIS_NAMES[a]} range {b[a].tolist()} is empty "
                             f"but the volume has {shape[a]} voxels along {AXIS_NAMES[a]}")
    return b


def voxel_spacing(bounds, shape: tuple[int, int, int]) -> np.ndarray:
    """Voxel cell size [3] in metres for meshes and pictures: ``(hi - lo) / (n - 1)``; an axis
    with a single voxel takes the smallest spacing of the other axes
    (:func:`sonarsim.dataset.volume.voxel_spacing`, rule ``'min'``).
    """
    b = check_bounds(bounds, shape)
    if not (np.asarray(shape) > 1).any():
        raise InputError("volume has a single voxel: its voxel size is undefined")
    return _spacing(b, shape, single="min")


def voxel_axes(bounds, shape: tuple[int, int, int]) -> list[np.ndarray]:
    """Voxel-centre coordinates per axis, ``[x [nx], y [ny], z [nz]]`` in metres."""
    return list(volume_voxel_axes(check_bounds(bounds, shape), shape))


def crop_volume(volume: np.ndarray, bounds, box) -> tuple[np.ndarray, np.ndarray]:
    """The voxels whose centres lie in ``box`` [3, 2] (metres, inclusive).

    Returns (sub-volume, its bounds [3, 2]); :class:`InputError` when the box holds no
    voxel centre along some axis.
    """
    arr = check_volume_array(volume)
    box = np.asarray(box, dtype=np.float64)
    if box.shape != (3, 2) or not np.all(box[:, 1] >= box[:, 0]):
        raise InputError(f"crop box: expected [[x0,x1],[y0,y1],[z0,z1]] with x0 <= x1, "
                         f"got {box.tolist()}")
    axes = voxel_axes(bounds, arr.shape)
    keep = [np.nonzero((c >= box[a, 0] - 1e-9) & (c <= box[a, 1] + 1e-9))[0]
            for a, c in enumerate(axes)]
    for a, k in enumerate(keep):
        if len(k) == 0:
            raise InputError(f"crop box {box[a].tolist()} along {AXIS_NAMES[a]} holds no voxel "
                             f"centre of the volume ({axes[a][0]:.4g} .. {axes[a][-1]:.4g} m)")
    sub = arr[keep[0][0]:keep[0][-1] + 1, keep[1][0]:keep[1][-1] + 1, keep[2][0]:keep[2][-1] + 1]
    sub_bounds = np.array([[axes[a][k[0]], axes[a][k[-1]]] for a, k in enumerate(keep)])
    return sub, sub_bounds


# ----------------------------------------------------------------------- magnitude

def normalized_magnitude(volume: np.ndarray, mode: str = "minmax") -> np.ndarray:
    """``|volume|`` scaled to [0, 1] as float32 ``[nx, ny, nz]``.

    ``mode='minmax'``: ``(m - min) / (max - min)`` (the reference); ``'max'``: ``m / max``.
    A constant volume gives all zeros.
    """
    if mode not in NORMALIZATIONS:
        raise InputError(f"normalisation must be one of {NORMALIZATIONS}, got {mode!r}")
    mag = np.abs(check_volume_array(volume)).astype(np.float64)
    hi = float(mag.max())
    lo = float(mag.min()) if mode == "minmax" else 0.0
    if not hi > lo:
        return np.zeros(mag.shape, dtype=np.float32)
    return ((mag - lo) / (hi - lo)).astype(np.float32)


def check_threshold(threshold: float) -> float:
    """A threshold on the normalised magnitude must lie in [0, 1)."""
    t = float(threshold)
    if not 0.0 <= t < 1.0:
        raise InputError(f"threshold must lie in [0, 1), got {threshold}")
    return t


def occupied_points(magnitude: np.ndarray, bounds, threshold: float) -> np.ndarray:
    """World coordinates [K, 3] of the voxel centres with ``magnitude > threshold``."""
    axes = voxel_axes(bounds, magnitude.shape)
    idx = np.nonzero(magnitude > check_threshold(threshold))
    return np.stack([axes[a][idx[a]] for a in range(3)], axis=1)


# ----------------------------------------------------------------------------- mesh

def extract_surface(magnitude: np.ndarray, bounds, threshold: float = DEFAULT_THRESHOLD
                    ) -> trimesh.Trimesh:
    """Iso-surface of a normalised magnitude ``[nx, ny, nz]`` at ``threshold``, in world metres.

    Faces are wound so that normals point out of the region above the threshold. A volume
    with nothing above the threshold gives an empty mesh (0 vertices, 0 faces).
    """
    import trimesh
    from skimage.measure import marching_cubes

    t = check_threshold(threshold)
    mag = np.asarray(magnitude, dtype=np.float32)
    spacing = voxel_spacing(bounds, mag.shape)
    lo = np.asarray(bounds, dtype=np.float64)[:, 0]
    if not (mag > t).any():
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    padded = np.pad(mag, 1, mode="constant", constant_values=min(0.0, float(mag.min())))
    verts, faces, _, _ = marching_cubes(padded, level=t, spacing=tuple(spacing),
                                        allow_degenerate=False)
    world = lo + verts.astype(np.float64) - spacing  # remove the one-voxel padding
    # 'descent' winding makes face normals point towards higher values; flip to outward.
    mesh = trimesh.Trimesh(world, faces[:, ::-1], process=False)
    return mesh


def mesh_from_volume(volume: np.ndarray, bounds, threshold: float = DEFAULT_THRESHOLD,
                     normalization: str = "minmax") -> trimesh.Trimesh:
    """:func:`extract_surface` of :func:`normalized_magnitude` of a complex volume."""
    return extract_surface(normalized_magnitude(volume, normalization), bounds, threshold)


# ----------------------------------------------------------------------------- MIPs

def mip(magnitude: np.ndarray, axis: int) -> np.ndarray:
    """Maximum-intensity projection along ``axis`` as an image ``[rows, cols]``.

    Rows/columns are the remaining axes, the higher-index axis as rows: along z ->
    ``[ny, nx]``, along y -> ``[nz, nx]``, along x -> ``[nz, ny]``; row 0 is the lowest
    coordinate (display with ``origin='lower'``).
    """
    return np.asarray(magnitude).max(axis=axis).T


def mip_axes(axis: int) -> tuple[int, int]:
    """(column axis, row axis) of :func:`mip` along ``axis``."""
    u, v = [a for a in range(3) if a != axis]
    return u, v


def pixel_extent(bounds, shape, axis: int) -> tuple[float, float]:
    """Outer edges (lo - d/2, hi + d/2) in metres of the voxels along ``axis``."""
    b = np.asarray(bounds, dtype=np.float64)
    d = voxel_spacing(b, shape)[axis]
    last = b[axis, 0] + (shape[axis] - 1) * d  # = hi, or lo for a single voxel
    return float(b[axis, 0] - d / 2), float(last + d / 2)


def write_mip_png(path: str | Path, magnitude: np.ndarray, bounds, title: str = "",
                  dpi: int = 120) -> Path:
    """Write the MIPs with metric axes and a colour bar as a PNG.

    A volume with several voxels along every axis gets the three MIPs (along z, y, x). A
    volume with one voxel along one axis is a single slice: one image of it, titled with the
    slice's coordinate (its other two "projections" would be strips one pixel high). A
    volume with several voxels along one axis only is drawn as a line plot along that axis.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    shape = magnitude.shape
    long_axes = [a for a in range(3) if shape[a] > 1]
    voxel_spacing(bounds, shape)                        # refuses a single voxel
    if len(long_axes) == 1:
        fig = _line_figure(plt, magnitude, bounds, long_axes[0])
    else:
        fig = _image_figure(plt, magnitude, bounds, long_axes)
    if title:
        fig.suptitle(title)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return path


def _image_figure(plt, magnitude, bounds, long_axes):
    """Three MIPs, or the one image of a single slice (one axis with one voxel)."""
    shape = magnitude.shape
    views = (2, 1, 0) if len(long_axes) == 3 else [a for a in range(3) if a not in long_axes]
    fig, axs = plt.subplots(1, len(views), figsize=(13, 4.2) if len(views) == 3 else (6, 5),
                            constrained_layout=True, squeeze=False)
    image = None
    for ax, axis in zip(axs[0], views):
        u, v = mip_axes(axis)
        extent = (*pixel_extent(bounds, shape, u), *pixel_extent(bounds, shape, v))
        image = ax.imshow(mip(magnitude, axis), origin="lower", extent=extent,
                          cmap="inferno", vmin=0.0, vmax=1.0, interpolation="nearest")
        ax.set_xlabel(f"{AXIS_NAMES[u]} (m)")
        ax.set_ylabel(f"{AXIS_NAMES[v]} (m)")
        if len(views) == 3:
            ax.set_title(f"max over {AXIS_NAMES[axis]}")
        else:
            at = float(np.asarray(bounds, dtype=np.float64)[axis, 0])
            ax.set_title(f"{AXIS_NAMES[axis]} = {at:.3f} m (single slice)")
        ax.set_aspect("equal")
    fig.colorbar(image, ax=list(axs[0]), shrink=0.85, label="normalised |σ|")
    return fig


def _line_figure(plt, magnitude, bounds, axis: int):
    """A volume with several voxels along ``axis`` only: the magnitude along it."""
    coords = voxel_axes(bounds, magnitude.shape)[axis]
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    ax.plot(coords, np.asarray(magnitude).reshape(-1), marker=".")
    ax.set_xlabel(f"{AXIS_NAMES[axis]} (m)")
    ax.set_ylabel("normalised |σ|")
    ax.set_ylim(0.0, 1.05)
    ax.grid(alpha=0.3)
    return fig


def mip_exr_paths(path: str | Path) -> dict[str, Path]:
    """The three files :func:`write_mip_exr` writes for ``path``: ``{'mip_z': STEM_z.exr,
    'mip_y': STEM_y.exr, 'mip_x': STEM_x.exr}`` (the letter: the axis projected along)."""
    path = Path(path)
    suffix = path.suffix or ".exr"
    return {f"mip_{a}": path.with_name(f"{path.stem}_{a}{suffix}") for a in "zyx"}


def write_mip_exr(path: str | Path, magnitude: np.ndarray, bounds) -> list[Path]:
    """Write the three MIPs as float32 single-channel OpenEXR images, one file each.

    ``STEM_z.exr``, ``STEM_y.exr``, ``STEM_x.exr`` (:func:`mip_exr_paths`): single-part
    scanline files with one channel ``Y`` (the grey channel every EXR reader knows), stored
    as displayed (row 0 = the highest row coordinate). Header attributes:
    ``sonarsim_u_axis``, ``sonarsim_v_axis`` (axis names of columns/rows) and
    ``sonarsim_u_range_m``, ``sonarsim_v_range_m`` (outer pixel edges, metres). Read back
    with :func:`read_mip_exr`.
    """
    import OpenEXR

    shape = magnitude.shape
    written = []
    for (name, out), axis in zip(mip_exr_paths(path).items(), (2, 1, 0)):
        image = np.ascontiguousarray(mip(magnitude, axis)[::-1], dtype=np.float32)
        u, v = mip_axes(axis)
        header = {
            "compression": OpenEXR.ZIP_COMPRESSION,
            "type": OpenEXR.scanlineimage,
            "sonarsim_u_axis": AXIS_NAMES[u],
            "sonarsim_v_axis": AXIS_NAMES[v],
            "sonarsim_u_range_m": " ".join(f"{x:.9g}" for x in pixel_extent(bounds, shape, u)),
            "sonarsim_v_range_m": " ".join(f"{x:.9g}" for x in pixel_extent(bounds, shape, v)),
            "comments": f"maximum of the normalised magnitude along {AXIS_NAMES[axis]}",
        }
        with atomic_path(out) as tmp, OpenEXR.File(header, {"Y": image}) as f:
            f.write(str(tmp))
        written.append(out)
    return written


def read_mip_exr(path: str | Path) -> dict[str, np.ndarray]:
    """The MIPs of :func:`write_mip_exr` as ``{'mip_z': [ny, nx], ...}`` (row 0 = lowest)."""
    import OpenEXR

    from sonarsim.errors import FormatError
    images = {}
    for name, file in mip_exr_paths(path).items():
        try:
            with OpenEXR.File(str(file)) as f:
                images[name] = np.array(f.channels()["Y"].pixels)[::-1]
        except Exception as exc:  # OpenEXR raises RuntimeError/OSError variants
            raise FormatError(f"{file}: not a readable OpenEXR file ({exc})") from None
    return images


# --------------------------------------------------------------------- 3-D volume files

def volume_channels(volume: np.ndarray) -> dict[str, np.ndarray]:
    """The values other tools get: ``magnitude`` = |v| and ``phase`` = arg v in radians
    (-π, π], both float32 ``[nx, ny, nz]`` (the magnitude as stored, not normalised)."""
    v = check_volume_array(volume)
    return {"magnitude": np.abs(v).astype(np.float32),
            "phase": np.angle(v).astype(np.float32)}


def grid_geometry(bounds, shape) -> tuple[np.ndarray, np.ndarray]:
    """(origin [3], spacing [3]) in metres: the first voxel centre and the voxel pitch
    (docs/frames.md; an axis with one voxel takes the smallest pitch of the others)."""
    b = check_bounds(bounds, shape)
    return b[:, 0].copy(), voxel_spacing(b, shape)


def write_vti(path: str | Path, volume: np.ndarray, bounds) -> Path:
    """Write a volume as VTK XML ImageData (``.vti``; ParaView, VisIt, PyVista, 3D Slicer).

    Point data ``magnitude`` and ``phase`` (:func:`volume_channels`) on the grid's points,
    which are the voxel centres: ``Origin`` = the first centre (x0, y0, z0) and ``Spacing``
    = the pitch (:func:`grid_geometry`), metres, world frame. Written with pyevtk (raw
    appended binary, the layout VTK's own writer uses).
    """
    import os

    from pyevtk.hl import imageToVTK

    path = Path(path)
    channels = volume_channels(volume)
    origin, spacing = grid_geometry(bounds, channels["magnitude"].shape)
    with atomic_path(path) as tmp:
        written = imageToVTK(str(tmp), origin=tuple(float(x) for x in origin),
                             spacing=tuple(float(x) for x in spacing),
                             pointData={k: np.ascontiguousarray(a) for k, a in channels.items()})
        os.replace(written, tmp)          # pyevtk appends ".vti" to the name it is given
    return path


def write_ome_tiff(path: str | Path, volume: np.ndarray, bounds) -> Path:
    """Write a volume as OME-TIFF (``.ome.tif``; napari, Fiji/Bio-Formats, ParaView).

    One float32 image stack, axes ``CZYX``: channel 0 ``magnitude``, channel 1 ``phase``
    (radians); plane k is z = z_k, row j is y = y_j, column i is x = x_i. OME metadata:
    ``PhysicalSizeX/Y/Z`` = the voxel pitch in metres (unit ``m``) and each plane's
    ``PositionX/Y/Z`` = the world position of its first voxel centre, metres. Written with
    tifffile.
    """
    import tifffile

    path = Path(path)
    channels = volume_channels(volume)
    origin, spacing = grid_geometry(bounds, channels["magnitude"].shape)
    stack = np.stack([channels["magnitude"], channels["phase"]]).transpose(0, 3, 2, 1)
    nz = stack.shape[1]
    z = origin[2] + spacing[2] * np.arange(nz)
    plane = {"PositionX": [float(origin[0])] * 2 * nz, "PositionXUnit": ["m"] * 2 * nz,
             "PositionY": [float(origin[1])] * 2 * nz, "PositionYUnit": ["m"] * 2 * nz,
             "PositionZ": [float(p) for p in z] * 2, "PositionZUnit": ["m"] * 2 * nz}
    metadata = {"axes": "CZYX", "Channel": {"Name": ["magnitude", "phase"]}, "Plane": plane,
                "PhysicalSizeX": float(spacing[0]), "PhysicalSizeXUnit": "m",
                "PhysicalSizeY": float(spacing[1]), "PhysicalSizeYUnit": "m",
                "PhysicalSizeZ": float(spacing[2]), "PhysicalSizeZUnit": "m"}
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, np.ascontiguousarray(stack), ome=True, metadata=metadata,
                         photometric="minisblack", compression="zlib")
    return path


# --------------------------------------------------------------------------- slices

def write_slices(directory: str | Path, magnitude: np.ndarray, bounds, axis: int = 2
                 ) -> list[Path]:
    """Write one 8-bit grey PNG per slice along ``axis`` plus ``slices.json``.

    Grey level = round(255 * normalised magnitude); rows/columns as in :func:`mip`
    (highest row coordinate at the top of the picture). ``slices.json`` lists the world
    coordinate (m) of each slice and the pixel extents. Each file is written atomically and
    the index last, so an interrupted run leaves no partial picture and no index; a failure
    part-way (a full disk) removes the slices this call had written.
    """
    from PIL import Image

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    coords = voxel_axes(bounds, magnitude.shape)[axis]
    u, v = mip_axes(axis)
    name = AXIS_NAMES[axis]
    written = []
    try:
        for k, c in enumerate(coords):
            img = np.take(magnitude, k, axis=axis).T[::-1]
            grey = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
            p = directory / f"slice_{name}_{k:04d}.png"
            with atomic_path(p) as tmp:
                Image.fromarray(grey, mode="L").save(tmp, format="PNG")
            written.append(p)
    except BaseException:        # a full disk or Ctrl-C: no incomplete set at the final paths
        for p in written:
            p.unlink(missing_ok=True)
        raise
    meta = {"axis": name, "coordinates_m": [float(c) for c in coords],
            "files": [p.name for p in written],
            "u_axis": AXIS_NAMES[u], "u_range_m": pixel_extent(bounds, magnitude.shape, u),
            "v_axis": AXIS_NAMES[v], "v_range_m": pixel_extent(bounds, magnitude.shape, v),
            "value": "round(255 * normalised magnitude); top row = highest v"}
    with atomic_path(directory / "slices.json") as tmp:    # the index last: complete set
        Path(tmp).write_text(json.dumps(meta, indent=1))
    return written


def write_mesh(path: str | Path, mesh: trimesh.Trimesh) -> Path:
    """Write a mesh (PLY, OBJ, STL, OFF, GLB, by suffix) atomically."""
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("ply", "obj", "stl", "off", "glb"):
        raise InputError(f"{path}: mesh format must be .ply, .obj, .stl, .off or .glb")
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=kind)
    return path
