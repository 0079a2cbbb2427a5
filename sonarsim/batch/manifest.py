"""Reading a batch manifest: TOML, ``[defaults]`` / ``[[job]]`` / ``[[sweep]]`` expansion
and each job's canonical parameters (docs/batch.md)."""
from __future__ import annotations

import dataclasses
import functools
import glob as globlib
import itertools
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

from .. import limits
from ..errors import InputError
from ..threads import check_threads

TOP_KEYS = ("defaults", "job", "sweep")
BATCH_KEYS = ("name", "scene", "mesh", "fit", "ground", "poses", "pulse", "fs",
              "pulse_samples", "reconstruct")
NOT_SETTINGS = ("pulse", "extra_meta", "log")    # SimulationSettings fields set by the batch
EXECUTION_ONLY = ("threads", "chunk_size")       # change the speed, never the output
DEFAULT_PULSE = "lfm-20k"
GLOB_CHARS = set("*?[")


def default_fs() -> float:
    """The sample rate of a job that sets none: the simulator's (AirSAS's) rate."""
    from ..signals import AIRSAS_FS
    return float(AIRSAS_FS)


@functools.lru_cache(maxsize=1)
def settings_fields() -> Mapping[str, dataclasses.Field]:
    """The :class:`SimulationSettings` fields a job may set (all but the batch's own); a
    read-only mapping, made once (planning asks for it several times a job)."""
    from ..simulate import SimulationSettings
    return MappingProxyType({f.name: f for f in dataclasses.fields(SimulationSettings)
                             if f.name not in NOT_SETTINGS})


@functools.lru_cache(maxsize=1)
def _setting_types() -> dict:
    from ..simulate import SimulationSettings
    return typing.get_type_hints(SimulationSettings)


def _type_text(hint) -> str:
    """How a setting's type reads in a message."""
    args = typing.get_args(hint)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        parts = [_type_text(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" (or left out)" if type(None) in args else "")
    if origin is tuple or hint is tuple:
        plural = {int: "integers", float: "numbers", str: "strings", bool: "true/false values"}
        return f"a list of {plural.get(args[0], _type_text(args[0]))}" if args else "a list"
    names = {int: "an integer", float: "a number", bool: "true or false", str: "a string",
             dict: "a table"}
    if hint in names:
        return names[hint]
    if origin is not None and origin.__name__ in ("Mapping", "dict"):
        return "a table"
    return getattr(hint, "__name__", str(hint))


def _fits(value, hint) -> bool:
    """Whether a TOML value fits a settings annotation (ints stand for floats, never the
    reverse; bools are not numbers; unknown annotations accept anything)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if origin is tuple or hint is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        item = args[0] if args else Any
        return all(_fits(v, item) for v in value)
    if hint is dict or (origin is not None and getattr(origin, "__name__", "") in
                        ("Mapping", "dict", "MutableMapping")):
        return isinstance(value, dict)
    return True


def check_setting(key: str, value, where: str) -> None:
    """A manifest value of a :class:`SimulationSettings` field checked against the field's
    type (one-line InputError naming the key): ``snr_db = "abc"``, ``paths_per_pose = 1e30``
    (a float where the CLI takes an integer). Ranges are the settings' own
    (``SimulationSettings.validate``)."""
    hint = _setting_types().get(key)
    if hint is None or _fits(value, hint):
        return
    raise InputError(f"{where}: {key} must be {_type_text(hint)}, got {value!r}")


def load_manifest(path: str | Path) -> dict:
    """The parsed TOML of ``path`` (InputError: missing, a directory, not TOML)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: manifest not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: manifest is a directory") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (a manifest is TOML)") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{where}: must be a table")
    return value


def tables(value, where: str) -> list[dict]:
    """A table or an array of tables as a list of tables (InputError naming ``where``)."""
    items = value if isinstance(value, list) else [value]
    return [_table(v, f"{where}[{i}]") for i, v in enumerate(items)]


def _expand_mesh(value, where: str, base: Path) -> list[str]:
    """Absolute mesh paths for a path, a glob or a list of them (in order, globs sorted)."""
    items = value if isinstance(value, list) else [value]
    out = []
    for item in items:
        if not isinstance(item, str) or not item:
            raise InputError(f"{where}: mesh must be a path or a glob, got {item!r}")
        pattern = item if Path(item).is_absolute() else str(base / item)
        if GLOB_CHARS & set(item):
            found = sorted(globlib.glob(pattern))
            if not found:
                raise InputError(f"{where}: mesh glob '{item}' matches no file")
            out += [str(Path(p).resolve()) for p in found]
        else:
            out.append(str(Path(pattern).resolve()))
    return out


def expand_manifest(doc: dict, base: Path, max_jobs: int | None = None
                    ) -> list[tuple[str, dict]]:
    """(where, raw job parameters) for every job of a parsed manifest, in manifest order.

    ``[defaults]`` fill every job; in a ``[[sweep]]`` every list value is an axis (a
    list-valued setting is given as a list of lists) and the jobs are the product of the
    axes; ``mesh`` globs are axes wherever they appear. More than ``max_jobs`` jobs (None:
    no cap) is refused before any job is built.
    """
    unknown = sorted(set(doc) - set(TOP_KEYS))
    if unknown:
        raise InputError(f"manifest: unknown top-level key(s) {', '.join(unknown)} "
                         f"(expected {', '.join(TOP_KEYS)})")
    defaults = _table(doc.get("defaults", {}), "defaults")
    entries = [(f"job[{i}]" + (f" '{t['name']}'" if isinstance(t.get("name"), str) else ""),
                t, False) for i, t in enumerate(tables(doc.get("job", []), "job"))]
    entries += [(f"sweep[{i}]", t, True)
                for i, t in enumerate(tables(doc.get("sweep", []), "sweep"))]
    if not entries:
        raise InputError("manifest: no jobs (add [[job]] tables or a [[sweep]])")
    expanded = []
    total = 0
    for where, table, is_sweep in entries:
        merged = {**defaults, **table}
        axes: dict[str, list] = {}
        for key, value in merged.items():
            if key == "mesh":
                axes[key] = _expand_mesh(value, where, base)
            elif is_sweep and key in table and isinstance(value, list) and key != "reconstruct":
                if not value:
                    raise InputError(f"{where}: sweep axis '{key}' is empty")
                axes[key] = value
        expanded.append((where, merged, axes))
        total += math.prod(len(v) for v in axes.values())
    if max_jobs is not None and total > max_jobs:
        raise InputError(f"manifest: {total} jobs, more than the {max_jobs} allowed without "
                         f"--max-jobs (check the sweep axes; --max-jobs N raises the cap)")
    out = []
    for where, merged, axes in expanded:
        fixed = {k: v for k, v in merged.items() if k not in axes}
        for combo in itertools.product(*axes.values()):
            chosen = dict(zip(axes, combo))
            label = where
            shown = {k: v for k, v in chosen.items() if len(axes[k]) > 1}
            if shown:
                label += " {" + ", ".join(f"{k}={short(v)}" for k, v in shown.items()) + "}"
            out.append((label, {**fixed, **chosen}))
    return out


def short(value) -> str:
    """A parameter value for messages: a path by its file name."""
    if isinstance(value, str) and ("/" in value):
        return Path(value).name
    return str(value)


def _resolve(value: str, base: Path) -> str:
    p = Path(value)
    return str((p if p.is_absolute() else base / p).resolve())


def canonical_params(raw: dict, where: str, base: Path) -> dict:
    """The job's parameters with paths made absolute and defaults of the batch's own keys
    filled in (InputError naming ``where`` for unknown keys and wrong types)."""
    fields_ = settings_fields()
    unknown = sorted(set(raw) - set(BATCH_KEYS) - set(fields_))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; a job takes "
                         f"{', '.join(BATCH_KEYS)} and the simulation settings "
                         f"{', '.join(sorted(fields_))}")
    if ("scene" in raw) == ("mesh" in raw):
        raise InputError(f"{where}: needs exactly one of 'scene' (a scene TOML or shipped "
                         f"scene name) or 'mesh' (a mesh file)")
    p: dict[str, Any] = {}
    if "scene" in raw:
        scene = raw["scene"]
        if not isinstance(scene, str) or not scene:
            raise InputError(f"{where}: scene must be a TOML path or a shipped scene name")
        looks_like_path = scene.lower().endswith(".toml") or "/" in scene
        p["scene"] = _resolve(scene, base) if looks_like_path or (base / scene).exists() \
            else scene
        for key in ("fit", "ground"):
            if key in raw:
                raise InputError(f"{where}: '{key}' applies to 'mesh' jobs only")
    else:
        p["mesh"] = raw["mesh"] if Path(raw["mesh"]).is_absolute() else _resolve(raw["mesh"], base)
        for key in ("fit", "ground"):
            value = raw.get(key, True)
            if not isinstance(value, bool):
                raise InputError(f"{where}: {key} must be true or false")
            p[key] = value
    if "poses" not in raw:
        raise InputError(f"{where}: no poses (set 'poses' in [defaults] or in the job)")
    poses = raw["poses"]
    if not isinstance(poses, str) or not poses:
        raise InputError(f"{where}: poses must be a trajectory spec or a pose file")
    p["poses"] = _resolve(poses, base) if poses.lower().endswith((".csv", ".npy")) else poses
    pulse = raw.get("pulse", DEFAULT_PULSE)
    if not isinstance(pulse, str):
        raise InputError(f"{where}: pulse must be a string")
    p["pulse"] = _resolve(pulse, base) if pulse.lower().endswith(".npy") else pulse
    fs = raw.get("fs", default_fs())
    if isinstance(fs, bool) or not isinstance(fs, (int, float)):
        raise InputError(f"{where}: fs must be a number (Hz), got {fs!r}")
    try:
        p["fs"] = limits.check_fs(float(fs), "fs")     # before any pulse is generated
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    if "pulse_samples" in raw:
        n = raw["pulse_samples"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise InputError(f"{where}: pulse_samples must be an integer >= 2")
        p["pulse_samples"] = n
    for key in sorted(set(raw) & set(fields_)):
        check_setting(key, raw[key], where)
        p[key] = raw[key]
    if "threads" in p:
        check_threads(p["threads"], f"{where}: threads")
    if p.get("chunk_size") is not None and p["chunk_size"] < 1:
        raise InputError(f"{where}: chunk_size must be >= 1, got {p['chunk_size']}")
    if "bounce_set" in p and "bounces" not in p and isinstance(p["bounce_set"], list) \
            and p["bounce_set"] and all(isinstance(b, int) for b in p["bounce_set"]):
        p["bounces"] = max(p["bounce_set"])            # as `sonarsim simulate`
    if "name" in raw:
        if not isinstance(raw["name"], str) or not raw["name"]:
            raise InputError(f"{where}: name must be a non-empty string")
        p["name"] = raw["name"]
    if "reconstruct" in raw:
        p["reconstruct"] = tables(raw["reconstruct"], f"{where}: reconstruct")
    return p
