"""``recon calibrate``: fit sound speed, a global time offset and a rig offset by autofocus."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from sonarsim.errors import InputError

from . import _common

HELP = ("Calibrate a scan: fit sound speed, a global time offset and a rig offset that make "
        "the backprojected image sharpest, by gradient (docs/differentiable.md).")
OUTPUTS = ("out", "corrected")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..calibrate import GROUPS
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5), e.g. a real scan")
    parser.add_argument("--out", type=Path, required=True,
                        help="the calibration found, with the focus before/after (.json)")
    parser.add_argument("--corrected", type=Path, default=None,
                        help="also write the corrected dataset (.h5): TX/RX moved, sound speed "
                             "changed, waveforms shifted by the time offset")
    parser.add_argument("--fit", default="time_offset",
                        help="free parameters, comma-separated, of: " + ", ".join(GROUPS)
                             + " (default time_offset: on a scan at one sonar height the focus "
                               "does not determine sound speed and rig offset, and the time "
                               "offset only for a known image height, docs/differentiable.md)")
    _common.add_grid_and_pings(parser, what="image grid's voxel-centre")
    parser.add_argument("--upsample", type=int, default=4,
                        help="FFT upsampling of the matched-filtered signal (default 4)")
    parser.add_argument("--mean-sound-speed", action="store_true",
                        help="ignore per-ping temperatures; start from the dataset's sound speed")
    parser.add_argument("--max-evaluations", type=int, default=60,
                        help="focus-and-gradient evaluations of L-BFGS-B, a hard limit: the "
                             "best focus evaluated is kept (default 60; the curvature adds 2 "
                             "per free parameter)")
    parser.add_argument("--no-curvature", action="store_true",
                        help="skip the curvature (conditioning) at the optimum (2 gradients per "
                             "free parameter)")
    parser.add_argument("--no-progress", action="store_true", help="no per-evaluation lines")


def run(args: argparse.Namespace) -> int:
    import logging
    import warnings

    from sonarsim import limits

    from .. import calibrate
    if args.out.suffix.lower() != ".json":
        raise InputError(f"--out {args.out}: the calibration is written as .json")
    if args.corrected is not None and args.corrected.suffix.lower() != ".h5":
        raise InputError(f"--corrected {args.corrected}: the corrected dataset is written as .h5")
    limits.check_upsample(args.upsample)
    free = calibrate.parse_free(args.fit)
    if args.max_evaluations < 1:
        raise InputError(f"--max-evaluations must be >= 1, got {args.max_evaluations}")
    ds = _common.load_dataset(args)
    grid = _common.grid_from_args(args, ds, bytes_per_voxel=calibrate.BYTES_PER_VOXEL,
                                  volume_out=False)
    log = None if args.no_progress else logging.getLogger("recon.calibrate").info
    result = calibrate.fit(ds, grid, free=free, upsample=args.upsample,
                           per_ping_sound_speed=not args.mean_sound_speed,
                           max_evaluations=args.max_evaluations,
                           curvature=not args.no_curvature, log=log)
    record = {"dataset": str(args.dataset), "pings": args.pings,
              "grid": {"bounds": grid.bounds.tolist(), "shape": list(grid.shape)},
              **result.as_dict()}
    for name in result.at_bounds:
        warnings.warn(f"{name} ended on its search bound: the focus kept rising, so this scan "
                      f"does not determine it (fix the image plane at the target's height, or "
                      f"fit fewer parameters)", stacklevel=1)
    from sonarsim.atomic import atomic_path
    with atomic_path(args.out) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=1))
    if args.corrected is not None:
        calibrate.apply(ds, result.calibration).write(args.corrected)
    print(f"wrote {args.out}: {result.calibration.describe()}; focus {result.focus_before:.4f} "
          f"-> {result.focus_after:.4f} ({100 * (result.focus_after / result.focus_before - 1):+.1f} %)")
    return 0
