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


@pytest.mark.parametrize("window_m", [(0.10, 0.65), (0.10, 0.80), (1.45, 1.60), (1.38, 1.60),
                                      (0.95, 1.05)])
def test_grid_coverage_check_matches_the_paths_of_the_grid_points(window_m):
    """recon.checks.check_grid_sees_data refuses a grid iff no round-trip path tx -> point ->
    rx of the grid's box lies in the recorded window. Monostatic (tx = rx), where its bound
    is exact, against the paths of 41³ points of the box (corners and the nearest point
    included): windows ending just before / after the nearest path (0.721 m) and starting
    just after / before the farthest one (1.414 m), and one inside."""
    from types import SimpleNamespace

    from recon.checks import check_grid_sees_data
    c, fs = 343.0, 1e4
    first_k = int(np.ceil(window_m[0] * fs / c))
    last_k = int(np.floor(window_m[1] * fs / c))
    ds = SimpleNamespace(tx=np.zeros((1, 3)), rx=np.zeros((1, 3)), start_sample=first_k,
                         waveforms=np.zeros((1, last_k - first_k + 1)), fs=fs, sound_speed=c)
    bounds = [[0.3, 0.5], [0.2, 0.4], [-0.3, 0.3]]
    axes = [np.linspace(lo, hi, 41) for lo, hi in bounds]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    paths = 2 * np.linalg.norm(points, axis=1)
    seen = np.any((paths >= c * first_k / fs) & (paths <= c * last_k / fs))
    assert seen == (window_m in [(0.10, 0.80), (1.38, 1.60), (0.95, 1.05)])   # the geometry
    grid = Grid(bounds, (5, 5, 5))
    if seen:
        check_grid_sees_data(ds, grid)
    else:
        with pytest.raises(InputError, match="no voxel of the grid lies within"):
            check_grid_sees_data(ds, grid)


def test_index_of_is_the_nearest_centre_clipped_to_the_grid():
    g = Grid([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]], (11, 11, 11))        # centres 0.1 apart
    assert g.index_of([0.26, 0.34, 0.5]) == (3, 3, 5)                   # nearest, not floor
    assert g.index_of([-5.0, 2.0, 0.96]) == (0, 10, 10)                 # outside: clipped
    assert g.index_of(g.position_of((7, 2, 9))) == (7, 2, 9)


def test_voxel_size_rounds_the_count_of_pitches():
    """round((hi - lo) / size) + 1 centres per axis, from lo to hi (pitch adjusted)."""
    g = Grid.from_voxel_size([[0.0, 0.1], [0.0, 0.2], [0.0, 0.05]], 0.035)
    assert g.shape == (4, 7, 2)                        # 2.86 -> 3, 5.71 -> 6, 1.43 -> 1 pitches
    np.testing.assert_allclose(g.spacing, [0.1 / 3, 0.2 / 6, 0.05])
