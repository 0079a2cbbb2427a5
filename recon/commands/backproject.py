"""``recon backproject``: coherent (or incoherent) time-domain backprojection of a dataset."""
from __future__ import annotations

import argparse

from . import _common

HELP = "Backproject a sonar dataset onto a voxel grid (delay-and-sum of the matched-filtered signal)."

def add_arguments(parser: argparse.ArgumentParser) -> None:
    _common.add_dataset_and_grid(parser)
    parser.add_argument("--incoherent", action="store_true", help="sum magnitudes instead of complex values")
    parser.add_argument("--upsample", type=int, default=5, help="FFT upsampling factor before interpolation (default 5)")
    parser.add_argument("--interpolation", choices=("linear", "nearest", "floor"), default="linear",
                        help="delay interpolation; 'floor' = the reference's truncation (default linear)")
    parser.add_argument("--beam-mask", type=float, default=None, metavar="DEG",
                        help="only voxels inside the TX cone of this full angle (degrees) around the boresight")
    parser.add_argument("--mean-sound-speed", action="store_true",
                        help="ignore per-ping temperatures; use the dataset's sound speed for every ping")


def run(args: argparse.Namespace) -> int:
    from .. import backprojection
    from sonarsim import limits
    limits.check_upsample(args.upsample)
    ds = _common.load_dataset(args)
    grid = _common.grid_from_args(args, ds, bytes_per_voxel=backprojection.BYTES_PER_VOXEL)
    backprojection.check_options(grid, ds, upsample=args.upsample,
                                 interpolation=args.interpolation, tx_beam_mask=args.beam_mask)
    vol = backprojection.solve(ds, grid, upsample=args.upsample, interpolation=args.interpolation,
                               incoherent=args.incoherent, tx_beam_mask=args.beam_mask,
                               per_ping_sound_speed=not args.mean_sound_speed,
                               progress=not args.no_progress)
    return _common.write_volume(vol, args, f"backprojection of {ds.n_pings} pings on "
                                           f"{grid.shape} voxels")
