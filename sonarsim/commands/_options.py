"""Command-line options shared by several ``sonarsim`` subcommands."""
from __future__ import annotations

import argparse

BOX_METAVAR = ("X0", "X1", "Y0", "Y1", "Z0", "Z1")


def add_box_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--box X0 X1 Y0 Y1 Z0 Z1`` (metres); read it back with :func:`parse_box`."""
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar=BOX_METAVAR,
                        help=help)


def parse_box(values):
    """SceneBox from 6 floats X0 X1 Y0 Y1 Z0 Z1, or None."""
    if values is None:
        return None
    from ..geometry import SceneBox
    return SceneBox.from_bounds([[values[0], values[1]], [values[2], values[3]],
                                 [values[4], values[5]]])
