"""Checkpoints of a run (``.npz``, atomic): parameters, Adam moments, the host generator's
state, the loss history and the run's identity; resuming another run is refused."""
from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np

from sonarsim.atomic import atomic_path
from sonarsim.errors import FormatError, InputError

from ..adam import Adam


def dataset_digest(dataset) -> str:
    """SHA-256 (hex, 16 chars) of a dataset's waveforms, poses, pulse and sampling."""
    h = hashlib.sha256()
    for a in (dataset.waveforms, dataset.tx, dataset.rx, dataset.pulse):
        h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
    h.update(repr((float(dataset.fs), float(dataset.sound_speed),
                   int(dataset.start_sample))).encode())
    return h.hexdigest()[:16]


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
    is not a complete checkpoint → FormatError; another run's checkpoint → InputError."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        saved = json.loads(str(data["identity"]))
        iteration = int(data["iteration"])
        history = json.loads(str(data["history"]))
        rng_state = json.loads(str(data["rng_state"]))
        saved_iterations = int(data["iterations"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable solver checkpoint "
                          f"({type(exc).__name__}: {str(exc)[:80]})") from None
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
    if iteration > settings.iterations:
        raise InputError(f"{path}: checkpoint is at iteration {iteration}, past --iterations "
                         f"{settings.iterations}")
    opt.load(data)
    rng.bit_generator.state = rng_state
    return iteration, history
