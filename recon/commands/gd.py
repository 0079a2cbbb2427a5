"""``recon gd``: gradient descent on complex voxels (the solver of ``recon nbp`` on voxels)."""
from __future__ import annotations

import argparse

from . import _solver_options

HELP = ("Reconstruct by gradient descent on complex voxels (Adam) through the ellipsoidal "
        "forward model (neural backprojection's solver with a voxel scene).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _solver_options.add_arguments(parser, network=False)


def run(args: argparse.Namespace) -> int:
    return _solver_options.run(args, network=False)
