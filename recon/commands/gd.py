"""``recon gd``: gradient descent on complex voxels through the ellipsoidal forward model."""
from __future__ import annotations

import argparse

from . import _common

HELP = "Reconstruct by gradient descent on complex voxels (Adam) through the ellipsoidal forward model."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..gradient_descent import PRESETS, GDSettings
    d = GDSettings()
    _common.add_dataset_and_grid(parser)
    a = parser.add_argument
    a("--preset", choices=sorted(PRESETS), default=None,
      help="the reference's model and priors for simulated ('sim': Lambertian, s_occ 500, sparsity 1, "
           "random init) or real AirSAS ('airsas': also smoothness 50, phase 0.1, 200 bins, scale 30, "
           "s_occ 1000) scenes; default: Lambertian + occlusion, no priors, from the scaled backprojection")
    a("--iterations", type=int, default=d.iterations, help=f"optimiser steps (default {d.iterations})")
    a("--seed", type=int, default=d.seed, help="random seed (ping/bin sampling, initialisation)")
    # Settings below default to the preset's (or GDSettings') value when not given.
    a("--lr", type=float, help=f"Adam learning rate (default {d.lr}, relative to the voxel scale "
                               "max |scaled backprojection| unless --lr-units absolute)")
    a("--lr-final", type=float, help=f"learning rate at the last iteration, exponential decay (default {d.lr_final})")
    a("--lr-units", choices=("relative", "absolute"),
      help="'relative' (default): --lr and --lr-final are fractions of max |scaled backprojection| "
           "per step; 'absolute': voxel units (targets are scaled to max --scale-factor)")
    a("--pings-per-iteration", type=int, help=f"pings per optimiser step (default {d.pings_per_iteration})")
    a("--bins-per-ping", type=int, help=f"range bins drawn per ping (reference max_weights; default {d.bins_per_ping})")
    a("--rays", type=int, dest="n_rays", help=f"rays in the TX cone per ping (default {d.n_rays})")
    a("--beamwidth", type=float, dest="beamwidth_deg", help=f"TX cone full angle, degrees (default {d.beamwidth_deg})")
    a("--data", choices=("matched", "analytic"),
      help="fit the matched-filtered analytic signal (default) or the raw waveform's analytic signal")
    a("--scale-factor", type=float, help=f"targets are normalised to max 1 then scaled by this (default {d.scale_factor})")
    a("--sparsity", type=float, help=f"sparsity weight (default {d.sparsity})")
    a("--smoothness", type=float, help=f"smoothness weight (default {d.smoothness})")
    a("--phase", type=float, help=f"phase-smoothness weight (default {d.phase})")
    a("--tv", type=float, help=f"total variation along rays weight (default {d.tv})")
    a("--reg-start", type=int, help=f"iteration from which the regularisers apply (default {d.reg_start})")
    a("--occlusion-scale", type=float, help=f"transmittance scale s_occ, 0 = off (default {d.occlusion_scale})")
    a("--lambertian", action=argparse.BooleanOptionalAction, default=None,
      help=f"Lambertian factor from the voxels' normals (default {'on' if d.lambertian else 'off'})")
    a("--init", choices=("bp", "random"),
      help="initial voxels: the backprojection scaled by its least-squares factor through the linear "
           "model (default) or tiny random values (as the reference)")
    a("--checkpoint", default=None, help="checkpoint file (.npz), written atomically")
    a("--checkpoint-every", type=int, default=500, help="iterations between checkpoints")
    a("--resume", action="store_true", help="continue from --checkpoint if it exists (same --iterations)")


_SETTINGS = ("lr", "lr_final", "lr_units", "lambertian", "pings_per_iteration", "bins_per_ping", "n_rays", "beamwidth_deg",
             "data", "scale_factor", "sparsity", "smoothness", "phase", "tv", "reg_start",
             "occlusion_scale", "init")


def run(args: argparse.Namespace) -> int:
    from .. import gradient_descent
    from sonarsim.errors import InputError
    if args.resume and not args.checkpoint:
        raise InputError("--resume needs --checkpoint FILE")
    if args.checkpoint_every < 1:
        raise InputError(f"--checkpoint-every: must be >= 1, got {args.checkpoint_every}")
    overrides = {k: getattr(args, k) for k in _SETTINGS if getattr(args, k) is not None}
    # Reject bad values before the (possibly large) dataset is read.
    gradient_descent.settings_for(args.preset, iterations=args.iterations, seed=args.seed, **overrides)
    ds = _common.load_dataset(args)
    grid = _common.grid_from_args(args, ds)
    vol = gradient_descent.solve(
        ds, grid, iterations=args.iterations, seed=args.seed, checkpoint=args.checkpoint,
        checkpoint_every=args.checkpoint_every, resume=args.resume, progress=not args.no_progress,
        preset=args.preset, **overrides)
    vol.params["dataset"] = str(args.dataset)
    vol.write(args.out)
    print(f"wrote {args.out}: gradient descent, {args.iterations} iterations on {grid.shape} voxels, "
          f"final loss {vol.params['final_loss']:.4g}")
    return 0
