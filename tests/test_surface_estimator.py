"""The bounce-1 surface estimator and the amplitude models of ``sonar_transient``.

References: closed forms (sphere, plane), the TX-cone path tracer at a high path count
(bunny), a direct NumPy sum of the seed's Eq. (1) with Möller–Trumbore visibility (pressure),
Rayleigh statistics (coherent), replicas (half-estimates).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from sonarsim import data

from test_sonar_transient import (DOWN, D_SPHERE, GROUND_HALF, R_SPHERE, W, SphereCap,  # noqa: F401
                                  _box_mesh, _occluded, _subdivide, box_on_ground, diffuse,
                                  integrator, render, tent_histogram)

BUNNY = data.path("bunny.obj")


def test_sphere_closed_form(mi, sphere_scene):
    """Total and energy CDF of the analytic sphere (cell grid of ``sample_position``)."""
    cap = SphereCap(D_SPHERE, R_SPHERE)
    integ = integrator(mi, tx_bw=12.0, rx_bw=12.0, surface_spacing=4e-3)
    pos, look = (D_SPHERE, 0, 0), (-1, 0, 0)
    start, n_bins = 1.75, int(0.3 / W)
    hist = render(integ, sphere_scene, pos, pos, look, look, start, n_bins, 1)[0, 0]
    expected = cap.total()
    assert abs(hist.sum() / expected - 1) < 0.01, (hist.sum(), expected)
    edges = start + (np.arange(n_bins) + 1) * W
    analytic = np.array([cap.total(e) for e in edges[::25]]) / expected
    assert np.max(np.abs(np.cumsum(hist)[::25] / hist.sum() - analytic)) < 0.01


def test_plane_facets_closed_form_profile(mi):
    """Triangle facets (the rectangle is a mesh): total and CDF over path length.

    Co-located at height h above a Lambertian plane, cone beams of half-angle α: the energy
    with path length ≤ L is ρ(1 − cos⁴β)/(2h²) with cos β = max(2h/L, cos α).
    """
    rho, h, alpha = 0.7, 0.6, math.radians(15)
    scene = mi.load_dict({"type": "scene", "plane": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([1.0, 1.0, 1.0]),
        "bsdf": diffuse(rho)}})
    pos = (0.05, -0.03, h)
    start, n_bins = 2 * h - 0.01, int(0.1 / W)
    hist = render(integrator(mi), scene, pos, pos, DOWN, DOWN, start, n_bins, 1)[0, 0]
    total = rho * (1 - math.cos(alpha) ** 4) / (2 * h * h)
    assert hist.sum() == pytest.approx(total, rel=0.003)
    edges = start + (np.arange(n_bins) + 1) * W
    cos_b = np.maximum(np.minimum(2 * h / edges, 1.0), math.cos(alpha))
    analytic = rho * (1 - cos_b ** 4) / (2 * h * h) / total
    assert np.max(np.abs(np.cumsum(hist) / hist.sum() - analytic)) < 0.01


@pytest.fixture(scope="module")
def bunny_scene(mi):
    return mi.load_dict({
        "type": "scene",
        "bunny": {"type": "obj", "filename": str(BUNNY), "bsdf": diffuse(1.0)},
        "ground": {"type": "rectangle", "bsdf": diffuse(1.0),
                   "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0])}})


def test_surface_matches_cone_on_the_bunny(mi, bunny_scene):
    """Bounce 1 on bunny + ground: energy within 2 % and the profile (1 cm of path per
    coarse bin) within the cone tracer's Monte-Carlo noise, measured from 8 replicas."""
    tx = np.array([0.0, -0.8485, 0.1725])
    rx = tx + np.array([0.0, -0.013, -0.038])
    aim = np.array([0.0, 0.0, 0.09])
    tx_dir, rx_dir = aim - tx, aim - rx
    start, n_bins, coarse = 1.25, 58 * int(0.6 / (58 * W)), 58          # 58 bins ≈ 1 cm
    surface = render(integrator(mi), bunny_scene, tx, rx, tx_dir, rx_dir, start, n_bins, 1)[0, 0]
    replicas = 8
    cone = render(integrator(mi, bounce1="cone"), bunny_scene, tx, rx, tx_dir, rx_dir, start,
                  n_bins, 150_000, replicas=replicas)[:, 0]
    totals = cone.sum(axis=1)
    assert abs(surface.sum() / totals.mean() - 1) < 0.02
    assert abs(surface.sum() - totals.mean()) < 5 * totals.std(ddof=1) / math.sqrt(replicas)
    s = surface.reshape(-1, coarse).sum(axis=1)
    c = cone.reshape(replicas, -1, coarse).sum(axis=2)
    se = c.std(axis=0, ddof=1) / math.sqrt(replicas)
    significant = c.mean(axis=0) > 1e-3 * c.mean(axis=0).max()
    assert significant.sum() >= 10
    z = np.abs(s - c.mean(axis=0))[significant] / (se[significant] + 1e-4 * s.max())
    assert z.max() < 5, z


def _box_scene(mi, path, ground_albedo):
    return mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": diffuse(ground_albedo),
                   "to_world": mi.ScalarTransform4f().scale([GROUND_HALF, GROUND_HALF, 1.0])},
        "box": {"type": "ply", "filename": str(path), "face_normals": True,
                "bsdf": diffuse(0.8)}})


def test_bounces_from_surface_points_match_the_cone_tracer(mi, tmp_path):
    """Bounces 2 and 3 started at the surface points (bounce1='surface', 1 and 2
    continuations per point) against the TX-cone tracer on a box standing on the ground:
    energies within 5 standard errors (replicas) and 4 %; with the same random numbers,
    halving the ground's albedo halves bounce 2."""
    path = tmp_path / "box.ply"
    _box_mesh().export(path)
    scene = _box_scene(mi, path, 1.0)
    tx = np.array([0.0, -0.45, 0.25])
    rx = tx + np.array([0.04, 0.0, 0.0])
    look = (np.array([0.0, 0.0, 0.03]) - tx) / np.linalg.norm(np.array([0.0, 0.0, 0.03]) - tx)
    args = (tx, rx, look, look, 0.8, int(0.8 / W))
    replicas = 8
    cone = render(integrator(mi, bounces=3, tx_bw=60.0, rx_bw=60.0, bounce1="cone"), scene,
                  *args, 60_000, replicas=replicas).sum(axis=2)
    integ = integrator(mi, bounces=3, tx_bw=60.0, rx_bw=60.0, surface_spacing=4e-3)
    surf = render(integ, scene, *args, 1, replicas=replicas).sum(axis=2)
    two = render(integrator(mi, bounces=3, tx_bw=60.0, rx_bw=60.0, surface_spacing=6e-3,
                            facet_paths=2), scene, *args, 1, replicas=replicas).sum(axis=2)
    for est in (surf, two):
        for b in (1, 2):
            se = math.sqrt((cone[:, b].var(ddof=1) + est[:, b].var(ddof=1)) / replicas)
            diff = est[:, b].mean() - cone[:, b].mean()
            assert abs(diff) < 5 * se, (b, diff, se)
            assert abs(diff) < 0.04 * cone[:, b].mean(), (b, diff / cone[:, b].mean())
    dark = render(integ, _box_scene(mi, path, 0.5), *args, 1, replicas=replicas).sum(axis=2)
    np.testing.assert_allclose(dark[:, 1], 0.5 * surf[:, 1], rtol=1e-5)


# ----------------------------------------------------------------- pressure: Eq. (1)
def test_pressure_matches_numpy_eq1(mi, tmp_path):
    """Box on a ground plate, bistatic: the integrator's pressure histogram against a
    direct NumPy sum of b_T b_R sqrt(ρ cosθ_i cosθ_o) dA / (2π r_T r_R) over surface
    points with explicit TX and RX visibility (Möller–Trumbore)."""
    import trimesh
    box = trimesh.creation.box(extents=[0.06] * 3)
    box.apply_transform(trimesh.transformations.rotation_matrix(math.radians(30), [0, 0, 1]))
    box.apply_translation([0.01, 0.02, 0.03])
    path = tmp_path / "box.ply"
    box.export(path)
    g = 0.12
    scene = mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": diffuse(0.5),
                   "to_world": mi.ScalarTransform4f().scale([g, g, 1.0])},
        "box": {"type": "ply", "filename": str(path), "face_normals": True,
                "bsdf": diffuse(0.8)}})
    gv = np.array([[-g, -g, 0], [g, -g, 0], [g, g, 0], [-g, g, 0]], float)
    triangles = np.concatenate([gv[np.array([[0, 1, 2], [0, 2, 3]])], box.vertices[box.faces]])
    albedo = np.concatenate([np.full(2, 0.5), np.full(len(box.faces), 0.8)])
    tx = np.array([0.0, -0.45, 0.25])
    rx = np.array([0.3, -0.35, 0.15])
    aim = np.array([0.0, 0.0, 0.03])
    tx_dir, rx_dir = (aim - tx) / np.linalg.norm(aim - tx), (aim - rx) / np.linalg.norm(aim - rx)
    cos_cut = math.cos(math.radians(30))

    # Independent reference: n² points per triangle (a few hundred per face), midpoint rule.
    lens, vals = [], []
    for tri, rho in zip(triangles, albedo):
        n = 40 if rho == 0.5 else 12
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        area = np.linalg.norm(normal) / 2
        normal /= 2 * area
        x = _subdivide(tri, n)
        vt, vr = tx - x, rx - x
        rt, rr = np.linalg.norm(vt, axis=1), np.linalg.norm(vr, axis=1)
        ci, co = vt @ normal / rt, vr @ normal / rr
        keep = (ci * co > 0) & ((-vt / rt[:, None]) @ tx_dir >= cos_cut) \
            & ((-vr / rr[:, None]) @ rx_dir >= cos_cut)
        keep &= ~_occluded(x, tx, triangles) & ~_occluded(x, rx, triangles)
        amp = np.sqrt(rho * np.abs(ci * co)) / (2 * math.pi * rt * rr) * area / n ** 2
        lens.append((rt + rr)[keep])
        vals.append(amp[keep])
    lens, vals = np.concatenate(lens), np.concatenate(vals)
    assert len(vals) > 2000
    start, n_bins = 0.7, int(0.5 / W)
    ref = tent_histogram(lens, vals, start, n_bins)

    integ = integrator(mi, tx_bw=60.0, rx_bw=60.0, amplitude="pressure", surface_spacing=4e-3)
    hist = render(integ, scene, tx, rx, tx_dir, rx_dir, start, n_bins, 1)[0, 0]
    assert hist.dtype == np.float32
    assert hist.sum() == pytest.approx(ref.sum(), rel=0.01)
    cdf, cdf_ref = np.cumsum(hist) / hist.sum(), np.cumsum(ref) / ref.sum()
    assert np.max(np.abs(cdf - cdf_ref)) < 0.01
    # Band-limited comparison (the waveform sees the histogram through the pulse): 1 cm boxcar.
    k = np.ones(58) / 58
    a, b = np.convolve(hist, k, "same"), np.convolve(ref, k, "same")
    assert np.linalg.norm(a - b) < 0.03 * np.linalg.norm(b)


# --------------------------------------------------------------- coherent: speckle
def _compressed(hist_complex, oversample=20):
    """hist ⊗ analytic LFM pulse at the oversampled rate (complex histogram [T])."""
    from sonarsim.signals import analytic
    from sonarsim.signals import pulse_from_spec
    from sonarsim.simulate import oversampled_pulse
    pulse = oversampled_pulse(pulse_from_spec("lfm-20k", 100e3).samples, oversample)
    n = len(hist_complex) + len(pulse) - 1
    spec = np.fft.fft(hist_complex, n) * np.fft.fft(analytic(pulse), n)
    return np.fft.ifft(spec)[: len(hist_complex)]


def test_coherent_speckle_is_rayleigh(mi):
    """A flat plate seen obliquely: over speckle seeds, the normalised intensity
    I/⟨I⟩ of the pulse-compressed echo is exponential (Rayleigh envelope): contrast
    std/mean of I ≈ 1 and of |s| ≈ √(4/π − 1) = 0.523; P(I > ⟨I⟩) = e⁻¹. (Without
    phases every seed gives the same echo: contrast 0.)"""
    scene = mi.load_dict({"type": "scene", "plate": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([0.15, 0.15, 1.0]),
        "bsdf": diffuse(1.0)}})
    tx = np.array([0.0, -0.6, 0.35])
    rx = tx + np.array([0.0, -0.013, -0.038])
    look = -tx / np.linalg.norm(tx)
    start, n_bins = 1.2, int(0.45 / W)
    envs = []
    for speckle_seed in range(12):
        integ = integrator(mi, amplitude="coherent", speckle_seed=speckle_seed,
                           tx_bw=40.0, rx_bw=40.0)
        hist = render(integ, scene, tx, rx, look, look, start, n_bins, 1)[0, 0]
        assert hist.dtype == np.complex64
        envs.append(np.abs(_compressed(hist.astype(np.complex128))))
    envs = np.array(envs)[:, ::20]                        # decimate to the sample rate
    mean_i = (envs ** 2).mean(axis=0)
    inside = mean_i > 0.2 * mean_i.max()
    assert inside.sum() > 40
    intensity = (envs ** 2)[:, inside] / mean_i[inside]
    contrast_i = intensity.std() / intensity.mean()
    amp = np.sqrt(intensity)
    contrast_a = amp.std() / amp.mean()
    assert 0.85 < contrast_i < 1.15, contrast_i
    assert abs(contrast_a - math.sqrt(4 / math.pi - 1)) < 0.06, contrast_a
    assert abs((intensity > 1).mean() - math.exp(-1)) < 0.05



def test_coherent_phases_follow_the_speckle_seed_only(mi):
    """The sampling seed moves only the quadrature; the speckle seed changes the echo."""
    scene = mi.load_dict({"type": "scene", "plate": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([0.1, 0.1, 1.0]),
        "bsdf": diffuse(1.0)}})
    pos, start, n_bins = (0.0, -0.3, 0.3), 0.7, int(0.3 / W)
    look = -np.array(pos) / np.linalg.norm(pos)
    a = render(integrator(mi, amplitude="coherent"), scene, pos, pos, look, look, start, n_bins, 1)
    b = render(integrator(mi, amplitude="coherent"), scene, pos, pos, look, look, start, n_bins,
               1, seed=5)
    c = render(integrator(mi, amplitude="coherent", speckle_seed=1), scene, pos, pos, look, look,
               start, n_bins, 1)
    ea, eb, ec = (_compressed(h[0, 0].astype(np.complex128)) for h in (a, b, c))
    assert np.linalg.norm(ea - eb) < 0.1 * np.linalg.norm(ea)       # sampling noise only
    # independent patterns: ‖a − c‖ ≈ √2 ‖a‖
    assert 1.1 < np.linalg.norm(ea - ec) / np.linalg.norm(ea) < 1.7


# ------------------------------------------------------------------ half-estimates
@pytest.mark.parametrize("bounce1", ["surface", "cone"])
def test_halves_are_independent_and_average_to_the_estimate(mi, bounce1):
    """Replicas of one pose: the spread of the full estimates across replicas matches the
    half difference (d = (h₀ − h₁)/2 has the variance of the mean's error only if the
    halves are independent), and the mean of the halves is the full estimate."""
    scene = mi.load_dict({"type": "scene",
                          "plate": {"type": "rectangle", "bsdf": diffuse(1.0),
                                    "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0])},
                          "ball": {"type": "sphere", "radius": 0.05, "center": [0, 0, 0.05],
                                   "bsdf": diffuse(1.0)}})
    pos = np.array([0.0, -0.5, 0.3])
    look = -pos / np.linalg.norm(pos)
    start, n_bins, coarse = 0.8, 58 * 8 * 4, 58 * 4
    integ = integrator(mi, bounces=2, bounce1=bounce1, surface_spacing=0.02)
    replicas, paths = 48, 2000
    halves = render(integ, scene, pos, pos, look, look, start, n_bins, paths,
                    replicas=replicas, halves=True)
    full = render(integ, scene, pos, pos, look, look, start, n_bins, paths, replicas=replicas)
    assert halves.shape == (2, replicas, 2, n_bins)
    np.testing.assert_allclose(halves.mean(axis=0), full, rtol=2e-6, atol=1e-7 * full.max())
    assert np.abs(halves[0] - halves[1]).max() > 1e-3 * full.max()
    for b in range(2):
        f = full[:, b].reshape(replicas, -1, coarse).sum(axis=2)
        d = ((halves[0, :, b] - halves[1, :, b]) / 2).reshape(replicas, -1, coarse).sum(axis=2)
        spread = f.var(axis=0, ddof=1).sum()
        predicted = (d ** 2).mean(axis=0).sum()
        assert 0.6 < predicted / spread < 1.6, (b, predicted / spread)


def test_surface_is_seeded_and_chunk_independent(mi):
    """Same seed and settings: the same bytes for any chunking; another seed moves the jitter."""
    from sonarsim.geometry import Poses
    from sonarsim.render import iter_render
    scene = mi.load_dict({"type": "scene",
                          "plate": {"type": "rectangle", "bsdf": diffuse(1.0),
                                    "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0])},
                          "ball": {"type": "sphere", "radius": 0.05, "center": [0, 0, 0.05],
                                   "bsdf": diffuse(1.0)}})
    ang = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    tx = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang), np.full(5, 0.2)], axis=1)
    poses = Poses.pointing_at(tx, tx + [0, 0, -0.04], np.array([0.0, 0.0, 0.03]))
    kw = dict(paths_per_pose=2, bounces=1, path_range=(0.6, 1.4), halves=True)

    def run(**extra):
        return np.concatenate([h for _, h in iter_render(scene, poses, **kw, **extra)], axis=1)

    whole = run(seed=3)
    for other in (run(seed=3, chunk_size=1), run(seed=3, chunk_size=2)):
        assert other.tobytes() == whole.tobytes()
    moved = run(seed=4)
    assert np.abs(moved - whole).max() > 1e-4 * whole.max()
    np.testing.assert_allclose(moved.sum(axis=-1), whole.sum(axis=-1), rtol=0.05)


def test_settings_are_checked(mi):
    for props in ({"bounce1": "area"}, {"amplitude": "loud"}, {"surface_spacing": 0.0},
                  {"path_samples": 0}, {"speckle_seed": -1}, {"facet_paths": 0},
                  {"guide_fraction": 1.0}):
        with pytest.raises(Exception, match="sonar_transient"):
            integrator(mi, **props)


def test_different_tx_and_rx_beams_match_brute_force(mi, box_on_ground):
    """TX and RX with different beam patterns, as --reference-parity has (isotropic TX,
    24° cone RX), wide baseline: the surface estimator against the NumPy midpoint
    quadrature. The beams' kinds differ, so a swap of the TX and RX beam objects changes
    the answer (with two cones it would not: their widths come with the pose constants)."""
    from test_sonar_transient import brute_force_single_bounce
    scene, triangles, albedo = box_on_ground
    tx = np.array([0.0, -0.45, 0.25])
    rx = tx + np.array([0.45, 0.3, -0.1])
    tx_dir = np.array([0.08, 0.0, 0.03]) - tx
    rx_dir = np.array([-0.05, 0.05, 0.0]) - rx
    tx_dir, rx_dir = tx_dir / np.linalg.norm(tx_dir), rx_dir / np.linalg.norm(rx_dir)
    rx_bw = 24.0
    start, n_bins = 0.6, int(1.0 / W)
    lens, vals, _ = brute_force_single_bounce(triangles, albedo, tx, rx, tx_dir, rx_dir,
                                              math.pi, 48, math.radians(rx_bw / 2))
    no_rx_beam = brute_force_single_bounce(triangles, albedo, tx, rx, tx_dir, rx_dir,
                                           math.pi, 48)[1].sum()
    assert no_rx_beam > 1.2 * vals.sum()                    # the RX beam matters here
    integ = integrator(mi, tx="isotropic", rx_bw=rx_bw, surface_spacing=2e-3)
    hist = render(integ, scene, tx, rx, tx_dir, rx_dir, start, n_bins, 1)[0, 0]
    expected = vals.sum()
    assert hist.sum() == pytest.approx(expected, rel=0.01), (hist.sum(), expected)
    reference = tent_histogram(lens, vals, start, n_bins)
    assert np.max(np.abs(np.cumsum(hist) / hist.sum() - np.cumsum(reference) / expected)) < 0.01


def test_bistatic_sphere_matches_numpy_quadrature(mi, sphere_scene):
    """Mitsuba's analytic sphere (the cell-grid strata) seen by a bistatic pair at different
    ranges: total and path-length distribution against a NumPy equal-area midpoint sum over
    the sphere (value ρ/π cosθ_i cosθ_o / (r_T² r_R²) dA at path length r_T + r_R)."""
    tx = np.array([0.9, 0.0, 0.1])
    rx = np.array([0.5, 0.55, -0.05])
    n_t, n_p = 600, 1200                         # equal-area cells: cosθ × φ
    ct = -1 + (np.arange(n_t) + 0.5) * 2 / n_t
    ph = (np.arange(n_p) + 0.5) * 2 * np.pi / n_p
    st = np.sqrt(1 - ct ** 2)
    n = np.stack([np.outer(st, np.cos(ph)), np.outer(st, np.sin(ph)),
                  np.outer(ct, np.ones(n_p))], axis=-1).reshape(-1, 3)
    x = R_SPHERE * n
    vt, vr = tx - x, rx - x
    rt, rr = np.linalg.norm(vt, axis=1), np.linalg.norm(vr, axis=1)
    ci, co = np.einsum("ij,ij->i", vt, n) / rt, np.einsum("ij,ij->i", vr, n) / rr
    keep = (ci > 0) & (co > 0)                  # a convex body: nothing else occludes
    area = 4 * np.pi * R_SPHERE ** 2 / len(x)
    vals = (ci * co / (np.pi * rt ** 2 * rr ** 2) * area)[keep]
    lens = (rt + rr)[keep]
    start, n_bins = 1.3, int(0.4 / W)
    assert lens.min() > start + W and lens.max() < start + (n_bins - 1) * W
    integ = integrator(mi, tx="isotropic", rx="isotropic", surface_spacing=2e-3)
    look = -tx / np.linalg.norm(tx)
    hist = render(integ, sphere_scene, tx, rx, look, look, start, n_bins, 1)[0, 0]
    assert hist.sum() == pytest.approx(vals.sum(), rel=0.003)
    centres = start + (np.arange(n_bins) + 0.5) * W
    mean_len = (hist * centres).sum() / hist.sum()
    assert mean_len == pytest.approx((vals * lens).sum() / vals.sum(), abs=0.05 * W)
    reference = tent_histogram(lens, vals, start, n_bins)
    assert np.max(np.abs(np.cumsum(hist) / hist.sum() - np.cumsum(reference) / vals.sum())) < 0.01
