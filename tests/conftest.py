"""Shared pytest fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The data shipped with sonarsim (:mod:`sonarsim.data`, docs/data.md): ``meshes/``,
    ``pulses/``, ``airsas_real/`` (the two scans as datasets, ``*.h5``, and the first 6 raw
    flights of each as LabVIEW CSV folders). Always present: nothing skips for want of data."""
    from sonarsim import data
    return data.root()


@pytest.fixture(scope="session")
def mi():
    """The mitsuba module with sonarsim's variant and plugins set up."""
    from sonarsim import runtime
    return runtime.mitsuba()


@pytest.fixture(scope="session")
def real_scan():
    """The real AirSAS 2-D scan of the cut-out target (360 pings, 5 kHz LFM), background
    subtracted: the shipped dataset ``sonarsim import-airsas`` made of it, read once."""
    from sonarsim import data
    return data.real_scan()


@pytest.fixture(scope="session")
def turntable_plane():
    """(grid, X, Y, near): the z = 0 plane over ±0.3 m (121² voxels), the voxel x, y and
    the mask of voxels within 0.15 m of the rotation axis (where the turntable's target is)."""
    import numpy as np
    from recon.grid import Grid
    g = Grid([[-0.3, 0.3], [-0.3, 0.3], [0.0, 0.0]], (121, 121, 1))
    x, y, _ = g.axes()
    X, Y = np.meshgrid(x, y, indexing="ij")
    return g, X, Y, np.hypot(X, Y) < 0.15
