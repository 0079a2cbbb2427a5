"""The shared command-line skeleton of ``sonarsim`` and ``recon``.

Each subcommand is a module in ``<package>.commands`` that defines ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> int``; the module name with
``_`` replaced by ``-`` is the subcommand name. User mistakes (:class:`SonarsimError`,
missing files) become one line on stderr and exit status 2; so does running out of memory.

Options every subcommand gets here:

* ``--max-memory SIZE``: the memory a run may plan to use (:mod:`sonarsim.limits`);
* ``--force`` on commands that write files: replace an existing output (otherwise refused);
  the outputs are checked before any work and locked for the run (:mod:`sonarsim.outputs`).
  A module names its file options in ``OUTPUTS`` (dests, e.g. ``("out", "mesh")``); without
  it, an ``--out`` option is one unless its metavar or help speaks of a directory. A module
  that handles an existing output itself (``simulate`` resumes or reports a finished run)
  sets ``OUTPUT_EXISTS_OK = True``;
* ``--threads N`` on every ``recon`` subcommand: Dr.Jit worker threads (as ``sonarsim
  render/simulate --threads``);
* ``-q/--quiet`` (warnings and errors only, no progress) and ``-v/--verbose`` (also debug
  details: the runtime set-up, the run's wall and CPU time and peak memory), before or
  after the subcommand (:mod:`sonarsim.progress`: results on stdout, diagnostics on
  stderr, progress as timed log lines when stderr is not a terminal).

An operating-system error no writer turned into a message (a full disk, a read-only file
system) is one line ``PROG: error: PATH: reason`` with exit status 1. Interruptions and
closed pipes end a command as Unix tools end: Ctrl-C prints one line
``PROG: interrupted`` and exits 130; output into a pipe whose reader has gone (``sonarsim
info D.h5 | head -1``) stops silently with exit status 141 (128 + SIGPIPE). A usage
mistake is one line plus a pointer to ``--help`` (exit 2), not argparse's usage block.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import resource
import sys
import time
from pathlib import Path

from . import limits, outputs, progress, runtime
from .threads import check_threads, dr_threads
from .errors import InputError, SonarsimError

EXIT_FAILURE = 1              # the system failed us (a full disk, ...), not a usage mistake
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130        # 128 + SIGINT, what a shell reports for Ctrl-C
EXIT_BROKEN_PIPE = 141        # 128 + SIGPIPE, what a shell reports for `yes | head -1`

log = logging.getLogger("sonarsim.cli")


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line on stderr (exit status 2)."""

    def error(self, message: str):
        _print_err(f"{self.prog}: error: {message} (see '{self.prog} --help')")
        self.exit(EXIT_USAGE)


def _print_err(line: str) -> None:
    try:
        print(line, file=sys.stderr, flush=True)
    except (BrokenPipeError, ValueError):
        pass


def _add_verbosity(parser: argparse.ArgumentParser, suppress: bool) -> None:
    default = argparse.SUPPRESS if suppress else progress.NORMAL
    g = parser.add_argument_group("messages") if suppress else parser
    g.add_argument("-q", "--quiet", dest="verbosity", action="store_const",
                   const=progress.QUIET, default=default,
                   help="print only results, warnings and errors (no progress)")
    g.add_argument("-v", "--verbose", dest="verbosity", action="store_const",
                   const=progress.VERBOSE, default=default,
                   help="also print debug details (runtime set-up, time and memory used)")


def _command_modules(package: str):
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), f"{package}.{info.name}"


def build_parser(prog: str, package: str, description: str) -> argparse.ArgumentParser:
    parser = OneLineParser(prog=prog, description=description)
    parser.add_argument("--version", action="version",
                        version=f"%(prog)s {importlib.import_module(prog).__version__}")
    parser.add_argument("--variant", choices=runtime.SUPPORTED_VARIANTS, default=None,
                        help="Mitsuba/Dr.Jit variant (default: $SONARSIM_VARIANT or "
                             f"{runtime.DEFAULT_VARIANT})")
    _add_verbosity(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, modname in _command_modules(package):
        module = importlib.import_module(modname)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        _add_common_options(p, module, threads=prog == "recon")
        _add_verbosity(p, suppress=True)
        p.set_defaults(_run=module.run)
    return parser


def _has_option(parser: argparse.ArgumentParser, option: str) -> bool:
    return any(option in a.option_strings for a in parser._actions)


def _file_outputs(parser: argparse.ArgumentParser, module) -> tuple[str, ...]:
    """Dests of the options naming output files (see the module docstring)."""
    declared = getattr(module, "OUTPUTS", None)
    if declared is not None:
        return tuple(declared)
    for action in parser._actions:
        if action.dest == "out" and action.option_strings:
            words = f"{action.metavar or ''} {action.help or ''}"
            if "DIR" not in words and "directory" not in words.lower():
                return ("out",)
    return ()


def _add_common_options(p: argparse.ArgumentParser, module, threads: bool) -> None:
    g = p.add_argument_group("resources and outputs")
    if not _has_option(p, "--max-memory"):
        g.add_argument("--max-memory", default=None, metavar="SIZE",
                       help="refuse a run whose estimated memory exceeds SIZE (e.g. 8G, 512M; "
                            "default: 80%% of this machine's memory or $SONARSIM_MAX_MEMORY)")
    if threads and not _has_option(p, "--threads"):
        g.add_argument("--threads", type=int, default=None, metavar="N",
                       help="Dr.Jit worker threads (default: all cores)")
    dests = _file_outputs(p, module)
    if dests and not _has_option(p, "--force"):
        g.add_argument("--force", action="store_true",
                       help="replace existing output files (otherwise an existing output is "
                            "refused)")
    p.set_defaults(_outputs=dests, _outputs_exist_ok=bool(getattr(module, "OUTPUT_EXISTS_OK",
                                                                   False)),
                   _output_suffixes=dict(getattr(module, "OUTPUT_SUFFIXES", {})))


def _output_paths(args: argparse.Namespace) -> list:
    """Check the output files before any work; return them (to be locked). Two output options
    that name the same file are refused: the second write would replace the first's result;
    so is an output that is one of the command's input files, even with --force."""
    paths, seen = [], {}
    outputs_ = set(getattr(args, "_outputs", ()))
    inputs = {}
    for dest, value in vars(args).items():
        if dest.startswith("_") or dest in outputs_:
            continue
        for v in (value if isinstance(value, (list, tuple)) else [value]):
            if isinstance(v, (str, os.PathLike)) and v and Path(v).is_file():
                inputs.setdefault(Path(v).resolve(), dest)
    for dest in getattr(args, "_outputs", ()):
        value = getattr(args, dest, None)
        if value is None:
            continue
        option = "--" + dest.replace("_", "-")
        suffixes = getattr(args, "_output_suffixes", {}).get(dest)
        if suffixes and not str(value).lower().endswith(tuple(suffixes)):
            raise InputError(f"{option} {value}: the file is written as {' or '.join(suffixes)}; "
                             "name it so")
        outputs.check_output(value, force=bool(getattr(args, "force", False)), option=option,
                             exists_ok=args._outputs_exist_ok)
        key = Path(value).resolve()
        if key in inputs:
            raise InputError(f"{option} {value}: is also the input {inputs[key]!r}; write the "
                             "result to another file")
        if key in seen:
            raise InputError(f"{seen[key]} and {option} both name {value}; give each output "
                             "its own file")
        seen[key] = option
        paths.append(value)
    return paths


def _check_seed(args: argparse.Namespace) -> None:
    """Every command's ``--seed`` must fit NumPy's and Dr.Jit's generators: [0, 2^32)."""
    seed = getattr(args, "seed", None)
    if isinstance(seed, int) and not 0 <= seed < 2**32:
        raise InputError(f"--seed must be in [0, 2^32), got {seed}")


def _thread_count(threads):
    """Dr.Jit runs on ``threads`` worker threads inside (None: unchanged); checked first."""
    threads = check_threads(threads)
    if threads is not None:
        runtime.mitsuba()       # a working libLLVM before drjit is imported
    return dr_threads(threads)


def run_main(prog: str, package: str, description: str, argv=None) -> int:
    """Parse ``argv``, run the subcommand and return the exit status (see module docstring)."""
    try:
        try:
            status = _run_main(prog, package, description, argv)
        except KeyboardInterrupt:
            _print_err(f"{prog}: interrupted")
            status = EXIT_INTERRUPTED
        except SystemExit:           # --help, --version, usage errors
            sys.stdout.flush()
            raise
        sys.stdout.flush()           # a closed pipe shows here when the output was buffered
        return status
    except BrokenPipeError:
        _silence_stdout()
        return EXIT_BROKEN_PIPE


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass


def _run_main(prog: str, package: str, description: str, argv) -> int:
    parser = build_parser(prog, package, description)
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 0
    undo = progress.setup_logging(f"{prog} {args.command}", args.verbosity)
    start, cpu0 = time.monotonic(), _cpu_seconds()
    try:
        return _run_command(prog, package, args)
    finally:
        log.debug("finished in %.1f s (CPU %.1f s), peak memory %.2f GiB",
                  time.monotonic() - start, _cpu_seconds() - cpu0, _peak_rss_gib())
        undo()


def _cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20   # KiB on Linux


def _run_command(prog: str, package: str, args: argparse.Namespace) -> int:
    try:
        if args.variant:
            runtime.set_variant(args.variant)
        limits.set_max_memory(getattr(args, "max_memory", None))
        _check_seed(args)
        progress.progress_interval()          # a bad $SONARSIM_PROGRESS_INTERVAL: one line now
        paths = _output_paths(args)
        threads = getattr(args, "threads", None) if "recon" in package else None
        with outputs.output_locks(paths), _thread_count(threads):
            return int(args._run(args) or 0)
    except MemoryError:
        _print_err(f"{prog}: error: ran out of memory (the run needed more than this machine "
                   "could give; use smaller sizes, or --max-memory to be refused earlier)")
        return EXIT_USAGE
    except BrokenPipeError:
        raise
    except (SonarsimError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        msg = str(exc) if not isinstance(exc, OSError) or not exc.filename else \
            f"{exc.filename}: {exc.strerror}"
        _print_err(f"{prog}: error: {msg}")
        return EXIT_USAGE
    except OSError as exc:           # a full disk, a read-only or vanished file system, ...
        where = f"{exc.filename}: " if exc.filename else ""
        _print_err(f"{prog}: error: {where}{exc.strerror or exc}")
        return EXIT_FAILURE
    finally:
        limits.set_max_memory(None)  # one command's --max-memory does not outlive it
