"""``recon compare V1.h5 V2.h5 ... --gt MESH --out FIG.png``: side-by-side figure."""
from __future__ import annotations

import argparse
from pathlib import Path

from sonarsim.errors import InputError

from .. import export

HELP = "Compare volumes side by side: MIPs, renders and metrics against a ground-truth mesh."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("volumes", type=Path, nargs="+", help="volume files (.h5)")
    parser.add_argument("--gt", required=True,
                        help="ground truth: mesh file, dataset .h5 with gt/, or scene TOML/name")
    parser.add_argument("--out", type=Path, required=True, help="figure (.png)")
    parser.add_argument("--threshold", type=float, default=export.DEFAULT_THRESHOLD)
    parser.add_argument("--normalize", choices=export.NORMALIZATIONS, default="minmax")
    parser.add_argument("--crop", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help="evaluate and show only this box (m), e.g. to leave out the ground")
    parser.add_argument("--view", type=int, default=1,
                        help="which of the 10 turntable views to show (default 1 = 36°)")


def run(args: argparse.Namespace) -> int:
    import matplotlib
    matplotlib.use("Agg")

    from .. import figures, metrics, views
    from ..evaluation import evaluate_file, fmt_value

    if args.out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise InputError(f"{args.out}: the figure must be .png, .pdf or .svg")
    n_views = views.Turntable().n_views
    if not 0 <= args.view < n_views:
        raise InputError(f"--view must lie in 0..{n_views - 1}, got {args.view}")
    threshold = export.check_threshold(args.threshold)
    gt = metrics.load_gt_mesh(args.gt)
    results = [evaluate_file(path, gt, threshold=threshold, normalize=args.normalize,
                             sweep=False, images=False, crop=args.crop)
               for path in args.volumes]
    import logging
    shown = set()
    for path, res in zip(args.volumes, results):   # the ground truth's warnings once
        for line in res.get("warnings", ()):
            if line not in shown:
                shown.add(line)
                logging.getLogger(__name__).warning(line)
    fig = figures.comparison(args.volumes, gt, labels=[p.stem for p in args.volumes],
                             crop=args.crop, threshold=threshold, view=args.view,
                             normalize=args.normalize, results=results)
    figures.save(fig, args.out)
    print(f"figure: {args.out}")
    for path, res in zip(args.volumes, results):
        print(f"  {path}: IoU {fmt_value(res['iou'])}, Chamfer² {fmt_value(res['chamfer_sq'])} m², "
              f"Chamfer {fmt_value(res['chamfer_m'])} m, normal error "
              f"{fmt_value(res.get('normal_error_deg'))} deg")
    return 0
