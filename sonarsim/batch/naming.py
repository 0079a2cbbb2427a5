"""Output names of batch jobs: from a ``name`` template, or built from the parameters that
differ between the jobs (docs/batch.md)."""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

from ..errors import InputError
from .identity import identity_params
from .manifest import DEFAULT_PULSE, default_fs, settings_fields

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")


def name_value(value) -> str:
    """A parameter value as a piece of a file name (paths by stem, lists joined by ``+``)."""
    if value is None:
        return "none"
    if isinstance(value, str) and ("/" in value or value.lower().endswith((".npy", ".csv"))):
        value = Path(value).stem
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, (list, tuple)):
        value = "+".join(name_value(v) for v in value)
    text = re.sub(r"[^A-Za-z0-9.+-]+", "-", str(value)).strip("-.")
    return text or "x"


def stem(params: dict) -> str:
    """The scene name or mesh file stem of a job."""
    ref = params.get("scene") or params.get("mesh")
    return name_value(Path(ref).stem if "/" in ref else ref)


def _name_defaults() -> dict:
    fields_ = settings_fields()
    out = {k: (f.default if f.default is not dataclasses.MISSING else None)
           for k, f in fields_.items()}
    out.update(pulse=DEFAULT_PULSE, fs=default_fs(), fit=True, ground=True)
    return out


def default_names(all_params: list[dict]) -> list[str]:
    """Names from the parameters: the scene or mesh stem, then ``key-value`` for every
    parameter whose value differs between jobs (e.g. ``bunny_snr_db-20_seed-1``); a
    setting a job leaves out counts with its default value. Linear in the job count."""
    defaults = _name_defaults()
    keys: dict[str, None] = {}
    for p in all_params:
        for k in identity_params(p):
            if k not in ("scene", "mesh"):
                keys.setdefault(k)
    value = lambda p, k: p.get(k, defaults.get(k))
    varying = [k for k in keys
               if len({json.dumps(value(p, k), sort_keys=True) for p in all_params}) > 1]
    return ["_".join([stem(p)] + [f"{k}-{name_value(value(p, k))}" for k in varying
                                  if k in p or k in defaults])
            for p in all_params]


def format_name(template: str, params: dict, where: str) -> str:
    """The name of a job with a ``name`` template such as ``"{stem}-snr{snr_db}"``."""
    values = {k: name_value(v) for k, v in params.items() if k != "reconstruct"}
    values["stem"] = stem(params)
    try:
        name = template.format_map(values)
    except (KeyError, ValueError, IndexError, AttributeError, TypeError) as exc:
        raise InputError(f"{where}: name template '{template}': {exc}") from None
    check_name(name, where)
    return name


def check_name(name: str, where: str, what: str = "name") -> str:
    if not NAME_RE.match(name):
        raise InputError(f"{where}: {what} '{name}' must be letters, digits and . _ + - "
                         "(it becomes a file name)")
    return name
