"""Options shared by the reconstruction subcommands (grid, ping selection, output).

Before any large array exists the commands check what they are about to do:
:func:`check_grid_memory` refuses a grid whose voxels alone cannot fit (a memory estimate
in the style of :mod:`sonarsim.limits`), :func:`load_dataset` refuses a dataset whose pulse
is all zero (matched filtering would zero every echo), and :func:`check_grid_sees_data`
refuses a grid that no ping's recorded window reaches (``--bounds`` far from the scan, a
wrong ``start_sample``): each of these used to give an all-zero volume with exit 0.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError

from ..grid import Grid, scene_box_of

DEFAULT_VOXEL_SIZE = 0.0032   # metres; the reference's simulated-scene pitch (reference code geometry.py)


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


def load_dataset(args):
    """The dataset of ``args.dataset`` with the ``--pings`` selection, after checking that its
    waveforms fit in memory and that its pulse is not all zero."""
    from sonarsim import limits
    from sonarsim.dataset import SonarDataset, inspect
    with inspect(args.dataset) as (_, fields):
        n, t = fields["waveforms"].shape
        itemsize = fields["waveforms"].dtype.itemsize
    n_sel = n if args.pings is None else len(parse_slice(args.pings, n))
    # The file's waveforms, the selected copy and the float64 matched-filter input.
    limits.check_memory(n * t * itemsize + n_sel * t * (itemsize + 8),
                        f"reading {args.dataset}", f"{n} pings x {t} samples",
                        "select fewer pings with --pings")
    ds = SonarDataset.read(args.dataset)
    check_signal(ds, args.dataset)
    idx = parse_slice(args.pings, ds.n_pings)
    return ds if idx is None else ds.select(idx)


def check_signal(ds, label) -> None:
    """Refuse an all-zero pulse (InputError); warn about all-zero waveforms."""
    from .. import measurements
    deconvolved = getattr(measurements, "is_deconvolved", lambda d: False)(ds)
    if not deconvolved and not np.any(np.asarray(ds.pulse)):
        raise InputError(f"{label}: the dataset's pulse is all zero; matched filtering would "
                         "turn every echo into zeros (fix the pulse of the dataset)")
    if not np.any(np.asarray(ds.waveforms)):
        print(f"warning: {label}: every waveform sample is zero; the volume will be all zero",
              file=sys.stderr)


BYTES_PER_VOXEL = 16   # the least any solver needs: the complex64 result and its copy


def check_grid_memory(grid: Grid, bytes_per_voxel: float = BYTES_PER_VOXEL, extra: float = 0,
                      what: str = "the volume", detail: str = "") -> None:
    """Refuse a grid whose estimated memory exceeds the limit (one line, before allocating)."""
    from sonarsim import limits
    nx, ny, nz = grid.shape
    voxels = nx * ny * nz            # Python ints: no overflow for absurd shapes
    need = voxels * bytes_per_voxel + extra
    limits.check_memory(need, what, detail or f"{nx} x {ny} x {nz} voxels x "
                                              f"{bytes_per_voxel:g} bytes",
                        "use a coarser --voxel-size, a smaller --shape or tighter --bounds")


def _distance_to_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance [N] from points [N, 3] to the axis-aligned box [lo, hi] (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)


def _farthest_corner(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance [N] from points [N, 3] to the farthest corner of the box [lo, hi]."""
    return np.linalg.norm(np.maximum(np.abs(points - lo), np.abs(points - hi)), axis=1)


def check_grid_sees_data(ds, grid: Grid) -> None:
    """Refuse a grid that lies outside every ping's recorded window (InputError).

    For each ping the round-trip paths tx -> voxel -> rx over the grid's box lie within
    [d(tx, box) + d(rx, box), far(tx) + far(rx)]; sample k of a waveform is the path
    c·(start_sample + k)/fs. If these intervals are disjoint for every ping, no voxel can
    receive anything and the result would be an all-zero volume.
    """
    from .. import measurements
    lo, hi = grid.bounds[:, 0], np.where(np.asarray(grid.shape) > 1, grid.bounds[:, 1],
                                         grid.bounds[:, 0])
    tx, rx = np.asarray(ds.tx, float), np.asarray(ds.rx, float)
    near = _distance_to_box(tx, lo, hi) + _distance_to_box(rx, lo, hi)
    far = _farthest_corner(tx, lo, hi) + _farthest_corner(rx, lo, hi)
    c = measurements.sound_speeds(ds)
    k0, t = int(ds.start_sample), np.asarray(ds.waveforms).shape[1]
    first, last = c * k0 / ds.fs, c * (k0 + t - 1) / ds.fs
    if np.any((near <= last) & (far >= first)):
        return
    raise InputError(
        f"no voxel of the grid lies within what any ping recorded: round-trip paths to the "
        f"grid are {near.min():.3f} .. {far.max():.3f} m, the waveforms cover "
        f"{first.min():.3f} .. {last.max():.3f} m (samples {k0} .. {k0 + t - 1} at "
        f"{ds.fs:g} Hz); check --bounds and the dataset's start_sample "
        "(the volume would be all zero)")


def grid_from_args(args, dataset, *, bytes_per_voxel: float = BYTES_PER_VOXEL) -> Grid:
    """The grid of ``--bounds``/``--shape``/``--voxel-size``, checked against the memory
    limit and against the dataset's recorded window (see the module docstring)."""
    grid = _grid(args, dataset)
    check_grid_memory(grid, bytes_per_voxel)
    check_grid_sees_data(dataset, grid)
    return grid


def _grid(args, dataset) -> Grid:
    if args.bounds is not None:
        bounds = np.asarray(args.bounds, dtype=np.float64).reshape(3, 2)
    else:
        box = scene_box_of(dataset)
        bounds = np.stack([np.asarray(box.lo, float), np.asarray(box.hi, float)], axis=1)
    if args.shape is not None:
        shape = tuple(args.shape)
    else:
        if not (np.isfinite(args.voxel_size) and args.voxel_size > 0):
            raise InputError(f"--voxel-size: must be a positive finite number, got "
                             f"{args.voxel_size}")
        counts = [(hi - lo) / args.voxel_size for lo, hi in bounds]
        if not all(np.isfinite(n) and n < 1e12 for n in counts):
            raise InputError(f"--voxel-size {args.voxel_size:g} gives more than 10^12 voxels "
                             "along an axis")
        shape = tuple(int(round(n)) + 1 for n in counts)
    return Grid(bounds, shape)


def write_volume(vol, args, summary: str) -> int:
    """Record the dataset a volume came from, write it to ``--out`` and say so (exit 0)."""
    vol.params["dataset"] = str(args.dataset)
    vol.write(args.out)
    print(f"wrote {args.out}: {summary}")
    return 0
