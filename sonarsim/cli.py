"""``sonarsim`` command line: render, simulate, import and inspect sonar data."""
from __future__ import annotations

from .cli_common import run_main


def main(argv=None) -> int:
    return run_main("sonarsim", "sonarsim.commands",
                    "Simulate and inspect coherent 3-D synthetic aperture sonar data.", argv)


if __name__ == "__main__":
    raise SystemExit(main())
