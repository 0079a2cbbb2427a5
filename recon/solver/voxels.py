"""The voxel scene representation of gradient descent (complex voxels, trilinear)."""
from __future__ import annotations

import numpy as np

from .. import forward
from ..grid import Grid
from .settings import SolverSettings


class VoxelScene:
    """Complex voxels on the grid (trilinear, zero outside): parameters 're', 'im' [nx*ny*nz]."""

    kind = "voxels"

    def __init__(self, grid: Grid, settings: SolverSettings, incoherent: bool = False):
        self.grid, self.vf, self.incoherent = grid, forward.VoxelField(grid), incoherent
        self.h = self.vf.h

    def initial(self, rng: np.random.Generator, x0: np.ndarray | None) -> dict:
        n = self.grid.size
        return {"re": np.zeros(n, np.float32), "im": np.zeros(n, np.float32)}

    def with_start(self, params: dict, x0: np.ndarray) -> dict:
        """Parameters that represent the complex volume ``x0`` [nx, ny, nz] (added)."""
        return {"re": params["re"] + x0.real.ravel().astype(np.float32),
                "im": params["im"] + x0.imag.ravel().astype(np.float32)}

    def bind(self, params) -> forward.BoundVoxels:
        im = params["im"] * 0.0 if self.incoherent else params["im"]
        return self.vf.field(params["re"], im)

    def volume(self, params, grid: Grid | None = None) -> np.ndarray:
        """The complex volume [nx, ny, nz] (on ``grid``: trilinear resampling)."""
        import drjit as dr
        re, im = np.asarray(dr.detach(params["re"])), np.asarray(dr.detach(params["im"]))
        if self.incoherent:
            im = im * 0
        if grid is None or grid == self.grid:
            return (re + 1j * im).astype(np.complex64).reshape(self.grid.shape)
        m = self.vf.m
        pts = grid.points().T.astype(np.float32)
        a, b = self.vf.sample(m.Float(re), m.Float(im), m.Array3f(*(m.Float(p) for p in pts)))
        return (np.asarray(a) + 1j * np.asarray(b)).astype(np.complex64).reshape(grid.shape)
