"""``sonarsim data [NAME]``: the data shipped with sonarsim (:mod:`sonarsim.data`).

Without NAME it lists the shipped files (size and path); with NAME it prints that file's
absolute path, for use in a shell: ``recon backproject "$(sonarsim data
small_features_cutout_5k.h5)" ...``. Provenance and licences: docs/data.md.
"""
from __future__ import annotations

import argparse

from .. import data

HELP = "List the shipped data (meshes, measured pulses, a real AirSAS scan) or print one's path."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", default=None,
                        help="a shipped file (e.g. bunny.obj, small_features_cutout_5k.h5, "
                             "pulses/airsas_20khz_measured.npy); omit to list them all")


def run(args: argparse.Namespace) -> int:
    if args.name is not None:
        print(data.path(args.name))
        return 0
    base = data.root()
    print(f"# shipped data in {base} (provenance: docs/data.md)")
    folders: dict[str, list[str]] = {}
    for name in data.names():
        if name.endswith(".csv"):               # raw LabVIEW scans: one line per folder
            folders.setdefault(name.rsplit("/", 1)[0], []).append(name)
        else:
            print(f"{(base / name).stat().st_size:>10,d}  {name}")
    for folder, files in folders.items():
        size = sum((base / f).stat().st_size for f in files)
        print(f"{size:>10,d}  {folder}/  ({len(files)} raw LabVIEW CSV files)")
    return 0
