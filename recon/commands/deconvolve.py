"""``recon deconvolve D.h5 --out D_pd.h5``: pulse deconvolution of a dataset (INR or Wiener)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = ("Pulse-deconvolve a sonar dataset (neural INR or Wiener); writes a dataset of "
        "deconvolved analytic signals that every solver reads.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..deconvolution import INRSettings
    d = INRSettings()
    parser.add_argument("dataset", type=Path, help="sonar dataset (.h5) with real waveforms")
    parser.add_argument("--out", type=Path, required=True, help="output dataset (.h5)")
    parser.add_argument("--method", choices=("inr", "wiener"), default="inr",
                        help="inr: the paper's neural deconvolution (default); wiener: "
                             "frequency-domain Wiener filter with λ from the noise level")
    parser.add_argument("--pings", default=None, metavar="START:STOP[:STEP]",
                        help="deconvolve only this slice of the pings")
    parser.add_argument("--wiener-lambda", type=float, default=None, metavar="L",
                        help="Wiener regulariser λ in units of |P(f)|² (default: noise "
                             "variance / reflectivity variance, estimated from the data)")
    g = parser.add_argument_group("INR settings")
    g.add_argument("--iterations", type=int, default=d.iterations,
                   help=f"Adam iterations per batch of pings (default {d.iterations})")
    g.add_argument("--pings-per-inr", type=int, default=d.pings_per_inr,
                   help=f"pings per network (default {d.pings_per_inr}, one AirSAS rotation)")
    g.add_argument("--lr", type=float, default=d.lr, help=f"initial learning rate (default {d.lr})")
    g.add_argument("--lr-final", type=float, default=d.lr_final,
                   help=f"final learning rate of the exponential decay (default {d.lr_final})")
    g.add_argument("--sparsity", type=float, default=d.sparsity,
                   help=f"weight of mean|w| (default {d.sparsity})")
    g.add_argument("--phase", type=float, default=d.phase,
                   help=f"weight of the phase-smoothness term (default {d.phase})")
    g.add_argument("--levels", type=int, default=d.n_levels,
                   help=f"hash-grid levels (default {d.n_levels})")
    g.add_argument("--log2-hashmap-size", type=int, default=d.log2_hashmap_size,
                   help=f"log2 of the entries per hash level (default {d.log2_hashmap_size})")
    g.add_argument("--width", type=int, default=d.width, help=f"MLP width (default {d.width})")
    g.add_argument("--hidden-layers", type=int, default=d.hidden_layers,
                   help=f"MLP hidden layers (default {d.hidden_layers})")
    g.add_argument("--seed", type=int, default=d.seed, help=f"seed (default {d.seed})")
    g.add_argument("--band-db", type=float, default=d.band_db,
                   help="fit the data only where the pulse spectrum is within this many dB "
                        f"of its peak ('inf' = full band; default {d.band_db:g})")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from sonarsim.dataset import SonarDataset
    from .. import deconvolution
    from . import _common
    settings = deconvolution.INRSettings(
        pings_per_inr=args.pings_per_inr, iterations=args.iterations, lr=args.lr,
        lr_final=args.lr_final, sparsity=args.sparsity, phase=args.phase,
        n_levels=args.levels, log2_hashmap_size=args.log2_hashmap_size, width=args.width,
        hidden_layers=args.hidden_layers, seed=args.seed, band_db=args.band_db)
    if args.method == "inr":
        settings.validate()
    ds = SonarDataset.read(args.dataset, transients=False)
    idx = _common.parse_slice(args.pings, ds.n_pings)
    if idx is not None:
        ds = ds.select(idx)
    out = deconvolution.deconvolve(ds, args.method, wiener_lambda=args.wiener_lambda,
                                   inr_settings=settings, progress=not args.no_progress)
    out.meta["deconvolution_settings"]["dataset"] = str(args.dataset)
    out.write(args.out)
    info = out.meta["deconvolution_settings"]
    tail = (f"loss {info['loss_first'][0]:.4g} -> {info['loss_last'][0]:.4g} (first batch), "
            f"{info['seconds']:.1f} s" if args.method == "inr"
            else f"lambda {info['lambda']:.4g}")
    print(f"wrote {args.out}: {args.method} deconvolution of {out.n_pings} pings x "
          f"{out.n_samples} samples; {tail}")
    return 0
