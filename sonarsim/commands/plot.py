"""``sonarsim plot``: echo images, pulse and trajectory pictures of a sonar dataset."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "Write echo images (PNG + EXR), pulse and trajectory plots of a sonar dataset."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--dynamic-range", type=float, default=60.0, metavar="DB",
                        help="dB range of the PNG echo images (default 60)")
    parser.add_argument("--complex-exr", action="store_true",
                        help="also store the matched filter's real and imaginary parts "
                             "(channels re, im) in echo_mf.exr")
    parser.add_argument("--box", type=float, nargs=6, default=None,
                        metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help="scene box (m) drawn in the trajectory plot (default: the box "
                             "recorded by the importer, else by data source)")


def run(args: argparse.Namespace) -> int:
    from ..dataset import SonarDataset
    from ..plot import plot_dataset
    from .import_airsas import parse_box

    ds = SonarDataset.read(args.dataset)
    for path in plot_dataset(ds, args.out, box=parse_box(args.box),
                             dynamic_range_db=args.dynamic_range,
                             complex_exr=args.complex_exr):
        print(path)
    return 0
