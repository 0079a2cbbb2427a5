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


def test_separate_parts_above_the_ground_are_kept_floaters_on_it_dropped():
    """Step 2's part rule on 1 cm voxels (box 0.39 m, lowest plane z = 0): a shell (2 920
    voxels) and three 48-voxel blocks, 1.6 % of it: one whose top is 30 cm up (kept with
    part_volume 40 cm³ and part_height 5 cm), one lying on the ground, top 3 cm (dropped: a
    floater's place), one up high but of 27 voxels (dropped: too small)."""
    shell, _, _ = _shell(centre=(20, 20, 20), r=10.0)
    mask = shell.copy()
    mask[2:6, 2:6, 27:30] = True               # 48 voxels, top z index 29
    mask[33:37, 33:37, 0:3] = True             # 48 voxels on the ground, top z index 2
    mask[2:5, 33:36, 30:33] = True             # 27 voxels, high up
    bounds = np.array([[0.0, 0.39]] * 3)       # spacing 1 cm
    kw = dict(min_fraction=0.1, close=0, bounds=bounds, part_height=0.05)
    out = solid.solidify(_as_field(mask), part_volume=40e-6, **kw)
    assert out[2:6, 2:6, 27:30].all() and out[20, 20, 20]
    assert not out[33:37, 33:37, 0:3].any()
    assert not out[2:5, 33:36, 30:33].any()
    # off (part_volume 0), the 10 % rule drops all three; a lower height keeps the grounded one
    off = solid.solidify(_as_field(mask), part_volume=0.0, **kw)
    assert not off[2:6, 2:6, 27:30].any() and not off[33:37, 33:37, 0:3].any()
    low = solid.solidify(_as_field(mask), part_volume=40e-6, **dict(kw, part_height=0.02))
    assert low[33:37, 33:37, 0:3].all()
    assert solid.part_rule(40e-6, 0.05, np.array([0.01, 0.01, 0.01])) == (40, 5)
    with pytest.raises(InputError, match="part_volume > 0 needs the bounds"):
        solid.solidify(_as_field(mask), part_volume=40e-6)
    with pytest.raises(InputError, match="part_height"):
        solid.solidify(_as_field(mask), part_volume=40e-6, bounds=bounds, part_height=-1.0)


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


# ------------------------------------------------ step 5: what no sensor saw is filled

def _ring(elevation_deg, count=24, radius=200.0, centre=(20.0, 20.0, 20.0)):
    """Sensor positions (voxel units, spacing 1) on a horizontal ring around ``centre``, seen
    from the centre at ``elevation_deg`` above the horizon."""
    az = np.linspace(0, 2 * np.pi, count, endpoint=False)
    el = np.deg2rad(elevation_deg)
    return np.asarray(centre) + radius * np.stack(
        [np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.full_like(az, np.sin(el))], 1)


def _box_with_chimney():
    """A hollow box (walls 2 voxels) whose cavity opens to the top through a 4×4 chimney:
    its inside is joined to the outside, so step 4 alone cannot fill it."""
    box = np.zeros((N,) * 3, dtype=bool)
    box[10:30, 10:30, 10:30] = True
    cavity = np.zeros_like(box)
    cavity[12:28, 12:28, 12:28] = True
    box &= ~cavity
    box[18:22, 18:22, 28:30] = False
    cavity[18:22, 18:22, 28:30] = True
    return box, cavity


def test_cavity_hidden_from_a_side_looking_scan_is_filled():
    """Sensors that look at the box from the side (10° up) never see into the cavity through
    the chimney: step 5 fills it; outside the box, only the plane right under its floor (the
    box's shadow, within the one-voxel margin searched) is hidden too."""
    box, cavity = _box_with_chimney()
    bounds = np.array([[0.0, N - 1.0]] * 3)
    kw = dict(threshold=0.5, min_fraction=0.0, close=0, floor=False)
    plain = solid.solidify(_as_field(box), **kw)
    assert not plain[cavity].any()
    out = solid.solidify(_as_field(box), hidden=24, sensors=_ring(10.0), bounds=bounds, **kw)
    assert out[:, :, :28][cavity[:, :, :28]].all()
    extra = out & ~(box | cavity)
    assert np.array_equal(np.flatnonzero(extra.any(axis=(0, 1))), [9])
    assert not extra[:, :, 9][~box[:, :, 10]].any()


def test_cavity_seen_from_above_stays_open():
    """The same box seen from steep sensors (80° up) is looked into through the chimney: the
    cavity's voxels under the chimney are visible and stay empty."""
    box, cavity = _box_with_chimney()
    bounds = np.array([[0.0, N - 1.0]] * 3)
    out = solid.solidify(_as_field(box), threshold=0.5, min_fraction=0.0, close=0, floor=False,
                         hidden=24, sensors=_ring(80.0), bounds=bounds)
    assert not out[19:21, 19:21, 14:28].any()


def _hidden_by_marching(occupied, directions, quorum=1.0):
    """Straightforward reference: per empty voxel and direction, walk t = 1, 2, ... voxels
    along the direction (rounded to the nearest voxel) until a True voxel or the box's edge;
    hidden when the walk met a True voxel for at least ``quorum`` × K of the K directions."""
    shape = np.array(occupied.shape)
    out = np.zeros_like(occupied)
    for v in np.argwhere(~occupied):
        blocked = 0
        for d in directions:
            t = 1
            while True:
                p = v + np.round(t * d).astype(int)
                if np.any(p < 0) or np.any(p >= shape):
                    break
                if occupied[tuple(p)]:
                    blocked += 1
                    break
                t += 1
        out[tuple(v)] = blocked >= quorum * len(directions)
    return out


@pytest.mark.parametrize("quorum", [1.0, 0.6, 0.34])
def test_hidden_from_matches_a_voxel_by_voxel_march(quorum):
    rng = np.random.default_rng(3)
    occupied = rng.random((9, 8, 7)) < 0.35
    occupied[0, 0, 0] = occupied[-1, -1, -1] = True   # the bounding box is the whole array
    sensors = np.array([[50.0, 3.0, 20.0], [-40.0, -30.0, 10.0], [4.0, 60.0, -5.0]])
    got = solid.hidden_from(occupied, np.ones(3), sensors, 3, quorum)
    centre = np.argwhere(occupied).mean(0)
    directions = solid.sensor_directions(sensors, 3, centre)
    assert np.array_equal(got, _hidden_by_marching(occupied, directions, quorum))
    assert 0 < got.sum() < (~occupied).sum()


def _porous_box():
    """A hollow box (walls 2 voxels) with a 2×2 pore through the middle of each side wall:
    a few sensors of a ring look through a pore into the cavity."""
    box = np.zeros((N,) * 3, dtype=bool)
    box[10:30, 10:30, 10:30] = True
    cavity = np.zeros_like(box)
    cavity[12:28, 12:28, 12:28] = True
    box &= ~cavity
    box[10:12, 19:21, 19:21] = box[28:30, 19:21, 19:21] = False
    box[19:21, 10:12, 19:21] = box[19:21, 28:30, 19:21] = False
    return box, cavity


def test_quorum_fills_a_porous_shell_that_every_sensor_rule_leaves_open():
    """Of 24 sensors on a ring 10° up, those facing a pore see into the cavity: hidden from
    every sensor (quorum 1) leaves the voxels on their lines empty, hidden from 80 % of them
    fills the whole cavity."""
    box, cavity = _porous_box()
    bounds = np.array([[0.0, N - 1.0]] * 3)
    kw = dict(threshold=0.5, min_fraction=0.0, close=0, floor=False, hidden=24,
              sensors=_ring(10.0), bounds=bounds)
    every = solid.solidify(_as_field(box), **kw)
    assert not every[cavity].all()
    assert solid.solidify(_as_field(box), quorum=0.8, **kw)[cavity].all()


def test_quorum_keeps_an_opening_most_sensors_look_into():
    """The chimney box seen from 80° up: every sensor looks down the chimney, so the voxels
    under it stay empty with a quorum of 0.8 as with 1."""
    box, cavity = _box_with_chimney()
    bounds = np.array([[0.0, N - 1.0]] * 3)
    out = solid.solidify(_as_field(box), threshold=0.5, min_fraction=0.0, close=0, floor=False,
                         hidden=24, sensors=_ring(80.0), bounds=bounds, quorum=0.8)
    assert not out[19:21, 19:21, 14:28].any()


@pytest.mark.parametrize("quorum", [0.0, -0.5, 1.5, float("nan")])
def test_quorum_outside_zero_one_is_refused(quorum):
    with pytest.raises(InputError, match="quorum"):
        solid.solidify(np.ones((4, 4, 4)), hidden=4, sensors=np.ones((2, 3)),
                       bounds=np.array([[0.0, 1.0]] * 3), quorum=quorum)


def test_hidden_needs_sensors_and_bounds():
    with pytest.raises(InputError, match="sensor"):
        solid.solidify(np.ones((4, 4, 4)), hidden=4)
    with pytest.raises(InputError, match="hidden"):
        solid.solidify(np.ones((4, 4, 4)), hidden=-1)


def test_hidden_fill_on_a_grid_one_voxel_thick():
    """A 2-D grid (one z plane: zero z spacing from the bounds) gives the same solid as the
    same plane given a z extent of one voxel, without NaN steps: a C open away from every
    sensor has its cavity filled."""
    import warnings
    vol = np.zeros((15, 15, 1))
    vol[3:12, 3, 0] = vol[3:12, 11, 0] = vol[3, 3:12, 0] = 1.0      # the C: walls at y 3, y 11, x 3
    sensors = np.array([[-1.0, 0.3, 0.1], [-1.0, -0.3, 0.1], [-1.0, 0.0, 0.1]])
    flat = np.array([[0.0, 0.14], [0.0, 0.14], [0.1, 0.1]])
    thick = np.array([[0.0, 0.14], [0.0, 0.14], [0.1, 0.11]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = solid.solidify(vol, threshold=0.5, close=0, hidden=3, sensors=sensors, bounds=flat)
    expected = solid.solidify(vol, threshold=0.5, close=0, hidden=3, sensors=sensors, bounds=thick)
    assert np.array_equal(got, expected)
    assert got[4:11, 4:11, 0].all() and got.sum() > (vol > 0.5).sum()


# Step 6: open cavities whose floor the data do not show. A square box of walls (x, y in
# 10..29, walls 2 voxels thick) standing on the ground, 1 cm voxels; sensors on a ring 3 m
# away, 10°–40° above the box's half height, so step 5 fills the box's lower part (hidden
# from every sensor) and leaves an open cavity under the rim.
def _walls(top=30):
    box = np.zeros((N, N, N), dtype=bool)
    box[10:30, 10:30, 0:top] = True
    box[12:28, 12:28, 0:top] = False
    return box


def _ring_sensors(count=64):
    az = np.linspace(0, 2 * np.pi, count, endpoint=False)
    el = np.deg2rad(np.linspace(10, 40, count))
    centre = np.array([0.195, 0.195, 0.15])
    return centre + 3.0 * np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el),
                                    np.sin(el)], axis=1)


BOUNDS = np.array([[0.0, 0.39]] * 3)          # 1 cm voxels


def _solid(field, **kw):
    return solid.solidify(field, threshold=0.5, close=0, hidden=64, sensors=_ring_sensors(),
                          bounds=BOUNDS, **kw)


def test_open_box_without_a_floor_in_the_data_is_filled_to_its_rim():
    walls = _walls()
    base = _solid(_as_field(walls))
    inside = np.zeros_like(walls)
    inside[12:28, 12:28, 0:30] = True
    k = np.indices(walls.shape)[2]
    lower, upper = inside & (k < 13), inside & (k >= 25)
    assert base[lower].all() and not base[upper].any()       # step 5 alone: an open cavity
    filled = _solid(_as_field(walls), cavity_floor=0.03)
    assert filled[inside].all()                               # step 6: filled up to the rim
    assert not filled[:, :, 30:].any()                        # and not above it


def test_container_with_its_floor_in_the_data_stays_open():
    """A tray: the same walls 8 voxels high with a floor plate (data) 2 voxels thick above
    the ground; its cavity's floor voxels rest on the plate, so step 6 keeps it open."""
    tray = _walls(top=8)
    tray[12:28, 12:28, 2:4] = True
    field = _as_field(tray)
    kept = _solid(field, cavity_floor=0.03)
    assert np.array_equal(kept, _solid(field))
    assert not kept[13:27, 13:27, 4:8].any()


def test_floorless_cavities_counts_support_within_reach():
    walls = _walls()
    occupied = walls.copy()
    occupied[12:28, 12:28, :20] = True                        # a fill level at k = 20
    data = walls.copy()
    cavity = np.zeros_like(walls)
    cavity[12:28, 12:28, 20:30] = True
    assert np.array_equal(solid.floorless_cavities(occupied, data, 3), cavity)
    data[12:28, 12:28, 17] = True                             # a data plate 3 below the floor
    assert not solid.floorless_cavities(occupied, data, 3).any()
    assert np.array_equal(solid.floorless_cavities(occupied, data, 2), cavity)
    # the ground counts as a floor within reach: a fill level at k = 2
    low = walls.copy()
    low[12:28, 12:28, :2] = True
    assert not solid.floorless_cavities(low, walls, 2).any()
    assert solid.floorless_cavities(low, walls, 2, ground=False).any()
    # a ring on the ground (no floor voxels at all) stays open
    assert not solid.floorless_cavities(walls, walls, 3).any()


@pytest.mark.parametrize("value", [-0.01, float("nan"), float("inf")])
def test_cavity_floor_out_of_range_is_refused(value):
    with pytest.raises(InputError, match="cavity_floor"):
        solid.solidify(np.ones((4, 4, 4)), bounds=BOUNDS, cavity_floor=value)


def test_cavity_floor_needs_bounds():
    with pytest.raises(InputError, match="bounds"):
        solid.solidify(np.ones((4, 4, 4)), cavity_floor=0.02)


# Step 1's options: a smoothed magnitude and a cut on the field's own Otsu level (the `gd`
# preset's since 2026-11-28; docs/reconstruction.md "Smoothed magnitude, Otsu level").

def _two_class(rng, n_background=4000, n_surface=1000):
    """Relative magnitudes of two classes, background in [0.03, 0.15], surface in [0.6, 0.9],
    plus many empty voxels (0) as in a reconstruction box."""
    values = np.concatenate([rng.uniform(0.03, 0.15, n_background),
                             rng.uniform(0.6, 0.9, n_surface), np.zeros(20000), [1.0]])
    return values.reshape(1, 1, -1)


def test_otsu_level_splits_the_two_classes_above_the_floor():
    from skimage.filters import threshold_otsu
    relative = _two_class(np.random.default_rng(1))
    level = solid.threshold_level(relative, 1.0, "otsu")
    assert 0.14 < level < 0.6          # between the classes (to a 256-bin histogram's resolution)
    assert solid.threshold_level(relative, 2.0, "otsu") == pytest.approx(2 * level)
    # the voxels at or below the floor take no part: more empty box, the same level
    more_empty = np.concatenate([relative.ravel(), np.full(100000, 0.01)]).reshape(1, 1, -1)
    assert solid.threshold_level(more_empty, 1.0, "otsu") == level
    assert threshold_otsu(more_empty.ravel()) != level     # (they would move it)
    assert solid.threshold_level(relative, 0.3, "peak") == 0.3


def test_otsu_cut_follows_the_field_not_its_brightest_voxel():
    shell, d, _ = _shell()
    field = _as_field(shell, level=0.3)
    field[0, 0, 39] = 1.0                       # a specular glint: the peak, far above the shell
    peak_cut = solid.solidify(field, threshold=0.5, min_fraction=0.0, close=0)
    # (the Otsu split of a large dim class and a small bright one lies at the dim class's top
    # edge; hence a factor above 1, as the preset's 1.7)
    otsu_cut = solid.solidify(field, threshold=1.5, threshold_mode="otsu", min_fraction=0.0, close=0)
    assert not peak_cut[shell].any()            # half the glint is above the whole shell
    assert otsu_cut[shell].all() and otsu_cut[d < 10].all()        # shell kept and filled
    assert not otsu_cut[(d > 14) & (d < 18)].any()                  # background stays out
    scaled = solid.solidify(field * 1e-3, threshold=1.5, threshold_mode="otsu", min_fraction=0.0,
                            close=0)
    assert (scaled == otsu_cut).all()           # scale-free


def test_blur_closes_a_shell_speckled_voxel_by_voxel():
    shell, d, _ = _shell()
    rng = np.random.default_rng(0)
    # half of the shell's voxels dark (above the cubic lattice's site-percolation threshold,
    # 0.31): the dark voxels join the inside to the outside through the shell
    speckle = np.where(rng.random(shell.shape) < 0.5, 1.0, 0.1)
    field = np.where(shell, speckle, 0.02).astype(np.complex64)
    raw = solid.solidify(field, threshold=0.2, min_fraction=0.0, close=0)
    smooth = solid.solidify(field, threshold=0.2, min_fraction=0.0, close=0, blur=0.7)
    assert not raw[d < 8].any()                 # porous: nothing filled
    assert smooth[d < 8].all()                  # smoothed within ~2 voxels the shell is closed
    assert not smooth[d > 15].any()


def test_plain_rule_is_unchanged_without_blur_or_otsu():
    shell = _shell()[0]
    field = _as_field(shell)
    assert (solid.thresholded(field, 0.3) == solid.occupancy(field, 0.3)).all()
    assert solid.relative_magnitude(np.zeros((3, 3, 3)), 0.7).max() == 0
    empty = solid.solidify(np.zeros((6, 6, 6)), threshold=1.7, threshold_mode="otsu", blur=0.7)
    assert not empty.any()                      # nothing above the floor: nothing occupied


@pytest.mark.parametrize("kw", [dict(blur=-1.0), dict(blur=float("nan")), dict(blur=11.0),
                                dict(threshold_mode="mean"),
                                dict(threshold=0.0, threshold_mode="otsu"),
                                dict(threshold=60.0, threshold_mode="otsu")])
def test_bad_blur_and_threshold_modes_are_refused(kw):
    with pytest.raises(InputError):
        solid.solidify(np.ones((4, 4, 4)), **kw)
    # a factor above 1 is fine with the Otsu mode
    solid.solidify(np.ones((4, 4, 4)), threshold=1.7, threshold_mode="otsu")


# ------------------------------------------------ step 7: the boundary smoothed

def _block(lo=(10, 10, 0), hi=(30, 30, 20)):
    """A box of voxels standing on the lowest plane (z index 0)."""
    out = np.zeros((N, N, N), dtype=bool)
    out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    return out


def test_smoothing_removes_bumps_and_dents_and_keeps_flat_faces():
    clean = _block()
    rough = clean.copy()
    rough[30:32, 18:20, 8:10] = True        # a 2-voxel bump on the +x face
    rough[10:12, 20:22, 12:14] = False      # a 2-voxel dent in the -x face
    rough[18:20, 14:16, 20] = True          # a 1-voxel bump on the top
    out = solid.smooth_boundary(rough, 2.0)
    inner = (slice(13, 27), slice(13, 27), slice(0, 17))
    assert out[inner].all() and (out == clean)[10:30, 13:27, 0:17].all()   # faces flat again
    assert not out[30:32, 18:20, 8:10].any() and out[10:12, 20:22, 12:14].all()
    assert not out[18:20, 14:16, 20].any()
    # only edges and corners rounded: 5.7 % of a 20-voxel block (1/3 of that at the cube's 62)
    assert 0 < int(clean.sum()) - int(out.sum()) < 0.07 * clean.sum()


def test_smoothing_keeps_the_base_on_the_ground_and_zero_is_identity():
    block = _block()
    out = solid.smooth_boundary(block, 2.5)
    assert out[13:27, 13:27, 0].all()           # not rounded where the box cuts it
    assert np.array_equal(solid.smooth_boundary(block, 0.0), block)
    assert not solid.smooth_boundary(np.zeros((4, 4, 4), bool), 1.0).any()


@pytest.mark.parametrize("sigma, kept, lost", [(1.5, 3, 2), (2.0, 4, 2), (2.5, 5, 3)])
def test_smoothing_thins_walls_below_its_width(sigma, kept, lost):
    """The documented limit: a wall ``kept`` voxels thick survives whole, one ``lost`` voxels
    thick is gone."""
    for width, survives in ((kept, True), (lost, False)):
        wall = np.zeros((N, N, N), dtype=bool)
        wall[5:35, 12:12 + width, 0:30] = True
        wall[5:35, 28:38, 0:30] = True           # the body the wall stands apart from
        wall[5:35, 12 + width:28, 0:3] = True    # joined to it by a slab on the ground
        out = solid.smooth_boundary(wall, sigma)
        assert out[10:30, 12:12 + width, 5:25].all() == survives
        assert out[10:30, 12:12 + width, 5:25].any() == survives
        assert out[10:30, 31:35, 5:25].all()


def test_smoothing_never_erases_a_whole_part():
    """A separate part of which nothing would remain (a point target's blob, a thin plate) is
    kept as it was; the block beside it is smoothed."""
    occupied = _block()
    occupied[34:36, 34:36, 30:32] = True     # a 2-voxel blob, gone under any smoothing
    occupied[2:8, 2:38, 30] = True           # a plate one voxel thick
    occupied[30, 18:20, 8:10] = True         # a bump on the block
    out = solid.smooth_boundary(occupied, 1.0)
    assert out[34:36, 34:36, 30:32].all() and out[2:8, 2:38, 30].all()
    assert not out[30, 18:20, 8:10].any()


def test_solidify_applies_the_smoothing_last():
    rough = _block()
    rough[30:32, 18:20, 8:10] = True
    field = _as_field(rough)
    plain = solid.solidify(field, threshold=0.5, min_fraction=0.0, close=0)
    smooth = solid.solidify(field, threshold=0.5, min_fraction=0.0, close=0, smooth=2.0)
    assert np.array_equal(plain, rough)
    assert not smooth[30:32, 18:20, 8:10].any() and smooth[10:30, 13:27, 0:17].all()
    with pytest.raises(InputError, match="smooth"):
        solid.solidify(field, smooth=-1.0)
