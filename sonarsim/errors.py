"""Exceptions that report a user mistake (bad file, bad option, impossible geometry).

The command-line tools print these as one line on stderr and exit non-zero;
anything else is a bug and keeps its traceback.
"""


class SonarsimError(Exception):
    """Base class of every error caused by input rather than by a bug."""


class InputError(SonarsimError, ValueError):
    """An argument, array or option is invalid (wrong shape, NaN, out of range)."""


class FormatError(SonarsimError):
    """A file is missing, unreadable, truncated or does not follow its schema."""


class WriteError(SonarsimError):
    """An output could not be written (disk full, read-only file system, permissions); the
    message names the path. Nothing is left at the final path."""
