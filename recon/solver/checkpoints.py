"""Checkpoints of a run (``.npz``, atomic): parameters, Adam moments, the host generator's
state, the loss history and the run's identity; resuming another run is refused."""
from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.errors import FormatError, InputError
from sonarsim.identity import dataset_digest  # noqa: F401  (the one dataset identity)

from ..adam import Adam

# Entries every checkpoint holds besides the parameters and Adam's moments.
ENTRIES = ("iteration", "rng_state", "history", "identity", "iterations", "t")


def is_checkpoint(path) -> bool:
    """True if ``path`` is a file written by :func:`save_checkpoint` (an ``.npz`` zip with
    the checkpoint's entries); False for anything else (a dataset, a volume, a text file)."""
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (OSError, zipfile.BadZipFile, ValueError):
        return False
    return all(f"{k}.npy" in names for k in ENTRIES)


def check_checkpoint_path(path, resume: bool) -> Path:
    """Refuse, before any work, a checkpoint path that is a directory, whose parent is not a
    directory, or that names an existing file which is not a solver checkpoint when the run
    would replace it (a dataset given by mistake must never be overwritten; a resumed run
    reads the file first and refuses it if it is not a checkpoint). The command line also
    asks for ``--force`` to replace an existing checkpoint."""
    from sonarsim.outputs import check_output
    p = check_output(path, option="--checkpoint", exists_ok=True)
    if p.exists() and not resume and not is_checkpoint(p):
        raise InputError(f"--checkpoint {p}: exists and is not a solver checkpoint; refusing "
                         "to replace it (choose another file name)")
    return p


def save_checkpoint(path, opt: Adam, rng, iteration, history, identity, settings):
    arrays = dict(opt.state())
    arrays["iteration"] = np.array(iteration, dtype=np.int64)
    arrays["rng_state"] = np.array(json.dumps(rng.bit_generator.state))
    arrays["history"] = np.array(json.dumps(history))
    arrays["identity"] = np.array(json.dumps(identity))
    arrays["iterations"] = np.array(settings.iterations, dtype=np.int64)
    with atomic_path(Path(path), keep_suffix=False) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def load_checkpoint(path, opt: Adam, rng, identity, settings):
    """Restore ``opt`` and ``rng`` from ``path``; returns (iteration, history). A file that
    is not a complete, consistent checkpoint → FormatError (every field is checked: types,
    ranges, sizes, finite values); another run's checkpoint → InputError."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        saved = json.loads(str(data["identity"]))
        iteration = int(data["iteration"])
        history = json.loads(str(data["history"]))
        rng_state = json.loads(str(data["rng_state"]))
        saved_iterations = int(data["iterations"])
        adam_steps = int(data["t"])
    except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable solver checkpoint "
                          f"({type(exc).__name__}: {str(exc)[:80]})") from None
    _check_fields(path, data, saved, iteration, history, rng_state, saved_iterations,
                  adam_steps)
    for key in ("dataset", "scene", "grid"):
        if saved.get(key) != identity[key]:
            raise InputError(f"{path}: checkpoint is of another run ({key} {saved.get(key)} "
                             f"!= {identity[key]})")
    a, b = saved.get("settings", {}), identity["settings"]
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if diff:
        k = diff[0]
        raise InputError(f"{path}: checkpoint has {k}={a.get(k)!r}, this run {b.get(k)!r}")
    if settings.lr_final is not None and saved_iterations != settings.iterations:
        raise InputError(f"{path}: checkpoint's learning-rate schedule is for {saved_iterations} "
                         f"iterations, this run has {settings.iterations}")
    if settings.ping_sampling == "stratified" and saved_iterations != settings.iterations:
        raise InputError(f"{path}: checkpoint's stratified ping schedule is for {saved_iterations} "
                         f"iterations, this run has {settings.iterations}")
    if iteration > settings.iterations:
        raise InputError(f"{path}: checkpoint is at iteration {iteration}, past --iterations "
                         f"{settings.iterations}")
    opt.load(data)
    try:
        rng.bit_generator.state = rng_state
    except (TypeError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: checkpoint's generator state is not valid "
                          f"({type(exc).__name__})") from None
    return iteration, history


def _check_fields(path, data, saved, iteration, history, rng_state, saved_iterations,
                  adam_steps):
    """Field-by-field validation of a loaded checkpoint (FormatError naming the field)."""
    def bad(what):
        raise FormatError(f"{path}: not a valid solver checkpoint ({what})")

    if not isinstance(saved, dict) or not isinstance(saved.get("settings", {}), dict):
        bad("identity is not a record")
    if saved_iterations < 1:
        bad(f"iterations {saved_iterations} < 1")
    if not 0 <= iteration <= saved_iterations:
        bad(f"iteration {iteration} outside 0..{saved_iterations}")
    if adam_steps != iteration:
        bad(f"optimiser step count {adam_steps} != iteration {iteration}")
    if not isinstance(history, list) or len(history) != iteration or not all(
            isinstance(h, dict) and all(isinstance(v, (int, float)) for v in h.values())
            for h in history):
        bad(f"loss history is not {iteration} records of numbers")
    if any(isinstance(v, float) and not math.isfinite(v) for h in history for v in h.values()):
        bad("loss history holds NaN or infinity")
    if not isinstance(rng_state, dict) or "bit_generator" not in rng_state:
        bad("generator state is not a record")
    for name, array in data.items():
        if name.startswith(("param/", "adam_m/", "adam_v/")):
            if array.ndim != 1 or not np.issubdtype(array.dtype, np.floating):
                bad(f"{name} is not a flat float array")
            if not np.all(np.isfinite(array)):
                bad(f"{name} holds NaN or infinity")
            if name.startswith("adam_v/") and np.any(array < 0):
                bad(f"{name} holds negative second moments")
