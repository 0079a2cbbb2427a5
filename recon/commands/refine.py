"""``recon refine``: fit a mesh to a dataset's waveforms by gradient descent through the renderer."""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from sonarsim.errors import InputError

from . import _common

HELP = ("Refine a surface mesh (from a volume's iso-surface or a mesh file) by fitting the "
        "rendered waveforms to the dataset's (docs/refine.md).")
OUTPUTS = ("out", "history")
OUTPUT_SUFFIXES = {"history": (".json",)}
GROW_THRESHOLD = 0.2           # --grow-threshold's default
DEFAULT_WRAP = "0,3,6"     # a volume --init: three starts, the data keep one (docs/refine.md "Defaults")
DEFAULT_SMOOTH = "1"       # and the unwrapped start smoothed once more (docs/refine.md "Smoothed starts")
DEFAULT_SHRINK = "0.5"     # a volume --init: and the unwrapped start shrunk, then smoothed (docs/refine.md "Shrunk starts")
DEFAULT_SEAL = "0"         # off: the sealed start (where the scan does not see) was never kept
                           # by the misfit on the bunny (docs/refine.md "Sealed starts")
DEFAULT_UNEXPLAINED = 0.2  # and the kept start grown by the unexplained data (docs/refine.md
                           # "Grown from the unexplained data")
SEAT_BY_DEFAULT = True     # a volume --init's mesh continued down to the ground (docs/refine.md
                           # "Seated on the ground")

OPTION_HELP = {
    "affine_steps": "steps of the affine stage (the start scaled per axis about its base and "
                    "shifted, fitted to the envelopes) before the envelope stage; 0: none",
    "envelope_steps": "steps of stage 1 (matched-filter envelopes)",
    "waveform_steps": "steps of stage 2 (raw waveforms)",
    "lr": "Adam step in metres of latent displacement (cosine decay to 1/10 per stage)",
    "large_steps_lambda": "lambda of mi.ad.LargeSteps (larger = smoother updates)",
    "edge_length": "target edge length of the isotropic remeshing (m)",
    "remesh_every": "steps between remeshings (0: only the start mesh)",
    "bounces": "bounces rendered (1: single scattering; 2+: object-ground multiple scattering)",
    "surface_spacing": "the renderer's surface strata size (m)",
    "path_samples": "the renderer's path-length quantiles per stratum",
    "pings_per_batch": "pings rendered per step",
    "fit_albedo": "fit the object's albedo relative to the ground's",
    "oversample": "histogram bins per sample (default: the dataset's)",
    "seed": "order of the batches and the renderer's random numbers",
    "envelope_blur": "coarse to fine: smooth both envelopes by a Gaussian of this sigma (m of "
                     "one-way range) at the envelope stage's first step, shrinking to 0 at its last",
    "uniform_adam": "one Adam scale for all vertices (UniformAdam, Nicolet et al.); default: per coordinate",
    "support_steps": "steps of the support stage (per-patch albedo fit, then unsupported patches "
                     "removed) before the geometry stages; 0: none",
    "patch_size": "support stage: patch size (m)",
    "support_keep": "support stage: keep patches whose albedo is >= this x the area-weighted median",
    "support_lr": "support stage: Adam step of the log-albedos",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..refine import RefineSettings
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5) with received waveforms")
    parser.add_argument("--init", type=Path, required=True,
                        help="start: a volume (.h5, its iso-surface at --threshold) or a mesh "
                             "(.ply/.obj/.stl/.off)")
    parser.add_argument("--out", type=Path, required=True, help="refined mesh (.ply/.obj/.stl/.off)")
    parser.add_argument("--threshold", type=float, default=0.2,
                        help="iso-level of the normalised |volume| for a volume --init (default 0.2)")
    parser.add_argument("--z-min", type=float, default=0.005,
                        help="volume --init: clear voxels below this height (the ground's echo), m "
                             "(default 0.005)")
    parser.add_argument("--wrap", default=None, metavar="K[,K...]",
                        help="volume --init: seal the occupied set's tunnels and holes by a closing "
                             "with a ball of K x the range resolution c/2B of the dataset's pulse, "
                             "then fill what it encloses (0: off). Several values: refine from "
                             "each start and keep the result with the lowest envelope misfit (the "
                             "envelope stage's last pass; without that stage the final misfit) "
                             f"(default {DEFAULT_WRAP} for a volume, 0 for a mesh; docs/refine.md)")
    parser.add_argument("--smooth", default=DEFAULT_SMOOTH, metavar="L[,L...]",
                        help="also refine from the unwrapped start (the volume's iso-surface, or "
                             "the --init mesh) remeshed and smoothed by (I + L lap)^-1 (lap: the "
                             "graph Laplacian of its edges; it reaches about sqrt(2L) edges): "
                             "roughness a few edges wide, below the range resolution, that the "
                             "fit does not remove; one candidate per L, ranked with the --wrap "
                             f"starts by the envelope misfit; 0: none (default {DEFAULT_SMOOTH}; "
                             "docs/refine.md 'Smoothed starts')")
    parser.add_argument("--shrink", default=None, metavar="F[,F...]",
                        help="volume --init: also refine from the unwrapped start's occupied set "
                             "shrunk by F x the range resolution c/2B (thick bodies eroded by a "
                             "ball of that radius, the ground below counting as occupied; parts "
                             "thinner than about twice it that reach farther than twice it from "
                             "the eroded body kept as they are), then smoothed at "
                             "each --smooth level: the NBP solids are fat, their faces 5-8 mm "
                             "outside the object; one candidate per F and level, ranked with the "
                             "others by the envelope misfit; 0: none (default "
                             f"{DEFAULT_SHRINK} for a volume; docs/refine.md 'Shrunk starts')")
    parser.add_argument("--seal", default=None, metavar="Q[,Q...]",
                        help="volume --init: also refine from the unwrapped start's occupied set "
                             "with the empty voxels it hides from a fraction Q of the scan's "
                             "sensor positions added (channels and pockets inside the shell whose "
                             "walls no ping sees; a concavity open to the sensors is seen from "
                             "about half of them); one candidate per Q in (0, 1], ranked with "
                             f"the others by the envelope misfit; 0: none (default {DEFAULT_SEAL} "
                             "for a volume; docs/refine.md 'Sealed starts')")
    parser.add_argument("--grow", type=Path, default=None, metavar="VOLUME",
                        help="volume --init: a second volume of the same scan on the same grid "
                             "(e.g. `recon backproject`'s): its parts above --grow-threshold of "
                             "its peak (z >= --z-min) that touch the start's occupied set are "
                             "added to it before the wrap; use with --support-steps, which "
                             "keeps what the data supports. Experimental: it halved the Table-2 "
                             "bunny and made a held-out box 5x worse (docs/refine.md 'Grown starts')")
    parser.add_argument("--grow-threshold", type=float, default=GROW_THRESHOLD,
                        help="--grow: level of the second volume's normalised |value| (default 0.2)")
    parser.add_argument("--grow-beyond", type=float, default=0.0, metavar="K",
                        help="--grow: add only structure that reaches farther than K x the range "
                             "resolution c/2B from the start (and its bridge to the start), not "
                             "the layer hugging it (default 0: every touching part)")
    parser.add_argument("--grow-unexplained", type=float, default=None, metavar="LEVEL",
                        help="volume --init: after the candidates, image the part of the data "
                             "the kept one leaves unexplained (backprojection of the data where "
                             "its rendered envelope falls short, relative to the data's own "
                             "image), add its parts above LEVEL that reach beyond one range "
                             "resolution from the start and that both elevation halves of the "
                             "scan image, refine that start too and keep it if "
                             "its envelope misfit is lower; 0: off (default "
                             f"{DEFAULT_UNEXPLAINED:g}; docs/refine.md 'Grown from the "
                             "unexplained data')")
    parser.add_argument("--keep-candidates", action="store_true",
                        help="also write each start and its refinement next to --out, named "
                             "OUT_STEM.wrapK.start.EXT and OUT_STEM.wrapK.EXT, or "
                             "OUT_STEM.smoothL.start.EXT and OUT_STEM.smoothL.EXT, the grown one "
                             "OUT_STEM.grown-....EXT, and the unexplained image as a volume, "
                             "OUT_STEM.unexplained.h5 (e.g. to score every candidate); the "
                             "refined ones seated as --out is (--seat)")
    parser.add_argument("--pings", default=None, metavar="START:STOP[:STEP]",
                        help="fit only this slice of the pings (e.g. '::41')")
    parser.add_argument("--no-ground", action="store_true",
                        help="no ground in the model (default: the dataset's scene ground)")
    parser.add_argument("--seat", action=argparse.BooleanOptionalAction, default=None,
                        help="volume --init: continue the written mesh straight down to the "
                             "ground (z = 0): its vertices below the start's cut (--z-min plus "
                             "one voxel of --init, where the closing face the fit cannot see "
                             "lies, raised by as much as the fit lifted the mesh's lowest "
                             "vertex) moved onto it, as the volume solids reach the ground "
                             "(default: on for a volume --init with a ground in the model; "
                             "docs/refine.md 'Seated on the ground')")
    parser.add_argument("--history", type=Path, default=None,
                        help="also write the per-step record (loss, scale, albedo, time) as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--checkpoint", type=Path, default=None, metavar="DIR",
                        help="keep each candidate's refinement in DIR as it finishes "
                             "(DIR/LABEL.npz, .json; DIR/identity.json names the run)")
    parser.add_argument("--resume", action="store_true",
                        help="with --checkpoint: load the candidates already in DIR instead of "
                             "refining them again (same dataset, --init, settings and options)")
    base = RefineSettings()
    for f in dataclasses.fields(RefineSettings):
        flag = "--" + f.name.replace("_", "-")
        default = getattr(base, f.name)
        text = f"{OPTION_HELP.get(f.name, '')} (default {default})"
        if isinstance(default, bool):
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction,
                                default=None, help=text)
        else:
            kind = float if isinstance(default, float) else int
            parser.add_argument(flag, dest=f.name, type=kind, default=None, help=text)


def settings_from_args(args):
    from ..refine import RefineSettings
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(RefineSettings)
             if getattr(args, f.name, None) is not None}
    settings = RefineSettings(**given)
    settings.validate()
    return settings


def wrap_factors(text: str, option: str = "--wrap", name: str = "K") -> list[float]:
    """The ``--wrap`` (or ``--smooth``) values: one or more comma-separated numbers >= 0."""
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise InputError(f"{option}: expected {name}[,{name}...] with numbers >= 0, "
                         f"got {text!r}") from None
    if not all(0 <= v < float("inf") for v in values):
        raise InputError(f"{option}: must be >= 0, got {text}")
    return values


def smoothing_levels(text: str) -> list[float]:
    """The ``--smooth`` levels that add a candidate (those > 0, each once, in order)."""
    levels = []
    for v in wrap_factors(text, "--smooth", "L"):
        if v > 0 and v not in levels:
            levels.append(v)
    return levels


def start_candidates(args, dataset, edge_length: float, specs: list[dict]) -> list[dict]:
    """The starts to refine: ``specs`` (:func:`candidate_specs`) each with its ``"mesh"``: the
    :func:`initial_meshes` for ``smooth`` 0, and for a level L > 0 the unwrapped start smoothed
    by :func:`recon.refine.smoothed_start` (one :func:`initial_meshes` call makes them all); a
    spec with ``shrink`` F > 0 starts from the unwrapped start shrunk by F (one call per F),
    smoothed at its level; one with ``seal`` Q > 0 from the unwrapped start sealed at Q (one
    call per Q)."""
    from ..refine import smoothed_start

    def derived(spec) -> tuple[float, float]:
        """(shrink, seal) of a spec: (0, 0) for a plain wrapped or smoothed start."""
        return spec.get("shrink", 0.0), spec.get("seal", 0.0)
    plain = [spec for spec in specs if not any(derived(spec))]
    if args.init.suffix.lower() == ".h5":      # every wrap factor and 0 for the smoothed ones, once
        wraps = ",".join(repr(k) for k in dict.fromkeys(spec["wrap"] for spec in plain))
        args = argparse.Namespace(**{**vars(args), "wrap": wraps})
    starts = dict(initial_meshes(args, dataset)) if plain else {}
    unwrapped = argparse.Namespace(**{**vars(args), "wrap": "0"})
    changed = {key: initial_meshes(unwrapped, dataset, shrink=key[0], seal=key[1])[0][1]
               for key in dict.fromkeys(derived(spec) for spec in specs) if any(key)}

    def unsmoothed(spec):
        return changed[derived(spec)] if any(derived(spec)) else starts[spec["wrap"]]
    return [{**spec, "mesh": smoothed_start(unsmoothed(spec), spec["smooth"], edge_length)
             if spec["smooth"] else unsmoothed(spec)} for spec in specs]


def keeps_creases(args, start: dict) -> bool:
    """Whether ``start``'s remeshing keeps its sharp edges: the given mesh of a mesh
    ``--init`` does (a CAD model's box stays a box), a volume's iso-surface (its voxel steps)
    and the smoothed or grown starts do not (:func:`recon.refine.remesh`)."""
    return (args.init.suffix.lower() != ".h5" and not start["smooth"]
            and not start.get("grown"))


def candidate_specs(args) -> list[dict]:
    """``[{"wrap": K, "smooth": L, "shrink": F, "seal": Q}]``, the candidates ``--wrap``,
    ``--smooth``, ``--shrink``, ``--seal`` and ``--init`` ask for, before any mesh is made (so
    that bad values and existing outputs are refused first): the wrap factors (0 for a mesh),
    then one unwrapped start per smoothing level, then per shrink factor the shrunk start at
    each level (unsmoothed when there is none), then per seal quorum the sealed start
    (unsmoothed)."""
    levels, shrinks = smoothing_levels(args.smooth), shrink_factors(args)
    seals = seal_quorums(args)
    if args.init.suffix.lower() == ".h5":
        factors = wrap_factors(DEFAULT_WRAP if args.wrap is None else args.wrap)
    else:
        factors = [0.0]
    specs = ([{"wrap": k, "smooth": 0.0, "shrink": 0.0} for k in dict.fromkeys(factors)]
             + [{"wrap": 0.0, "smooth": lam, "shrink": 0.0} for lam in levels]
             + [{"wrap": 0.0, "smooth": lam, "shrink": f}
                for f in shrinks for lam in (levels or [0.0])])
    return ([{**spec, "seal": 0.0} for spec in specs]
            + [{"wrap": 0.0, "smooth": 0.0, "shrink": 0.0, "seal": q} for q in seals])


def occupancy_values(args, attr: str, name: str, default: str,
                     upper: float | None = None, noun: str = "value") -> list[float]:
    """The values > 0 of the option ``--attr``, each once: its value, else ``default`` for a
    volume ``--init``; each at most ``upper`` when given (``noun`` names them in the error);
    refused for a mesh (it has no occupied set)."""
    is_volume = args.init.suffix.lower() == ".h5"
    text = getattr(args, attr, None)
    if text is None:
        text = default if is_volume else "0"
    values = [v for v in dict.fromkeys(wrap_factors(text, f"--{attr}", name)) if v > 0]
    if upper is not None and any(v > upper for v in values):
        raise InputError(f"--{attr}: each {noun} must be in (0, {upper:g}] (0: none), got {text}")
    if values and not is_volume:
        raise InputError(f"--{attr} applies to a volume --init (.h5), not to a mesh")
    return values


def shrink_factors(args) -> list[float]:
    """The ``--shrink`` factors that add candidates (:func:`occupancy_values`, default
    :data:`DEFAULT_SHRINK`)."""
    return occupancy_values(args, "shrink", "F", DEFAULT_SHRINK)


def seal_quorums(args) -> list[float]:
    """The ``--seal`` quorums that add candidates (:func:`occupancy_values`, default
    :data:`DEFAULT_SEAL`), each <= 1."""
    return occupancy_values(args, "seal", "Q", DEFAULT_SEAL, upper=1.0, noun="quorum")


def initial_meshes(args, dataset, add=None, shrink: float = 0.0,
                   seal: float = 0.0) -> list[tuple[float, object]]:
    """[(wrap factor, start mesh)] of ``--init``: a volume's iso-surface wrapped at each
    ``--wrap`` factor × the range resolution of ``dataset``'s pulse, or a mesh file; ``add``:
    voxels (bool, the volume's grid) united with the volume's occupied set first; ``shrink``:
    the occupied set then shrunk by that factor × the range resolution
    (:func:`recon.refine.shrink_occupancy`); ``seal``: sealed at that quorum of the dataset's
    sensor positions, the midpoints of its transmitters and receivers
    (:func:`recon.refine.seal_occupancy`)."""
    from ..refine import range_resolution, start_mesh
    import numpy as np
    path = args.init
    if not np.isfinite(args.z_min):
        raise InputError(f"--z-min: must be a finite height in metres, got {args.z_min}")
    if not path.is_file():
        raise InputError(f"--init {path}: file not found")
    grow_path = getattr(args, "grow", None)
    if grow_path is None and (args.grow_threshold != GROW_THRESHOLD or args.grow_beyond != 0):
        raise InputError("--grow-threshold and --grow-beyond apply with --grow VOLUME; "
                         "without it they would be ignored")
    given = None if args.wrap is None else wrap_factors(args.wrap)
    if path.suffix.lower() == ".h5":
        factors = wrap_factors(DEFAULT_WRAP) if given is None else given
        from sonarsim.dataset import Volume
        vol = Volume.read(path)
        grow = None
        if grow_path is not None:
            if not grow_path.is_file():
                raise InputError(f"--grow {grow_path}: file not found")
            other = Volume.read(grow_path)
            if other.volume.shape != vol.volume.shape or not np.allclose(other.bounds, vol.bounds):
                raise InputError(f"--grow {grow_path}: its grid {other.volume.shape} over "
                                 f"{np.asarray(other.bounds).tolist()} differs from --init's "
                                 f"{vol.volume.shape} over {np.asarray(vol.bounds).tolist()}")
            if not 0 <= args.grow_threshold < 1:
                raise InputError(f"--grow-threshold: must be in [0, 1), got {args.grow_threshold}")
            if not (np.isfinite(args.grow_beyond) and args.grow_beyond >= 0):
                raise InputError(f"--grow-beyond: must be >= 0, got {args.grow_beyond}")
            grow = other.volume
        resolution = range_resolution(dataset.pulse, dataset.fs, dataset.sound_speed)
        beyond = args.grow_beyond * resolution
        sensors = 0.5 * (np.asarray(dataset.tx) + np.asarray(dataset.rx)) if seal > 0 else None
        return [(k, start_mesh(vol.volume, vol.bounds, args.threshold, args.z_min,
                               min_component=min_component(vol),
                               wrap_radius=k * resolution, grow=grow,
                               grow_threshold=args.grow_threshold, grow_beyond=beyond,
                               add=add, shrink_radius=shrink * resolution,
                               seal_quorum=seal, sensors=sensors))
                for k in factors]
    if any(given or ()) or grow_path is not None:
        raise InputError("--wrap and --grow apply to a volume --init (.h5), not to a mesh")
    from sonarsim.scene import load_mesh
    return [(0.0, load_mesh(path))]


def min_component(volume) -> float:
    """The smallest part of a start, in faces relative to its largest
    (:func:`recon.refine.start_mesh`): 0.05 for a field, whose isolated blobs are noise; 0 for
    an exported solid (``params['output'] == 'solid'``, `recon nbp`/`recon gd`), which dropped
    its floaters by its own rule and kept its separate parts on purpose (the Table-2 bunny's
    ear tips, 21 voxels after the solid's smoothing: its start's Chamfer² 1.57 × 10⁻⁴ without
    them, 7.8 × 10⁻⁵ with; docs/refine.md "A solid's parts"); its wrapped starts keep them
    too."""
    return 0.0 if dict(volume.params or {}).get("output") == "solid" else 0.05


def selection_misfit(candidate: dict) -> float:
    """The misfit that ranks ``--wrap`` candidates: the envelope stage's last-pass mean where it
    ran (the centimetre-scale verdict; the waveform misfit measures the carrier phase, which a
    surface centimetres off matches no better than one millimetres off), else the final misfit
    (docs/refine.md "Wrapped starts")."""
    e = candidate.get("envelope_misfit")
    return candidate["final_misfit"] if e is None else e


def choose_candidate(candidates: list[dict]) -> int:
    """Index of the candidate with the lowest :func:`selection_misfit` (the first on a tie)."""
    return min(range(len(candidates)), key=lambda i: selection_misfit(candidates[i]))


def candidate_label(candidate: dict) -> str:
    """``wrapK``, ``smoothL``, ``shrinkF-smoothL``, ``shrinkF`` or ``sealQ``, prefixed
    ``grown-`` for the start grown by the unexplained data: a candidate's name in file names and
    messages."""
    if candidate.get("smooth", 0):
        name = f"smooth{candidate['smooth']:g}"
    else:
        name = f"wrap{candidate['wrap']:g}"
    for key in ("shrink", "seal"):
        if candidate.get(key, 0):
            name = f"{key}{candidate[key]:g}" + (f"-{name}" if candidate.get("smooth", 0) else "")
    return f"grown-{name}" if candidate.get("grown", 0) else name


def unexplained_level(args) -> float:
    """The ``--grow-unexplained`` level: its value, else the default for a volume ``--init``
    and 0 (off) for a mesh."""
    is_volume = args.init.suffix.lower() == ".h5"
    level = args.grow_unexplained
    if level is None:
        return DEFAULT_UNEXPLAINED if is_volume else 0.0
    if not (0 <= level < 1):
        raise InputError(f"--grow-unexplained: must be in [0, 1), got {level}")
    if level > 0 and not is_volume:
        raise InputError("--grow-unexplained applies to a volume --init (.h5), not to a mesh")
    return float(level)


def grown_start(args, dataset, chosen: dict, result, settings, index, level: float):
    """(start, record): the kept candidate's start grown by the data it leaves unexplained
    (``{"wrap", "smooth", "grown", "mesh"}``, None when the unexplained image adds nothing) and
    what was found (``{"level", "share", "voxels_proposed", "voxels_added", "beyond_m",
    "split_elevation_deg", "image"}``, the image a :class:`~sonarsim.dataset.Volume` on
    ``--init``'s grid): the voxels of :func:`recon.unexplained.unexplained_image` (of the
    refined mesh ``result``) that :func:`recon.unexplained.grown_voxels` proposes at ``level``,
    in parts that both elevation halves image (:func:`recon.unexplained.consistent_parts`), are
    united with ``--init``'s occupied set, which then gets the kept start's wrap or
    smoothing."""
    import numpy as np
    from sonarsim.dataset import Volume

    from ..grid import Grid
    from ..refine import dataset_ground, range_resolution, smoothed_start
    from ..unexplained import (UNEXPLAINED_BEYOND, consistent_parts, grown_voxels,
                               residual_pings, unexplained_image)
    vol = Volume.read(args.init)
    index = np.arange(dataset.n_pings) if index is None else np.asarray(index)
    ground = None if args.no_ground else dataset_ground(dataset)
    n_pings = len(residual_pings(index))
    print(f"unexplained: rendering the kept candidate for {n_pings} pings and imaging what it "
          "leaves unexplained")
    found = unexplained_image(dataset, result.mesh,
                              1.0 if result.albedo is None else result.albedo,
                              Grid(vol.bounds, vol.volume.shape), index, settings, ground,
                              settings.seed)
    beyond = UNEXPLAINED_BEYOND * range_resolution(dataset.pulse, dataset.fs, dataset.sound_speed)
    proposed = grown_voxels(vol.volume, vol.bounds, args.threshold, args.z_min, found.image,
                            level, beyond)
    added = consistent_parts(proposed, found, level)
    print(f"unexplained: {found.share:.1%} of the data's envelope energy; {int(proposed.sum())} "
          f"voxels of its image above {level:g} of the data's peak reach beyond "
          f"{beyond * 1e3:.1f} mm of the start"
          + ("" if found.split_deg is None else
             f"; {int(added.sum())} of them in parts that both elevation halves image "
             f"(split at {found.split_deg:.1f} deg)"))
    record = {"level": level, "share": found.share, "voxels_proposed": int(proposed.sum()),
              "voxels_added": int(added.sum()), "beyond_m": beyond,
              "split_elevation_deg": found.split_deg,
              "image": Volume(volume=found.image.astype(np.complex64), bounds=vol.bounds,
                              method="unexplained",
                              params={"level": level, "share": found.share,
                                      "pings": n_pings})}
    if not added.any():
        return None, record
    smooth, shrink, seal = chosen["smooth"], chosen.get("shrink", 0.0), chosen.get("seal", 0.0)
    wrap = 0.0 if smooth or shrink or seal else chosen["wrap"]
    [(_, mesh)] = initial_meshes(argparse.Namespace(**{**vars(args), "wrap": repr(wrap)}),
                                 dataset, add=added, shrink=shrink, seal=seal)
    if smooth:
        mesh = smoothed_start(mesh, smooth, settings.edge_length)
    return {"wrap": chosen["wrap"], "smooth": smooth, "shrink": shrink, "seal": seal,
            "grown": level, "mesh": mesh}, record


def checkpoint_store(args, dataset, settings, specs: list, level: float):
    """The :class:`recon.refine_checkpoint.CandidateStore` of ``--checkpoint``: the run named
    by the dataset, ``--init``, the settings, the candidates ``specs`` and the options that
    decide their starts."""
    from ..refine_checkpoint import CandidateStore, file_digest, run_identity
    options = {"threshold": args.threshold, "z_min": args.z_min,
               "starts": [candidate_label(spec) for spec in specs],
               "grow_threshold": args.grow_threshold,
               "grow_beyond": args.grow_beyond, "grow_unexplained": level,
               "pings": args.pings, "no_ground": bool(args.no_ground),
               "grow": None if args.grow is None else file_digest(args.grow)}
    identity = run_identity(dataset, args.init, dataclasses.asdict(settings), options)
    return CandidateStore(args.checkpoint, identity, args.resume,
                          bool(getattr(args, "force", False)))


def unexplained_path(out: Path) -> Path:
    """Where ``--keep-candidates`` writes the unexplained image (``OUT_STEM.unexplained.h5``)."""
    return out.with_name(f"{out.stem}.unexplained.h5")


def candidate_paths(out: Path, candidate: dict) -> tuple[Path, Path]:
    """(start, refined) mesh paths of a candidate for ``--keep-candidates``."""
    stem = f"{out.stem}.{candidate_label(candidate)}"
    return out.with_name(f"{stem}.start{out.suffix}"), out.with_name(f"{stem}{out.suffix}")


def run(args: argparse.Namespace) -> int:
    if args.resume and args.checkpoint is None:
        raise InputError("--resume needs --checkpoint DIR")
    settings = settings_from_args(args)
    if args.out.suffix.lower() not in (".ply", ".obj", ".stl", ".off"):
        raise InputError(f"--out {args.out}: mesh format must be .ply, .obj, .stl or .off")
    ds = _common.load_dataset(argparse.Namespace(dataset=args.dataset, pings=None),
                              refuse_silence="there is nothing to fit")
    specs = candidate_specs(args)
    level = unexplained_level(args)
    if args.keep_candidates:
        from sonarsim.outputs import check_output
        named = {Path(args.out).resolve()} | ({Path(args.history).resolve()}
                                              if args.history is not None else set())
        grown_specs = [{**spec, "grown": level} for spec in specs] if level else []
        paths = [p for spec in specs + grown_specs for p in candidate_paths(args.out, spec)]
        for path in paths + ([unexplained_path(args.out)] if level else []):
            if path.resolve() in named:
                raise InputError(f"--keep-candidates: {path} is also another output")
            check_output(path, force=bool(getattr(args, "force", False)),
                         option="--keep-candidates", exists_ok=args.resume)
    if args.checkpoint is None:
        return refine_candidates(args, ds, settings, specs, level, None)
    from sonarsim.outputs import output_lock
    with output_lock(args.checkpoint):
        return refine_candidates(args, ds, settings, specs, level,
                                 checkpoint_store(args, ds, settings, specs, level))


def seat_height(args, dataset) -> float | None:
    """The height (m) below which a start's closing face lies, the ``base`` of
    :func:`recon.refine.seat_cut`, or None when ``--seat`` is off: ``--z-min`` plus one voxel
    of the ``--init`` volume (the face lies within a voxel of the cut,
    :func:`recon.refine.start_mesh`). On by default for a volume ``--init`` with a ground in
    the model; a mesh ``--init`` has no cut."""
    from sonarsim.dataset import Volume
    from sonarsim.dataset.volume import voxel_spacing

    from ..refine import dataset_ground
    is_volume = args.init.suffix.lower() == ".h5"
    seat = args.seat
    if seat is None:
        seat = (SEAT_BY_DEFAULT and is_volume and not args.no_ground
                and dataset_ground(dataset) is not None)
    if not seat:
        return None
    if not is_volume:
        raise InputError("--seat applies to a volume --init (.h5), whose start is cut at "
                         "--z-min; a mesh --init is written as fitted")
    vol = Volume.read(args.init)
    return float(args.z_min + voxel_spacing(vol.bounds, vol.volume.shape, single="zero")[2])


def refine_candidates(args, ds, settings, specs: list, level: float, store) -> int:
    """Refine every start of ``specs`` (then the grown one at ``level``), keep the one with
    the lowest envelope misfit, write ``--out`` (and ``--history``, ``--keep-candidates``);
    ``store``: the ``--checkpoint`` (:class:`recon.refine_checkpoint.CandidateStore`) or None."""
    from ..export import write_mesh
    from ..refine import seat_cut, seat_on_ground, solve
    starts = start_candidates(args, ds, settings.edge_length, specs)
    base = seat_height(args, ds)

    def seated(start, mesh) -> tuple:
        """(the mesh as written, the height below which its vertices were seated or None,
        how many)."""
        cut = None if base is None else seat_cut(start, mesh, base)
        if cut is None:
            return mesh, None, 0
        out, moved = seat_on_ground(mesh, cut)
        return out, cut, moved

    from ..checks import check_box_sees_data
    for start in starts:
        check_box_sees_data(ds, *start["mesh"].bounds, f"--init {args.init}: no part of the start mesh",
                            "is it in metres and in the dataset's frame? (nothing to fit)")
    index = _common.parse_slice(args.pings, ds.n_pings)
    candidates, results, fitted_from = [], [], []

    def refine_start(start: dict, several: bool) -> None:
        init, name = start["mesh"], candidate_label(start)
        if several:
            print(f"start {name}: {len(init.faces)} faces")
        res = None if store is None else store.load(name)
        if res is not None:
            print(f"start {name}: resumed from {store.directory}")
        else:
            res = solve(ds, init, settings, ping_index=index,
                        ground=None if args.no_ground else "dataset",
                        progress=not args.no_progress, log=print,
                        keep_creases=keeps_creases(args, start))
            if store is not None:
                store.save(name, res)
        candidates.append({"wrap": start["wrap"], "smooth": start["smooth"],
                           "shrink": start.get("shrink", 0.0),
                           "seal": start.get("seal", 0.0),
                           "grown": start.get("grown", 0.0),
                           "final_misfit": res.final_misfit, "faces": len(res.faces),
                           **{f"{s}_misfit": res.stage_misfit(s) for s in ("envelope", "waveform")},
                           "albedo": res.albedo,
                           "affine": None if res.affine is None else {
                               k: res.affine[k] for k in ("scale", "shift")}})
        if args.keep_candidates:           # after the fit: a failed one leaves no files
            start_path, refined_path = candidate_paths(args.out, start)
            write_mesh(start_path, init)
            write_mesh(refined_path, seated(init, res.mesh)[0])
        results.append(res)
        fitted_from.append(init)
        if several:
            env = candidates[-1]["envelope_misfit"]
            print(f"start {name}: envelope misfit "
                  f"{'-' if env is None else format(env, '.4f')}, final misfit {res.final_misfit:.4f}")

    several = len(starts) > 1 or level > 0
    for start in starts:
        refine_start(start, several)
    found = None
    if level > 0:
        best = choose_candidate(candidates)
        grown, found = grown_start(args, ds, candidates[best], results[best], settings, index,
                                   level)
        if args.keep_candidates:
            found["image"].write(unexplained_path(args.out))
        if grown is not None:
            refine_start(grown, several)
    best = choose_candidate(candidates)
    result, chosen = results[best], candidates[best]
    mesh, z_seat, moved = seated(fitted_from[best], result.mesh)
    write_mesh(args.out, mesh)
    if args.history is not None:
        from sonarsim.atomic import atomic_path
        with atomic_path(args.history) as tmp:
            tmp.write_text(json.dumps({"settings": result.settings, "albedo": result.albedo,
                                       "wrap": chosen["wrap"], "smooth": chosen["smooth"],
                                       "shrink": chosen["shrink"], "seal": chosen["seal"],
                                       "grown": chosen["grown"],
                                       "seat": None if z_seat is None else {
                                           "below_m": z_seat, "vertices_moved": moved},
                                       "unexplained": None if found is None else {
                                           k: v for k, v in found.items() if k != "image"},
                                       "candidates": candidates,
                                       "history": result.history}, indent=1, default=str))
    last = result.history[-1]
    albedo = "" if result.albedo is None else f", albedo {result.albedo:.3f} of the ground's"
    picked = f" (from the start {candidate_label(chosen)})" if len(candidates) > 1 else ""
    seat = ("" if z_seat is None else
            f"; {moved} vertices below {z_seat * 1e3:.1f} mm seated on the ground")
    print(f"wrote {args.out}: {len(result.faces)} faces after {len(result.history)} steps{picked}; "
          f"final {last['stage']} loss {last['loss']:.4f}, final misfit {result.final_misfit:.4f}"
          f"{albedo}{seat}")
    return 0
