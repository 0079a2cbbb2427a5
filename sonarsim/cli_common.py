"""The shared command-line skeleton of ``sonarsim`` and ``recon``.

Each subcommand is a module in ``<package>.commands`` that defines ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> int``; the module name with
``_`` replaced by ``-`` is the subcommand name. User mistakes (:class:`SonarsimError`,
missing files) become one line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from . import runtime
from .errors import SonarsimError


def _command_modules(package: str):
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), f"{package}.{info.name}"


def build_parser(prog: str, package: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--version", action="version",
                        version=f"%(prog)s {importlib.import_module(prog).__version__}")
    parser.add_argument("--variant", choices=runtime.SUPPORTED_VARIANTS, default=None,
                        help="Mitsuba/Dr.Jit variant (default: $SONARSIM_VARIANT or "
                             f"{runtime.DEFAULT_VARIANT})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, modname in _command_modules(package):
        module = importlib.import_module(modname)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def run_main(prog: str, package: str, description: str, argv=None) -> int:
    parser = build_parser(prog, package, description)
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 0
    try:
        if args.variant:
            runtime.set_variant(args.variant)
        return int(args._run(args) or 0)
    except (SonarsimError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        msg = str(exc) if not isinstance(exc, OSError) or not exc.filename else \
            f"{exc.filename}: {exc.strerror}"
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
