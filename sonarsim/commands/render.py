"""``sonarsim render SCENE --poses POSES --out T.h5``: energy transients of a scene.

Writes a transients file (per-bounce histograms over round-trip path length; schema in
docs/formats.md) chunk by chunk (:func:`sonarsim.render.render_to_file`): memory holds one
chunk of poses (a budget of 768 MiB of histogram buffers), whatever the number of poses;
the file (N·B·T·4 bytes: 9.3 GB for the 54 000-pose scan at 3 bounces over the reference
window) is written under a temporary name and renamed when complete.
"""
from __future__ import annotations

import argparse

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


def _check_resources(scene, poses, settings, out, box) -> None:
    """Refuse, before rendering, a render whose file cannot fit on the output's disk or
    whose chunk buffers cannot fit in memory (one line each)."""
    import shutil

    from .. import limits
    from ..render import chunk_memory, path_window
    window = path_window(scene, poses, fs=settings.fs, oversample=settings.oversample,
                         sound_speed=settings.sound_speed, path_range=settings.path_range,
                         box=box)
    per_pose = settings.bounces * window.n_bins
    size = f"{len(poses)} poses x {settings.bounces} bounces x {window.n_bins} bins"
    file_bytes = len(poses) * per_pose * 4
    free = shutil.disk_usage(out.resolve().parent).free
    if file_bytes > free:
        raise InputError(f"the transients file needs {limits.gib(file_bytes)} ({size}) but "
                         f"{out.resolve().parent} has {limits.gib(free)} free; render "
                         f"fewer poses or bins (--path-range, --oversample)")
    chunk, need = chunk_memory(len(poses), settings.paths_per_pose, settings.bounces,
                               window.n_bins, settings.chunk_size)
    limits.check_memory(need, "the transient buffers of one chunk",
                        f"{chunk} poses x {settings.bounces} bounces x {window.n_bins} bins",
                        "lower --chunk-size, --bounces or the number of bins")


def settings_from_args(args: argparse.Namespace, beams: dict):
    """The checked :class:`sonarsim.render.RenderSettings` of the command line."""
    from ..render import RenderSettings
    return RenderSettings(
        paths_per_pose=args.paths_per_pose, bounces=args.bounces, fs=args.fs,
        oversample=args.oversample, sound_speed=args.sound_speed,
        path_range=None if args.path_range is None else tuple(args.path_range),
        seed=args.seed, beams=beams, bounce1=args.bounce1_estimator, amplitude=args.amplitude,
        surface_spacing=args.surface_spacing, speckle_seed=args.speckle_seed,
        chunk_size=args.chunk_size).validate()


def run(args: argparse.Namespace) -> int:
    from .. import limits
    from ..geometry import trajectory
    from ..render import make_integrator, render_to_file
    from ..scene import load_scene
    from ..threads import dr_threads

    check_common(args)
    if args.bounces is None:
        args.bounces = 1 if args.reference_parity else 3
    beams = beams_from_args(args)
    settings = settings_from_args(args, beams)
    limits.check_fs(args.fs)
    spec = load_scene(args.scene)
    poses = parity_poses(args, trajectory(args.poses, box=spec.box))
    scene = spec.to_mitsuba()
    make_integrator(settings)            # the plugin checks the beams before any work
    _check_resources(scene, poses, settings, args.out, spec.box)
    meta = dict(scene=spec.name, scene_source=spec.source, poses=str(args.poses),
                **parity_meta(args))
    with dr_threads(args.threads):
        out, shape, window = render_to_file(scene, poses, args.out, settings, meta=meta,
                                            box=spec.box, progress=not args.no_progress)
    size = 4 * shape[0] * shape[1] * shape[2]
    print(f"wrote {out}: {shape[0]} pings x {shape[1]} bounces x {shape[2]} bins "
          f"({size / 2**20:.1f} MiB), path {window.path_start:.4f}..{window.path_end:.4f} m")
    return 0
