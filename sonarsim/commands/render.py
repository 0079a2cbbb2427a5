"""``sonarsim render SCENE --poses POSES --out T.h5``: energy transients of a scene.

Writes a transients file (per-bounce histograms over round-trip path length; schema in
docs/formats.md) atomically. The whole file is assembled in memory: N·B·T·4 bytes (the
54 000-pose scan at 3 bounces is 9.3 GB); for long scans use ``sonarsim simulate
--keep-transients``, which streams.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import InputError

HELP = "Render per-bounce energy transients (path-length histograms) of a scene for a set of poses."

MEMORY_NOTE_BYTES = 4 * 2**30


def add_scene_and_pose_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    from ..geometry import TRAJECTORY_HELP
    parser.add_argument("scene", metavar="SCENE",
                        help="scene TOML file or the name of a shipped scene (sphere, cube, ...)")
    parser.add_argument("--poses", required=True, metavar="POSES", help=TRAJECTORY_HELP)
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.h5", help=out_help)


PARITY_HELP = ("match the reference simulation (REFERENCE_SPEC §6): isotropic TX, RX cone 25° "
               "aimed at (0, 0, 0.09) m, bounce 1 only; conflicts with the beam options "
               "(differences that remain: docs/simulation.md)")


def add_render_arguments(parser: argparse.ArgumentParser, *, bounces_help: str) -> None:
    """Options shared by ``render`` and ``simulate``: sampling, window, physics, beams."""
    from ..render import DEFAULT_SOUND_SPEED
    g = parser.add_argument_group("rendering")
    g.add_argument("--paths-per-pose", type=int, default=10_000, metavar="N",
                   help="Monte-Carlo paths per pose (default 10000)")
    g.add_argument("--bounces", type=int, default=None, metavar="B",
                   help=f"render bounces 1..B ({bounces_help})")
    g.add_argument("--oversample", type=int, default=20, metavar="K",
                   help="path-length bins per sample period (default 20, as the reference)")
    g.add_argument("--sound-speed", type=float, default=DEFAULT_SOUND_SPEED, metavar="C",
                   help=f"speed of sound in m/s (default {DEFAULT_SOUND_SPEED})")
    g.add_argument("--fs", type=float, default=100e3, metavar="HZ",
                   help="sample rate in Hz (default 100e3)")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    g.add_argument("--chunk-size", type=int, default=None, metavar="N",
                   help="poses per kernel launch (default: from a memory budget)")
    g.add_argument("--threads", type=int, default=None, metavar="N",
                   help="Dr.Jit threads for rendering (default: all cores; results do not "
                        "depend on it, see docs/simulation.md)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    b = parser.add_argument_group("beams")
    for end in ("tx", "rx"):
        b.add_argument(f"--{end}-beam", choices=("cone", "piston", "isotropic"), default=None,
                       help=f"{end.upper()} beam pattern (default cone)")
        b.add_argument(f"--{end}-beamwidth", type=float, default=None, metavar="DEG",
                       help=f"{end.upper()} full beamwidth in degrees (default 30; piston: "
                            "half-power width)")
    b.add_argument("--isotropic", action="store_true",
                   help="isotropic TX and RX (no beam pattern)")
    b.add_argument("--reference-parity", action="store_true", help=PARITY_HELP)


def beams_from_args(args: argparse.Namespace) -> dict:
    """The ``beams`` mapping of :func:`sonarsim.render.render` from the beam options."""
    if args.reference_parity:
        from ..render import REFERENCE_PARITY_BEAMS
        for option in ("isotropic", "tx_beam", "tx_beamwidth", "rx_beam", "rx_beamwidth"):
            if getattr(args, option) not in (None, False):
                raise InputError(f"--reference-parity sets the beams; it contradicts "
                                 f"--{option.replace('_', '-')}")
        return dict(REFERENCE_PARITY_BEAMS)
    beams = {}
    for end in ("tx", "rx"):
        kind = getattr(args, f"{end}_beam")
        width = getattr(args, f"{end}_beamwidth")
        if args.isotropic:
            if kind not in (None, "isotropic"):
                raise InputError(f"--isotropic contradicts --{end}-beam {kind}")
            kind = "isotropic"
        if kind is not None:
            beams[f"{end}_beam"] = kind
        if width is not None:
            if not 0 < width < 180:
                raise InputError(f"--{end}-beamwidth must be in (0, 180) degrees, got {width}")
            beams[f"{end}_beamwidth"] = width
    return beams


def check_common(args: argparse.Namespace) -> None:
    """Range checks of the shared options (one-line InputError)."""
    for name in ("paths_per_pose", "oversample"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.bounces is not None and args.bounces < 1:
        raise InputError(f"--bounces must be >= 1, got {args.bounces}")
    if not 0 <= args.seed < 2**32:
        raise InputError(f"--seed must be in [0, 2^32), got {args.seed}")
    for name in ("sound_speed", "fs"):
        if not getattr(args, name) > 0:
            raise InputError(f"--{name.replace('_', '-')} must be positive")
    if args.chunk_size is not None and args.chunk_size < 1:
        raise InputError(f"--chunk-size must be >= 1, got {args.chunk_size}")
    if args.threads is not None and args.threads < 1:
        raise InputError(f"--threads must be >= 1, got {args.threads}")
    if not args.out.parent.is_dir():
        raise InputError(f"{args.out}: output directory does not exist")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_and_pose_arguments(parser, "output transients file (.h5)")
    parser.add_argument("--path-range", type=float, nargs=2, default=None,
                        metavar=("LMIN", "LMAX"),
                        help="round-trip path-length window in m, used as given (default: "
                             "the reference's crop window of the scene box for these poses, "
                             "shifted by half a bin so that bins 0, K, 2K, ... are centred on "
                             "the sample times)")
    add_render_arguments(parser, bounces_help="default 3; 1 with --reference-parity")


def parity_poses(args: argparse.Namespace, poses):
    """``poses``, with RX boresights aimed at the reference's target under --reference-parity."""
    if not args.reference_parity:
        return poses
    from ..render import reference_parity_poses
    return reference_parity_poses(poses)


def parity_meta(args: argparse.Namespace) -> dict:
    """Free-form metadata recording --reference-parity (empty without it)."""
    if not args.reference_parity:
        return {}
    from ..render import REFERENCE_RX_TARGET
    return {"reference_parity": True, "rx_target": list(REFERENCE_RX_TARGET)}


def _check_memory(scene, poses, args, box) -> None:
    """Refuse a render whose transients cannot fit in memory (one line, not a MemoryError)."""
    import os
    from ..render import path_window
    window = path_window(scene, poses, fs=args.fs, oversample=args.oversample,
                         sound_speed=args.sound_speed, path_range=args.path_range, box=box)
    need = len(poses) * args.bounces * window.n_bins * 4
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return
    if need > 0.8 * total:
        raise InputError(f"the transients need {need / 2**30:.1f} GiB ({len(poses)} poses x "
                         f"{args.bounces} bounces x {window.n_bins} bins) but this machine has "
                         f"{total / 2**30:.1f} GiB; render fewer poses, or use `sonarsim "
                         f"simulate --keep-transients`, which streams to disk")


def run(args: argparse.Namespace) -> int:
    from ..geometry import trajectory
    from ..render import render
    from ..scene import load_scene
    from ..simulate import dr_threads

    check_common(args)
    if args.bounces is None:
        args.bounces = 1 if args.reference_parity else 3
    spec = load_scene(args.scene)
    poses = parity_poses(args, trajectory(args.poses, box=spec.box))
    beams = beams_from_args(args)
    scene = spec.to_mitsuba()
    _check_memory(scene, poses, args, spec.box)
    with dr_threads(args.threads):
        transients = render(scene, poses, paths_per_pose=args.paths_per_pose,
                            bounces=args.bounces, fs=args.fs, oversample=args.oversample,
                            sound_speed=args.sound_speed, path_range=args.path_range,
                            seed=args.seed, chunk_size=args.chunk_size, beams=beams,
                            box=spec.box, progress=not args.no_progress)
    transients.meta.update(scene=spec.name, scene_source=spec.source, poses=str(args.poses),
                           **parity_meta(args))
    transients.write(args.out)
    size = transients.transients.nbytes
    print(f"wrote {args.out}: {transients.n_pings} pings x {transients.n_bounces} bounces x "
          f"{transients.n_bins} bins ({size / 2**20:.1f} MiB), path "
          f"{transients.path_start:.4f}..{transients.path_end:.4f} m", file=sys.stderr)
    return 0
