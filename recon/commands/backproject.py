"""``recon backproject``: coherent (or incoherent) time-domain backprojection of a dataset."""
from __future__ import annotations

import argparse

from . import _common

HELP = "Backproject a sonar dataset onto a voxel grid (delay-and-sum of the matched-filtered signal)."

# Peak bytes of a run (see memory_estimate): per voxel, the Dr.Jit coordinates, |v|² and
# accumulators (6 float32), the real/imaginary results, their complex128 sum and the
# complex64 volume; per upsampled sample of a ping block, the upsampled complex128 signal and
# its spectrum, the complex64 copy, the 4-float interpolation buffer and its Dr.Jit copy
# (on the CPU up to four blocks are alive: two prepared ahead, the running one, the last).
BYTES_PER_VOXEL = 24 + 8 + 16 + 8
BYTES_PER_UPSAMPLED_SAMPLE = 16 + 16 + 8 + 16 + 2 * 16


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


def memory_estimate(n_pings: int, n_samples: int, grid, upsample: int) -> tuple[int, str]:
    """(peak bytes, how they are made up) of backprojecting n_pings x n_samples onto grid."""
    from .. import backprojection
    block = min(n_pings, 4 * getattr(backprojection, "PINGS_PER_BLOCK", 256))
    nx, ny, nz = grid.shape
    voxels = nx * ny * nz
    per_block = block * n_samples * upsample * BYTES_PER_UPSAMPLED_SAMPLE
    need = voxels * BYTES_PER_VOXEL + per_block
    detail = (f"{nx} x {ny} x {nz} voxels x {BYTES_PER_VOXEL} bytes + {block} pings x "
              f"{n_samples} samples x upsample {upsample} x {BYTES_PER_UPSAMPLED_SAMPLE} bytes")
    return need, detail


def run(args: argparse.Namespace) -> int:
    from sonarsim import limits

    from .. import backprojection
    limits.check_upsample(args.upsample)
    ds = _common.load_dataset(args)
    grid = _common.grid_from_args(args, ds, bytes_per_voxel=BYTES_PER_VOXEL)
    need, detail = memory_estimate(ds.n_pings, ds.n_samples, grid, args.upsample)
    limits.check_memory(need, "backprojection", detail,
                        "use a smaller grid, a smaller --upsample or fewer --pings")
    vol = backprojection.solve(ds, grid, upsample=args.upsample, interpolation=args.interpolation,
                               incoherent=args.incoherent, tx_beam_mask=args.beam_mask,
                               per_ping_sound_speed=not args.mean_sound_speed,
                               progress=not args.no_progress)
    return _common.write_volume(vol, args, f"backprojection of {ds.n_pings} pings on "
                                           f"{grid.shape} voxels")
