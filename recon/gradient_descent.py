"""Gradient descent on complex voxels: the solver of :mod:`recon.solver` with a voxel scene
(the reference's ``--no_network`` baseline: the same sampling, forward model, loss and
optimiser as neural backprojection, :mod:`recon.nbp`).

Defaults (the frozen preset ``gd``, docs/reconstruction.md, "Presets"): start from the
backprojection scaled by its least-squares factor through the linear model, a learning rate
relative to that voxel scale decaying from 2e-2 to 2e-3, the linear model (no Lambertian
factor, no occlusion) with sparsity 2 in energy units from step 200; 5 pings × 110 bins ×
2000 rays per step. The exported volume is the solid occupancy of the fitted voxels
(:mod:`recon.solid`, threshold 0.5, hidden voxels filled; ``output='field'`` exports the
voxels themselves).

Grid mapping (a quirk of the reference fixed): the optimised voxels are exactly the
:class:`~recon.grid.Grid` centres, trilinear in between and zero outside, so GD and BP
volumes are comparable voxel by voxel.
"""
from __future__ import annotations

from . import solver
from .grid import Grid
from .solver import SolverSettings


BYTES_PER_VOXEL = solver.resources.GD_BYTES_PER_VOXEL


def check_options(grid: Grid, preset: str | None = solver.DEFAULT_PRESET[False], **options) -> None:
    """Refuse, before any work, what :func:`solve` would refuse (ranges, lane limit, memory
    estimate): the command line and ``sonarsim batch`` call this."""
    solver.check_options(grid, False, preset, **options)


def settings_for(preset: str | None = solver.DEFAULT_PRESET[False], **overrides) -> SolverSettings:
    """Settings of a voxel run from a preset and explicit overrides."""
    return solver.settings_for(preset, network=False, **overrides)


def solve(dataset, grid: Grid, *, checkpoint=None,
          checkpoint_every: int = solver.CHECKPOINT_EVERY, resume: bool = False,
          progress: bool = True, callback=None,
          preset: str | None = solver.DEFAULT_PRESET[False], **overrides):
    """Fit complex voxels on ``grid`` to ``dataset``; returns a Volume (method 'gd').

    Any :class:`~recon.solver.SolverSettings` field can be given as a keyword.
    """
    return solver.solve(dataset, grid, network=False, method="gd", preset=preset,
                        checkpoint=checkpoint, checkpoint_every=checkpoint_every, resume=resume,
                        progress=progress, callback=callback, **overrides)
