"""``sonarsim export-openstb``: a sonar dataset → openSTB's result format (Zarr)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "Write a sonar dataset in openSTB's result format (Zarr baseband pressure)."
OUTPUTS = ()            # a Zarr directory: checked by the exporter itself (--force)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5)")
    parser.add_argument("--out", type=Path, required=True, metavar="R.zarr",
                        help="output Zarr directory")
    parser.add_argument("--baseband-frequency", type=float, default=None, metavar="HZ",
                        help="carrier removed for the baseband (default: the pulse's mean "
                             "frequency)")
    parser.add_argument("--sample-rate", type=float, default=None, metavar="HZ",
                        help="baseband sample rate: fs divided by a whole number, wide enough "
                             "for the pulse's band (default: fs, lossless)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out")


def run(args: argparse.Namespace) -> int:
    from ..dataset import SonarDataset
    from ..importers.openstb import write_openstb

    ds = SonarDataset.read(args.dataset, transients=False)
    out = write_openstb(ds, args.out, baseband_frequency=args.baseband_frequency,
                        sample_rate=args.sample_rate, force=args.force)
    import zarr
    root = zarr.open_group(str(out), mode="r")
    print(f"wrote {out}: pressure {tuple(root['pressure'].shape)} (pings, receivers, samples), "
          f"baseband {root.attrs['baseband_frequency']:g} Hz, sample rate "
          f"{root.attrs['sample_rate']:g} Hz")
    return 0
