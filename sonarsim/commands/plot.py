"""``sonarsim plot``: pictures of a sonar dataset or of a transients file."""
from __future__ import annotations

import argparse
from pathlib import Path

from ._options import add_box_option, parse_box

HELP = ("Write pictures (PNG + float EXR) of a sonar dataset (echo images, pulse, trajectory) "
        "or of a transients file (per-bounce ping x path-length images, energy per bounce).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, metavar="FILE",
                        help="sonar dataset or transients file (.h5)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--dynamic-range", type=float, default=60.0, metavar="DB",
                        help="dB range (floor below the maximum) of the PNG images (default 60)")
    parser.add_argument("--complex-exr", action="store_true",
                        help="also store the matched filter's real and imaginary parts "
                             "(channels re, im) in echo_mf.exr")
    add_box_option(parser, "scene box (m) drawn in the trajectory plot (default: the box "
                             "recorded by the importer, else by data source)")
    parser.add_argument("--pings", type=int, nargs="+", default=None, metavar="I",
                        help="ping indices of the transients' energy-vs-path-length plot "
                             "(default: 4 spread over the scan)")


def run(args: argparse.Namespace) -> int:
    from ..dataset import KIND_TRANSIENTS, KIND_VOLUME, SonarDataset, Transients, file_kind
    from ..errors import FormatError, InputError
    from ..plot import plot_dataset
    from ..plot_transients import energy_lines, plot_transients

    kind = file_kind(args.file)
    if kind == KIND_VOLUME:
        raise FormatError(f"{args.file}: is a volume (reconstruction), which sonarsim plot does "
                          f"not draw; use `recon export {args.file} --mip MIP.png` instead")
    if kind == KIND_TRANSIENTS:
        transients = Transients.read(args.file)
        written = plot_transients(transients, args.out, dynamic_range_db=args.dynamic_range,
                                  pings=args.pings)
    else:
        ds = SonarDataset.read(args.file)
        transients = ds.transients
        if args.pings is not None and transients is None:
            raise InputError(f"{args.file}: --pings needs transients, and this dataset keeps "
                             "none (simulate with --keep-transients)")
        written = plot_dataset(ds, args.out, box=parse_box(args.box),
                               dynamic_range_db=args.dynamic_range,
                               complex_exr=args.complex_exr, profile_pings=args.pings)
    for path in written:
        print(path)
    if transients is not None:
        print("\n".join(energy_lines(transients)))
    return 0
