"""recon.grid: voxel-centre convention, ordering, defaults and input errors."""
import numpy as np
import pytest

from recon.grid import Grid, scene_box_of
from sonarsim import geometry
from sonarsim.errors import InputError


def test_centres_are_linspace_with_endpoints_and_single_voxel_at_lo():
    g = Grid([[-0.1, 0.1], [0.0, 0.3], [0.05, 0.05]], (5, 4, 1))
    x, y, z = g.axes()
    np.testing.assert_allclose(x, [-0.1, -0.05, 0.0, 0.05, 0.1])
    np.testing.assert_allclose(y, [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(z, [0.05])
    np.testing.assert_allclose(g.spacing, [0.05, 0.1, 0.0])
    assert g.size == 20


def test_points_are_c_order_over_x_y_z():
    g = Grid([[0, 1], [0, 2], [0, 3]], (2, 3, 4))
    pts = g.points()
    assert pts.shape == (24, 3)
    vol = pts.reshape(2, 3, 4, 3)
    # Index (ix, iy, iz) of the reshaped array sits at (x[ix], y[iy], z[iz]).
    x, y, z = g.axes()
    for ix, iy, iz in [(0, 0, 0), (1, 2, 3), (1, 0, 2), (0, 1, 3)]:
        np.testing.assert_allclose(vol[ix, iy, iz], [x[ix], y[iy], z[iz]])
        np.testing.assert_allclose(g.position_of((ix, iy, iz)), [x[ix], y[iy], z[iz]])
        assert g.index_of(vol[ix, iy, iz] + 0.1 * g.spacing) == (ix, iy, iz)


def test_single_voxel_axis_may_have_hi_below_lo_ignored_but_not_reversed():
    Grid([[0, 1], [0, 1], [0.2, 0.2]], (3, 3, 1))      # 2-D grid at z = 0.2
    with pytest.raises(InputError):
        Grid([[0, 1], [0, 1], [0.3, 0.2]], (3, 3, 1))


@pytest.mark.parametrize("bounds, shape", [
    ([[0, 1], [0, 1]], (2, 2, 2)),                   # bounds not [3, 2]
    ([[0, 1], [0, 1], [0, np.nan]], (2, 2, 2)),      # NaN
    ([[1, 0], [0, 1], [0, 1]], (2, 2, 2)),           # reversed
    ([[0, 1], [0, 0], [0, 1]], (2, 2, 2)),           # empty extent with 2 voxels
    ([[0, 1], [0, 1], [0, 1]], (2, 2)),              # two axes
    ([[0, 1], [0, 1], [0, 1]], (2, 0, 2)),           # zero voxels
    ([[0, 1], [0, 1], [0, 1]], (2, 2.5, 2)),         # non-integer
    ([[0, 1], [0, 1], [0, 1]], ("a", 2, 2)),
])
def test_bad_bounds_or_shape_raise_input_error(bounds, shape):
    with pytest.raises(InputError):
        Grid(bounds, shape)


def test_flat_six_number_bounds_accepted():
    g = Grid([0, 1, 2, 3, 4, 5], (2, 2, 2))
    np.testing.assert_allclose(g.bounds, [[0, 1], [2, 3], [4, 5]])


class _DS:
    def __init__(self, meta):
        self.meta = meta


def test_default_bounds_from_dataset_box_else_sim_box():
    g = Grid.from_dataset(_DS({"box": [[-0.1, 0.1], [-0.2, 0.2], [0.0, 0.25]]}), (3, 3, 3))
    np.testing.assert_allclose(g.bounds, [[-0.1, 0.1], [-0.2, 0.2], [0.0, 0.25]])
    g = Grid.from_dataset(_DS({}), (3, 3, 3))
    np.testing.assert_allclose(g.bounds[:, 0], geometry.SIM_BOX.lo)
    np.testing.assert_allclose(g.bounds[:, 1], geometry.SIM_BOX.hi)
    g = Grid.from_dataset(_DS({}), (3, 3, 1), bounds=[[0, 1], [0, 1], [0, 0]])
    assert g.shape == (3, 3, 1)


@pytest.mark.parametrize("meta", [
    {"box": [[-0.1, -0.2, 0.0], [0.1, 0.2, 0.25]]},          # [lo, hi] rows: not the convention
    {"box": [[0.1, -0.1], [-0.2, 0.2], [0.0, 0.25]]},        # x1 < x0
    {"box": [[0, 1], [0, 1], [0, float("nan")]]},
    {"box": "big"},
    {"box_lo": [-0.1, -0.1, 0.0], "box_hi": [0.1, 0.1, 0.2]},  # old keys: refused, not ignored
])
def test_bad_dataset_box_is_an_input_error(meta):
    with pytest.raises(InputError, match="box"):
        scene_box_of(_DS(meta))


def test_points_range_matches_points():
    g = Grid([[0, 1], [-1, 1], [0, 0.5]], (4, 3, 5))
    np.testing.assert_allclose(g.points_range(7, 29), g.points()[7:29])
    np.testing.assert_allclose(g.points_range(50, 100), g.points()[50:])


def test_single_voxel_rule_has_one_home():
    """Grid, Volume and export use one function, each with its declared single-voxel rule."""
    from recon import export
    from sonarsim.dataset.volume import Volume, voxel_spacing

    bounds, shape = np.array([[0.0, 0.4], [0.0, 0.2], [0.05, 0.9]]), (5, 3, 1)
    assert np.allclose(voxel_spacing(bounds, shape, "zero"), [0.1, 0.1, 0.0])
    assert np.allclose(voxel_spacing(bounds, shape, "min"), [0.1, 0.1, 0.1])
    nan = voxel_spacing(bounds, shape)
    assert np.allclose(nan[:2], [0.1, 0.1]) and np.isnan(nan[2])
    np.testing.assert_array_equal(Grid(bounds, shape).spacing, voxel_spacing(bounds, shape, "zero"))
    np.testing.assert_array_equal(export.voxel_spacing(bounds, shape), voxel_spacing(bounds, shape, "min"))
    vol = Volume(np.zeros(shape, np.complex64), bounds, "test")
    np.testing.assert_array_equal(vol.voxel_size(), nan)
    with pytest.raises(ValueError):
        voxel_spacing(bounds, (1, 1, 1), "min")
