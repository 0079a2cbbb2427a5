"""``recon nbp``: neural backprojection (hash-grid + MLP complex field, Reed et al. 2023)."""
from __future__ import annotations

import argparse

from . import _solver_options

HELP = ("Reconstruct by neural backprojection: a hash-grid + MLP complex field fitted through "
        "the ellipsoidal forward model (--preset cpu | reference).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _solver_options.add_arguments(parser, network=True)


def run(args: argparse.Namespace) -> int:
    return _solver_options.run(args, network=True)
