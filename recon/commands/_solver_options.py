"""Command-line options of ``recon gd`` and ``recon nbp``, derived from
:class:`recon.solver.SolverSettings` (one option per field: names, types, choices and help
come from the dataclass and :data:`recon.solver.HELP`)."""
from __future__ import annotations

import argparse
import dataclasses

from . import _common

# Extra spellings kept for compatibility with earlier releases.


def _type_of(field):
    hint = str(field.type)
    if "bool" in hint:
        return bool
    if "int" in hint:
        return int
    if "float" in hint:
        return float
    return str


def add_arguments(parser: argparse.ArgumentParser, network: bool) -> None:
    from ..solver import (CHECKPOINT_EVERY, CHOICES, DEFAULT_PRESET, HELP, PRESETS,
                          SolverSettings, applies_to, settings_for)
    base = settings_for(DEFAULT_PRESET[network], network=network)
    _common.add_dataset_and_grid(parser)
    frozen = DEFAULT_PRESET[network]
    parser.add_argument("--preset", default=frozen,
                        help=f"named settings, several joined by '+': {', '.join(PRESETS)} "
                             f"(default {frozen}: the frozen defaults, docs/reconstruction.md); "
                             "explicit options override it")
    for f in dataclasses.fields(SolverSettings):
        if not applies_to(f.name, network):
            continue
        flag = "--" + f.name.replace("_", "-")
        names = (flag,)
        kind = _type_of(f)
        text = f"{HELP.get(f.name, '')} (default {getattr(base, f.name)})"
        if kind is bool:
            parser.add_argument(*names, dest=f.name, action=argparse.BooleanOptionalAction,
                                default=None, help=text)
        elif f.name in CHOICES:
            parser.add_argument(*names, dest=f.name, choices=CHOICES[f.name], default=None, help=text)
        elif f.name == "lr_final":
            parser.add_argument(*names, dest=f.name, type=_float_or_none, default=None,
                                help=text + "; 'none' = constant")
        else:
            parser.add_argument(*names, dest=f.name, type=kind, default=None, help=text)
    parser.add_argument("--checkpoint", default=None, help="checkpoint file (.npz), written atomically")
    parser.add_argument("--checkpoint-every", type=int, default=CHECKPOINT_EVERY,
                        help="iterations between checkpoints")
    parser.add_argument("--resume", action="store_true",
                        help="continue from --checkpoint if it exists (same dataset, grid, settings)")


_NONE = object()


def _float_or_none(text):
    return _NONE if text.lower() == "none" else float(text)


def overrides(args) -> dict:
    """The settings given on the command line (None = not given)."""
    from ..solver import SolverSettings
    out = {}
    for f in dataclasses.fields(SolverSettings):
        v = getattr(args, f.name, None)
        if v is not None:
            out[f.name] = None if v is _NONE else v
    return out


def run(args, network: bool) -> int:
    import contextlib

    from sonarsim import outputs
    from sonarsim.errors import InputError
    from .. import solver
    if args.resume and not args.checkpoint:
        raise InputError("--resume needs --checkpoint FILE")
    if args.checkpoint_every < 1:
        raise InputError(f"--checkpoint-every: must be >= 1, got {args.checkpoint_every}")
    kw = overrides(args)
    # Reject bad values before the (possibly large) dataset is read.
    settings = solver.settings_for(args.preset, network=network, **kw)
    solver.resources.check_ranges(settings, network)
    if args.checkpoint is not None:
        # never replace an existing file without --force (a resumed checkpoint is expected
        # to exist), and never a file that is not a checkpoint (the input dataset, say)
        outputs.check_output(args.checkpoint, force=bool(getattr(args, "force", False)),
                             option="--checkpoint", exists_ok=args.resume)
        solver.check_checkpoint_path(args.checkpoint, args.resume)
    ds = _common.load_dataset(args)
    bytes_per_voxel = (solver.resources.NBP_BYTES_PER_VOXEL if network
                       else solver.resources.GD_BYTES_PER_VOXEL)
    grid = _common.grid_from_args(args, ds, bytes_per_voxel=bytes_per_voxel)
    solver.check_resources(grid, settings, network)
    method = "nbp" if network else "gd"
    with (outputs.output_lock(args.checkpoint) if args.checkpoint is not None
          else contextlib.nullcontext()):
        vol = solver.solve(ds, grid, network=network, method=method, preset=args.preset,
                           checkpoint=args.checkpoint, checkpoint_every=args.checkpoint_every,
                           resume=args.resume, progress=not args.no_progress, **kw)
    what = "neural backprojection" if network else "gradient descent"
    cut = (f"{vol.params.get('solid_level', settings.solid_threshold):.3g} of the peak"
           + (f" = {settings.solid_threshold:g} x the Otsu level"
              if settings.solid_threshold_mode == "otsu" else "")
           + (f", |σ| smoothed by {settings.solid_blur:g} voxels" if settings.solid_blur > 0 else "")
           + (f", boundary smoothed by {settings.solid_smooth:g} voxels"
              if settings.solid_smooth > 0 else ""))
    solid = (f"; exported the solid occupancy ({vol.params['solid_voxels']} voxels, threshold "
             f"{cut}; --output field for the field)"
             if "solid_voxels" in vol.params else "")
    tenths = vol.params["data_loss_by_tenth"]
    trend = (f"; data loss {tenths[0]:.4g} -> {tenths[-1]:.4g} (means of the first and last "
             "tenth of the steps)" if len(tenths) > 1 else "")
    return _common.write_volume(
        vol, args, f"{what}, {settings.iterations} iterations on {grid.shape} voxels, final "
                   f"loss {vol.params['final_loss']:.4g} (data {vol.params['final_data_loss']:.4g})"
                   + trend + solid)
