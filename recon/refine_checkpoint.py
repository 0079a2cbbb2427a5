"""Resuming ``recon refine``: each candidate's refinement kept in a directory as it finishes.

The command refines up to five candidates in turn (minutes each on a CPU). With
``--checkpoint DIR`` every finished refinement is written to ``DIR/LABEL.npz`` (vertices [V, 3]
float64 m, faces [F, 3]) and ``DIR/LABEL.json`` (albedo, the per-step history, the settings
record, the affine fit), each atomically; ``DIR/identity.json`` names the run (the dataset's
digest, the ``--init`` file's digest, the refinement settings and the options that shape the
starts). With ``--resume`` a candidate found there is loaded instead of refined again — the
same floats, so the rest of the command (the ranking, the grown candidate's unexplained image)
goes on exactly as in one uninterrupted run; another run's directory is refused in one line.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError

IDENTITY = "identity.json"


def run_identity(dataset, init: Path, settings: dict, options: dict) -> dict:
    """What makes two ``recon refine`` runs the same: the dataset's digest
    (:func:`sonarsim.identity.dataset_digest`), the digest of the ``--init`` file's bytes, the
    refinement settings (a dict) and the options that decide the starts (``options``: JSON
    values)."""
    from sonarsim.identity import dataset_digest
    return {"dataset": dataset_digest(dataset), "init": file_digest(init),
            "settings": settings, "options": options}


def file_digest(path: Path) -> str:
    """Digest of a file's bytes (:func:`sonarsim.identity.digest`)."""
    from sonarsim.identity import digest
    return digest(np.frombuffer(Path(path).read_bytes(), np.uint8))


class CandidateStore:
    """The checkpoint directory of one run (see the module docstring)."""

    def __init__(self, directory: Path, identity: dict, resume: bool, force: bool):
        from sonarsim.atomic import atomic_path
        self.directory = Path(directory)
        if self.directory.exists() and not self.directory.is_dir():
            raise InputError(f"--checkpoint {self.directory}: is not a directory")
        marker = self.directory / IDENTITY
        same = json.loads(json.dumps(identity))       # as it reads back (tuples → lists)
        if marker.exists():
            if resume:
                try:
                    saved = json.loads(marker.read_text())
                except (OSError, ValueError):
                    saved = None
                if saved != same:
                    raise InputError(f"--checkpoint {self.directory}: holds another run (dataset, "
                                     "--init, settings or options differ); choose another "
                                     "directory or drop --resume and pass --force")
                return
            if not force:
                raise InputError(f"--checkpoint {self.directory}: holds a run; pass --resume to "
                                 "continue it or --force to start again")
            for old in self.directory.glob("*.npz"):
                old.unlink()
            for old in self.directory.glob("*.json"):
                old.unlink()
        elif self.directory.is_dir() and any(self.directory.iterdir()):
            raise InputError(f"--checkpoint {self.directory}: not empty and not a refine "
                             "checkpoint")
        self.directory.mkdir(parents=True, exist_ok=True)
        with atomic_path(marker) as tmp:
            tmp.write_text(json.dumps(same, indent=1))

    def _paths(self, label: str) -> tuple[Path, Path]:
        return self.directory / f"{label}.npz", self.directory / f"{label}.json"

    def load(self, label: str):
        """The :class:`recon.refine.RefineResult` saved for candidate ``label``, or None."""
        from .refine import RefineResult
        arrays, record = self._paths(label)
        if not (arrays.exists() and record.exists()):
            return None
        with np.load(arrays) as data:
            vertices, faces = data["vertices"], data["faces"]
        saved = json.loads(record.read_text())
        return RefineResult(vertices=vertices, faces=faces, albedo=saved["albedo"],
                            history=saved["history"], settings=saved["settings"],
                            affine=saved["affine"])

    def save(self, label: str, result) -> None:
        """Write candidate ``label``'s result (arrays first, the record last: a candidate
        counts as finished once its record exists)."""
        from sonarsim.atomic import atomic_path
        from sonarsim.dataset.attributes import json_default
        arrays, record = self._paths(label)
        with atomic_path(arrays) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, vertices=np.asarray(result.vertices, np.float64),
                         faces=np.asarray(result.faces, np.int64))
        with atomic_path(record) as tmp:
            tmp.write_text(json.dumps({"albedo": result.albedo, "history": result.history,
                                       "settings": result.settings, "affine": result.affine},
                                      default=json_default))

