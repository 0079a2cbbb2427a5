"""Command-line pieces shared by ``sonarsim render`` and ``sonarsim simulate``: scene and
pose arguments, sampling/physics/beam options, their range checks, and --reference-parity."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from ..signals import AIRSAS_FS


def add_scene_and_pose_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    from ..geometry import TRAJECTORY_HELP
    parser.add_argument("scene", metavar="SCENE",
                        help="scene TOML file or the name of a shipped scene (sphere, cube, ...)")
    parser.add_argument("--poses", required=True, metavar="POSES", help=TRAJECTORY_HELP)
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.h5", help=out_help)


PARITY_HELP = ("match the reference simulation (docs/simulation.md): isotropic TX, RX cone 25° "
               "aimed at (0, 0, 0.09) m, bounce 1 only; conflicts with the beam options "
               "(differences that remain: docs/simulation.md)")


def add_render_arguments(parser: argparse.ArgumentParser, *, bounces_help: str,
                         paths_help: str = "default 10000", paths_default: int | None = 10_000
                         ) -> None:
    """Options shared by ``render`` and ``simulate``: sampling, estimator, amplitude model,
    window, physics, beams."""
    from ..render import DEFAULT_SOUND_SPEED
    g = parser.add_argument_group("rendering")
    g.add_argument("--paths-per-pose", type=int, default=paths_default, metavar="N",
                   help=f"TX-cone Monte-Carlo paths per pose: bounces >= 2, and bounce 1 with "
                        f"--bounce1-estimator cone ({paths_help})")
    g.add_argument("--bounce1-estimator", choices=("surface", "cone"), default=None,
                   help="bounce-1 estimator: 'surface' (stratified quadrature over the "
                        "surfaces with shadow rays; the integrator's default) or 'cone' "
                        "(TX-cone path tracing, a cross-check)")
    g.add_argument("--surface-spacing", type=float, default=None, metavar="M",
                   help="strata size of the surface estimator in m (density 1/M^2; "
                        "default: the integrator's, or chosen for --mc-snr-db)")
    g.add_argument("--amplitude", choices=("intensity", "pressure", "coherent"),
                   default=None,
                   help="amplitude model: 'intensity' (energy histogram x pulse, the "
                        "reference's; default, and what --reference-parity selects), "
                        "'pressure' (b_T b_R / (2 pi r_T r_R) per scatterer, Lambertian) or "
                        "'coherent' (pressure with a seeded random phase per surface "
                        "scatterer: speckle); docs/simulation.md")
    g.add_argument("--speckle-seed", type=int, default=0, metavar="S",
                   help="seed of the coherent model's scatterer phases, independent of "
                        "--seed (default 0)")
    g.add_argument("--bounces", type=int, default=None, metavar="B",
                   help=f"render bounces 1..B ({bounces_help})")
    g.add_argument("--oversample", type=int, default=20, metavar="K",
                   help="path-length bins per sample period (default 20, as the reference)")
    g.add_argument("--sound-speed", type=float, default=DEFAULT_SOUND_SPEED, metavar="C",
                   help=f"speed of sound in m/s (default {DEFAULT_SOUND_SPEED})")
    g.add_argument("--fs", type=float, default=AIRSAS_FS, metavar="HZ",
                   help=f"sample rate in Hz (default {AIRSAS_FS:g})")
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
    """The ``beams`` mapping of :func:`sonarsim.render.render_poses` from the beam options."""
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
    """Checks of the shared options that only the command line has (one-line InputError):
    --reference-parity against --amplitude, the output directory. The values themselves
    are checked by the settings (:meth:`sonarsim.render.RenderSettings.validate`,
    :meth:`sonarsim.simulate.SimulationSettings.validate`), the one rule for the Python API,
    the command line and the batch."""
    if args.amplitude is None:
        args.amplitude = "intensity"
    elif args.reference_parity and args.amplitude != "intensity":
        raise InputError(f"--reference-parity selects --amplitude intensity; it contradicts "
                         f"--amplitude {args.amplitude}")
    if not args.out.parent.is_dir():
        raise InputError(f"{args.out}: output directory does not exist")


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
