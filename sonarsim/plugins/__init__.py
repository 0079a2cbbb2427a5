"""Mitsuba plugins shipped with sonarsim (one plugin per module).

Each module depends on ``mitsuba`` and ``drjit`` only and exposes ``register(mi)``.
:func:`register_all` is called by :func:`sonarsim.runtime.set_variant` once a
variant is selected, because Mitsuba's Python classes exist per variant.
"""
import importlib

PLUGIN_MODULES = ("sonar_transient",)


def register_all(mi) -> None:
    """Import every plugin module and register it with the active Mitsuba variant."""
    for name in PLUGIN_MODULES:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__name__}.{name}":
                continue  # not written yet
            raise
        module.register(mi)
