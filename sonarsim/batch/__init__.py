"""Batch manifests: many simulations (each optionally reconstructed and evaluated) as one run.

A manifest (TOML, docs/batch.md) lists jobs, or sweeps whose product gives the jobs::

    [defaults]                  # every job: any simulate setting
    poses = "cylindrical:36:2"
    paths_per_pose = 500
    [[job]]                     # explicit jobs ...
    scene = "sphere"
    [[sweep]]                   # ... and products: a list is an axis
    mesh = "meshes/*.obj"       # a glob is an axis too
    snr_db = [10, 20]
    seed = [0, 1]

A job is one :func:`sonarsim.simulate.simulate` run. Its keys are the batch's own
(``name``, ``scene`` | ``mesh`` with ``fit``/``ground``, ``poses``, ``pulse``, ``fs``,
``pulse_samples``, ``reconstruct``) and every field of
:class:`sonarsim.simulate.SimulationSettings` (``snr_db``, ``seed``, ``paths_per_pose``, ...,
and whatever fields the simulator gains later), passed through as they are.

:func:`plan_batch` expands and validates the whole manifest before anything runs: every
scene and mesh is loaded, every trajectory, pulse and setting is checked, every output name
is unique; a bad job raises :class:`~sonarsim.errors.InputError` naming it.

**Identity.** A job's id is a digest of everything that determines its dataset: the
parameters, the effective settings (defaults included), the scene's geometry, the poses and
the pulse samples. It is stored in the dataset (meta ``batch_job_id``, with the parameters
as ``batch_job``). A re-run skips a job only when its output is a *complete* dataset (the
file's own completeness marker, checked by :func:`sonarsim.dataset.inspect`) with the same
id; anything else is simulated again (an interrupted one resumes from its ``.partial`` file).
Reconstructions store their own id (volume param ``batch_step_id``).

:func:`run_batch` runs the jobs on a :class:`sonarsim.batch_engine.Engine` and records
every job in ``DIR/batch.csv``.

Modules: ``manifest`` (TOML, expansion, a job's parameters), ``identity`` (digests and job
ids), ``naming`` (output names), ``plan`` (:func:`plan_batch`, :class:`Job`,
:class:`ReconStep`, :class:`Plan`), ``records`` (what is complete on disk), ``locks``,
``tasks`` (what the workers run), ``table`` (``batch.csv``), ``run`` (:func:`run_batch`).
The reconstruction steps' schema and code belong to recon (``recon.batch_step``, reached
through the ``sonarsim.batch_steps`` entry point).
"""
from __future__ import annotations

from .identity import (identity_params, job_id_of, job_meta, poses_digest, pulse_digest,
                       scene_digest, settings_digest, step_id_of)
from .locks import OutputBusy, locked
from .manifest import (BATCH_KEYS, DEFAULT_PULSE, EXECUTION_ONLY, NOT_SETTINGS, TOP_KEYS,
                       canonical_params, default_fs, expand_manifest, load_manifest,
                       settings_fields)
from .naming import NAME_RE, default_names
from .plan import (MAX_JOBS, RECON_ENTRY_POINTS, Job, Plan, ReconStep, build_simulation,
                   check_collisions, check_existing, job_files, load_job_scene, plan_batch,
                   preflight, recon_plugin, recon_step)
from .records import (SUMMARY_METRICS, dataset_record, existing_owner, fidelity, step_record,
                      summary_metrics)
from .run import NOT_RUN, BatchResult, JobState, job_state, run_batch
from .table import CSV_NAME, BatchTable, read_previous_csv
from .tasks import run_reconstruction, run_simulation

__all__ = ["BATCH_KEYS", "BatchResult", "BatchTable", "CSV_NAME", "DEFAULT_PULSE",
           "EXECUTION_ONLY", "Job", "JobState", "MAX_JOBS", "NAME_RE", "NOT_RUN",
           "NOT_SETTINGS", "OutputBusy", "Plan", "check_collisions", "check_existing",
           "existing_owner", "job_files", "job_state", "preflight",
           "RECON_ENTRY_POINTS", "ReconStep", "SUMMARY_METRICS", "TOP_KEYS",
           "build_simulation", "canonical_params", "dataset_record", "default_fs",
           "default_names", "expand_manifest", "fidelity", "identity_params", "job_id_of",
           "job_meta", "load_job_scene", "load_manifest", "locked", "plan_batch",
           "poses_digest", "pulse_digest", "read_previous_csv", "recon_plugin", "recon_step",
           "run_batch", "run_reconstruction", "run_simulation", "scene_digest",
           "settings_digest", "settings_fields", "step_id_of", "step_record",
           "summary_metrics"]
