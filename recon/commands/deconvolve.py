"""``recon deconvolve D.h5 --out D_pd.h5``: pulse deconvolution of a dataset (Wiener by
default, or the INR)."""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path


DEFAULT_MAX_HOURS = 1.0
OUTPUT_SUFFIXES = {"out": (".h5",)}       # checked before any work (sonarsim.cli_common)

HELP = ("Pulse-deconvolve a sonar dataset (Wiener by default, or the neural INR); writes a "
        "dataset of deconvolved analytic signals that every solver reads.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..deconvolution import INR_HELP, RENAMED, INRSettings
    d = INRSettings()
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5) with real waveforms")
    parser.add_argument("--out", type=Path, required=True, help="output dataset (.h5)")
    parser.add_argument("--method", choices=("wiener", "inr"), default=None,
                        help="wiener (default): frequency-domain Wiener filter with λ from the "
                             "noise level, seconds per scan; inr: the paper's neural "
                             "deconvolution, minutes per 1 000 pings (giving any INR setting "
                             "selects it). Why Wiener is the default: docs/reconstruction.md")
    parser.add_argument("--pings", default=None, metavar="START:STOP[:STEP]",
                        help="deconvolve only this slice of the pings")
    parser.add_argument("--wiener-lambda", type=float, default=None, metavar="L",
                        help="Wiener regulariser λ in units of |P(f)|² (default: noise "
                             "variance / reflectivity variance, estimated from the data)")
    g = parser.add_argument_group("INR settings")
    for f in dataclasses.fields(INRSettings):
        kind = int if "int" in str(f.type) else float
        g.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=kind, default=None,
                       help=f"{INR_HELP[f.name]} (default {getattr(d, f.name)})")
    for old in RENAMED:                 # the old names: one line naming the new one
        g.add_argument("--" + old.replace("_", "-"), action=_Renamed, help=argparse.SUPPRESS)
    parser.add_argument("--max-hours", type=float, default=DEFAULT_MAX_HOURS, metavar="H",
                        help="refuse an INR run whose estimated wall time on this machine's "
                             f"cores exceeds H hours (default {DEFAULT_MAX_HOURS:g}; the "
                             "estimate is printed before the fit)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class _Renamed(argparse.Action):
    """An option that was renamed: refused at parse time (one-line usage error, exit 2)."""

    def __init__(self, option_strings, dest, **kwargs):
        kwargs.pop("nargs", None)
        super().__init__(option_strings, dest="_renamed_" + dest, nargs="?", **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from ..deconvolution import renamed_setting
        parser.error(renamed_setting(option_string.lstrip("-").replace("-", "_"), option=True))


def inr_settings_given(args: argparse.Namespace) -> dict:
    """The INR settings given on the command line ({field: value}; the others are None)."""
    from ..deconvolution import INRSettings
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(INRSettings)
            if getattr(args, f.name) is not None}


def chosen_method(args: argparse.Namespace, given: dict) -> str:
    """``--method``, else 'inr' when INR settings are given, else 'wiener' (the default);
    settings of the other method are refused in one line (InputError), not ignored."""
    from sonarsim.errors import InputError
    method = args.method or ("inr" if given else "wiener")
    if method == "wiener" and given:
        names = ", ".join("--" + k.replace("_", "-") for k in given)
        raise InputError(f"INR settings ({names}) apply to --method inr only")
    if method == "inr" and args.wiener_lambda is not None:
        raise InputError("--wiener-lambda applies to --method wiener only")
    return method


def run(args: argparse.Namespace) -> int:
    from sonarsim.dataset import SonarDataset
    from sonarsim.errors import InputError
    from .. import deconvolution
    from . import _common
    given = inr_settings_given(args)
    settings = deconvolution.INRSettings(**given)
    if given:                   # checked first: a bad value is named before a method clash
        settings.validate()
    method = chosen_method(args, given)
    if not (args.max_hours > 0 and math.isfinite(args.max_hours)):
        raise InputError(f"--max-hours: must be a positive number of hours, got {args.max_hours!r}")
    ds = SonarDataset.read(args.dataset, transients=False)
    idx = _common.parse_slice(args.pings, ds.n_pings)
    if idx is not None:
        ds = ds.select(idx)
    from sonarsim.atomic import check_free_space
    # the output: the dataset with complex64 instead of float32 waveforms
    check_free_space(args.out, ds.nbytes() + ds.waveforms.size * 4, "the deconvolved dataset")
    out = deconvolution.deconvolve(ds, method, wiener_lambda=args.wiener_lambda,
                                   inr_settings=settings, progress=not args.no_progress,
                                   max_hours=args.max_hours)
    out.meta["deconvolution_settings"]["dataset"] = str(args.dataset)
    out.write(args.out)
    info = out.meta["deconvolution_settings"]
    tail = (f"loss {info['loss_first'][0]:.4g} -> {info['loss_last'][0]:.4g} (first batch), "
            f"{info['seconds']:.1f} s" if method == "inr"
            else f"lambda {info['lambda']:.4g}")
    print(f"wrote {args.out}: {method} deconvolution of {out.n_pings} pings x "
          f"{out.n_samples} samples; {tail}")
    return 0
