"""``recon compare V1.h5 V2.h5 ... --gt MESH --out FIG.png``: side-by-side figure."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.errors import InputError

from .. import export, metrics
from ..evaluation import evaluate_file, fmt_value

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
    import matplotlib.pyplot as plt

    from sonarsim.dataset import Volume

    from .. import views

    if args.out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise InputError(f"{args.out}: the figure must be .png, .pdf or .svg")
    cams = views.Turntable()
    if not 0 <= args.view < cams.n_views:
        raise InputError(f"--view must lie in 0..{cams.n_views - 1}, got {args.view}")
    threshold = export.check_threshold(args.threshold)
    gt = metrics.load_gt_mesh(args.gt)
    gt_render = views.render_views(gt, cams)["shaded"][args.view]
    rows = []
    for path in args.volumes:
        vol = Volume.read(path)
        volume, bounds = vol.volume, vol.bounds
        if args.crop:
            volume, bounds = export.crop_volume(volume, bounds, np.reshape(args.crop, (3, 2)))
        mag = export.normalized_magnitude(volume, args.normalize)
        res = evaluate_file(path, gt, threshold=threshold, normalize=args.normalize,
                            sweep=False, images=True, crop=args.crop)
        shaded = views.render_views(export.extract_surface(mag, bounds, threshold), cams)
        rows.append((path, vol.method, bounds, mag, res, shaded["shaded"][args.view]))

    fig, axs = plt.subplots(len(rows) + 1, 4, figsize=(15, 3.4 * (len(rows) + 1)),
                            squeeze=False)
    for ax in axs[0]:
        ax.axis("off")
    axs[0, 2].imshow(gt_render, cmap="gray", vmin=0, vmax=1)
    axs[0, 2].set_title("ground truth (render)")
    axs[0, 3].text(0, 0.5, f"GT: {args.gt}\n{len(gt.faces)} faces\nthreshold {threshold:g}",
                   va="center", family="monospace")
    for r, (path, method, bounds, mag, res, shaded) in enumerate(rows, start=1):
        for c, axis in enumerate((2, 1)):
            u, v = export.mip_axes(axis)
            ext = (*export.pixel_extent(bounds, mag.shape, u),
                   *export.pixel_extent(bounds, mag.shape, v))
            ax = axs[r, c]
            ax.imshow(export.mip(mag, axis), origin="lower", extent=ext, cmap="inferno",
                      vmin=0, vmax=1, interpolation="nearest")
            ax.set_xlabel(f"{'xyz'[u]} (m)")
            ax.set_ylabel(f"{'xyz'[v]} (m)")
            ax.set_title(f"{path.name}: MIP over {'xyz'[axis]}")
        axs[r, 2].imshow(shaded, cmap="gray", vmin=0, vmax=1)
        axs[r, 2].set_title(f"{method}: mesh @ {threshold:g}")
        axs[r, 2].axis("off")
        text = "\n".join([
            f"IoU          {fmt_value(res['iou'])}",
            f"Chamfer² m²  {fmt_value(res['chamfer_sq'])}",
            f"Chamfer m    {fmt_value(res['chamfer_m'])}",
            f"normal cons. {fmt_value(res['normal_consistency'])}",
            f"PSNR depth   {fmt_value(res['psnr_depth'])} dB",
            f"SSIM depth   {fmt_value(res['ssim_depth'])}",
            f"PSNR shaded  {fmt_value(res['psnr_shaded'])} dB"])
        axs[r, 3].text(0, 0.5, text, va="center", family="monospace")
        axs[r, 3].axis("off")
    fig.tight_layout()
    try:
        with atomic_path(args.out) as tmp:
            fig.savefig(tmp, dpi=100)
    finally:
        plt.close(fig)
    print(f"figure: {args.out}")
    for path, _, _, _, res, _ in rows:
        print(f"  {path}: IoU {fmt_value(res['iou'])}, Chamfer² {fmt_value(res['chamfer_sq'])} m², "
              f"Chamfer {fmt_value(res['chamfer_m'])} m")
    return 0
