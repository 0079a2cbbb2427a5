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
    found = unexplained.unexplained_image(ds, _ball(*BIG), 1.0, grid, pings, settings, None)
    big_only, share_big = found.image, found.share
    both_mesh = trimesh.util.concatenate([_ball(*BIG), _ball(*SMALL)])
    both, share_both = (lambda f: (f.image, f.share))(unexplained.unexplained_image(
        ds, both_mesh, 1.0, grid, pings, settings, None))
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
    # the halves: the two lower rings (the median's ties) against the top one; their coherent
    # sum is the image, and each images the small ball (seen from every height) well above
    # its share of the level, so its part is kept
    assert found.lower_fraction == pytest.approx(2 / 3) and 0 < found.split_deg < 30
    lower, upper = found.lower, found.upper
    assert np.all(lower + upper >= big_only - 1e-5)
    ball = unexplained.consistent_parts(near_small & (big_only > 0.5 * big_only.max()), found,
                                        0.5 * big_only.max())
    assert ball.any() and ball.sum() == (near_small & (big_only > 0.5 * big_only.max())).sum()
    assert min(lower[near_small].max(), upper[near_small].max()) > 0.3 * big_only.max()


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


def _found(lower, upper, fraction=0.5):
    return unexplained.UnexplainedImage(image=lower + upper, lower=lower, upper=upper,
                                        lower_fraction=fraction, split_deg=10.0, share=0.3)


def test_consistent_parts_keep_what_both_elevation_halves_image():
    """Three parts proposed at level 0.2: one imaged by both halves (0.15 and 0.12), one by the
    lower half alone (0.5, upper 0.02: a face's flash), one by the upper alone: only the first
    is kept, whole (its weak voxels too). With unequal halves the bar scales with each share;
    with no halves (one elevation) everything is kept."""
    shape = (20, 20, 20)
    lower, upper = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    added = np.zeros(shape, bool)
    added[2:5, 2:5, 2:5] = added[10:13, 2:5, 2:5] = added[2:5, 10:13, 10:13] = True
    lower[2:5, 2:5, 2:5], upper[2:5, 2:5, 2:5] = 0.05, 0.05
    lower[3, 3, 3], upper[2, 4, 4] = 0.15, 0.12
    lower[10:13, 2:5, 2:5], upper[10:13, 2:5, 2:5] = 0.5, 0.02
    lower[2:5, 10:13, 10:13], upper[2:5, 10:13, 10:13] = 0.03, 0.6
    kept = unexplained.consistent_parts(added, _found(lower, upper), 0.2)
    assert kept[2:5, 2:5, 2:5].all() and kept.sum() == 27
    # a quarter of the pings below: the lower bar 0.05, the upper 0.15 (not met by 0.12)
    assert not unexplained.consistent_parts(added, _found(lower, upper, 0.25), 0.2).any()
    assert unexplained.consistent_parts(added, _found(lower, upper, 0.75), 0.2).sum() == 27
    none = unexplained.UnexplainedImage(lower + upper, None, None, 1.0, None, 0.3)
    assert (unexplained.consistent_parts(added, none, 0.2) == added).all()


def test_elevation_halves_split_at_the_median_elevation_seen_from_the_grid():
    """Pings at three heights around a grid centred at z = 0.1 m: the lower half holds the
    lowest ring and the median ring's ties; one height only → None; all but one at the lowest
    elevation → the ties cannot go below, the upper half keeps the one."""
    import types
    grid = types.SimpleNamespace(bounds=np.array([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]]))
    az = np.radians(np.tile(np.arange(0, 360, 60.0), 3))
    z = np.repeat([0.0, 0.1, 0.5], 6)
    tx = np.stack([np.cos(az), np.sin(az), z], axis=1)
    ds = types.SimpleNamespace(tx=tx, rx=tx + [0.0, 0.0, 0.02])
    lower, split = unexplained.elevation_halves(ds, np.arange(18), grid)
    assert lower.tolist() == [True] * 12 + [False] * 6
    assert np.degrees(split) == pytest.approx(np.degrees(np.arctan2(0.01, 1.0)))
    flat = types.SimpleNamespace(tx=tx[:6], rx=tx[:6])
    assert unexplained.elevation_halves(flat, np.arange(6), grid) is None
    lopsided = types.SimpleNamespace(tx=tx[:7], rx=tx[:7])
    lower, split = unexplained.elevation_halves(lopsided, np.arange(7), grid)
    assert lower.tolist() == [True] * 6 + [False]
    assert np.degrees(split) == pytest.approx(np.degrees(np.arctan2(-0.1, 1.0)))


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
            "--wrap", "0", "--smooth", "0", "--shrink", "0", "--seal", "0",
            "--affine-steps", "0", "--envelope-steps", "8",
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
    assert found["voxels_proposed"] >= found["voxels_added"] and found["split_elevation_deg"] > 0
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


def test_refine_command_resumes_from_its_checkpoint(snowman_scan, tmp_path, capsys):
    """--checkpoint DIR keeps each refined candidate as it finishes; after an interruption (the
    grown candidate's record not yet written) --resume loads the first candidate, refines the
    grown one again and writes the same mesh and history as the run that was not
    interrupted, byte for byte. Another run's directory, a directory holding a run without
    --resume or --force, and --resume without --checkpoint are refused in one line."""
    import json

    from recon.cli import main
    init = _volume_of([BIG], _grid(), tmp_path / "big.h5")
    ck = tmp_path / "ck"
    args = ["refine", str(snowman_scan), "--init", str(init), "--no-ground", "--wrap", "0",
            "--smooth", "0", "--shrink", "0", "--seal", "0",
            "--affine-steps", "0", "--envelope-steps", "8",
            "--waveform-steps", "0", "--lr", "1e-3", "--pings-per-batch", "36",
            "--edge-length", "0.01", "--surface-spacing", "0.003", "--no-progress",
            "--grow-unexplained", "0.12", "--threads", "1"]    # one thread: the same sums
    run = [*args, "--checkpoint", str(ck), "--keep-candidates"]

    def outputs(tag):
        return ["--out", str(tmp_path / f"{tag}.ply"), "--history", str(tmp_path / f"{tag}.json")]
    assert main([*run, *outputs("whole")]) == 0
    assert sorted(p.name for p in ck.iterdir()) == ["grown-wrap0.json", "grown-wrap0.npz",
                                                    "identity.json", "wrap0.json", "wrap0.npz"]
    mesh, history = ((tmp_path / f"whole.{e}").read_bytes() for e in ("ply", "json"))
    # interrupted during the grown candidate: no record of it, no --out, no --history; the
    # finished candidates' --keep-candidates files are there (and may be written again)
    for done in (ck / "grown-wrap0.json", tmp_path / "whole.ply", tmp_path / "whole.json"):
        done.unlink()
    capsys.readouterr()
    assert main([*run, *outputs("whole"), "--resume"]) == 0
    printed = capsys.readouterr().out
    assert "start wrap0: resumed from" in printed and "grown-wrap0: resumed" not in printed
    assert "start grown-wrap0: envelope misfit" in printed
    assert (tmp_path / "whole.ply").read_bytes() == mesh
    whole, resumed = json.loads(history), json.loads((tmp_path / "whole.json").read_text())
    for record in (whole, resumed):             # the wall time of each step is not the same
        for step in record["history"]:
            del step["seconds"]
    assert whole == resumed and whole["grown"] == 0.12
    for extra, words in (
            (["--resume", "--lr", "2e-3"], "holds another run"),
            ([], "holds a run; pass --resume to continue it or --force"),
            (["--checkpoint", str(init)], "is not a directory")):
        assert main([*run, *outputs("bad"), *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main([*args, *outputs("bad"), "--resume"]) == 2
    assert "--resume needs --checkpoint DIR" in capsys.readouterr().err
