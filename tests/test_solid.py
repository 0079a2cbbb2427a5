"""recon.solid: the solid extraction of a reconstructed field (closed shells filled, open
objects and plates kept open, floaters dropped), checked on analytic voxel shapes."""
import numpy as np
import pytest

from recon import solid
from sonarsim.errors import InputError

N = 40


def _radius(centre):
    i, j, k = np.meshgrid(*(np.arange(N),) * 3, indexing="ij")
    return np.sqrt((i - centre[0]) ** 2 + (j - centre[1]) ** 2 + (k - centre[2]) ** 2), k


def _shell(centre=(20, 20, 20), r=12.0, width=1.5):
    d, k = _radius(centre)
    return (np.abs(d - r) < width), d, k


def _as_field(mask, rng=None, level=1.0):
    """A complex field bright (|σ| ≈ level) on ``mask``, dark (|σ| ≤ 0.05) elsewhere."""
    rng = np.random.default_rng(0) if rng is None else rng
    phase = np.exp(2j * np.pi * rng.random(mask.shape))
    mag = np.where(mask, level * (0.8 + 0.2 * rng.random(mask.shape)), 0.05 * rng.random(mask.shape))
    return (mag * phase).astype(np.complex64)


def test_closed_shell_becomes_the_solid_ball():
    shell, d, _ = _shell()
    out = solid.solidify(_as_field(shell))
    ball = d < 12.0 + 1.5
    assert (out == ball).all()
    assert out[d < 10].all() and not shell[d < 10].any()   # the interior was added


def test_pinhole_is_closed_only_with_closing():
    shell, d, k = _shell()
    holed = shell & ~((np.abs(d - 12) < 1.5) & (k > 30) & (np.hypot(*(np.indices((N, N, N))[:2] - 20)) < 1.0))
    assert holed.sum() < shell.sum()
    open_fill = solid.solidify(_as_field(holed), close=0)
    closed_fill = solid.solidify(_as_field(holed), close=1)
    assert open_fill.sum() < 1.1 * holed.sum()  # a hole: the interior is joined to the outside
    assert closed_fill[d < 10].all() and not open_fill[d < 10].any()


def test_bowl_open_upward_is_not_filled():
    shell, d, k = _shell(centre=(20, 20, 14), r=12.0)
    bowl = shell & (k <= 14)                   # lower half-shell resting on the floor (k = 2)
    out = solid.solidify(_as_field(bowl))
    inside = (d < 10) & (k <= 14)
    assert not out[inside].any()
    assert (out == bowl).all()


def test_dome_on_the_floor_is_filled_only_when_the_floor_closes_it():
    shell, d, k = _shell(centre=(20, 20, 0), r=14.0)
    dome = shell & (k >= 0)                     # upper half-shell standing on the z0 plane
    inside = d < 12
    assert solid.solidify(_as_field(dome), floor=True)[inside].all()
    assert not solid.solidify(_as_field(dome), floor=False)[inside].any()


def test_thin_plate_is_kept_as_is():
    plate = np.zeros((N, N, N), dtype=bool)
    plate[5:35, 5:35, 10:12] = True
    out = solid.solidify(_as_field(plate))
    assert (out == plate).all()


def test_floaters_are_dropped_and_big_objects_kept():
    shell, d, _ = _shell(centre=(20, 20, 20), r=10.0)
    mask = shell.copy()
    mask[2:4, 2:4, 35:37] = True               # a floater (8 voxels)
    mask[31:38, 31:38, 2:9] = True             # a second object: 343 voxels, 9 % of the shell
    assert 0.05 < 343 / shell.sum() < 0.3
    out = solid.solidify(_as_field(mask), min_fraction=0.05)
    assert not out[2:4, 2:4, 35:37].any()
    assert out[31:38, 31:38, 2:9].all()
    assert out[20, 20, 20]
    # a larger fraction also drops the second object
    assert not solid.solidify(_as_field(mask), min_fraction=0.3)[31:38, 31:38, 2:9].any()


def test_threshold_is_on_the_min_max_normalised_magnitude():
    shell = _shell()[0]
    field = _as_field(shell, level=1.0)
    field[0, 0, 39] = 1e3                       # one very bright voxel moves the peak
    out = solid.solidify(field, threshold=0.2, min_fraction=0.0)
    assert out[0, 0, 39] and not out[20, 20, 20]
    assert solid.occupancy(np.zeros((3, 3, 3)), 0.2).sum() == 0


@pytest.mark.parametrize("kw", [dict(threshold=1.0), dict(threshold=-0.1), dict(min_fraction=2.0),
                                dict(close=-1), dict(close=1.5)])
def test_bad_settings_are_refused(kw):
    with pytest.raises(InputError):
        solid.solidify(np.ones((4, 4, 4)), **kw)


def test_not_3d_is_refused():
    with pytest.raises(InputError, match="3-D"):
        solid.solidify(np.ones((4, 4)))
