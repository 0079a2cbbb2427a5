"""Options shared by the reconstruction subcommands (grid, ping selection, output)."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError

from ..grid import Grid, scene_box_of

DEFAULT_VOXEL_SIZE = 0.0032   # metres; the reference's simulated-scene pitch (REFERENCE_SPEC §1.5)


def add_dataset_and_grid(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5) written by sonarsim")
    parser.add_argument("--out", type=Path, required=True, help="output volume (.h5)")
    parser.add_argument("--bounds", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help="voxel-centre bounds in metres (default: the dataset's scene box, "
                             "else the simulator's box x,y in [-0.2,0.2], z in [0,0.3])")
    parser.add_argument("--shape", type=int, nargs=3, metavar=("NX", "NY", "NZ"),
                        help="voxels per axis (default: from --voxel-size)")
    parser.add_argument("--voxel-size", type=float, default=DEFAULT_VOXEL_SIZE,
                        help=f"voxel pitch in metres when --shape is not given (default {DEFAULT_VOXEL_SIZE})")
    parser.add_argument("--pings", default=None, metavar="START:STOP[:STEP]",
                        help="use only this slice of the pings (e.g. ':43200' = the first 43 200)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def parse_slice(text: str | None, n: int) -> np.ndarray | None:
    if text is None:
        return None
    parts = text.split(":")
    try:
        if len(parts) == 1:
            return np.array([int(parts[0])])
        if len(parts) > 3:
            raise ValueError
        args = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise InputError(f"--pings: expected START:STOP[:STEP], got {text!r}") from None
    idx = np.arange(n)[slice(*args)]
    if len(idx) == 0:
        raise InputError(f"--pings {text!r} selects no pings (the dataset has {n})")
    return idx


def load_dataset(args):
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(args.dataset)
    idx = parse_slice(args.pings, ds.n_pings)
    return ds if idx is None else ds.select(idx)


def grid_from_args(args, dataset) -> Grid:
    if args.bounds is not None:
        bounds = np.asarray(args.bounds, dtype=np.float64).reshape(3, 2)
    else:
        box = scene_box_of(dataset)
        bounds = np.stack([np.asarray(box.lo, float), np.asarray(box.hi, float)], axis=1)
    if args.shape is not None:
        shape = tuple(args.shape)
    else:
        if not args.voxel_size > 0:
            raise InputError(f"--voxel-size: must be positive, got {args.voxel_size}")
        shape = tuple(int(round((hi - lo) / args.voxel_size)) + 1 for lo, hi in bounds)
    return Grid(bounds, shape)
