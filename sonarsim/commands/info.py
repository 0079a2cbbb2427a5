"""``sonarsim info FILE``: a human summary of a transients, dataset or volume file.

``info`` validates a file as the readers do (:func:`sonarsim.dataset.describe_and_check`):
it prints what it can read, then one line per problem (each one a reader would refuse the
file for: an unfinished ``.partial`` file too), and exits with status 1 for an invalid
file; 0 when the file is valid.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..dataset import describe, describe_and_check  # noqa: F401  (describe: tests/test_fidelity.py)
from ..errors import FormatError

HELP = "Print a summary of a sonarsim HDF5 file (transients, sonar dataset or volume)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="a .h5 file written by sonarsim or recon")


def run(args: argparse.Namespace) -> int:
    from ..dataset.reader import _check_file
    path = Path(args.file)
    _check_file(path)                   # not a file / not HDF5: a user mistake (exit 2)
    try:
        lines, problems = describe_and_check(path)
    except FormatError as exc:          # not even the schema could be read
        lines, problems = [f"{path}: not a valid sonarsim file"], [str(exc)]
    for line in lines:
        print(line)
    if problems:
        print(f"  {'PROBLEMS':<22} {len(problems)}: a reader refuses this file")
        for problem in problems:
            print(f"    - {problem}")
        return 1
    return 0
