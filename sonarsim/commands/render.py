"""``sonarsim render SCENE --poses POSES --out T.h5``: energy transients of a scene.

Writes a transients file (per-bounce histograms over round-trip path length; schema in
docs/formats.md) chunk by chunk (:func:`sonarsim.render.render_to_file`): memory holds one
chunk of poses (a budget of 768 MiB of histogram buffers), whatever the number of poses;
the file (N·B·T·4 bytes: 9.3 GB for the 54 000-pose scan at 3 bounces over the reference
window) is written under a temporary name and renamed when complete.
"""
from __future__ import annotations

import argparse
import sys

from ..errors import InputError
from ._render_common import (add_render_arguments, add_scene_and_pose_arguments, beams_from_args,
                             check_common, parity_meta, parity_poses)

HELP = "Render per-bounce energy transients (path-length histograms) of a scene for a set of poses."

def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_and_pose_arguments(parser, "output transients file (.h5)")
    parser.add_argument("--path-range", type=float, nargs=2, default=None,
                        metavar=("LMIN", "LMAX"),
                        help="round-trip path-length window in m, used as given (default: "
                             "the reference's crop window of the scene box for these poses, "
                             "shifted by half a bin so that bins 0, K, 2K, ... are centred on "
                             "the sample times)")
    add_render_arguments(parser, bounces_help="default 3; 1 with --reference-parity")


def _check_resources(scene, poses, args, box) -> None:
    """Refuse, before rendering, a render whose file cannot fit on the output's disk or
    whose chunk buffers cannot fit in memory (one line each)."""
    import shutil

    from .. import limits
    from ..render import chunk_memory, path_window
    window = path_window(scene, poses, fs=args.fs, oversample=args.oversample,
                         sound_speed=args.sound_speed, path_range=args.path_range, box=box)
    per_pose = args.bounces * window.n_bins
    size = f"{len(poses)} poses x {args.bounces} bounces x {window.n_bins} bins"
    file_bytes = len(poses) * per_pose * 4
    free = shutil.disk_usage(args.out.resolve().parent).free
    if file_bytes > free:
        raise InputError(f"the transients file needs {limits.gib(file_bytes)} ({size}) but "
                         f"{args.out.resolve().parent} has {limits.gib(free)} free; render "
                         f"fewer poses or bins (--path-range, --oversample)")
    chunk, need = chunk_memory(len(poses), args.paths_per_pose or 1, args.bounces,
                               window.n_bins, args.chunk_size)
    limits.check_memory(need, "the transient buffers of one chunk",
                        f"{chunk} poses x {args.bounces} bounces x {window.n_bins} bins",
                        "lower --chunk-size, --bounces or the number of bins")


def _estimator_kwargs(args: argparse.Namespace) -> dict:
    """Keyword arguments of :func:`sonarsim.render.render_to_file` for the estimator and amplitude
    options (only those that differ from the defaults)."""
    wanted = {"bounce1": args.bounce1_estimator, "surface_spacing": args.surface_spacing,
              "amplitude": None if args.amplitude == "intensity" else args.amplitude,
              "speckle_seed": args.speckle_seed if args.amplitude == "coherent" else None}
    wanted = {k: v for k, v in wanted.items() if v is not None}
    return wanted


def run(args: argparse.Namespace) -> int:
    from ..geometry import trajectory
    from ..render import render_to_file
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
    _check_resources(scene, poses, args, spec.box)
    estimator = _estimator_kwargs(args)
    meta = dict(scene=spec.name, scene_source=spec.source, poses=str(args.poses),
                **parity_meta(args))
    with dr_threads(args.threads):
        out, shape, window = render_to_file(
            scene, poses, args.out, meta=meta, paths_per_pose=args.paths_per_pose,
            **estimator, bounces=args.bounces, fs=args.fs, oversample=args.oversample,
            sound_speed=args.sound_speed, path_range=args.path_range, seed=args.seed,
            chunk_size=args.chunk_size, beams=beams, box=spec.box,
            progress=not args.no_progress)
    size = 4 * shape[0] * shape[1] * shape[2]
    print(f"wrote {out}: {shape[0]} pings x {shape[1]} bounces x {shape[2]} bins "
          f"({size / 2**20:.1f} MiB), path {window.path_start:.4f}..{window.path_end:.4f} m",
          file=sys.stderr)
    return 0
