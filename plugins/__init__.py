"""Mitsuba plugins shipped with sonarsim, one plugin per module (installed as ``sonarsim.plugins``).

A plugin module depends on ``mitsuba`` and ``drjit`` only. Like Mitsuba's own Python
integrators it defines its class at module level and registers it on import
(``mi.register_integrator(NAME, ...)``), so it must be imported after a variant is set:
:func:`sonarsim.runtime.set_variant` selects the variant and then calls
:func:`register_all`. To add a plugin, drop a module here; it is discovered by name.
"""
from __future__ import annotations

import importlib
import pkgutil
import sys


class PluginImportError(ImportError):
    """A plugin module of this package failed to import (its name is in the message)."""


def plugin_modules() -> list[str]:
    """Names of the plugin modules in this package (every public module is a plugin)."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def register_all(mi) -> list[str]:
    """Import (or, after a variant change, re-import) every plugin module.

    Importing a module registers its plugin with the active variant. Returns the module
    names. Raises :class:`PluginImportError` naming the module that failed.
    """
    names = plugin_modules()
    for name in names:
        full = f"{__name__}.{name}"
        try:
            module = sys.modules.get(full)
            if module is None:
                importlib.import_module(full)
            elif getattr(module, "VARIANT", None) != mi.variant():
                importlib.reload(module)   # classes derive from the variant's base classes
        except Exception as exc:   # any failure names the plugin; never skipped silently
            raise PluginImportError(
                f"sonarsim plugin {name!r} failed to import: {type(exc).__name__}: {exc}") from exc
    return names
