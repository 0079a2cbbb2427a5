"""Dr.Jit / Mitsuba runtime set-up: a working libLLVM, the variant, the plugins.

Dr.Jit's CPU (LLVM) backend loads ``libLLVM`` at run time. libLLVM 15 aborts the
interpreter on Dr.Jit 1.5 kernels and libLLVM 14 is refused, so before drjit is
imported we point ``DRJIT_LIBLLVM_PATH`` at the newest libLLVM >= 16 we can find
(:func:`configure_llvm`; called by :func:`set_variant` on first use, never at import).

:func:`mitsuba` returns the ``mitsuba`` module with the variant selected
(``llvm_ad_mono`` unless ``SONARSIM_VARIANT`` or :func:`set_variant` ask for
another, e.g. ``cuda_ad_mono``) and the plugins of :mod:`sonarsim.plugins`
registered, so ``mi.load_dict({"type": "sonar_transient", ...})`` works.
"""
from __future__ import annotations

import glob
import logging
import os
import re
import subprocess
import sys

MIN_LLVM = 16
DEFAULT_VARIANT = "llvm_ad_mono"
SUPPORTED_VARIANTS = ("llvm_ad_mono", "cuda_ad_mono")
VARIANT_ENV = "SONARSIM_VARIANT"
LLVM_FIX = "sudo apt-get install libllvm19   (or run `make install` as root)"

_LIB_DIRS = (
    "/lib/x86_64-linux-gnu", "/usr/lib/x86_64-linux-gnu",
    "/lib/aarch64-linux-gnu", "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64", "/usr/lib", "/usr/local/lib",
    "/usr/lib/llvm-*/lib", "/usr/local/opt/llvm/lib", "/opt/homebrew/opt/llvm/lib",
)
_VERSION_RE = re.compile(r"libLLVM(?:-(\d+)|\.so\.(\d+)|\.(\d+)\.dylib|-(\d+)\.dylib)")


from .errors import SonarsimError

log = logging.getLogger(__name__)


class RuntimeSetupError(SonarsimError, RuntimeError):
    """The Dr.Jit backend or the Mitsuba variant cannot be set up on this machine."""


def llvm_version(path: str) -> int | None:
    """Major LLVM version encoded in a libLLVM file name, e.g. ``libLLVM.so.19.1`` -> 19.

    Falls back to the ``llvm-NN`` directory a file sits in; ``None`` when unknown.
    """
    name = os.path.basename(path)
    m = _VERSION_RE.search(name)
    if m:
        return int(next(g for g in m.groups() if g))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_llvm_candidates() -> list[tuple[int, str]]:
    """All libLLVM shared libraries found on this system as ``(major, path)``, newest first."""
    paths: set[str] = set()
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True,
                             timeout=10).stdout
        paths.update(m.group(1) for m in re.finditer(r"=>\s*(\S*libLLVM\S*)", out))
    except (OSError, subprocess.SubprocessError):
        pass
    for d in _LIB_DIRS:
        paths.update(glob.glob(os.path.join(d, "libLLVM*.so*")))
        paths.update(glob.glob(os.path.join(d, "libLLVM*.dylib")))
    found = []
    for p in paths:
        v = llvm_version(p)
        if v is not None and os.path.isfile(p):
            found.append((v, os.path.realpath(p)))
    # Prefer newest version; among equal versions prefer the shortest (canonical) name.
    found = sorted(set(found), key=lambda vp: (-vp[0], len(vp[1]), vp[1]))
    return found


def configure_llvm() -> str | None:
    """Point ``DRJIT_LIBLLVM_PATH`` at a working libLLVM (>= 16) and return its path.

    A valid user setting (an existing file whose version is >= 16 or unknown) is kept.
    Returns ``None`` when nothing suitable exists; :func:`mitsuba` then raises
    :class:`RuntimeSetupError` with the fix. Never imports drjit.
    """
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user and os.path.isfile(user):
        v = llvm_version(user)
        if v is None or v >= MIN_LLVM:
            return user
    for v, path in find_llvm_candidates():
        if v >= MIN_LLVM:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return path
    if user:  # an invalid user setting must not lead Dr.Jit to an aborting libLLVM
        os.environ.pop("DRJIT_LIBLLVM_PATH", None)
    return None


_state: dict = {"variant": None}


def requested_variant() -> str:
    """The variant asked for through ``SONARSIM_VARIANT`` (default ``llvm_ad_mono``)."""
    return os.environ.get(VARIANT_ENV, "").strip() or DEFAULT_VARIANT


def set_variant(name: str | None = None):
    """Select the Mitsuba variant (default: :func:`requested_variant`) and register plugins.

    Returns the ``mitsuba`` module. Raises :class:`RuntimeSetupError` with a one-line
    reason when the variant is unknown or its backend is unavailable.
    """
    name = name or requested_variant()
    if name not in SUPPORTED_VARIANTS:
        raise RuntimeSetupError(
            f"unknown variant {name!r}: choose one of {', '.join(SUPPORTED_VARIANTS)}")
    if _state["variant"] == name:
        import mitsuba as mi
        return mi
    if name.startswith("llvm") and configure_llvm() is None:
        raise RuntimeSetupError(
            f"no libLLVM >= {MIN_LLVM} found for Dr.Jit's CPU backend "
            f"(libLLVM 15 aborts, 14 is refused); fix: {LLVM_FIX}")
    import drjit as dr
    backend = dr.JitBackend.CUDA if name.startswith("cuda") else dr.JitBackend.LLVM
    if not dr.has_backend(backend):
        what = "no CUDA GPU/driver is available" if name.startswith("cuda") else \
            "Dr.Jit could not load libLLVM"
        raise RuntimeSetupError(f"variant {name!r} cannot run here: {what}")
    import mitsuba as mi
    try:
        mi.set_variant(name)
    except (ImportError, AttributeError, ValueError) as exc:
        raise RuntimeSetupError(f"variant {name!r} cannot run here: {exc}") from exc
    from . import plugins
    try:
        plugins.register_all(mi)
    except plugins.PluginImportError as exc:
        raise RuntimeSetupError(str(exc)) from exc
    _state["variant"] = name
    log.debug("Mitsuba %s, Dr.Jit %s, variant %s, libLLVM %s", mi.__version__, dr.__version__,
              name, os.environ.get("DRJIT_LIBLLVM_PATH") if name.startswith("llvm") else "-")
    return mi


def mitsuba():
    """The ``mitsuba`` module with a variant set and sonarsim's plugins registered."""
    if _state["variant"] is not None:
        import mitsuba as mi
        return mi
    return set_variant()


def current_variant() -> str | None:
    """The variant selected so far, or ``None`` before the first :func:`mitsuba` call."""
    return _state["variant"]


def describe() -> str:
    """A one-paragraph description of the runtime (for ``--version``-style output)."""
    lines = [f"python {sys.version.split()[0]}",
             f"DRJIT_LIBLLVM_PATH={os.environ.get('DRJIT_LIBLLVM_PATH')}",
             f"variant={_state['variant'] or requested_variant()}"]
    return "; ".join(lines)
