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


#: The analytic sphere of the renderer's closed-form tests: radius (m), centred at the origin.
SPHERE_RADIUS = 0.1


@pytest.fixture(scope="session")
def sphere_scene(mi):
    """One analytic Mitsuba sphere (radius :data:`SPHERE_RADIUS`, centre at the origin, white
    Lambertian, albedo 1): exact intersections and normals (a triangle mesh would bias a cap
    integral by far more than 1 %). Shared by the renderer's tests; do not modify it."""
    return mi.load_dict({"type": "scene", "target": {
        "type": "sphere", "radius": SPHERE_RADIUS, "center": [0, 0, 0],
        "bsdf": {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 1.0}}}})


#: The point target of the solver tests (m), between the voxel centres of point_target_grid.
POINT_TARGET = (0.004, -0.006, 0.1015)


@pytest.fixture(scope="session")
def point_target_scan():
    """A noiseless 20-ping circular scan at 6 heights (0 .. 0.25 m) of one point at
    :data:`POINT_TARGET` (:func:`recon.synthetic.point_dataset`), made once."""
    import numpy as np
    from recon import synthetic
    return synthetic.point_dataset([np.array(POINT_TARGET)], n_pings=20,
                                   heights=np.linspace(0.0, 0.25, 6))


@pytest.fixture(scope="session")
def point_target_grid():
    """A 21 x 21 x 21 grid of 2 mm voxels, x, y in [-0.02, 0.02] m, z in [0.08, 0.12] m."""
    from recon.grid import Grid
    return Grid([[-0.02, 0.02], [-0.02, 0.02], [0.08, 0.12]], (21, 21, 21))


def within_one_voxel(index, grid, point) -> bool:
    """Whether voxel ``index`` of ``grid`` (:class:`recon.grid.Grid`) has its centre within one
    voxel pitch of ``point`` (m) on every axis: a focus test's tolerance."""
    import numpy as np
    return bool(np.all(np.abs(grid.position_of(index) - np.asarray(point)) <= grid.spacing + 1e-12))


#: Test modules by measured CPU time, the costliest first (house, 2026-11-25 03:25: CPU-s per
#: file of ``make test``'s -n 2 run at 5cde4be on the shared 2-core machine, test_batch after
#: bcf8bdc: test_table2 64, test_metrics 28, test_batch 22, test_refine 20, test_examples 19,
#: test_nbp 19, test_reliability 17, test_plot 15, test_layout 12, test_simulate 10,
#: test_scattering 9, test_runtime 8, test_gradient_descent 8, test_fidelity 6,
#: test_differentiable 5; every other file < 5). Under pytest-xdist (``make test``:
#: ``-n 2 --dist loadfile``) files are handed to the workers in this order, so the longest
#: ones start first and the short ones fill the gaps at the end.
COSTLIEST_FIRST = ("test_table2.py", "test_metrics.py", "test_batch.py", "test_refine.py",
                   "test_examples.py", "test_nbp.py", "test_reliability.py", "test_plot.py",
                   "test_layout.py", "test_simulate.py", "test_scattering.py", "test_runtime.py",
                   "test_gradient_descent.py", "test_fidelity.py", "test_differentiable.py")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist only (a serial run keeps the file order): the costliest test files
    first (:data:`COSTLIEST_FIRST`), each file's tests in their own order."""
    import os
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    rank = {name: i for i, name in enumerate(COSTLIEST_FIRST)}
    order = {}
    for item in items:
        order.setdefault(item.nodeid.split("::")[0], len(order))
    items.sort(key=lambda it: (rank.get(it.nodeid.split("::")[0].rpartition("/")[2],
                                        len(rank)), order[it.nodeid.split("::")[0]]))


@pytest.fixture(autouse=True)
def _sigint_raises_keyboardinterrupt():
    """Each test runs with Python's own SIGINT handling (KeyboardInterrupt), as a command
    started from a shell gets it. pytest-xdist workers were seen running tests with SIGINT
    *ignored* (house, 2026-11-25: ``make test`` with -n 2, three runs out of three, never
    serially); a child process inherits an ignored SIGINT, so test_reliability's Ctrl-C
    test could not interrupt its ``recon backproject``. The worker's own setting is put back
    after the test."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    if ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


#: A tiny `recon nbp` run (after the dataset): a 9³ grid over point_target_grid's box, two
#: steps of a 4-level, 16-wide network from a random start (the CLI tests of test_nbp and
#: test_scattering).
TINY_NBP_OPTIONS = ("--bounds", "-0.02", "0.02", "-0.02", "0.02", "0.08", "0.12",
                    "--shape", "9", "9", "9", "--iterations", "2", "--hash-levels", "4",
                    "--hash-log2-size", "12", "--mlp-width", "16", "--mlp-hidden", "1",
                    "--n-rays", "200", "--bins-per-ping", "16", "--pings-per-iteration", "4",
                    "--beamwidth-deg", "5", "--seed", "3", "--init", "random")
