"""``recon pfa``: polar-format (far-field Fourier-domain) reconstruction of a dataset."""
from __future__ import annotations

import argparse

from ..pfa import DEFAULT_BAND_DB, DEFAULT_TAPER, DEFAULT_WEIGHTS, WEIGHTS
from . import _common

HELP = ("Polar formatting: place each ping's spectrum at k = 2πf/c·(û_TX + û_RX) about a "
        "reference point and invert with a 3-D non-uniform FFT (far-field baseline).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _common.add_dataset_and_grid(parser)
    parser.add_argument("--reference-point", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="phase (motion-compensation) centre in metres (default: grid centre)")
    parser.add_argument("--patches", type=int, default=1, metavar="N",
                        help="sub-patch processing: N blocks per axis, each imaged about its "
                             "own centre (removes the far-field defocus away from the grid "
                             "centre; N³ non-uniform FFTs of all samples; default 1)")
    parser.add_argument("--weights", choices=WEIGHTS, default=DEFAULT_WEIGHTS,
                        help="polar-sample weighting: uniform = every sample alike "
                             "(backprojection's sum of the same data); density = |k|^D times "
                             "the aperture area per ping (the polar raster's Jacobian: sharper "
                             f"in range, without the object's low-frequency body; default "
                             f"{DEFAULT_WEIGHTS})")
    parser.add_argument("--band-db", type=float, default=DEFAULT_BAND_DB,
                        help="keep frequencies whose pulse power is within this many dB of "
                             f"the peak (default {DEFAULT_BAND_DB:g})")
    parser.add_argument("--taper", type=float, default=DEFAULT_TAPER,
                        help="Tukey window ratio over the band, 0 = none, 1 = Hann "
                             f"(default {DEFAULT_TAPER:g})")
    parser.add_argument("--eps", type=float, default=1e-6, help="finufft tolerance (default 1e-6)")
    parser.add_argument("--mean-sound-speed", action="store_true",
                        help="ignore per-ping temperatures; use the dataset's sound speed for every ping")


def run(args: argparse.Namespace) -> int:
    from .. import pfa
    ds = _common.load_dataset(args)
    grid = _common.grid_from_args(args, ds, bytes_per_voxel=pfa.BYTES_PER_VOXEL)
    pfa.check_options(grid, ds, reference_point=args.reference_point, band_db=args.band_db,
                      taper=args.taper, eps=args.eps, patches=args.patches, weights=args.weights)
    vol = pfa.solve(ds, grid, reference_point=args.reference_point, band_db=args.band_db,
                    taper=args.taper, eps=args.eps, patches=args.patches, weights=args.weights,
                    per_ping_sound_speed=not args.mean_sound_speed,
                    progress=not args.no_progress)
    return _common.write_volume(vol, args, f"polar formatting of {ds.n_pings} pings on "
                                           f"{grid.shape} voxels")
