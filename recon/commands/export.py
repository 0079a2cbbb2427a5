"""``recon export V.h5``: the volume for other tools (VTK ImageData, OME-TIFF), MIPs
(PNG/EXR), slices and an iso-surface mesh (docs/formats.md, "Exported files")."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sonarsim import outputs
from sonarsim.dataset import Volume
from sonarsim.errors import InputError

from .. import export

HELP = ("Export a volume: .vti (ParaView) / OME-TIFF (napari, Fiji), maximum-intensity "
        "projections, slices, marching-cubes mesh.")
OUTPUTS = ("mesh", "mip", "vti", "tiff")    # checked, locked and kept unless --force (cli_common)
OUTPUT_SUFFIXES = {"mesh": (".ply", ".obj", ".stl", ".off", ".glb"), "mip": (".png",), "vti": (".vti",),
                   "tiff": (".tif", ".tiff")}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volume", type=Path, help="volume file (.h5) from a recon solver")
    parser.add_argument("--mesh", type=Path, help="iso-surface mesh (.ply/.obj/.stl), world metres")
    parser.add_argument("--mip", type=Path, help="PNG of the MIPs along z, y, x with a colour bar")
    parser.add_argument("--exr", type=Path, metavar="E.exr",
                        help="the MIPs as float32 single-channel OpenEXR images: "
                             "E_z.exr, E_y.exr, E_x.exr (max along z, y, x)")
    parser.add_argument("--vti", type=Path, metavar="V.vti",
                        help="the volume as VTK ImageData (ParaView, VisIt, PyVista): "
                             "magnitude and phase at the voxel centres, metres")
    parser.add_argument("--tiff", type=Path, metavar="V.ome.tif",
                        help="the volume as OME-TIFF (napari, Fiji): channels magnitude and "
                             "phase, z-stack, voxel size in metres")
    parser.add_argument("--slices", type=Path, metavar="DIR",
                        help="directory for one grey PNG per slice plus slices.json")
    parser.add_argument("--slice-axis", choices=("x", "y", "z"), default="z",
                        help="axis the slices are taken along (default z)")
    parser.add_argument("--threshold", type=float, default=export.DEFAULT_THRESHOLD,
                        help="iso-level on the normalised magnitude (default 0.2)")
    parser.add_argument("--normalize", choices=export.NORMALIZATIONS, default="minmax",
                        help="magnitude normalisation: min-max (reference) or divide by max")


def run(args: argparse.Namespace) -> int:
    if not any((args.mesh, args.mip, args.exr, args.slices, args.vti, args.tiff)):
        raise InputError("nothing to export: give at least one of --vti, --tiff, --mesh, "
                         "--mip, --exr, --slices")
    exr_files = list(export.mip_exr_paths(args.exr).values()) if args.exr else []
    for path in exr_files:
        outputs.check_output(path, force=args.force, option="--exr")
    with outputs.output_locks(exr_files):
        return _export(args)


def _export(args: argparse.Namespace) -> int:
    threshold = export.check_threshold(args.threshold)
    if args.slices is not None and args.slices.is_dir() and any(args.slices.iterdir()) \
            and not args.force:
        raise InputError(f"--slices {args.slices}: directory is not empty; pass --force to "
                         "write the slices into it")
    if args.slices is not None and args.slices.exists() and not args.slices.is_dir():
        raise InputError(f"--slices {args.slices}: exists and is not a directory")
    vol = Volume.read(args.volume)
    mag = export.normalized_magnitude(vol.volume, args.normalize)
    mesh = None
    if args.mesh:               # before any file is written: a volume without a surface
        mesh = export.extract_surface(mag, vol.bounds, threshold)   # writes nothing at all
        if len(mesh.faces) == 0:
            hint = ("the volume is all zero" if not np.any(vol.volume)
                    else "try a lower --threshold")
            raise InputError(f"{args.volume}: no voxel above threshold {threshold:g} "
                             "(normalised magnitude); no surface to write to "
                             f"{args.mesh}; {hint}")
    if args.vti:
        export.write_vti(args.vti, vol.volume, vol.bounds)
        print(f"vti: {args.vti} (magnitude, phase; {_grid_text(vol)})")
    if args.tiff:
        export.write_ome_tiff(args.tiff, vol.volume, vol.bounds)
        print(f"tiff: {args.tiff} (channels magnitude, phase; {_grid_text(vol)})")
    if mesh is not None:
        export.write_mesh(args.mesh, mesh)
        print(f"mesh: {args.mesh} ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces, "
              f"threshold {threshold:g})")
    title = f"{args.volume.name}: {vol.method}, |σ| normalised ({args.normalize})"
    if args.mip:
        export.write_mip_png(args.mip, mag, vol.bounds, title=title)
        print(f"mip: {args.mip}")
    if args.exr:
        files = export.write_mip_exr(args.exr, mag, vol.bounds)
        print(f"exr: {', '.join(str(f) for f in files)} (max along z, y, x; channel Y)")
    if args.slices:
        files = export.write_slices(args.slices, mag, vol.bounds, "xyz".index(args.slice_axis))
        print(f"slices: {len(files)} PNGs in {args.slices}")
    return 0


def _grid_text(vol) -> str:
    origin, spacing = export.grid_geometry(vol.bounds, vol.shape)
    return (f"{' x '.join(map(str, vol.shape))} voxels, first centre "
            f"({', '.join(f'{x:.4g}' for x in origin)}) m, pitch "
            f"({', '.join(f'{x:.4g}' for x in spacing)}) m")
