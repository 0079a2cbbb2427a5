"""Checks of sonarsim.geometry against hand-computed poses and the reference crop window."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sonarsim import geometry as g
from sonarsim.errors import FormatError, InputError

CENTER_Z = 0.1775


@pytest.fixture(scope="module")
def full_scan() -> g.Poses:
    return g.trajectory("cylindrical")


@pytest.mark.parametrize("angle,height,tx,rx", [
    # angle 0: the rig frame itself, minus the centre, plus the height
    (0.0, 0.005, (0, -0.8485, 0.285 - CENTER_Z + 0.005), (0, -0.8615, 0.247 - CENTER_Z + 0.005)),
    # +90° about +z maps -y to +x
    (90.0, 0.005, (0.8485, 0, 0.285 - CENTER_Z + 0.005), (0.8615, 0, 0.247 - CENTER_Z + 0.005)),
    (180.0, 0.75, (0, 0.8485, 0.285 - CENTER_Z + 0.75), (0, 0.8615, 0.247 - CENTER_Z + 0.75)),
    (45.0, 0.1, (0.8485 / math.sqrt(2), -0.8485 / math.sqrt(2), 0.285 - CENTER_Z + 0.1),
     (0.8615 / math.sqrt(2), -0.8615 / math.sqrt(2), 0.247 - CENTER_Z + 0.1)),
])
def test_pose_formula_by_hand(angle, height, tx, rx):
    poses = g.rig_poses([angle], [height])
    np.testing.assert_allclose(poses.tx[0], tx, atol=1e-12)
    np.testing.assert_allclose(poses.rx[0], rx, atol=1e-12)
    # boresights: unit vectors from each transducer to the box centre (0, 0, 0.15)
    centre = np.array([0.0, 0.0, 0.15])
    for pos, b in ((poses.tx[0], poses.tx_boresight[0]), (poses.rx[0], poses.rx_boresight[0])):
        expected = (centre - pos) / np.linalg.norm(centre - pos)
        np.testing.assert_allclose(b, expected, atol=1e-12)


def test_renderer_config_pose():
    # the reference renderer's simulated first pose
    p = g.trajectory("cylindrical")[0]
    np.testing.assert_allclose(p.tx[0], (0, -0.8485, 0.1125), atol=1e-12)
    np.testing.assert_allclose(p.rx[0], (0, -0.8615, 0.0745), atol=1e-12)


def test_scene_box():
    box = g.SIM_BOX
    corners = box.corners()
    assert corners.shape == (8, 3)
    assert len({tuple(c) for c in corners}) == 8
    np.testing.assert_allclose(corners.mean(axis=0), box.center)
    np.testing.assert_allclose(box.center, (0, 0, 0.15))
    assert g.SceneBox.from_bounds(box.bounds) == box
    assert box.contains([[0, 0, 0.1], [0, 0, 0.31]]).tolist() == [True, False]
    with pytest.raises(InputError):
        g.SceneBox((0, 0, 0), (1, -1, 1))
    with pytest.raises(InputError):
        g.SceneBox((0, 0, np.nan), (1, 1, 1))


def test_cylindrical_counts_and_ordering(full_scan):
    assert len(full_scan) == 54_000
    # height-major: ping j*360 + k is angle k degrees at height 5 mm + j*5 mm
    for j, k in ((0, 0), (1, 1), (149, 359), (75, 200)):
        single = g.rig_poses([k], [0.005 + 0.005 * j])
        np.testing.assert_allclose(full_scan.tx[j * 360 + k], single.tx[0], atol=1e-12)
        np.testing.assert_allclose(full_scan.rx[j * 360 + k], single.rx[0], atol=1e-12)
    radii = np.hypot(full_scan.tx[:, 0], full_scan.tx[:, 1])
    np.testing.assert_allclose(radii, 0.8485, atol=1e-12)


def test_cylindrical_custom_grid():
    poses = g.trajectory("cylindrical:4:3")
    assert len(poses) == 12
    angles = np.degrees(np.arctan2(poses.tx[:4, 0], -poses.tx[:4, 1])) % 360
    np.testing.assert_allclose(angles, [0, 90, 180, 270], atol=1e-9)
    np.testing.assert_allclose(poses.tx[::4, 2], 0.285 - CENTER_Z + np.array([0.005, 0.01, 0.015]))


def test_sparse_is_every_nth(full_scan):
    sparse = g.trajectory("sparse:4")
    assert len(sparse) == 13_500
    np.testing.assert_array_equal(sparse.tx, full_scan.tx[::4])
    np.testing.assert_array_equal(sparse.rx, full_scan.rx[::4])


def test_helical_subset(full_scan):
    idx = g.helical_indices()
    assert len(np.unique(idx)) == len(idx)
    assert 2_600 <= len(idx) <= 2_900                  # ~18-19 poses per level, 150 levels
    assert idx.min() >= 0 and idx.max() < 54_000
    levels = idx // 360
    assert set(levels.tolist()) == set(range(150))
    assert np.all(np.diff(levels) >= 0)                  # the helix only climbs
    # within a level the angles are consecutive degrees (mod 360) spanning ~18 degrees
    per_level = np.bincount(levels)
    assert per_level[1:].min() >= 18 and per_level.max() <= 20
    # one turn climbs 20 levels: the azimuth at level j is about j * 18 degrees
    first_angle = np.array([idx[levels == j][0] % 360 for j in range(1, 150)])
    expected = (np.arange(1, 150) * 18 - 9) % 360
    assert np.all(np.abs((first_angle - expected + 180) % 360 - 180) <= 1)
    helical = g.trajectory("helical")
    np.testing.assert_array_equal(helical.tx, full_scan.tx[idx])


def test_pose_file_round_trips(tmp_path, full_scan):
    poses = full_scan[np.arange(0, 54_000, 997)]
    for name in ("p.csv", "p.npy"):
        g.save_poses(tmp_path / name, poses)
        back = g.load_poses(tmp_path / name)
        for field in ("tx", "rx", "tx_boresight", "rx_boresight"):
            np.testing.assert_array_equal(getattr(back, field), getattr(poses, field))


def test_pose_csv_without_header_and_with_boresight(tmp_path):
    tx = np.array([[0.5, 0.0, 0.1], [0.0, 0.5, 0.2]])
    rx = tx + [0.0, 0.0, -0.04]
    plain = tmp_path / "plain.csv"
    np.savetxt(plain, np.hstack([tx, rx]), delimiter=",")
    p = g.load_poses(plain, box=g.AIRSAS_REAL_BOX)
    np.testing.assert_allclose(p.tx, tx)
    centre = g.AIRSAS_REAL_BOX.center
    np.testing.assert_allclose(p.rx_boresight[1], (centre - rx[1]) / np.linalg.norm(centre - rx[1]))
    b = np.array([[-2.0, 0.0, 0.0], [0.0, -1.0, -1.0]])
    headed = tmp_path / "headed.csv"
    headed.write_text("tx_x,tx_y,tx_z,rx_x,rx_y,rx_z,b_x,b_y,b_z\n"
                      + "\n".join(",".join(repr(float(v)) for v in row) for row in np.hstack([tx, rx, b])) + "\n")
    q = g.load_poses(headed)
    unit_b = b / np.linalg.norm(b, axis=1, keepdims=True)
    np.testing.assert_allclose(q.tx_boresight, unit_b)
    np.testing.assert_allclose(q.rx_boresight, unit_b)  # one boresight column serves both
    g.save_poses(tmp_path / "shared.csv", q)
    assert (tmp_path / "shared.csv").read_text().splitlines()[0].count(",") == 8
    np.save(tmp_path / "b.npy", np.hstack([tx, rx, b]))
    np.testing.assert_allclose(g.trajectory(str(tmp_path / "b.npy")).tx_boresight, unit_b)


@pytest.mark.parametrize("content,error", [
    ("1,2,3,4,5\n", InputError),                         # 5 columns
    ("1,2,3,4,5,6\n1,2,3,4,5\n", InputError),            # ragged rows
    ("1,2,3,4,5,nan\n", InputError),                     # NaN
    ("h1,h2,h3,h4,h5,h6\n", InputError),                 # header only
    ("1,2,3,4,5,6\n1,2,x,4,5,6\n", InputError),          # text in a data row
    ("1,2,3,4,5,6,0,0,0\n", InputError),                 # zero boresight
])
def test_bad_pose_csv(tmp_path, content, error):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(error, match="bad.csv"):
        g.load_poses(path)


def test_bad_pose_files(tmp_path):
    with pytest.raises(FormatError, match="missing.csv"):
        g.load_poses(tmp_path / "missing.csv")
    with pytest.raises(FormatError, match="missing.npy"):
        g.trajectory(str(tmp_path / "missing.npy"))
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 6)))
    with pytest.raises(InputError, match="cube.npy"):
        g.load_poses(tmp_path / "cube.npy")
    (tmp_path / "trunc.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(FormatError, match="trunc.npy"):
        g.load_poses(tmp_path / "trunc.npy")
    for spec in ("spiral", "sparse:0", "sparse:x", "cylindrical:3", "cylindrical:0:2", "poses.txt"):
        with pytest.raises(InputError):
            g.trajectory(spec)


def test_poses_validation_and_indexing(full_scan):
    with pytest.raises(InputError):
        g.Poses(np.zeros((2, 3)), np.zeros((3, 3)), np.ones((2, 3)), np.ones((2, 3)))
    with pytest.raises(InputError):
        g.Poses(np.zeros((2, 2)), np.zeros((2, 2)), np.ones((2, 2)), np.ones((2, 2)))
    with pytest.raises(InputError):
        g.rig_poses([0.0, np.nan], [0.005, 0.005])
    one = full_scan[5]
    assert len(one) == 1 and one.tx.shape == (1, 3)
    assert len(full_scan[-1]) == 1
    np.testing.assert_array_equal(full_scan[-1].tx[0], full_scan.tx[-1])
    assert len(full_scan[10:20]) == 10


def test_crop_window_matches_reference(full_scan):
    # the reference renderer's config of the simulated scenes
    win = g.crop_window(full_scan, g.SIM_BOX, 344.973, 100e3)
    assert (win.min_sample, win.num_samples) == (217, 718)
    assert win.min_dist == pytest.approx(0.748591648507111, abs=1e-6)
    assert win.max_dist == pytest.approx(3.2254985776688887, abs=1e-5)
    # the quoted distances imply c = 344.97311...; with it the match is exact
    c = 0.748591648507111 * 100e3 / 217
    exact = g.crop_window(full_scan, g.SIM_BOX, c, 100e3)
    assert (exact.min_sample, exact.num_samples) == (217, 718)
    assert exact.min_dist == pytest.approx(0.748591648507111, abs=1e-12)
    assert exact.max_dist == pytest.approx(3.2254985776688887, abs=1e-12)
    np.testing.assert_allclose(win.path_lengths(344.973, 100e3)[[0, -1]],
                               [win.min_dist, win.max_dist - 344.973 / 100e3])


def test_crop_window_contains_every_echo():
    poses = g.trajectory("cylindrical:36:15")
    c, fs = 343.0, 100e3
    win = g.crop_window(poses, g.SIM_BOX, c, fs, pulse_samples=100, pad=0.05)
    dist = poses.round_trip(g.SIM_BOX.corners())
    first = np.floor((dist.min() - 0.05 - 100 * c / fs) * fs / c)
    assert win.min_sample == first
    assert win.max_dist >= dist.max() + 0.05 + 100 * c / fs
    assert win.max_dist - c / fs < dist.max() + 0.05 + 100 * c / fs


def test_real_airsas_crop_is_608_samples(full_scan):
    # the reference's real bunny_20k box, all 150 heights, c about 345 m/s -> 608
    assert g.crop_window(full_scan, g.AIRSAS_REAL_BOX, 345.0, 100e3).num_samples == 608
