"""Reading a batch manifest: TOML, ``[defaults]`` / ``[[job]]`` / ``[[sweep]]`` expansion
and each job's canonical parameters (docs/batch.md)."""
from __future__ import annotations

import dataclasses
import glob as globlib
import itertools
import tomllib
from pathlib import Path
from typing import Any

from ..errors import InputError

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


def settings_fields() -> dict[str, dataclasses.Field]:
    """The :class:`SimulationSettings` fields a job may set (all but the batch's own)."""
    from ..simulate import SimulationSettings
    return {f.name: f for f in dataclasses.fields(SimulationSettings) if f.name not in NOT_SETTINGS}


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


def expand_manifest(doc: dict, base: Path) -> list[tuple[str, dict]]:
    """(where, raw job parameters) for every job of a parsed manifest, in manifest order.

    ``[defaults]`` fill every job; in a ``[[sweep]]`` every list value is an axis (a
    list-valued setting is given as a list of lists) and the jobs are the product of the
    axes; ``mesh`` globs are axes wherever they appear.
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
    out = []
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
    if isinstance(fs, bool) or not isinstance(fs, (int, float)) or not fs > 0:
        raise InputError(f"{where}: fs must be a positive number (Hz)")
    p["fs"] = float(fs)
    if "pulse_samples" in raw:
        n = raw["pulse_samples"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise InputError(f"{where}: pulse_samples must be an integer >= 2")
        p["pulse_samples"] = n
    for key in sorted(set(raw) & set(fields_)):
        p[key] = raw[key]
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
