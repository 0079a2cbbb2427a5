"""Validation of the ``sonar_transient`` integrator and the chunked driver (sonarsim.render).

Closed forms and an independent NumPy quadrature are the references. Statistical tolerances
are stated as multiples of the Monte-Carlo standard error, which is either computed from
the same integrals (E[X²] of the estimator) or measured from independent replicas: a pose
repeated K times in one call gets K independent random streams.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq
from scipy.special import j1

from conftest import SPHERE_RADIUS
from sonarsim.errors import InputError

C = 344.973                 # m/s
FS = 100e3                  # Hz
W = C / (FS * 20)           # m of round-trip path per bin (reference oversampling)
DOWN = (0.0, 0.0, -1.0)


# ----------------------------------------------------------------------------- helpers
def diffuse(rho: float) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "spectrum", "value": float(rho)}}


def integrator(mi, bounces=1, tx="cone", tx_bw=30.0, rx="cone", rx_bw=30.0, **props):
    """``props``: further integrator properties, e.g. bounce1='cone' for the TX-cone tracer."""
    return mi.load_dict({"type": "sonar_transient", "max_bounces": bounces, "tx_beam": tx,
                         "tx_beamwidth": tx_bw, "rx_beam": rx, "rx_beamwidth": rx_bw, **props})


def render(integ, scene, tx, rx, tx_dir, rx_dir, start, n_bins, paths, seed=0, width=W,
           replicas=1, **kw):
    rows = [np.tile(np.asarray(a, float).reshape(-1, 3), (replicas, 1))
            for a in (tx, rx, tx_dir, rx_dir)]
    return integ.render_transients(scene, *rows, start, width, n_bins, paths, seed, **kw)


def centres(start, n_bins, width=W):
    return start + (np.arange(n_bins) + 0.5) * width


def tent_histogram(lengths, values, start, n_bins, width=W):
    """The documented binning, in NumPy: linear split between the two nearest bin centres."""
    u = (lengths - start) / width - 0.5
    j0 = np.floor(u).astype(int)
    f = u - j0
    hist = np.zeros(n_bins)
    for j, w in ((j0, 1 - f), (j0 + 1, f)):
        ok = (j >= 0) & (j < n_bins)
        np.add.at(hist, j[ok], (values * w)[ok])
    return hist


def cone_solid_angle(full_deg):
    return 2 * math.pi * (1 - math.cos(math.radians(full_deg) / 2))


# ------------------------------------------------------- closed form: Lambertian sphere
D_SPHERE, R_SPHERE = 1.0, SPHERE_RADIUS   # sphere_scene (conftest): Mitsuba's analytic sphere


class SphereCap:
    """Co-located TX/RX at distance D from the centre of a Lambertian sphere of radius R.

    φ is the polar angle on the sphere from the sensor axis; the visible cap is
    cos φ > R/D; r(φ) the range, cosθ = (D cos φ − R)/r the cosine at the surface.
    """

    def __init__(self, d, r, rho=1.0):
        self.d, self.r, self.rho = d, r, rho
        self.phi_max = math.acos(r / d)

    def rng(self, phi):
        return math.sqrt(self.d ** 2 + self.r ** 2 - 2 * self.d * self.r * math.cos(phi))

    def _integral(self, integrand, phi_hi):
        def f(phi):
            rr = self.rng(phi)
            cos_t = (self.d * math.cos(phi) - self.r) / rr
            return integrand(cos_t, rr) * 2 * math.pi * self.r ** 2 * math.sin(phi)
        return quad(f, 0.0, phi_hi, epsabs=0, epsrel=1e-10, limit=200)[0]

    def total(self, length_max=None):
        """∫ ρ cos²θ / (π r⁴) dA over the cap part with path length 2r < length_max."""
        hi = self.phi_max
        if length_max is not None:
            c = (self.d ** 2 + self.r ** 2 - (length_max / 2) ** 2) / (2 * self.d * self.r)
            hi = min(hi, math.acos(min(1.0, max(-1.0, c))))
        return self._integral(lambda c, rr: self.rho * c * c / (math.pi * rr ** 4), hi)

    def relative_std(self, solid_angle, paths):
        """Standard error of the estimator X = Ω ρ/π cosθ/r² (TX direction uniform in Ω)."""
        second = solid_angle * self._integral(
            lambda c, rr: (self.rho / math.pi) ** 2 * c ** 3 / rr ** 6, self.phi_max)
        return math.sqrt(second / self.total() ** 2 - 1) / math.sqrt(paths)


def test_sphere_matches_closed_form(mi, sphere_scene):
    cap = SphereCap(D_SPHERE, R_SPHERE)
    beam = 12.0       # full width: covers the sphere (half-angle 6° > asin(R/D) = 5.74°)
    paths = 400_000
    integ = integrator(mi, bounces=3, tx_bw=beam, rx_bw=beam, bounce1="cone")
    pos, look = (D_SPHERE, 0, 0), (-1, 0, 0)
    start, n_bins = 1.75, int(0.3 / W)
    hist = render(integ, sphere_scene, pos, pos, look, look, start, n_bins, paths)[0]

    expected = cap.total()
    sigma = cap.relative_std(cone_solid_angle(beam), paths)
    assert 5 * sigma < 0.01, "test design: too few paths for a 1 % check"
    measured = hist[0].sum()
    assert abs(measured / expected - 1) < min(0.01, 5 * sigma + 1e-3), (measured, expected)

    # Energy versus path length: normalised cumulative distribution at bin upper edges.
    edges = start + (np.arange(n_bins) + 1) * W
    analytic = np.array([cap.total(e) for e in edges[::25]]) / expected
    empirical = np.cumsum(hist[0])[::25] / measured
    assert np.max(np.abs(empirical - analytic)) < 0.01

    # A convex object alone cannot light itself: no energy after the first bounce.
    assert np.all(hist[1:] == 0)


def test_sphere_echo_extent(mi, sphere_scene):
    # Coarser bins (4 per sample): the grazing limb is approached like a square root in
    # path length, so 1.7 mm-bins near 2·sqrt(D²−R²) would be hit by very few paths.
    width = C / (FS * 4)
    integ = integrator(mi, bounces=1, tx_bw=12.0, rx_bw=12.0)
    pos, look = (D_SPHERE, 0, 0), (-1, 0, 0)
    start, n_bins = 1.7, int(0.4 / width)
    hist = render(integ, sphere_scene, pos, pos, look, look, start, n_bins, 400_000,
                  width=width)[0, 0]
    nz = np.nonzero(hist)[0]
    c = centres(start, n_bins, width)
    assert abs(c[nz[0]] - 2 * (D_SPHERE - R_SPHERE)) < 2 * width
    assert abs(c[nz[-1]] - 2 * math.sqrt(D_SPHERE ** 2 - R_SPHERE ** 2)) < 2 * width


# ------------------------------------------- closed form: inside an integrating sphere
def test_integrating_sphere_bounces_and_tent_binning(mi):
    """Isotropic TX and RX at the centre of a hollow Lambertian sphere of radius R.

    Bounce 1 reaches the wall at normal incidence, so the wall radiance is uniform,
    ρ/(πR²); each further bounce multiplies it by ρ. The RX integrates 4π of it:
    bounce k carries exactly 4ρ^k/R², and every estimator sample has the same value
    (zero variance). Bounce 1 arrives at exactly L = 2R, which is placed 30 % of the
    way from one bin centre to the next: the tent gives weights 0.7 and 0.3.
    """
    rho, k, bounces = 0.6, 1159, 8
    radius = (k + 0.8) * W / 2                 # (2R − start)/W − 1/2 = k + 0.3
    centre = [0.01, -0.02, 0.03]
    scene = mi.load_dict({"type": "scene", "shell": {
        "type": "sphere", "radius": radius, "center": centre, "bsdf": diffuse(rho)}})
    integ = integrator(mi, bounces=bounces, tx="isotropic", rx="isotropic", bounce1="cone")
    n_bins = (bounces + 1) * k                 # longest path: 2R per bounce
    hist = render(integ, scene, centre, centre, DOWN, DOWN, 0.0, n_bins, 20_000)[0]
    np.testing.assert_allclose(hist.sum(axis=1),
                               [4 * rho ** b / radius ** 2 for b in range(1, bounces + 1)],
                               rtol=1e-4)
    first = hist[0]
    assert np.count_nonzero(first) == 2
    assert first[k] / first.sum() == pytest.approx(0.7, abs=2e-3)
    assert first[k + 1] / first.sum() == pytest.approx(0.3, abs=2e-3)
    # Later bounces travel further: R + chords + R.
    assert np.nonzero(hist[1])[0].min() >= k and hist[1, : k].sum() == 0
    # Every path hits the wall and sees the RX at every bounce.
    stats: dict = {}
    render(integ, scene, centre, centre, DOWN, DOWN, 0.0, n_bins, 1000, ray_stats=stats)
    assert stats == {"intersect": 1000 * bounces, "shadow": 1000 * bounces}


def _numpy_mean_chord(radius, n, rng):
    """Independent check of 4R/3: mean chord of a sphere along cosine-distributed directions.

    Points uniform on the sphere, directions cosine-weighted about the inward normal (Malley:
    uniform disk lifted to the hemisphere), chord = the far root of |p + t d − c| = R.
    """
    p = rng.standard_normal((n, 3))
    p *= radius / np.linalg.norm(p, axis=1, keepdims=True)        # centre at the origin
    inward = -p / radius
    helper = np.where(np.abs(inward[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(inward, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(inward, e1)
    r, phi = np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    d = (r * np.cos(phi))[:, None] * e1 + (r * np.sin(phi))[:, None] * e2 \
        + np.sqrt(1 - r * r)[:, None] * inward
    b = np.einsum("ij,ij->i", p, d)                                 # |p + t d|² = R²
    return (-b + np.sqrt(b * b - (np.einsum("ij,ij->i", p, p) - radius ** 2))).mean()


def test_integrating_sphere_mean_path_lengths(mi):
    """Mean path length of bounce k inside a hollow sphere: R + (k − 1)·4R/3 + R.

    TX and RX at the centre: the first and the last segment are R. A chord leaving the wall
    at angle θ from the inward normal is 2R cosθ; cosine-weighted sampling gives
    E[cosθ] = 2/3 and E[cos²θ] = 1/2, so a chord has mean 4R/3 and variance 2R²/9. Every
    path carries the same energy and the tent splat preserves means, so the energy-weighted
    mean of the bin centres is the mean path length. A small R keeps the standard error
    (∝ R) far below the bias of continuing paths from an origin offset along the normal
    (Mitsuba's spawn_ray, ~1e-4 m per inner segment whatever R), which this test detects.
    """
    radius, paths = 0.01, 1_000_000
    chord = 4 * radius / 3
    assert _numpy_mean_chord(radius, 400_000, np.random.default_rng(1)) == pytest.approx(
        chord, abs=5 * math.sqrt(2 / 9) * radius / math.sqrt(400_000))
    centre = [0.01, -0.02, 0.03]
    scene = mi.load_dict({"type": "scene", "shell": {
        "type": "sphere", "radius": radius, "center": centre, "bsdf": diffuse(0.6)}})
    integ = integrator(mi, bounces=3, tx="isotropic", rx="isotropic", bounce1="cone")
    n_bins = int(6 * radius / W) + 10           # longest path: 2R per bounce
    hist = render(integ, scene, centre, centre, DOWN, DOWN, 0.0, n_bins, paths)[0]
    mean = (hist * centres(0.0, n_bins)).sum(axis=1) / hist.sum(axis=1)
    for k in (1, 2, 3):
        expected = 2 * radius + (k - 1) * chord
        se = math.sqrt((k - 1) * 2 / 9) * radius / math.sqrt(paths)
        assert abs(mean[k - 1] - expected) < 5 * se + 1e-7, (k, mean[k - 1] - expected, se)


# ------------------------------------------------------------- closed form: large plane
@pytest.mark.parametrize("bounce1", ["cone", "surface"])
def test_plane_first_return_and_total(mi, bounce1):
    rho, h = 0.7, 1.0
    scene = mi.load_dict({"type": "scene", "plane": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2.0, 2.0, 1.0]),
        "bsdf": diffuse(rho)}})
    beam = 30.0
    alpha = math.radians(beam / 2)
    pos = (0.1, -0.05, h)                  # footprint radius h·tan15° = 0.27 m < 1 m
    start, n_bins = 1.9, int(0.25 / W)
    integ = integrator(mi, tx_bw=beam, rx_bw=beam, bounce1=bounce1)
    hist = render(integ, scene, pos, pos, DOWN, DOWN, start, n_bins, 200_000)[0, 0]
    # ∫_disk ρ/π cos²θ / r⁴ dA with cosθ = h/r: closed form ρ (1 − cos⁴α) / (2h²).
    expected = rho * (1 - math.cos(alpha) ** 4) / (2 * h * h)
    assert hist.sum() == pytest.approx(expected, rel=0.005)
    nz = np.nonzero(hist)[0]
    c = centres(start, n_bins)
    assert abs(c[nz[0]] - 2 * h) <= W        # perpendicular distance
    # The surface estimator decides the beam edge per facet (at its sample point) and
    # spreads a facet over its path-length span: up to 2·spacing·sinα past the edge.
    smear = 0.0 if bounce1 == "cone" else 2 * integ.surface_spacing * math.sin(alpha)
    assert abs(c[nz[-1]] - 2 * h / math.cos(alpha)) <= 2 * W + smear


def test_piston_beam_on_plane(mi):
    """Circular-piston TX pattern against ∫ b(θ) over an (effectively infinite) plane."""
    h, beam, paths, replicas = 0.5, 30.0, 50_000, 8
    scene = mi.load_dict({"type": "scene", "plane": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([20.0, 20.0, 1.0]),
        "bsdf": diffuse(1.0)}})
    integ = integrator(mi, tx="piston", tx_bw=beam, rx="isotropic", bounce1="cone")
    pos = (0, 0, h)
    start, n_bins = 2 * h - 0.01, int(60 / W)     # long window: side lobes reach far out
    hist = render(integ, scene, pos, pos, DOWN, DOWN, start, n_bins, paths,
                  replicas=replicas)
    totals = hist[:, 0].sum(axis=1)
    # Independent pattern: |2 J1(x)/x|², x = ka sinθ, ka from the half-power condition.
    ka = brentq(lambda x: (2 * j1(x) / x) ** 2 - 0.5, 1.0, 3.0) / math.sin(math.radians(beam / 2))

    def gain(t):
        x = ka * math.sin(t)
        return 1.0 if x < 1e-9 else (2 * j1(x) / x) ** 2

    # Co-located, plane at height h: total = (2/h²) ∫ b(θ) cos³θ sinθ dθ.
    expected = 2 / h ** 2 * quad(lambda t: gain(t) * math.cos(t) ** 3 * math.sin(t),
                                 0, math.pi / 2, limit=400)[0]
    mean, se = totals.mean(), totals.std(ddof=1) / math.sqrt(replicas)
    assert abs(mean - expected) < 5 * se + 0.002 * expected, (mean, expected, se)
    assert abs(mean / expected - 1) < 0.01


# ----------------------------------------------- bistatic pose vs brute-force quadrature
GROUND_HALF = 0.15
BOX_SIZE = 0.06


def _box_mesh():
    import trimesh
    box = trimesh.creation.box(extents=[BOX_SIZE] * 3)
    rot = trimesh.transformations.rotation_matrix(math.radians(30), [0, 0, 1])
    box.apply_transform(rot)
    box.apply_translation([0.01, 0.02, BOX_SIZE / 2])      # standing on the ground
    return box


def _ground_triangles():
    g = GROUND_HALF
    v = np.array([[-g, -g, 0], [g, -g, 0], [g, g, 0], [-g, g, 0]], float)
    return v[np.array([[0, 1, 2], [0, 2, 3]])]


@pytest.fixture(scope="module")
def box_on_ground(mi, tmp_path_factory):
    box = _box_mesh()
    path = tmp_path_factory.mktemp("scene") / "box.ply"
    box.export(path)
    scene = mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": diffuse(1.0),
                   "to_world": mi.ScalarTransform4f().scale([GROUND_HALF, GROUND_HALF, 1.0])},
        "box": {"type": "ply", "filename": str(path), "face_normals": True,
                "bsdf": diffuse(0.8)}})
    triangles = np.concatenate([_ground_triangles(), box.vertices[box.faces]])
    albedo = np.concatenate([np.full(2, 1.0), np.full(len(box.faces), 0.8)])
    return scene, triangles, albedo


def _subdivide(tri, n):
    """Centroids [n², 3] of the n² congruent sub-triangles of ``tri`` [3, 3]."""
    a, e1, e2 = tri[0], (tri[1] - tri[0]) / n, (tri[2] - tri[0]) / n
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j) <= n - 1
    down = (i + j) <= n - 2
    pts = [a + (i[up, None] + 1 / 3) * e1 + (j[up, None] + 1 / 3) * e2,
           a + (i[down, None] + 2 / 3) * e1 + (j[down, None] + 2 / 3) * e2]
    return np.concatenate(pts)


def _occluded(origins, target, triangles):
    """Möller–Trumbore: does the segment origin→target cross any triangle? [M] bool."""
    d = target - origins
    hit = np.zeros(len(origins), bool)
    for tri in triangles:
        e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
        p = np.cross(d, e2)
        det = p @ e1
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        s = origins - tri[0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", q, d) * inv
        t = (q @ e2) * inv
        hit |= ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-6)
    return hit


def brute_force_single_bounce(triangles, albedo, tx, rx, tx_dir, rx_dir, half_angle, n_sub,
                              rx_half_angle=None):
    """Single scattering by midpoint quadrature on n_sub² sub-triangles per triangle; cone
    beams of half-angle ``half_angle`` (the RX's ``rx_half_angle`` if given).

    Returns path lengths [M] and contributions [M] of the visible elements, and the
    second moment ∫ g² dω_T of the per-TX-solid-angle value g = ρ/π cosθ_o / r_R²
    (for the Monte-Carlo standard error).
    """
    xs, vals, lens, seconds = [], [], [], []
    cos_cut = math.cos(half_angle)
    cos_cut_rx = cos_cut if rx_half_angle is None else math.cos(rx_half_angle)
    for tri, rho in zip(triangles, albedo):
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        area = np.linalg.norm(normal) / 2
        normal /= 2 * area
        x = _subdivide(tri, n_sub)
        vt, vr = tx - x, rx - x
        rt, rr = np.linalg.norm(vt, axis=1), np.linalg.norm(vr, axis=1)
        ci, co = vt @ normal / rt, vr @ normal / rr
        keep = (ci * co > 0)                                          # two-sided Lambertian
        keep &= (-vt / rt[:, None]) @ tx_dir >= cos_cut               # TX cone
        keep &= (-vr / rr[:, None]) @ rx_dir >= cos_cut_rx            # RX cone
        g = rho / math.pi * np.abs(co) / rr ** 2
        d_omega = np.abs(ci) / rt ** 2 * area / n_sub ** 2            # TX solid angle of dA
        xs.append(x[keep])
        vals.append((g * d_omega)[keep])
        lens.append((rt + rr)[keep])
        seconds.append((g * g * d_omega)[keep])
    x, vals, lens, seconds = (np.concatenate(a) for a in (xs, vals, lens, seconds))
    visible = ~_occluded(x, tx, triangles) & ~_occluded(x, rx, triangles)
    return lens[visible], vals[visible], seconds[visible].sum()


@pytest.mark.parametrize("rx_offset", [(0.04, 0.0, 0.0), (0.45, 0.3, -0.1)],
                         ids=["4cm-baseline", "wide-baseline"])
def test_bistatic_matches_brute_force(mi, box_on_ground, rx_offset):
    """The 4 cm pose is the AirSAS-like case; the wide baseline makes RX shadowing matter."""
    scene, triangles, albedo = box_on_ground
    tx = np.array([0.0, -0.45, 0.25])
    rx = tx + np.array(rx_offset)
    aim = np.array([0.0, 0.0, 0.03])
    tx_dir, rx_dir = (aim - tx) / np.linalg.norm(aim - tx), (aim - rx) / np.linalg.norm(aim - rx)
    beam, paths = 60.0, 1_000_000
    lens, vals, second = brute_force_single_bounce(
        triangles, albedo, tx, rx, tx_dir, rx_dir, math.radians(beam / 2), n_sub=48)
    start, n_bins = 0.6, int(1.0 / W)
    assert lens.min() > start + W and lens.max() < start + (n_bins - 1) * W
    hist = render(integrator(mi, tx_bw=beam, rx_bw=beam, bounce1="cone"), scene, tx, rx,
                  tx_dir, rx_dir, start, n_bins, paths)[0, 0]
    expected = vals.sum()
    sigma = math.sqrt(cone_solid_angle(beam) * second - expected ** 2) / math.sqrt(paths)
    # 5 standard errors plus 0.5 % for the quadrature (partly shadowed elements).
    assert abs(hist.sum() - expected) < 5 * sigma + 0.005 * expected, (hist.sum(), expected, sigma)
    reference = tent_histogram(lens, vals, start, n_bins)
    cdf_mc, cdf_bf = np.cumsum(hist) / hist.sum(), np.cumsum(reference) / expected
    assert np.max(np.abs(cdf_mc - cdf_bf)) < 0.01


def test_bounce_two_needs_a_second_surface(mi, box_on_ground, sphere_scene, tmp_path):
    """A convex box on a plane: every bounce-2 path meets the box once and the ground once,
    so with the same random numbers halving the ground's albedo halves bounce 2 exactly;
    bounce 3 (box-ground-box and ground-box-ground) scales by a factor strictly between
    1/4 and 1/2; bounce 1 of the box alone does not change. A convex object alone has
    exactly no bounce 2 or 3."""
    scene, _, _ = box_on_ground
    path = tmp_path / "box.ply"
    _box_mesh().export(path)
    darker = mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "bsdf": diffuse(0.5),
                   "to_world": mi.ScalarTransform4f().scale([GROUND_HALF, GROUND_HALF, 1.0])},
        "box": {"type": "ply", "filename": str(path), "face_normals": True,
                "bsdf": diffuse(0.8)}})
    tx = np.array([0.0, -0.45, 0.25])
    rx = tx + np.array([0.04, 0.0, 0.0])
    aim = np.array([0.0, 0.0, 0.03])
    look = (aim - tx) / np.linalg.norm(aim - tx)
    integ = integrator(mi, bounces=3, tx_bw=60.0, rx_bw=60.0, bounce1="cone")
    args = (tx, rx, look, look, 0.8, int(0.8 / W), 50_000)
    hist = render(integ, scene, *args, replicas=4)
    totals = hist.sum(axis=2)                       # [replica, bounce]
    mean, se = totals.mean(axis=0), totals.std(axis=0, ddof=1) / 2
    assert mean[1] > 10 * se[1] and mean[2] > 10 * se[2]      # box ↔ ground interreflection
    dark = render(integ, darker, *args, replicas=4).sum(axis=2).mean(axis=0)
    assert dark[1] / mean[1] == pytest.approx(0.5, rel=1e-5)
    assert 0.25 + 0.01 < dark[2] / mean[2] < 0.5 - 0.01
    # Same integrator, a convex object alone: bounces 2 and 3 are exactly empty.
    pos, look = (D_SPHERE, 0, 0), (-1, 0, 0)
    alone = render(integ, sphere_scene, pos, pos, look, look, 1.75, int(0.3 / W), 50_000)
    assert alone[0, 0].sum() > 0 and np.all(alone[0, 1:] == 0)


# ------------------------------------------------------------------------ reciprocity
def test_reciprocity_isotropic(mi, box_on_ground):
    scene, _, _ = box_on_ground
    a, b = np.array([-0.08, -0.1, 0.12]), np.array([0.1, 0.06, 0.2])
    up = (0, 0, 1.0)              # isotropic beams: boresights do not matter
    integ = integrator(mi, bounces=2, tx="isotropic", rx="isotropic")
    start, n_bins, replicas = 0.0, 12 * int(0.1 / W), 8
    ab = render(integ, scene, a, b, up, up, start, n_bins, 100_000, replicas=replicas)
    ba = render(integ, scene, b, a, up, up, start, n_bins, 100_000, seed=1, replicas=replicas)
    # Compare per bounce in 12 coarse path-length bins (each about 10 cm of path).
    coarse = lambda h: h.reshape(replicas, 2, 12, -1).sum(axis=3)
    m1, m2 = coarse(ab).mean(axis=0), coarse(ba).mean(axis=0)
    se = np.sqrt(coarse(ab).var(axis=0, ddof=1) + coarse(ba).var(axis=0, ddof=1)) / math.sqrt(replicas)
    significant = m1 + m2 > 1e-3 * (m1 + m2).max()
    z = np.abs(m1 - m2)[significant] / se[significant]
    assert significant[0].sum() >= 2 and significant[1].sum() >= 2
    assert z.max() < 5.0, z
    totals_ab, totals_ba = ab.sum(axis=(0, 2)), ba.sum(axis=(0, 2))
    np.testing.assert_allclose(totals_ab, totals_ba, rtol=0.03)


# ------------------------------------------------------------------------------ beams
def test_targets_outside_either_beam_give_nothing(mi, sphere_scene):
    pos = np.array([D_SPHERE, 0.0, 0.0])
    at = np.array([-1.0, 0.0, 0.0])
    away = np.array([-math.cos(math.radians(25)), math.sin(math.radians(25)), 0.0])
    integ = integrator(mi, bounces=2, tx_bw=30.0, rx_bw=30.0)
    tx_dirs = np.array([at, away, at, at])
    rx_dirs = np.array([at, at, away, -at])
    hist = integ.render_transients(sphere_scene, np.tile(pos, (4, 1)), np.tile(pos, (4, 1)),
                                   tx_dirs, rx_dirs, 1.75, W, int(0.3 / W), 20_000, 0)
    assert hist[0].sum() > 0
    assert np.all(hist[1] == 0)     # target outside the TX cone
    assert np.all(hist[2] == 0)     # target outside the RX cone
    assert np.all(hist[3] == 0)     # target behind the RX


def test_no_transmission_through_a_thin_surface(mi):
    """Two-sided surfaces reflect on the side the sound arrives from; nothing passes through."""
    scene = mi.load_dict({"type": "scene", "sheet": {"type": "rectangle", "bsdf": diffuse(1.0)}})
    integ = integrator(mi, bounces=2, tx="isotropic", rx="isotropic")
    above, below = (0.1, 0.0, 0.5), (0.0, 0.1, -0.4)
    hist = integ.render_transients(scene, np.array([above, above, below]),
                                   np.array([below, above, below]), np.tile(DOWN, (3, 1)),
                                   np.tile(DOWN, (3, 1)), 0.0, W, int(2.0 / W), 20_000, 0)
    assert np.all(hist[0] == 0)
    assert hist[1, 0].sum() > 0 and hist[2, 0].sum() > 0     # same side: echoes from both faces


# ----------------------------------------------------- determinism, chunking, kernels
def _poses(n):
    from sonarsim.geometry import Poses
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    tx = np.stack([0.6 * np.cos(ang), 0.6 * np.sin(ang), np.full(n, 0.2)], axis=1)
    rx = tx + np.array([0.0, 0.0, -0.04])
    return Poses.pointing_at(tx, rx, np.array([0.0, 0.0, 0.03]))


def test_seeded_and_independent_of_chunking(mi, box_on_ground):
    from sonarsim.render import render_poses
    scene, _, _ = box_on_ground
    poses = _poses(5)
    kw = dict(paths_per_pose=20_000, bounces=2, seed=7, progress=False)
    whole = render_poses(scene, poses, **kw).transients
    again = render_poses(scene, poses, **kw).transients
    singles = render_poses(scene, poses, chunk_size=1, **kw).transients
    pairs = render_poses(scene, poses, chunk_size=2, **kw).transients
    other = render_poses(scene, poses, **{**kw, "seed": 8}).transients
    scale = whole.max()
    assert scale > 0
    for h in (again, singles, pairs):      # float64 accumulation: equal but for a rare ulp
        np.testing.assert_allclose(h, whole, rtol=3e-7, atol=0)
    assert np.abs(other - whole).max() > 1e-3 * scale


def test_thread_count_and_pose_range_do_not_change_the_bytes(mi, box_on_ground):
    """float64 sums rounded once: 1 or 2 Dr.Jit threads, any sub-range, the same bytes."""
    from sonarsim.render import iter_render, render_poses
    from sonarsim.simulate import dr_threads
    scene, _, _ = box_on_ground
    poses = _poses(5)
    kw = dict(paths_per_pose=40_000, bounces=2, seed=3, progress=False)
    with dr_threads(1):
        one = render_poses(scene, poses, **kw)
    with dr_threads(2):
        two = [render_poses(scene, poses, **kw) for _ in range(2)]
        # the default window is that of all the poses, whatever the range
        part = list(iter_render(scene, poses, start=2, stop=5, chunk_size=2, **kw))
    assert np.count_nonzero(one.transients) > 1000
    for t in two:
        assert t.transients.tobytes() == one.transients.tobytes()
    assert [sl for sl, _ in part] == [slice(2, 4), slice(4, 5)]
    assert np.concatenate([h for _, h in part]).tobytes() == one.transients[2:5].tobytes()
    for bad in (dict(start=-1), dict(start=3, stop=2), dict(stop=6)):
        with pytest.raises(InputError, match="start"):
            next(iter_render(scene, poses, **kw, **bad))


def test_no_recompilation_between_chunks(mi, box_on_ground):
    """New poses, window, seed, path count and chunk size must reuse the same kernel(s).

    Compared by kernel hash (a value baked into the IR changes the hash), so Dr.Jit's
    on-disk kernel cache cannot hide a recompilation.
    """
    import drjit as dr
    scene, _, _ = box_on_ground
    integ = integrator(mi, bounces=2)
    p1, p2 = _poses(4), _poses(7)[2:5]

    def launch_hashes(p, start, n_bins, paths, seed, offset):
        dr.kernel_history()                      # clear
        integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                                start, W, n_bins, paths, seed, pose_offset=offset)
        return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        first = launch_hashes(p1, 0.8, 3000, 1000, 0, 0)
        second = launch_hashes(p2, 0.7, 4000, 1500, 3, 11)
        single = launch_hashes(p1[:1], 0.9, 2500, 700, 5, 2)     # a one-pose chunk
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert first and second == first and single == first


def test_coherent_lane_order_changes_no_result(mi, box_on_ground, monkeypatch):
    """The TX-cone tracer traces each pose's paths in an order sorted by their first
    direction (for coherent rays); each path keeps its random numbers, so the histograms
    equal those traced in index order, also when a pose's paths are split over several
    launches (up to the rare 1-ulp of a float64 sum regrouped). The order is a
    permutation, sorted by (pose, direction cell) and stable within a cell."""
    import sys

    import drjit as dr
    st = sys.modules["sonarsim.plugins._cone_tracer"]
    scene, _, _ = box_on_ground
    poses = _poses(3)
    integ = integrator(mi, bounces=2, bounce1="cone")

    def run():
        return integ.render_transients(scene, poses.tx, poses.rx, poses.tx_boresight,
                                       poses.rx_boresight, 0.8, W, 4000, 5000, 4,
                                       pose_offset=2, halves=True)

    ordered = run()
    assert np.count_nonzero(ordered) > 1000
    monkeypatch.setattr(st, "_ORDER_MIN_PATHS", 10**9)        # index order
    plain = run()
    np.testing.assert_allclose(ordered, plain, rtol=3e-7, atol=0)
    monkeypatch.setattr(st, "_ORDER_MIN_PATHS", 64)
    monkeypatch.setattr(st, "_TRACE_BATCH", 2048)             # a pose in three launches
    np.testing.assert_allclose(run(), plain, rtol=3e-7, atol=0)

    ctx = integ._context(poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight, 0.8, W,
                         4000, 4, 2, False, dr.ReduceMode.Local)
    n_paths = 2000
    batch = {"pose0": dr.opaque(mi.UInt32, 1), "path0": dr.opaque(mi.UInt32, 0),
             "n_paths": dr.opaque(mi.UInt32, n_paths)}
    order = integ._coherent_order(ctx, batch, 2, n_paths, n_paths).numpy()
    assert np.array_equal(np.sort(order), np.arange(2 * n_paths))
    level = int(math.log(n_paths / st._ORDER_PER_CELL, 4.0))
    _, _, cell = integ._direction_cell(ctx, batch, mi.UInt32(order), dr.opaque(mi.UInt32, level))
    key = (order // n_paths).astype(np.int64) * 4 ** level + cell.numpy()
    assert np.all(np.diff(key) >= 0)                          # sorted by (pose, cell)
    same = np.flatnonzero(np.diff(key) == 0)
    assert np.all(order[same + 1] > order[same])             # stably


# ----------------------------------------------------------------------------- window
def test_window_drops_outside_contributions(mi, sphere_scene):
    integ = integrator(mi, tx_bw=12.0, rx_bw=12.0)
    pos, look = (D_SPHERE, 0, 0), (-1, 0, 0)
    start, n_bins = 1.75, int(0.3 / W)
    full = render(integ, sphere_scene, pos, pos, look, look, start, n_bins, 100_000)[0, 0]
    # A window that cuts the echo in the middle, on the same bin grid.
    k0, k1 = int((1.86 - start) / W), int((1.95 - start) / W)
    cut = render(integ, sphere_scene, pos, pos, look, look, start + k0 * W, k1 - k0,
                 100_000)[0, 0]
    assert full.sum() > 0 and cut.sum() < 0.9 * full.sum()
    # Bin for bin (edges included) the cut window equals the full one: nothing piles up.
    # (Tolerance: path lengths are float32, ~2e-7 m, so the tent weights move by ~1e-3
    # of a bin when the window start changes; piling up would change edge bins by O(1).)
    np.testing.assert_allclose(cut, full[k0:k1], rtol=2e-3, atol=0)
    # Everything outside the window: empty.
    far = render(integ, sphere_scene, pos, pos, look, look, 2.5, 100, 10_000)
    assert np.all(far == 0)


# ----------------------------------------------------------------------------- driver
def test_driver_returns_transients(mi, box_on_ground):
    from sonarsim.dataset import Transients
    from sonarsim.geometry import SIM_BOX, crop_window
    from sonarsim.render import iter_render, render_poses
    scene, _, _ = box_on_ground
    poses = _poses(3)
    t = render_poses(scene, poses, paths_per_pose=2000, bounces=2, box=SIM_BOX, progress=False)
    crop = crop_window(poses, SIM_BOX, C, FS)
    assert isinstance(t, Transients)
    assert t.transients.shape == (3, 2, crop.num_samples * 20)
    # aligned window: bins 0, K, 2K, ... are centred on the sample times
    assert t.path_start == pytest.approx(crop.min_dist - W / 2)
    np.testing.assert_allclose(t.path_lengths()[::20], crop.path_lengths(C, FS),
                               rtol=0, atol=1e-12)
    assert t.path_bin_width == pytest.approx(W)
    assert t.meta["paths_per_pose"] == 2000 and t.transients[:, 0].sum() > 0
    np.testing.assert_array_equal(t.tx, poses.tx)

    t2 = render_poses(scene, poses, paths_per_pose=500, bounces=1, path_range=(0.5, 1.5),
                      oversample=10, progress=False)
    assert t2.transients.shape == (3, 1, math.ceil(1.0 / (C / (FS * 10)) - 1e-9))
    chunks = list(iter_render(scene, poses, paths_per_pose=500, bounces=1,
                              path_range=(0.5, 1.5), oversample=10, chunk_size=2))
    assert [c[0] for c in chunks] == [slice(0, 2), slice(2, 3)]
    np.testing.assert_allclose(np.concatenate([c[1] for c in chunks]), t2.transients,
                               rtol=1e-5, atol=1e-6 * t2.transients.max())


@pytest.mark.parametrize("kwargs", [
    {"paths_per_pose": 0}, {"bounces": 0}, {"seed": -1}, {"path_range": (1.0, 0.5)},
    {"beams": {"tx_beam": "laser"}}, {"beams": {"width": 3}}, {"fs": -1.0},
    {"chunk_size": 0}, {"oversample": 0},
])
def test_driver_rejects_bad_input(mi, box_on_ground, kwargs):
    from sonarsim.render import render_poses
    scene, _, _ = box_on_ground
    with pytest.raises(InputError):
        render_poses(scene, _poses(2), **{"paths_per_pose": 10, "progress": False, **kwargs})


def test_plugin_refuses_the_old_mode_property(mi):
    """'mode' was renamed 'amplitude' (issue 22 item 6: no compatibility aliases)."""
    with pytest.raises(Exception, match="'mode' is now called 'amplitude'"):
        mi.load_dict({"type": "sonar_transient", "mode": "pressure"})
    assert mi.load_dict({"type": "sonar_transient", "amplitude": "pressure"}).amplitude == "pressure"


def test_driver_default_window_is_the_scene_box(mi):
    """Without box or path_range the window covers the scene's bounding box (here a flat plane)."""
    from sonarsim.geometry import Poses, SceneBox, crop_window
    from sonarsim.render import render_poses
    scene = mi.load_dict({"type": "scene", "plane": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f().scale([0.3, 0.3, 1.0]),
        "bsdf": diffuse(1.0)}})
    poses = Poses.pointing_at([[0.0, 0.0, 0.5]], [[0.02, 0.0, 0.5]], [0.0, 0.0, 0.0])
    t = render_poses(scene, poses, paths_per_pose=5000, bounces=1, progress=False)
    crop = crop_window(poses, SceneBox((-0.3, -0.3, -1e-6), (0.3, 0.3, 1e-6)), C, FS)
    assert t.path_start == pytest.approx(crop.min_dist - W / 2)
    assert t.n_bins == crop.num_samples * 20
    assert [x1 for _, x1 in t.meta["window_box"][:2]] == pytest.approx([0.3, 0.3])
    assert t.transients.sum() > 0
