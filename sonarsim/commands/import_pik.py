"""``sonarsim import-pik``: the reference's ``system_data.pik`` → sonar dataset (HDF5)."""
from __future__ import annotations

import argparse
from pathlib import Path

from ._options import add_box_option, parse_box

HELP = "Import a reference system_data.pik (loaded safely, no code runs) into a sonar dataset."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("pik", type=Path, help="system_data.pik of the reference code")
    parser.add_argument("--out", type=Path, required=True, help="output dataset (.h5)")
    add_box_option(parser, "scene box (m) whose centre the beams point at unless the pickle "
                             "has tx_vectors (default: the box of geometry.corners, else the "
                             "AirSAS real box)")


def run(args: argparse.Namespace) -> int:
    from ..importers.pik import import_pik

    ds = import_pik(args.pik, box=parse_box(args.box))
    ds.write(args.out)
    n, t = ds.waveforms.shape
    print(f"{args.out}: {n} pings x {t} samples from sample {ds.start_sample}, "
          f"fs {ds.fs:g} Hz, c {ds.sound_speed:.3f} m/s")
    return 0
