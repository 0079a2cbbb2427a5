"""Tests of recon.metrics, recon.views and `recon evaluate` / `recon compare` against
closed forms: containment, IoU and Chamfer of a shifted cube, threshold sweeps,
depth renders of a sphere, degenerate reconstructions."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from recon import export, metrics, protocol_reference as ref
from sonarsim.errors import FormatError, InputError

# Cube of side S with faces between lattice points of spacing H, so that exactly
# S/H voxel centres per axis lie inside and they fill whole 5 mm IoU cells.
S, D, H = 0.05, 0.01, 0.0025
CUBE_LO = -0.0262
BOX = np.array([[-0.1, 0.1]] * 3)
N = 81  # voxel centres -0.1, -0.0975, ..., 0.1


def lattice():
    return np.meshgrid(*export.voxel_axes(BOX, (N, N, N)), indexing="ij")


def cube_volume(shift: float = 0.0) -> np.ndarray:
    """0.5 + (signed Chebyshev distance)/H, clipped: the 0.5 level is the cube's surface."""
    x, y, z = lattice()
    c = CUBE_LO + S / 2
    cheb = np.maximum.reduce([np.abs(x - c - shift), np.abs(y - c), np.abs(z - c)])
    return np.clip(0.5 + (S / 2 - cheb) / H, 0.0, 1.0).astype(np.complex64)


def cube_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[S] * 3).apply_translation([CUBE_LO + S / 2] * 3)


def shifted_cube_chamfer(s: float, d: float) -> tuple[float, float]:
    """Closed-form Chamfer between the surfaces of a cube of side s and its copy shifted
    by d < s along x, for area-uniform samples: (squared definition [m²], mean L2 [m]).

    Per face of the first cube (each 1/6 of the area): the -x face is d away; on the +x
    face the distance is min(d, distance to the face's border); on the 4 side faces
    max(0, d - u) over the first d of the width. Both directions are equal by symmetry.
    """
    mean = (d + s / 6 * (1 - (1 - 2 * d / s) ** 3) + 4 * d * d / (2 * s)) / 6
    mean_sq = (d * d + (d * d - 8 * d ** 3 / (3 * s) + 2 * d ** 4 / s ** 2)
               + 4 * d ** 3 / (3 * s)) / 6
    return 2 * mean_sq, mean


def test_containment_majority_vote_survives_a_hole():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    coords = [np.linspace(-0.08, 0.08, 33)] * 3
    x, y, z = np.meshgrid(*coords, indexing="ij")
    r = np.sqrt(x ** 2 + y ** 2 + z ** 2)
    clear = np.abs(r - 0.05) > 0.002  # icosphere facets deviate < 0.5 mm from r = 0.05
    inside = metrics.inside_mesh_lattice(sphere, coords)
    assert np.array_equal(inside[clear], (r < 0.05)[clear])
    holed = sphere.copy()
    holed.update_faces(holed.face_normals[:, 2] < 0.97)  # open the north pole
    assert not holed.is_watertight
    z_parity = metrics._axis_parity(np.asarray(holed.triangles), coords, 2)
    assert not np.array_equal(z_parity[clear], (r < 0.05)[clear])  # one vote is wrong...
    inside = metrics.inside_mesh_lattice(holed, coords)
    assert np.array_equal(inside[clear], (r < 0.05)[clear])  # ...the majority is right


def test_normal_agreement_closed_form():
    """Normals tilted by θ against the same points: angle θ, consistency cos θ, both ways;
    the orientation does not count; the exact protocol's iso-surface of the cube is within a
    few degrees of the GT's faces."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    up = np.tile([0.0, 0.0, 1.0], (500, 1))
    theta = np.deg2rad(25.0)
    tilted = np.tile([np.sin(theta), 0.0, -np.cos(theta)], (500, 1))   # flipped orientation
    nc, angle = metrics.normal_agreement(pts, up, pts, tilted)
    assert angle == pytest.approx(25.0, abs=1e-9) and nc == pytest.approx(np.cos(theta))
    assert metrics.normal_agreement(pts, up, pts[:0], up[:0]) == (None, None)
    res = metrics.evaluate(cube_volume(), BOX, cube_mesh(), threshold=0.5, sweep=None,
                           n_samples=4000)
    assert res["normal_error_deg"] < 6.0      # the marching-cubes bevels at edges and corners


def test_cell_grid_and_iou_basics():
    grid = metrics.CellGrid(np.zeros(3), np.array([0.02, 0.01, 0.01]), 0.005)
    assert grid.shape == (4, 2, 2)
    occ = grid.occupancy(np.array([[0.0, 0.0, 0.0], [0.02, 0.01, 0.01], [0.005, 0.0, 0.0],
                                   [0.03, 0.0, 0.0], [-0.001, 0.0, 0.0]]))
    assert occ.sum() == 3 and occ[0, 0, 0] and occ[3, 1, 1] and occ[1, 0, 0]
    assert metrics.iou(occ, occ) == 1.0
    assert metrics.iou(occ, np.zeros_like(occ)) == 0.0
    assert metrics.iou(np.zeros_like(occ), np.zeros_like(occ)) == 1.0


def test_chamfer_closed_form_and_empty():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = a + [0.0, 0.003, 0.0]
    c = metrics.chamfer(a, b)
    assert c["sq"] == pytest.approx(2 * 0.003 ** 2) and c["m"] == pytest.approx(0.003)
    assert metrics.chamfer(a, a)["sq"] == 0.0
    assert metrics.chamfer(a, np.zeros((0, 3)))["sq"] is None


def test_volume_of_the_gt_itself_scores_perfectly_and_a_shift_costs_the_closed_form():
    gt = cube_mesh()
    n = 20_000
    # the sampling floor: two independent sample sets of the same surface are about
    # 0.5 * sqrt(area / n) apart on average (random points in the plane)
    floor = 0.5 * np.sqrt(gt.area / n)
    perfect = metrics.evaluate(cube_volume(), BOX, gt, threshold=0.5, sweep=None)
    assert perfect["iou"] == 1.0
    assert perfect["chamfer_m"] < 1.5 * floor
    assert perfect["chamfer_sq"] < 1e-6
    assert perfect["normal_consistency"] > 0.95
    shifted = metrics.evaluate(cube_volume(D), BOX, gt, threshold=0.5, sweep=None)
    assert shifted["iou"] == pytest.approx((S - D) / (S + D), abs=1e-12)
    expected_sq, expected_m = shifted_cube_chamfer(S, D)
    assert shifted["chamfer_sq"] == pytest.approx(expected_sq, rel=0.05)
    assert shifted["chamfer_m"] == pytest.approx(np.hypot(expected_m, floor), rel=0.1)
    assert shifted["normal_consistency"] < perfect["normal_consistency"] - 0.1


def test_binary_voxelisation_of_a_ball_scores_high():
    """The prediction is the *analytic* ball r < R on the lattice (independent of the mesh
    containment that makes the GT): a fine icosphere deviates < 0.03 mm from the ball, so the
    5 mm cells must agree (a broken containment or cell assignment fails this)."""
    radius = 0.04
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    bounds = np.array([[-0.1, 0.1], [-0.1, 0.1], [-0.06, 0.06]])
    shape = (63, 63, 38)
    x, y, z = np.meshgrid(*export.voxel_axes(bounds, shape), indexing="ij")
    ball = (x * x + y * y + z * z < radius ** 2).astype(np.complex64)
    res = metrics.evaluate(ball, bounds, sphere, threshold=0.2, sweep=None, n_samples=5000)
    assert res["iou"] >= 0.99
    assert res["gt_cells"] == pytest.approx(res["occupied_cells"], abs=2)
    assert res["chamfer_m"] < export.voxel_spacing(bounds, shape).max()


def test_threshold_sweep_is_monotone_where_it_must_be_and_finds_the_true_level():
    # Gaussian blob exp(-(r/sigma)^2) against a sphere of radius R: the iso-surface at
    # threshold t has radius sigma*sqrt(-ln t), so the true level is exp(-(R/sigma)^2).
    radius, sigma = 0.04, 0.05
    bounds = np.array([[-0.1, 0.1]] * 3)
    shape = (41, 41, 41)
    x, y, z = np.meshgrid(*export.voxel_axes(bounds, shape), indexing="ij")
    blob = np.exp(-(x * x + y * y + z * z) / sigma ** 2)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    res = metrics.evaluate(blob, bounds, sphere, n_samples=4000)
    rows = res["sweep"]
    ts = [r["threshold"] for r in rows]
    assert ts == sorted(ts) and 0.2 in ts
    voxels = [r["occupied_voxels"] for r in rows]
    assert all(a >= b for a, b in zip(voxels, voxels[1:]))
    true_level = np.exp(-(radius / sigma) ** 2)  # 0.527
    for key in ("best_chamfer_sq_threshold", "best_chamfer_m_threshold"):
        assert abs(res[key] - true_level) <= 0.05 + 1e-9
    assert abs(res["best_iou_threshold"] - true_level) <= 0.1 + 1e-9
    cham = [r["chamfer_m"] for r in rows]
    k = int(np.argmin(cham))
    assert all(a > b for a, b in zip(cham[:k], cham[1:k + 1]))  # falls to the minimum
    assert all(a < b for a, b in zip(cham[k:], cham[k + 1:]))   # rises after it
    assert res["best_iou"] >= res["iou"] and res["best_iou"] > 0.9


def test_all_zero_volume_is_defined():
    res = metrics.evaluate(np.zeros((10, 10, 10), np.complex64), BOX, cube_mesh(),
                           n_samples=1000)
    assert res["empty"] and res["iou"] == 0.0
    assert res["chamfer_sq"] is None and res["chamfer_m"] is None
    assert res["best_chamfer_sq"] is None and res["best_iou"] == 0.0


def test_depth_render_of_a_sphere_matches_ray_sphere_intersection(mi):
    from recon import views

    cams = views.Turntable(n_views=3, resolution=48)
    centre, radius = np.array([0.0, 0.0, 0.1]), 0.05
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    sphere.apply_translation(centre)
    out = views.render_views(sphere, cams)
    o, d, forward = cams.rays()
    oc = o - centre
    b = np.sum(oc * d, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - radius ** 2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), 0.0)
    # rays start on the near plane, ZNEAR along the camera axis in front of the eye
    depth = np.where(disc > 0, t * np.sum(d * np.repeat(forward, 48 * 48, axis=0), axis=1)
                     + views.ZNEAR, 0.0).reshape(3, 48, 48)
    safe = np.abs(disc.reshape(3, 48, 48)) > 2e-4  # skip pixels grazing the silhouette
    assert np.abs(out["depth"] - depth)[safe].max() < 2e-4
    assert out["shaded"].max() <= 1.0 and out["shaded"][depth > 0].min() >= 0.0
    same = views.image_metrics(sphere, sphere, cams)
    assert same["psnr_depth"] == float("inf") and same["ssim_depth"] == pytest.approx(1.0)
    moved = views.image_metrics(sphere, sphere.copy().apply_translation([0, 0.01, 0]), cams)
    assert np.isfinite(moved["psnr_depth"]) and moved["ssim_shaded"] < 0.99


def test_cli_evaluate_json_and_compare(tmp_path, capsys, mi):
    from recon.cli import main
    from sonarsim.dataset import Volume

    gt = tmp_path / "cube.ply"
    cube_mesh().export(gt)
    Volume(cube_volume(), BOX, "test").write(tmp_path / "v.h5")
    Volume(np.zeros((8, 8, 8), np.complex64), BOX, "zero").write(tmp_path / "z.h5")
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(gt), "--json",
                 "--samples", "3000", "--threshold", "0.5"]) == 0
    res = json.loads(capsys.readouterr().out)
    for key in ("iou", "chamfer_sq", "chamfer_m", "threshold", "best_iou",
                "best_iou_threshold", "best_chamfer_sq", "best_chamfer_sq_threshold",
                "psnr_depth", "ssim_depth", "psnr_shaded", "ssim_shaded"):
        assert key in res
    assert res["iou"] == 1.0 and res["threshold"] == 0.5
    assert main(["evaluate", str(tmp_path / "z.h5"), "--gt", str(gt), "--json",
                 "--samples", "500", "--no-images", "--no-sweep"]) == 0
    text = capsys.readouterr().out
    assert "NaN" not in text and "Infinity" not in text
    zero = json.loads(text)
    assert zero["iou"] == 0.0 and zero["chamfer_sq"] is None and zero["empty"] is True
    assert main(["evaluate", str(tmp_path / "z.h5"), "--gt", str(tmp_path / "no.obj")]) == 2
    out = tmp_path / "cmp.png"            # two volumes, cropped (one run: each costs seconds)
    crop = [str(v) for v in np.asarray(BOX, dtype=float).ravel()]
    assert main(["compare", str(tmp_path / "v.h5"), str(tmp_path / "z.h5"), "--gt", str(gt),
                 "--crop", *crop, "--out", str(out)]) == 0
    assert out.is_file() and out.stat().st_size > 10_000


def test_load_gt_mesh_errors(tmp_path):
    with pytest.raises(FormatError):
        metrics.load_gt_mesh(tmp_path / "missing.obj")
    (tmp_path / "bad.obj").write_text("this is not a mesh\n")
    with pytest.raises(FormatError):
        metrics.load_gt_mesh(tmp_path / "bad.obj")


def test_crop_leaves_out_a_ground_slab():
    vol = cube_volume()
    vol[:, :, :2] = 1.0  # a bright "ground" in the two lowest layers, z = -0.1, -0.0975
    gt = cube_mesh()
    full = metrics.evaluate(vol, BOX, gt, threshold=0.5, sweep=None, n_samples=4000)
    crop = np.array([[-0.1, 0.1], [-0.1, 0.1], [-0.09, 0.1]])
    cut = metrics.evaluate(vol, BOX, gt, threshold=0.5, sweep=None, n_samples=4000, crop=crop)
    # the slab fills the 40 x 40 lowest cells; the cube fills 10 x 10 x 10 cells
    assert full["iou"] == pytest.approx(1000 / (1000 + 1600)) and cut["iou"] == 1.0
    assert cut["evaluated_bounds"][2] == pytest.approx([-0.09, 0.1])
    assert cut["chamfer_m"] < 0.1 * full["chamfer_m"]
    sub, b = export.crop_volume(vol, BOX, crop)
    assert sub.shape == (N, N, N - 4) and b[2, 0] == pytest.approx(-0.09)
    with pytest.raises(InputError):
        export.crop_volume(vol, BOX, [[0.2, 0.3], [-0.1, 0.1], [-0.1, 0.1]])


# ------------------------------------------------------------- the reference's protocol

def test_inside_mesh_points_matches_the_ball_and_survives_a_hole():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    pts = np.random.default_rng(3).uniform(-0.07, 0.07, (4000, 3))
    r = np.linalg.norm(pts, axis=1)
    clear = np.abs(r - 0.05) > 0.002
    assert np.array_equal(ref.inside_mesh_points(sphere, pts)[clear], (r < 0.05)[clear])
    holed = sphere.copy()
    holed.update_faces(holed.face_normals[:, 2] < 0.97)
    assert np.array_equal(ref.inside_mesh_points(holed, pts)[clear], (r < 0.05)[clear])


def test_volume_samples_are_rejection_samples_of_the_bounding_box():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    pts = ref.volume_samples(sphere, 20_000, seed=1)
    assert np.linalg.norm(pts, axis=1).max() < 0.05
    # binomial: 20 000 tries, p = V/V_box = π/6 -> std 0.0035
    assert len(pts) / 20_000 == pytest.approx(sphere.volume / 0.1 ** 3, abs=0.015)
    assert np.array_equal(pts, ref.volume_samples(sphere, 20_000, seed=1))


def test_reference_mesh_is_the_smoothed_binary_surface_in_world_coordinates():
    bounds = np.array([[-0.1, 0.1]] * 3)
    shape = (81, 81, 81)                           # 2.5 mm voxels
    x, y, z = np.meshgrid(*export.voxel_axes(bounds, shape), indexing="ij")
    centre = np.array([0.012, -0.02, 0.007])
    r = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2)
    mesh = ref.reference_mesh((r < 0.05).astype(np.float32), bounds, 0.2, mapping="centre")
    dist = np.linalg.norm(mesh.vertices - centre, axis=1)
    assert np.abs(mesh.vertices.mean(axis=0) - centre).max() < 0.2 * 0.0025   # centred
    assert abs(dist.mean() - 0.05) < 0.5 * 0.0025                            # radius
    assert dist.std() < 0.0025
    assert ref.reference_mesh(np.zeros((5, 5, 5)), bounds, 0.2).faces.shape[0] == 0


def test_reference_protocol_iou_ceiling_and_shifted_cube_chamfer():
    """A perfect reconstruction scores the reference's sampling ceiling: n volume samples in
    the mesh's box (volume S³) occupy cell c with probability p_c = 1 − exp(−n·|c ∩ cube|/S³),
    so E[IoU] = Σ_{c∈P} p_c / (|P| + Σ_{c∉P} p_c), P the cells of the predicted voxels;
    and the squared Chamfer of a shifted cube is the closed form."""
    gt = cube_mesh()
    n = 2000
    overlap = []
    for a in range(3):
        edges = ref.BOX[a, 0] + 0.005 * np.arange(ref.IOU_CELLS[a] + 1)
        overlap.append(np.clip(np.minimum(edges[1:], CUBE_LO + S)
                               - np.maximum(edges[:-1], CUBE_LO), 0, None))
    pred = ref.voxelize(export.occupied_points(np.abs(cube_volume()), BOX, 0.5))
    # the cells k = -1, ..., -6 below z = 0 (the cube reaches 26.2 mm down) wrap to the top
    # layers 60 + k (NumPy's negative index), for GT samples and predicted voxels alike
    top = -0.005 * np.arange(6)
    overlap[2][60 - 6:][::-1] = np.clip(np.minimum(top, 0) - np.maximum(top - 0.005, CUBE_LO),
                                       0, None)

    def expected(n):
        p = 1 - np.exp(-n * np.einsum("i,j,k->ijk", *overlap) / S ** 3)
        return p[pred].sum() / (pred.sum() + p[~pred].sum())
    res, mesh = ref.evaluate_reference(cube_volume(), BOX, gt, threshold=0.5, n_volume=n,
                                       sweep=None, chamfer_sweep=None, mapping="centre")
    assert res["iou"] == pytest.approx(expected(n), abs=0.03)
    assert res["iou_bounds"] == [[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]]
    assert res["iou_cells"] == [80, 80, 60]
    full, _ = ref.evaluate_reference(cube_volume(), BOX, gt, threshold=0.5, sweep=None,
                                     chamfer_sweep=None, mapping="centre")
    assert full["iou"] == pytest.approx(expected(50_000), abs=0.02)
    assert full["chamfer_sq"] < 1e-5 and full["normal_error_deg"] < 15   # smoothed voxels
    shifted, _ = ref.evaluate_reference(cube_volume(D), BOX, gt, threshold=0.5,
                                        sweep=(0.3, 0.5), chamfer_sweep=(0.5,),
                                        mapping="centre")
    expected_sq, _ = shifted_cube_chamfer(S, D)
    assert shifted["chamfer_sq"] == pytest.approx(expected_sq, rel=0.15)
    assert shifted["best_iou_threshold"] in (0.3, 0.5)
    assert shifted["best_chamfer_sq"] == shifted["chamfer_sq"]
    assert len(mesh.faces) > 0


def test_reference_voxelize_keeps_the_references_grid_quirks():
    """80 x 80 x 60 cells; indices above the grid clamp to the last cell, negative ones wrap
    (NumPy), far-below points are dropped."""
    assert ref.IOU_CELLS == (80, 80, 60)
    pts = np.array([[0.0, 0.0, 0.0012],      # z cell 0
                    [0.01, 0.0, -0.002],     # wraps to z cell 59
                    [0.0, 0.0, 0.3],         # index 60 -> clamped to 59
                    [0.2, -0.2, 0.1],        # x index 80 -> 79, y 0
                    [0.0, 0.0, -0.5]])       # dropped
    occ = ref.voxelize(pts)
    assert occ.sum() == 4
    assert occ[40, 40, 0] and occ[42, 40, 59] and occ[40, 40, 59] and occ[79, 0, 20]


def test_reference_vertex_mapping_is_the_references_normalize_vertices():
    """mapping='reference' places a vertex at lo + p/n·(hi − lo) (p: padded index), i.e. the
    'centre' mesh moved by that closed form, up to one voxel towards +x, +y, +z."""
    bounds = np.array([[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]])
    shape = (40, 40, 30)
    x, y, z = np.meshgrid(*export.voxel_axes(bounds, shape), indexing="ij")
    blob = ((x - 0.03) ** 2 + y ** 2 + (z - 0.12) ** 2 < 0.07 ** 2).astype(np.float32)
    centre = ref.reference_mesh(blob, bounds, 0.2, mapping="centre")
    quirk = ref.reference_mesh(blob, bounds, 0.2, mapping="reference")
    n = np.asarray(shape, float)
    ext = bounds[:, 1] - bounds[:, 0]
    p = (centre.vertices - bounds[:, 0]) / (ext / (n - 1)) + 1      # padded index
    assert np.allclose(quirk.vertices, bounds[:, 0] + p / n * ext, atol=1e-12)
    shift = (quirk.vertices - centre.vertices).mean(axis=0)
    assert np.all(shift > 0) and np.all(shift < ext / (n - 1))


def test_smoothing_equals_pymcubes_constrained_smoothing():
    """recon.smoothing builds the matrix without PyMCubes' Python loop; same function."""
    import mcubes

    from recon.smoothing import smooth_constrained
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n) for n in (22, 25, 19)], indexing="ij")
    b = (x ** 2 + y ** 2 + z ** 2 < 0.4) | (np.abs(z + 0.85) < 0.1) | \
        ((np.abs(x - 0.5) < 0.1) & (np.abs(y) < 0.6))
    b = np.pad(b, 1)
    ours, theirs = smooth_constrained(b), mcubes.smooth(b)
    assert np.abs(ours - theirs).max() < 1e-9
    assert not np.array_equal(b, ours > 0)          # it did smooth something


def test_cli_evaluate_reference_protocol(tmp_path, capsys, mi):
    from recon.cli import main
    from sonarsim.dataset import Volume

    gt = tmp_path / "cube.ply"
    cube_mesh().apply_translation([0, 0, 0.05]).export(gt)
    vol = Volume(cube_volume(), BOX + [[0, 0], [0, 0], [0.05, 0.05]], "test")
    vol.write(tmp_path / "v.h5")
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(gt), "--json", "--threshold",
                 "0.5", "--protocol", "reference", "--no-sweep"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["protocol"] == "reference" and res["n_volume"] == 50_000
    api, _ = ref.evaluate_reference(vol.volume, vol.bounds, metrics.load_gt_mesh(gt),
                                    threshold=0.5, sweep=None, chamfer_sweep=None)
    assert res["iou"] == api["iou"] > 0.7 and res["chamfer_sq"] == api["chamfer_sq"] < 2e-5
    assert res["psnr_depth"] > 25 and 0.9 < res["ssim_depth"] <= 1.0
    # the reference's camera table for a GT named 'cube': 0.45 m, yfov pi/4, looking at 7 cm
    assert res["views"] == {"n_views": 10, "resolution": 512, "yfov_rad": pytest.approx(np.pi / 4),
                            "distance_m": 0.45, "elevation_m": 0.21, "look_height_m": 0.07,
                            "set": "paper"}
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(gt), "--json", "--threshold",
                 "0.5", "--protocol", "reference", "--no-sweep", "--reference-views",
                 "released"]) == 0
    released = json.loads(capsys.readouterr().out)
    assert released["views"]["yfov_rad"] == 60.0 and released["views"]["distance_m"] == 0.3
    assert released["iou"] == res["iou"] and released["psnr_depth"] != res["psnr_depth"]
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(gt), "--protocol",
                 "reference", "--normalize", "max"]) == 2
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(gt), "--protocol", "nope"])
    assert exc.value.code == 2


# ------------------------------------------------------------ meshes and the ground truth

def tiny_dataset_with_gt(path, mesh):
    """A 2-ping dataset whose gt/ holds ``mesh`` (the placed mesh), written to ``path``."""
    from sonarsim.dataset import SonarDataset
    tx = np.array([[0.5, 0.0, 0.1], [0.0, 0.5, 0.1]])
    bore = -tx / np.linalg.norm(tx, axis=1, keepdims=True)
    SonarDataset(waveforms=np.zeros((2, 64), np.float32), tx=tx, rx=tx, boresight=bore,
                 pulse=np.ones(8, np.float32), fs=100e3, sound_speed=343.0, source="test",
                 gt_vertices=np.asarray(mesh.vertices, float),
                 gt_faces=np.asarray(mesh.faces, np.int64)).write(path)


def test_evaluate_mesh_closed_form():
    """A mesh scores against the GT as a volume does: itself -> IoU 1 and the sampling
    floor; the cube moved by two IoU cells along x -> IoU (s - d)/(s + d) exactly (cells of
    5 mm, faces off the half-cell lattice) and the shifted-cube Chamfer."""
    gt = cube_mesh()
    same = metrics.evaluate_mesh(gt, gt, n_samples=4000)
    # nearest samples across an edge pair faces at 90°: a floor of a few degrees
    assert same["iou"] == 1.0 and same["chamfer_sq"] < 1e-5 and same["normal_error_deg"] < 5
    moved = metrics.evaluate_mesh(gt.copy().apply_translation([D, 0, 0]), gt, n_samples=20_000)
    assert moved["iou"] == pytest.approx((S - D) / (S + D), abs=1e-12)
    expected_sq, expected_m = shifted_cube_chamfer(S, D)
    assert moved["chamfer_sq"] == pytest.approx(expected_sq, rel=0.05)
    assert moved["chamfer_m"] == pytest.approx(expected_m, rel=0.1)   # + the sampling floor
    crop = [[-1, 1], [-1, 1], [0.0, 1]]                       # the upper half of the cube
    half = metrics.evaluate_mesh(gt, gt, n_samples=4000, crop=crop)
    assert half["iou"] == 1.0 and half["evaluated_bounds"][2][0] == 0.0
    ref_same = ref.evaluate_reference_mesh(gt.copy().apply_translation([0, 0, 0.05]),
                                           gt.copy().apply_translation([0, 0, 0.05]),
                                           n_volume=20_000, n_surface=4000)
    assert ref_same["chamfer_sq"] < 1e-5 and 0.5 < ref_same["iou"] < 1.0     # sampling ceiling


def test_cli_evaluate_a_mesh_and_name_the_ground_truth(tmp_path, capsys, mi):
    """`recon evaluate MESH.ply --gt ...` in both protocols; the output names the GT and its
    frame; a raw mesh file that the volume's dataset placed elsewhere is scored as given and
    a warning says so (stderr), the dataset's own GT matches silently."""
    from recon.cli import main
    from sonarsim.dataset import Volume

    placed = cube_mesh().apply_translation([0, 0, 0.05])      # inside both protocols' boxes
    raw = placed.copy().apply_scale(2.0)                       # the file before the scene fit
    raw.export(tmp_path / "raw.obj")
    placed.export(tmp_path / "placed.ply")
    tiny_dataset_with_gt(tmp_path / "d.h5", placed)
    for protocol in ("exact", "reference"):
        assert main(["evaluate", str(tmp_path / "placed.ply"), "--gt", str(tmp_path / "d.h5"),
                     "--json", "--no-images", "--samples", "2000", "--volume-samples", "5000",
                     "--protocol", protocol]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["kind"] == "mesh" and res["gt"]["kind"] == "dataset"
        assert res["chamfer_sq"] < 2e-5 and res["warnings"] == []
    assert res["iou"] > 0.5
    vol = Volume(cube_volume(), BOX, "test", params={"dataset": str(tmp_path / "d.h5")})
    vol.write(tmp_path / "v.h5")
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / "raw.obj"),
                 "--no-images", "--no-sweep", "--samples", "1000", "--threshold", "0.5"]) == 0
    out, err = capsys.readouterr()
    assert "ground truth: " + str(tmp_path / "raw.obj") + " (mesh file" in out
    assert err.count("\n") == 1 and "scored as given" in err and "d.h5" in err
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / "d.h5"),
                 "--no-images", "--no-sweep", "--samples", "1000", "--threshold", "0.5"]) == 0
    out, err = capsys.readouterr()
    assert "(dataset: as the simulator placed it" in out and err == ""


def test_degenerate_ground_truths_are_refused_or_warned_in_one_line(tmp_path, capsys):
    from recon.cli import main
    from sonarsim.dataset import Volume

    Volume(cube_volume(), BOX, "test").write(tmp_path / "v.h5")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 0.1 0 0\nv nan 0.1 0\nf 1 2 3\n")
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nf 1 2 3\n")
    for bad, words in (("nan.obj", "NaN"), ("line.obj", "degenerate")):
        assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / bad)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err and "Traceback" not in err
    trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0.01]], [[0, 1, 2]]).export(
        tmp_path / "flat.obj")
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / "flat.obj"),
                 "--no-images", "--no-sweep", "--samples", "500"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "encloses no volume" in err
    open_box = trimesh.creation.box(extents=[0.05] * 3)
    open_box.update_faces(np.arange(10))                        # one face of the box missing
    open_box.export(tmp_path / "open.obj")
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / "open.obj"),
                 "--no-images", "--no-sweep", "--samples", "500"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "open (" in err
    assert main(["evaluate", str(tmp_path / "v.h5"), "--gt", str(tmp_path / "nan.obj").replace(
        "nan.obj", "none.ply")]) == 2


def test_reference_camera_table_per_shape():
    """--protocol reference's cameras: the reference's camera table (predefined_configs.py) by
    the GT's shape name, its default for other names; 'released' = the 60-rad views."""
    from recon import views
    from sonarsim.errors import InputError
    cube = views.reference_views("cube")
    assert (cube.distance, cube.elevation, cube.look_height) == (0.45, 0.21, 0.07)
    assert cube.yfov == pytest.approx(np.pi / 4) and cube.n_views == 10 and cube.resolution == 512
    assert views.reference_views("cylinder").distance == 0.45
    assert views.reference_views("lucy").distance == 0.25
    for name in ("bunny", None, "anything"):
        assert views.reference_views(name) == views.REFERENCE_VIEWS
    assert views.REFERENCE_VIEWS.yfov == pytest.approx(np.pi / 3)
    assert views.reference_views("cube", "released") == views.RELEASED_VIEWS
    assert views.RELEASED_VIEWS.yfov == 60.0
    with pytest.raises(InputError):
        views.reference_views("cube", "nope")


def test_reference_views_read_60_as_radians_like_pyrender(mi):
    """yfov = 60 (radians, as pyrender receives the reference's '--fov 60'): tan(30) < 0, so
    the render is the one with a 2·atan(|tan 30|) = 162° field of view turned by 180°; its
    PSNR takes the data range from the reconstruction's images (torchmetrics, no range)."""
    import dataclasses

    from recon import views
    cams = dataclasses.replace(views.RELEASED_VIEWS, n_views=2, resolution=40)
    wide = dataclasses.replace(cams, yfov=2 * np.arctan(abs(np.tan(30.0))))
    assert np.degrees(wide.yfov) == pytest.approx(162.26, abs=0.01)
    bunnyish = trimesh.creation.icosphere(subdivisions=3, radius=0.06).apply_translation(
        [0.02, -0.01, 0.09])
    a = views.render_views(bunnyish, cams)["depth"]
    b = views.render_views(bunnyish, wide)["depth"]
    assert a.max() > 0 and np.allclose(a, np.rot90(b, 2, axes=(1, 2)), atol=1e-6)
    assert (a > 0).mean() < 0.1                          # a small object in a huge view
    test = np.array([[0.0, 0.25], [0.3, 0.0]])
    mse = np.mean((test - 0.1) ** 2)
    assert views.psnr(np.full((2, 2), 0.1), test, data_range=None) == pytest.approx(
        10 * np.log10(0.3 ** 2 / mse))


def test_comparison_figure_has_gt_mips_a_colour_bar_and_marks_the_best(tmp_path):
    """recon.figures.comparison: a GT row whose MIP panels show the GT occupancy (not empty),
    one shared colour bar, titles naming method and view, the best IoU starred on the better
    volume's row."""
    import matplotlib
    matplotlib.use("Agg")
    from recon import figures
    from sonarsim.dataset import Volume
    good = Volume(cube_volume(), BOX, "bp")
    noisy = Volume(cube_volume() + 1.5 * np.random.default_rng(0).random((N, N, N)), BOX, "gd")
    fig = figures.comparison([good, noisy], cube_mesh(), labels=["BP", "GD"], threshold=0.5)
    axes = fig.axes
    images = [ax for ax in axes if ax.get_images()]
    gt_top = images[0].get_images()[0].get_array()
    assert np.asarray(gt_top).max() == 1.0 and np.asarray(gt_top).min() == 0.0   # GT MIP drawn
    assert any(ax.get_label() == "<colorbar>" for ax in axes)
    titles = [ax.get_title() for ax in axes]
    assert "BP — top view (MIP along z)" in titles and "GD — side view (MIP along y)" in titles
    bp_title = next(t for t in titles if t.startswith("BP: surface"))
    gd_title = next(t for t in titles if t.startswith("GD: surface"))
    assert "IoU 1.000 ★" in bp_title and "★" not in gd_title.split("Chamfer")[0]
    out = figures.save(fig, tmp_path / "cmp.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_comparison_rows_show_their_own_volumes_projections_at_the_voxel_edges():
    """The one comparison figure (recon compare, the demo, examples/reconstruct.py): each
    method's row draws the MIP along z and the MIP along y of *its* volume (normalised),
    placed at the voxel edges in metres (centres ± half a voxel); a single-voxel axis
    spans its one centre ± half the smallest other spacing (export.pixel_extent, the upper
    bound of that axis is ignored)."""
    import matplotlib
    matplotlib.use("Agg")
    from recon import figures
    from sonarsim.dataset import Volume
    rng = np.random.default_rng(0)
    a = rng.random((5, 4, 3)).astype(np.float32)
    b = np.zeros((5, 4, 3), np.float32)
    b[1, 2, 0] = 1.0
    bounds = np.array([[-0.2, 0.2], [0.0, 0.3], [0.01, 0.05]])
    res = [{"iou": 0.5, "chamfer_m": 0.01}, {"iou": 0.4, "chamfer_m": 0.02}]
    fig = figures.comparison([Volume(a, bounds, "bp"), Volume(b, bounds, "gd")], cube_mesh(),
                             labels=["A", "B"], results=res)
    panels = {ax.get_title(): ax.get_images()[0] for ax in fig.axes if ax.get_images()
              and ax.get_label() != "<colorbar>"}
    top_a, side_b = panels["A — top view (MIP along z)"], panels["B — side view (MIP along y)"]
    norm_a = (a - a.min()) / (a.max() - a.min())
    np.testing.assert_allclose(top_a.get_array(), norm_a.max(axis=2).T, rtol=1e-6)
    np.testing.assert_array_equal(side_b.get_array(), b.max(axis=1).T)
    assert top_a.get_clim() == (0, 1)
    # x centres -0.2..0.2 at 0.1 m -> edges -0.25..0.25; z 0.01..0.05 at 0.02 -> 0..0.06
    np.testing.assert_allclose(side_b.get_extent(), [-0.25, 0.25, 0.0, 0.06])
    np.testing.assert_allclose(top_a.get_extent(), [-0.25, 0.25, -0.05, 0.35])
    flat = figures.comparison([Volume(a[:, :, :1], bounds, "bp")], cube_mesh(), labels=["F"],
                              results=res[:1])
    side_f = next(ax.get_images()[0] for ax in flat.axes
                  if ax.get_title() == "F — side view (MIP along y)")
    np.testing.assert_allclose(side_f.get_extent(), [-0.25, 0.25, 0.01 - 0.05, 0.01 + 0.05])
    import matplotlib.pyplot as plt
    plt.close(fig)
    plt.close(flat)


def test_render_views_of_chosen_cameras_equal_those_of_the_whole_ring(mi):
    """render_views(..., views=[i]) renders camera i only, bit-identical to the ring's image i
    (figures draw one view without rendering the other nine)."""
    from recon import views
    cams = views.Turntable(n_views=5, resolution=24)
    mesh = trimesh.creation.box(extents=[0.1, 0.06, 0.08]).apply_translation([0.01, 0.0, 0.1])
    ring = views.render_views(mesh, cams)
    some = views.render_views(mesh, cams, views=[3, 1])
    for kind in ("depth", "shaded"):
        assert some[kind].shape == (2, 24, 24)
        assert np.array_equal(some[kind][0], ring[kind][3])
        assert np.array_equal(some[kind][1], ring[kind][1])
    assert not np.array_equal(ring["depth"][3], ring["depth"][1])
