"""``sonarsim render SCENE --poses POSES --out T.h5``: energy transients of a scene.

Writes a transients file (per-bounce histograms over round-trip path length; schema in
docs/formats.md) atomically. The whole file is assembled in memory: N·B·T·4 bytes (the
54 000-pose scan at 3 bounces is 9.3 GB); for long scans use ``sonarsim simulate
--keep-transients``, which streams.
"""
from __future__ import annotations

import argparse
import sys

from ._render_common import (add_render_arguments, add_scene_and_pose_arguments, beams_from_args,
                             check_common, parity_meta, parity_poses)

HELP = "Render per-bounce energy transients (path-length histograms) of a scene for a set of poses."

MEMORY_NOTE_BYTES = 4 * 2**30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_and_pose_arguments(parser, "output transients file (.h5)")
    parser.add_argument("--path-range", type=float, nargs=2, default=None,
                        metavar=("LMIN", "LMAX"),
                        help="round-trip path-length window in m, used as given (default: "
                             "the reference's crop window of the scene box for these poses, "
                             "shifted by half a bin so that bins 0, K, 2K, ... are centred on "
                             "the sample times)")
    add_render_arguments(parser, bounces_help="default 3; 1 with --reference-parity")


def _check_memory(scene, poses, args, box) -> None:
    """Refuse a render whose transients cannot fit in memory (one line, not a MemoryError)."""
    from ..render import path_window
    window = path_window(scene, poses, fs=args.fs, oversample=args.oversample,
                         sound_speed=args.sound_speed, path_range=args.path_range, box=box)
    from .. import limits
    need = len(poses) * args.bounces * window.n_bins * 4
    limits.check_memory(need, "the transients", f"{len(poses)} poses x {args.bounces} bounces "
                        f"x {window.n_bins} bins", "render fewer poses, or use `sonarsim "
                        "simulate --keep-transients`, which streams to disk")


def _estimator_kwargs(args: argparse.Namespace) -> dict:
    """Keyword arguments of :func:`sonarsim.render.render_poses` for the estimator and amplitude
    options (only those that differ from the defaults)."""
    wanted = {"bounce1": args.bounce1_estimator, "surface_spacing": args.surface_spacing,
              "amplitude": None if args.amplitude == "intensity" else args.amplitude,
              "speckle_seed": args.speckle_seed if args.amplitude == "coherent" else None}
    wanted = {k: v for k, v in wanted.items() if v is not None}
    return wanted


def run(args: argparse.Namespace) -> int:
    from ..geometry import trajectory
    from ..render import render_poses
    from ..scene import load_scene
    from ..threads import dr_threads

    check_common(args)
    if args.bounces is None:
        args.bounces = 1 if args.reference_parity else 3
    spec = load_scene(args.scene)
    poses = parity_poses(args, trajectory(args.poses, box=spec.box))
    beams = beams_from_args(args)
    scene = spec.to_mitsuba()
    from .. import limits
    limits.check_fs(args.fs)
    _check_memory(scene, poses, args, spec.box)
    estimator = _estimator_kwargs(args)
    with dr_threads(args.threads):
        transients = render_poses(scene, poses, paths_per_pose=args.paths_per_pose,
                                  **estimator, bounces=args.bounces, fs=args.fs,
                                  oversample=args.oversample, sound_speed=args.sound_speed,
                                  path_range=args.path_range, seed=args.seed,
                                  chunk_size=args.chunk_size, beams=beams, box=spec.box,
                                  progress=not args.no_progress)
    transients.meta.update(scene=spec.name, scene_source=spec.source, poses=str(args.poses),
                           **parity_meta(args))
    transients.write(args.out)
    size = transients.transients.nbytes
    print(f"wrote {args.out}: {transients.n_pings} pings x {transients.n_bounces} bounces x "
          f"{transients.n_bins} bins ({size / 2**20:.1f} MiB), path "
          f"{transients.path_start:.4f}..{transients.path_end:.4f} m", file=sys.stderr)
    return 0
