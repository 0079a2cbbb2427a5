"""``sonarsim import-openstb``: an openSTB result (Zarr baseband pressure) → sonar dataset."""
from __future__ import annotations

import argparse
from pathlib import Path

from ._options import add_box_option, parse_box

HELP = "Import an openSTB simulation result (Zarr baseband pressure) into a sonar dataset."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=Path, help="openSTB result: a Zarr directory")
    parser.add_argument("--out", type=Path, required=True, help="output dataset (.h5)")
    parser.add_argument("--config", type=Path, default=None, metavar="SIM.toml",
                        help="the openSTB simulation configuration (trajectory, transducers, "
                             "signal, sound speed); needed unless sonarsim wrote the result")
    parser.add_argument("--fs", type=float, default=None,
                        help="sample rate (Hz) of the real waveforms: a whole multiple of the "
                             "result's sample_rate (default: the rate sonarsim exported, "
                             "else the smallest multiple >= 2.5 x the band's top)")
    parser.add_argument("--sound-speed", type=float, default=None,
                        help="speed of sound (m/s; default: the configuration's)")
    add_box_option(parser, "scene box (m) stored with the dataset: the region reconstructions "
                           "default to (openSTB results have none)")


def run(args: argparse.Namespace) -> int:
    from ..importers.openstb import read_openstb

    ds = read_openstb(args.result, config=args.config, fs=args.fs,
                      sound_speed=args.sound_speed, box=parse_box(args.box))
    ds.write(args.out)
    n, t = ds.waveforms.shape
    print(f"wrote {args.out}: {n} pings ({ds.meta['openstb_receivers']} receivers per openSTB "
          f"ping) x {t} samples from sample {ds.start_sample}, fs {ds.fs:g} Hz, "
          f"c {ds.sound_speed:.3f} m/s")
    return 0
