"""Shared pytest fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the project; tests that need it skip where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


@pytest.fixture(scope="session")
def mi():
    """The mitsuba module with sonarsim's variant and plugins set up."""
    from sonarsim import runtime
    return runtime.mitsuba()


@pytest.fixture(scope="session")
def real_scan(shared_data):
    """The real AirSAS 2-D scan (background subtracted when the empty scan is there), read once."""
    from sonarsim.importers.airsas import import_airsas
    scan = shared_data / "airsas_real" / "small_features_cutout_5k"
    bg = shared_data / "airsas_real" / "bg_5k"
    if not scan.is_dir():
        pytest.skip("real AirSAS scan not present")
    return import_airsas(scan, bg if bg.is_dir() else None, progress=False)


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
