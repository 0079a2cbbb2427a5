"""``recon`` command line: reconstruct, export and evaluate sonar volumes."""
from __future__ import annotations

from sonarsim.cli_common import run_main


def main(argv=None) -> int:
    return run_main("recon", "recon.commands",
                    "Reconstruct scenes from coherent 3-D SAS datasets.", argv)


if __name__ == "__main__":
    raise SystemExit(main())
