"""``recon evaluate RECONSTRUCTION --gt GT``: IoU, Chamfer, normals, image metrics of a volume
(``.h5``) or a mesh (PLY/OBJ/STL/OFF/GLB, world metres) against a ground-truth mesh."""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from .. import export
from ..evaluation_options import MAPPINGS, N_SURFACE_SAMPLES, N_VOLUME_SAMPLES, PROTOCOLS, \
    REFERENCE_VIEW_SETS

HELP = ("Evaluate a volume or a mesh against a ground-truth mesh (IoU, Chamfer, normals, "
        "PSNR/SSIM, threshold sweep).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volume", type=Path, metavar="RECONSTRUCTION",
                        help="volume file (.h5), or a mesh file (.ply/.obj/.stl/.off/.glb, "
                             "world metres: e.g. the output of recon refine)")
    parser.add_argument("--gt", required=True,
                        help="ground truth: a dataset .h5 with gt/ (the mesh as the simulator "
                             "placed it), a scene TOML/name (placed by the scene), or a mesh "
                             "file (its own coordinates, as given: no scene transform)")
    parser.add_argument("--threshold", type=float, default=export.DEFAULT_THRESHOLD,
                        help="threshold on the normalised magnitude (default 0.2; volumes only)")
    parser.add_argument("--normalize", choices=export.NORMALIZATIONS, default="minmax")
    parser.add_argument("--crop", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help="evaluate only inside this box (m), e.g. to leave out the ground")
    parser.add_argument("--no-sweep", action="store_true", help="skip the threshold sweep")
    parser.add_argument("--no-images", action="store_true",
                        help="skip the rendered-image metrics (PSNR, SSIM)")
    parser.add_argument("--samples", type=int, default=N_SURFACE_SAMPLES,
                        help="surface samples per mesh for Chamfer (default 20000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--with-sweep-rows", action="store_true",
                        help="include every sweep row in the JSON output")
    parser.add_argument("--protocol", choices=PROTOCOLS, default="exact",
                        help="exact (default): containment-test GT on the volume's own lattice, "
                             "sub-voxel iso-surface; reference: the reference's definitions "
                             "and quirks (50 000 GT volume samples, its 80x80x59 IoU grid, "
                             "binarised + smoothed mesh with its vertex mapping, its 10 views "
                             "from its camera table); see docs/evaluation.md")
    parser.add_argument("--volume-samples", type=int, default=N_VOLUME_SAMPLES,
                        help="GT volume samples of the reference protocol (default 50000)")
    parser.add_argument("--vertex-mapping", choices=MAPPINGS,
                        default="reference",
                        help="reference protocol's mesh vertex mapping: 'reference' (its "
                             "padding offset and /n, default) or 'centre' (voxel centres)")
    parser.add_argument("--reference-views", choices=REFERENCE_VIEW_SETS, default="paper",
                        help="reference protocol's cameras: 'paper' (its camera table, per GT "
                             "shape; default) or 'released' (its released command line's "
                             "--fov 60, read as 60 rad by pyrender)")


def run(args: argparse.Namespace) -> int:
    from ..evaluation import evaluate_file, format_table, json_safe
    result = evaluate_file(args.volume, args.gt, threshold=args.threshold,
                           normalize=args.normalize, sweep=not args.no_sweep,
                           images=not args.no_images, samples=args.samples, seed=args.seed,
                           crop=args.crop, protocol=args.protocol,
                           volume_samples=args.volume_samples, mapping=args.vertex_mapping,
                           reference_views=args.reference_views)
    for line in result["warnings"]:
        logging.getLogger(__name__).warning(line)
    if not args.with_sweep_rows:
        result.pop("sweep", None)
    if args.json:
        print(json.dumps(json_safe(result), allow_nan=False))
    else:
        print("\n".join(format_table(result)))
    return 0
