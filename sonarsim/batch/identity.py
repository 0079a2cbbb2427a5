"""A batch job's identity: digests of its scene, poses, pulse and effective settings, and
the job id built from them (the rule is in :mod:`sonarsim.batch`'s docstring)."""
from __future__ import annotations

import numpy as np

from ..identity import digest
from .manifest import EXECUTION_ONLY, settings_fields

JOB_ID_CHARS = 20


def scene_digest(spec) -> str:
    """Digest of a :class:`sonarsim.scene.SceneSpec`: box, ground and every object's mesh."""
    parts = [spec.name, spec.source, spec.box.lo, spec.box.hi,
             None if spec.ground is None else [spec.ground.albedo, list(spec.ground.size)]]
    for obj in spec.objects:
        parts += [obj.label, obj.albedo, obj.normals, np.asarray(obj.mesh.vertices, float),
                  np.asarray(obj.mesh.faces, np.int64),
                  None if obj.file_normals is None else np.asarray(obj.file_normals, float)]
    return digest(*parts)


def poses_digest(poses) -> str:
    return digest(poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight)


def pulse_digest(pulse) -> str:
    return digest(pulse.samples, pulse.fs, pulse.spec)


def settings_digest(settings) -> str:
    """Digest of the settings that determine the output (defaults included; not the
    execution-only ones, :data:`EXECUTION_ONLY`)."""
    effective = {k: getattr(settings, k) for k in settings_fields()
                 if k not in EXECUTION_ONLY and not callable(getattr(settings, k))}
    return digest(effective)


def identity_params(params: dict) -> dict:
    """The parameters that determine a job's dataset (no name, reconstruction or speed)."""
    return {k: v for k, v in params.items()
            if k not in ("name", "reconstruct") and k not in EXECUTION_ONLY}


def job_id_of(params: dict, digests: dict) -> str:
    """The job's id: its inputs as given (scene, poses, pulse references) and the digests of
    what they hold and of the effective settings (so ``seed = 0`` written out or left to
    its default is the same job)."""
    fields_ = settings_fields()
    inputs = {k: v for k, v in identity_params(params).items() if k not in fields_}
    return digest(inputs, digests, length=JOB_ID_CHARS)


def step_id_of(job_id: str, params: dict) -> str:
    """The id of a reconstruction step of job ``job_id`` with the step's ``params``."""
    return digest(job_id, params, length=JOB_ID_CHARS)


def job_meta(job) -> dict:
    """What the batch adds to a dataset's meta (extra_meta of the settings)."""
    return {"poses": job.params["poses"], "batch_name": job.name, "batch_job_id": job.job_id,
            "batch_job": identity_params(job.params)}
