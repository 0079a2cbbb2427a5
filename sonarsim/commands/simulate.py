"""``sonarsim simulate SCENE --poses POSES --out D.h5``: a simulated sonar dataset.

Render -> sum bounces -> convolve with the pulse at fs·oversample -> decimate to fs ->
optional noise at ``--snr-db``; see :mod:`sonarsim.simulate`. Streams chunk by chunk into
``D.h5.partial``; if the run is interrupted, the same command resumes it (``--restart``
starts over).
"""
from __future__ import annotations

import argparse

from ..errors import InputError
from ._render_common import (add_render_arguments, add_scene_and_pose_arguments,
                             beams_from_args, check_common, parity_meta, parity_poses)

HELP = "Simulate a sonar dataset (waveforms, pulse, geometry, ground truth) of a scene."
OUTPUT_EXISTS_OK = True   # run() resumes a partial output, reports a finished one (--force)
EPILOG = ("Fidelity: every pose is rendered as two independent half-estimates; their "
          "difference measures the Monte-Carlo noise after matched filtering, stored as meta "
          "mc_snr_db (with --snr-db also effective_snr_db: the added noise tops the Monte-Carlo "
          "noise up to the requested total). Amplitude models and when to use which: "
          "docs/simulation.md.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..signals import PULSE_HELP
    parser.epilog = EPILOG
    add_scene_and_pose_arguments(parser, "output sonar dataset (.h5)")
    s = parser.add_argument_group("signal")
    s.add_argument("--pulse", default="lfm-20k", metavar="PULSE",
                   help=f"transmitted pulse: {PULSE_HELP} (default lfm-20k)")
    s.add_argument("--pulse-samples", type=int, default=None, metavar="N",
                   help="keep only the first N samples of a measured pulse file (the reference "
                        "uses 100)")
    s.add_argument("--snr-db", type=float, default=None, metavar="X",
                   help="add white Gaussian noise at this SNR in dB (signal power = mean square "
                        "of the noiseless waveforms over their non-silent samples); "
                        "default: no noise")
    s.add_argument("--bounce-set", default=None, metavar="LIST",
                   help="bounces summed into the waveforms, e.g. '1' or '1,2' "
                        "(default: all rendered)")
    s.add_argument("--keep-transients", action="store_true",
                   help="also store the rendered transients in the dataset")
    s.add_argument("--restart", action="store_true",
                   help="discard the partial output of an interrupted run instead of resuming it")
    s.add_argument("--mc-snr-db", type=float, default=None, metavar="X",
                   help="Monte-Carlo SNR after matched filtering to reach (default 30 unless "
                        "--paths-per-pose or --surface-spacing is given): a pilot on a few "
                        "poses chooses the sampling density; the dataset records the "
                        "measured value (meta mc_snr_db)")
    add_render_arguments(parser, bounces_help="default: the largest of --bounce-set, "
                                               f"else {DEFAULT_BOUNCES} (single scattering, "
                                               "as the reference's simulated data; bounces "
                                               ">= 2 cost more for the same --mc-snr-db, "
                                               "see docs/simulation.md)",
                         paths_default=None,
                         paths_help="default: chosen for --mc-snr-db; the two "
                                    "half-estimates get half each")


# Single scattering by default: the reference simulated bounce 1 only, and bounces >= 2
# (about 1.6 % of the energy after matched filtering on the bunny) cost several times more
# rendering for the same measured Monte-Carlo SNR (docs/simulation.md).
DEFAULT_BOUNCES = 1


def parse_bounce_set(text: str | None) -> tuple[int, ...] | None:
    """'1,2' -> (1, 2); None -> None (InputError for anything else)."""
    if text is None:
        return None
    try:
        values = tuple(sorted({int(t) for t in text.replace(" ", "").split(",") if t}))
    except ValueError:
        raise InputError(f"--bounce-set must be a comma-separated list of bounces, got '{text}'") from None
    if not values or values[0] < 1:
        raise InputError(f"--bounce-set must list bounces >= 1, got '{text}'")
    return values


def _check_before_pulse(args: argparse.Namespace) -> None:
    """--fs and an LFM's duration within bounds before the pulse is generated."""
    from .. import limits
    limits.check_fs(args.fs)
    parts = str(args.pulse).split(":")
    if parts[0].lower() == "lfm" and len(parts) >= 4:
        try:
            duration = float(parts[3])
        except ValueError:
            return                       # the pulse parser reports it
        limits.check_pulse_length(round(duration * args.fs), args.fs, f"pulse {args.pulse}")


def _preflight(args: argparse.Namespace, spec, poses, settings) -> bool:
    """The library's checks before any work (:func:`sonarsim.simulate.preflight`), then
    the output: True when ``--out`` already holds this very run (reported, nothing to
    do). An existing other file needs ``--force``."""
    from .. import outputs
    from ..identity import digest
    from ..simulate import preflight
    preflight(spec, poses, settings)
    request = digest(spec, poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight,
                     {k: v for k, v in vars(settings).items()
                      if k not in ("chunk_size", "threads", "log")})
    settings.extra_meta["request_id"] = request
    if args.out.exists() and not args.force:
        if outputs.finished_request(args.out, request):
            print(f"{args.out}: already complete (same scene, poses and settings); nothing "
                  "to do (--force renders it again)")
            return True
        raise InputError(f"--out {args.out}: file exists (not this run's result); pass "
                         "--force to replace it")
    return False


def run(args: argparse.Namespace) -> int:
    from ..geometry import trajectory
    from ..scene import load_scene
    from ..signals import pulse_from_spec
    from ..simulate import SimulationSettings, simulate

    check_common(args)
    _check_before_pulse(args)
    bounce_set = parse_bounce_set(args.bounce_set)
    beams = beams_from_args(args)
    if args.reference_parity:
        from ..render import REFERENCE_BOUNCES
        if bounce_set not in (None, REFERENCE_BOUNCES):
            raise InputError(f"--reference-parity sums bounce 1 only; it contradicts "
                             f"--bounce-set {args.bounce_set}")
        bounce_set = REFERENCE_BOUNCES
    bounces = args.bounces or (max(bounce_set) if bounce_set else DEFAULT_BOUNCES)
    if args.pulse_samples is not None and args.pulse_samples < 2:
        raise InputError(f"--pulse-samples must be >= 2, got {args.pulse_samples}")
    spec = load_scene(args.scene)
    poses = parity_poses(args, trajectory(args.poses, box=spec.box))
    settings = SimulationSettings(
        pulse=pulse_from_spec(args.pulse, args.fs, args.pulse_samples), snr_db=args.snr_db,
        paths_per_pose=args.paths_per_pose, bounces=bounces, bounce_set=bounce_set,
        oversample=args.oversample, sound_speed=args.sound_speed, seed=args.seed,
        beams=beams, keep_transients=args.keep_transients,
        chunk_size=args.chunk_size, threads=args.threads, mc_snr_db=args.mc_snr_db,
        surface_spacing=args.surface_spacing, amplitude=args.amplitude,
        speckle_seed=args.speckle_seed, bounce1=args.bounce1_estimator,
        extra_meta={"poses": str(args.poses), **parity_meta(args)})
    if _preflight(args, spec, poses, settings):
        return 0
    out = simulate(spec, poses, args.out, settings, resume=not args.restart,
                   progress=not args.no_progress)
    from ..dataset import inspect
    with inspect(out) as (_, fields):
        meta = fields["meta"]
    noise = ("noiseless" if args.snr_db is None
             else f"effective SNR {meta.get('effective_snr_db', float('nan')):.1f} dB")
    print(f"wrote {out}: {len(poses)} pings, {noise}, Monte-Carlo SNR "
          f"{meta.get('mc_snr_db', float('nan')):.1f} dB after matched filtering "
          f"({(meta.get('sampling') or {}).get('sampling', '?')}), pulse {settings.pulse.spec}")
    return 0
