"""The unexplained data of a refined mesh (recon.unexplained) and the grown candidate of
``recon refine``: closed-form weights, a real scan of two touching balls of which the mesh
holds one, and the command."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon import unexplained

FS = 100_000.0
BIG = ((0.0, 0.0, 0.05), 0.035)       # centre (m), radius (m)
SMALL = ((0.0, 0.0, 0.105), 0.022)    # on top of BIG, overlapping it by 2 mm


def test_weights_are_one_where_the_model_is_silent_and_zero_where_it_explains():
    """Data = two echoes; the model has the first only (any scale): w = 0 on the first, 1 on the
    second; a model of both explains everything; a silent model nothing."""
    t = np.arange(200)
    echo = lambda c: np.exp(-0.5 * ((t - c) / 3.0) ** 2)      # noqa: E731
    data = (echo(50) + 0.6 * echo(140))[None]
    w = unexplained.unexplained_weights(data, 7.0 * echo(50)[None])
    assert np.all(w[0, 40:61] < 1e-9) and np.all(w[0, 130:151] > 0.999)
    assert np.allclose(w, unexplained.unexplained_weights(data, 0.01 * echo(50)[None]))
    assert np.all(unexplained.unexplained_weights(data, 3.0 * data) < 1e-9)
    assert np.all(unexplained.unexplained_weights(data, np.zeros_like(data)) == 1.0)


def test_residual_pings_stride_to_at_most_the_count():
    assert list(unexplained.residual_pings(np.arange(10), 4)) == [0, 3, 6, 9]
    assert len(unexplained.residual_pings(np.arange(54_000))) == 2160
    assert len(unexplained.residual_pings(np.arange(100))) == 100


@pytest.fixture(scope="module")
def snowman_scan(tmp_path_factory):
    """A noiseless scan of a 3.5 cm ball with a 2.2 cm ball on top (no ground): 216 poses
    around it at three heights."""
    from sonarsim import simulate as sim
    from sonarsim.geometry import SceneBox, rig_poses
    from sonarsim.scene import load_scene
    from sonarsim.signals import pulse_from_spec
    d = tmp_path_factory.mktemp("snowman")
    box = ([-0.1, -0.1, 0.0], [0.1, 0.1, 0.15])
    balls = "".join(f'[[object]]\nshape = "sphere"\nradius = {r}\ncenter = {list(c)}\n'
                    for c, r in (BIG, SMALL))
    (d / "snowman.toml").write_text(f"ground = false\nbox = {{lo = {box[0]}, hi = {box[1]}}}\n"
                                    + balls)
    spec = load_scene(d / "snowman.toml")
    angles = np.tile(np.arange(0, 360, 5.0), 3)
    heights = np.repeat([0.05, 0.2, 0.35], 72)
    poses = rig_poses(angles, heights, box=SceneBox(np.array(box[0]), np.array(box[1])))
    out = d / "snowman.h5"
    sim.simulate(spec, poses, out, sim.SimulationSettings(
        pulse=pulse_from_spec("lfm-20k", FS), surface_spacing=2e-3, seed=1))
    return out


def _ball(centre, radius):
    m = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    m.vertices += centre
    return m


def _grid():
    from recon.grid import Grid
    return Grid(np.array([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.15]]), (41, 41, 31))


def _distance_to_sphere(points, sphere):
    (c, r) = sphere
    return np.abs(np.linalg.norm(points - np.asarray(c), axis=-1) - r)


def test_the_unexplained_image_finds_the_ball_the_mesh_lacks(mi, snowman_scan):
    """The mesh of the big ball alone leaves the small ball's echoes unexplained: the image
    peaks on the small ball's surface (at 0.16 of the data image's peak, which the big ball
    holds), and most voxels above half its peak lie on it. With both balls in the mesh the image there falls to a
    fraction of that, and the unexplained share of the energy drops."""
    from recon.export import voxel_axes
    from recon.refine import RefineSettings
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(snowman_scan)
    grid, settings = _grid(), RefineSettings(surface_spacing=2e-3)
    pings = np.arange(ds.n_pings)
    big_only, share_big = unexplained.unexplained_image(ds, _ball(*BIG), 1.0, grid, pings,
                                                        settings, None)
    both_mesh = trimesh.util.concatenate([_ball(*BIG), _ball(*SMALL)])
    both, share_both = unexplained.unexplained_image(ds, both_mesh, 1.0, grid, pings,
                                                     settings, None)
    axes = voxel_axes(grid.bounds, grid.shape)
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    near_small = (_distance_to_sphere(points, SMALL) < 0.01) & (points[..., 2] > 0.09)
    assert big_only.max() > 0.1
    assert _distance_to_sphere(points[np.unravel_index(big_only.argmax(), grid.shape)],
                               SMALL) < 0.01
    strong = big_only > 0.5 * big_only.max()
    assert near_small[strong].mean() > 0.7
    assert both[near_small].max() < 0.1 * big_only[near_small].max()
    assert share_both < 0.05 * share_big


def test_grown_voxels_add_the_far_parts_not_the_layer_around_the_start():
    """An occupied block; an image with a layer hugging it (within `beyond`), a bar reaching
    out of it and a detached blob: the bar (with its bridge) and the blob are added, the layer
    not, nor the blob when it lies below z_min."""
    vol = np.zeros((30, 30, 30), np.complex64)
    vol[10:20, 10:20, 5:15] = 1.0
    image = np.zeros((30, 30, 30))
    image[9:21, 9:21, 4:16] = 0.5           # the hugging layer, 1 voxel
    image[14:16, 14:16, 15:25] = 0.6        # a bar rising from the top
    image[2:4, 2:4, 20:22] = 0.9            # a detached blob
    bounds = np.array([[0.0, 0.29], [0.0, 0.29], [0.0, 0.29]])   # 1 cm voxels
    added = unexplained.grown_voxels(vol, bounds, 0.5, 0.0, image, 0.2, beyond=0.025)
    assert added[14:16, 14:16, 15:25].all()
    assert not added[9, 12, 8] and added[2:4, 2:4, 20:22].all()
    layer = added.copy()
    layer[14:16, 14:16, 15:25] = False
    layer[2:4, 2:4, 20:22] = False
    assert layer.sum() <= 8 and not layer[:, :, :15].any()   # at most the bar's foot
    high = unexplained.grown_voxels(vol, bounds, 0.5, 0.0, image, 0.7, beyond=0.025)
    assert high.sum() == 8 and high[2:4, 2:4, 20:22].all()
    assert not unexplained.grown_voxels(vol, bounds, 0.5, 0.215, image, 0.7, beyond=0.025).any()


def _volume_of(balls, grid, path):
    """A 0/1 volume (complex64) of the balls on ``grid``, written to ``path``."""
    from recon.export import voxel_axes
    from sonarsim.dataset import Volume
    points = np.stack(np.meshgrid(*voxel_axes(grid.bounds, grid.shape), indexing="ij"), -1)
    inside = np.zeros(grid.shape, bool)
    for c, r in balls:
        inside |= np.linalg.norm(points - np.asarray(c), axis=-1) < r
    Volume(volume=inside.astype(np.complex64), bounds=grid.bounds, method="test").write(path)
    return path


def test_refine_command_adds_and_keeps_the_start_grown_by_the_unexplained_data(
        snowman_scan, tmp_path, capsys):
    """From a volume of the big ball alone: the command images what its refinement leaves
    unexplained, grows the start by the small ball, refines that start too, and keeps it (its
    envelope misfit is the lower); --keep-candidates writes it as OUT.grown-wrap0(.start).ply;
    with a mesh --init or a level outside [0, 1) it refuses in one line."""
    import json

    from recon.cli import main
    init = _volume_of([BIG], _grid(), tmp_path / "big.h5")
    out, hist = tmp_path / "refined.ply", tmp_path / "h.json"
    args = ["refine", str(snowman_scan), "--init", str(init), "--out", str(out), "--no-ground",
            "--wrap", "0", "--smooth", "0", "--affine-steps", "0", "--envelope-steps", "8",
            "--waveform-steps", "0", "--lr", "1e-3",
            "--pings-per-batch", "36", "--edge-length", "0.01", "--surface-spacing", "0.003",
            "--history", str(hist), "--no-progress"]
    assert main([*args, "--grow-unexplained", "0.12", "--keep-candidates"]) == 0
    printed = capsys.readouterr().out
    record = json.loads(hist.read_text())
    cands = record["candidates"]
    assert [(c["wrap"], c["smooth"], c["grown"]) for c in cands] == [(0.0, 0.0, 0.0),
                                                                     (0.0, 0.0, 0.12)]
    assert cands[1]["envelope_misfit"] < cands[0]["envelope_misfit"], printed
    assert record["grown"] == 0.12 and "unexplained:" in printed
    plain = trimesh.load(tmp_path / "refined.wrap0.start.ply")
    grown = trimesh.load(tmp_path / "refined.grown-wrap0.start.ply")
    top_small = SMALL[0][2] + SMALL[1]
    assert plain.bounds[1, 2] < BIG[0][2] + BIG[1] + 0.01 < top_small - 0.01 < grown.bounds[1, 2]
    assert len(trimesh.load(out).faces) == cands[1]["faces"]
    found = record["unexplained"]
    assert found["level"] == 0.12 and found["voxels_added"] > 0 and 0 < found["share"] < 1
    from sonarsim.dataset import Volume
    image = Volume.read(tmp_path / "refined.unexplained.h5")
    assert image.method == "unexplained" and image.volume.shape == _grid().shape
    assert np.abs(image.volume).max() >= 0.12
    trimesh.creation.icosphere(radius=0.03).export(tmp_path / "big.ply")
    for extra, words in ((["--grow-unexplained", "1.5"], "--grow-unexplained: must be in [0, 1)"),
                         (["--grow-unexplained", "0.2", "--init", str(tmp_path / "big.ply")],
                          "--grow-unexplained applies to a volume --init")):
        assert main([*args, "--force", *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
