"""``recon evaluate V.h5 --gt MESH``: IoU, Chamfer, normal consistency, image metrics."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import export, metrics
from ..evaluation import PROTOCOLS, evaluate_file, format_table, json_safe

HELP = "Evaluate a volume against a ground-truth mesh (IoU, Chamfer, PSNR/SSIM, threshold sweep)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volume", type=Path, help="volume file (.h5)")
    parser.add_argument("--gt", required=True,
                        help="ground truth: mesh file, dataset .h5 with gt/, or scene TOML/name")
    parser.add_argument("--threshold", type=float, default=export.DEFAULT_THRESHOLD,
                        help="threshold on the normalised magnitude (default 0.2)")
    parser.add_argument("--normalize", choices=export.NORMALIZATIONS, default="minmax")
    parser.add_argument("--crop", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help="evaluate only inside this box (m), e.g. to leave out the ground")
    parser.add_argument("--no-sweep", action="store_true", help="skip the threshold sweep")
    parser.add_argument("--no-images", action="store_true",
                        help="skip the rendered-image metrics (PSNR, SSIM)")
    parser.add_argument("--samples", type=int, default=metrics.N_SURFACE_SAMPLES,
                        help="surface samples per mesh for Chamfer (default 20000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--with-sweep-rows", action="store_true",
                        help="include every sweep row in the JSON output")
    parser.add_argument("--protocol", choices=PROTOCOLS, default="exact",
                        help="exact (default): containment-test GT on the volume's own lattice, "
                             "sub-voxel iso-surface; reference: the reference's definitions "
                             "(50 000 GT volume samples, fixed 80x80x60 IoU grid, binarised + "
                             "smoothed mesh, its 10 views); see docs/evaluation.md")
    parser.add_argument("--volume-samples", type=int, default=metrics.N_VOLUME_SAMPLES,
                        help="GT volume samples of the reference protocol (default 50000)")


def run(args: argparse.Namespace) -> int:
    gt = metrics.load_gt_mesh(args.gt)
    result = evaluate_file(args.volume, gt, threshold=args.threshold,
                           normalize=args.normalize, sweep=not args.no_sweep,
                           images=not args.no_images, samples=args.samples, seed=args.seed,
                           crop=args.crop, protocol=args.protocol,
                           volume_samples=args.volume_samples)
    if not args.with_sweep_rows:
        result.pop("sweep", None)
    if args.json:
        print(json.dumps(json_safe(result), allow_nan=False))
    else:
        print("\n".join(format_table(result)))
    return 0

