"""Options shared by the reconstruction subcommands (grid, ping selection, output).

The rules behind them live in the library, where ``sonarsim batch`` and the Python API
reach them too: the grid rule in :func:`recon.grid.grid_from_options`, the checks before
any large array exists (grid memory, all-zero pulse, data coverage) in :mod:`recon.checks`.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError

from ..checks import BYTES_PER_VOXEL, check_grid, check_signal
from ..grid import DEFAULT_VOXEL_SIZE, Grid, box_bounds, grid_from_options, scene_box_of


#: Bytes a voxel takes in a volume file (complex64).
VOLUME_BYTES_PER_VOXEL = 8


def add_dataset_and_grid(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5) written by sonarsim")
    parser.add_argument("--out", type=Path, required=True, help="output volume (.h5)")
    add_grid_and_pings(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_grid_and_pings(parser: argparse.ArgumentParser, what: str = "voxel-centre") -> None:
    """--bounds, --shape, --voxel-size (the grid rule: recon.grid.grid_from_options) and
    --pings; ``what`` names the grid in the help (e.g. "image grid's voxel-centre")."""
    parser.add_argument("--bounds", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                        help=f"{what} bounds in metres (default: the dataset's scene box, "
                             "else the simulator's box x,y in [-0.2,0.2], z in [0,0.3])")
    parser.add_argument("--shape", type=int, nargs=3, metavar=("NX", "NY", "NZ"),
                        help="voxels per axis (default: from --voxel-size)")
    parser.add_argument("--voxel-size", type=float, default=DEFAULT_VOXEL_SIZE,
                        help=f"voxel pitch in metres when --shape is not given (default {DEFAULT_VOXEL_SIZE})")
    parser.add_argument("--pings", default=None, metavar="START:STOP[:STEP]",
                        help="use only this slice of the pings (e.g. ':43200' = the first 43 200)")


def parse_slice(text: str | None, n: int) -> np.ndarray | None:
    if text is None:
        return None
    parts = text.split(":")
    try:
        if len(parts) > 3:
            raise ValueError
        args = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise InputError(f"--pings: expected START:STOP[:STEP], got {text!r}") from None
    if len(args) == 1:
        index = args[0]
        if index is None:
            raise InputError(f"--pings: expected START:STOP[:STEP] or one ping, got {text!r}")
        if not -n <= index < n:
            raise InputError(f"--pings {text!r}: ping {index} does not exist (the dataset "
                             f"has {n}: 0 .. {n - 1})")
        return np.array([index % n])
    if len(args) == 3 and args[2] is not None and args[2] <= 0:
        raise InputError(f"--pings {text!r}: STEP must be a positive integer")
    idx = np.arange(n)[slice(*args)]
    if len(idx) == 0:
        raise InputError(f"--pings {text!r} selects no pings (the dataset has {n})")
    return idx


def load_dataset(args, refuse_silence: str | None = None):
    """The dataset of ``args.dataset`` with the ``--pings`` selection, after checking that its
    waveforms fit in memory and that its pulse is not all zero (all-zero waveforms: a warning,
    or an InputError with ``refuse_silence`` as the reason)."""
    from sonarsim import limits
    from sonarsim.dataset import KIND_DATASET, SonarDataset, inspect
    with inspect(args.dataset, expected=KIND_DATASET) as (_, fields):
        n, t = fields["waveforms"].shape
        itemsize = fields["waveforms"].dtype.itemsize
    n_sel = n if args.pings is None else len(parse_slice(args.pings, n))
    # The file's waveforms, the selected copy and the float64 matched-filter input.
    limits.check_memory(n * t * itemsize + n_sel * t * (itemsize + 8),
                        f"reading {args.dataset}", f"{n} pings x {t} samples",
                        "select fewer pings with --pings")
    ds = SonarDataset.read(args.dataset)
    check_signal(ds, args.dataset, refuse_silence=refuse_silence)
    idx = parse_slice(args.pings, ds.n_pings)
    return ds if idx is None else ds.select(idx)


def grid_from_args(args, dataset, *, bytes_per_voxel: float = BYTES_PER_VOXEL,
                   volume_out: bool = True) -> Grid:
    """The grid of ``--bounds``/``--shape``/``--voxel-size`` (:func:`recon.grid.grid_from_options`
    over the dataset's scene box), checked against the memory limit and against the dataset's
    recorded window (:func:`recon.checks.check_grid`); with ``volume_out`` (``--out`` is the
    volume), ``--out``'s file system must hold the volume (complex64, 8 bytes a voxel) before
    any work, so that a long fit does not end on a full disk."""
    grid = grid_from_options(box_bounds(scene_box_of(dataset)), args.bounds,
                             args.shape, args.voxel_size)
    grid = check_grid(dataset, grid, bytes_per_voxel)
    if volume_out and getattr(args, "out", None) is not None:
        from sonarsim.atomic import check_free_space
        check_free_space(args.out, VOLUME_BYTES_PER_VOXEL * grid.size, "the volume")
    return grid


def write_volume(vol, args, summary: str) -> int:
    """Record the dataset a volume came from, write it to ``--out`` and say so (exit 0)."""
    vol.params["dataset"] = str(args.dataset)
    vol.write(args.out)
    print(f"wrote {args.out}: {summary}")
    return 0
