"""Neural backprojection (Reed et al., SIGGRAPH 2023, §4; reference
``inr_reconstruction/reconstruct_scene.py``): a hash-grid + MLP complex field
(:mod:`recon.field`) fitted through the ellipsoidal forward model by the solver of
:mod:`recon.solver` — the same code as gradient descent with a network in place of voxels.

``preset='nbp'`` (the default, frozen: :data:`recon.solver.PRESETS`) is sized for a 2-core
CPU (12 hash levels, a 32-wide MLP with 1 hidden layer, 5 pings × 64 bins × 600 rays per
step; the same sizes as ``preset='cpu'``); ``preset='reference'`` has the reference's sizes
(14 levels, 128 × 3, 200 bins, 4777 rays) for a GPU variant. The frozen preset exports the
solid occupancy of the field (:mod:`recon.solid`, threshold 0.3, hidden voxels filled: 1
inside, 0 outside);
``output='field'`` exports the complex field itself (docs/reconstruction.md, "Solid output").
"""
from __future__ import annotations

from . import solver
from .grid import Grid


BYTES_PER_VOXEL = solver.resources.NBP_BYTES_PER_VOXEL


def check_options(grid: Grid, preset: str | None = solver.DEFAULT_PRESET[True], **options) -> None:
    """Refuse, before any work, what :func:`solve` would refuse (ranges, lane limit, memory
    estimate): the command line and ``sonarsim batch`` call this."""
    solver.check_options(grid, True, preset, **options)


def settings_for(preset: str | None = solver.DEFAULT_PRESET[True], **overrides) -> solver.SolverSettings:
    return solver.settings_for(preset, network=True, **overrides)


def solve(dataset, grid: Grid, *, preset: str | None = solver.DEFAULT_PRESET[True],
          checkpoint=None,
          checkpoint_every: int = solver.CHECKPOINT_EVERY, resume: bool = False,
          progress: bool = True, callback=None, export_grid: Grid | None = None, **overrides):
    """Fit the neural field to ``dataset`` over ``grid``'s box; returns a Volume (method
    'nbp') sampled on ``export_grid`` (default ``grid``; any resolution). Any
    :class:`~recon.solver.SolverSettings` field can be given as a keyword."""
    return solver.solve(dataset, grid, network=True, method="nbp", preset=preset,
                        checkpoint=checkpoint, checkpoint_every=checkpoint_every, resume=resume,
                        progress=progress, callback=callback, export_grid=export_grid,
                        **overrides)
