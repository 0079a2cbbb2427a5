"""recon.scattering: SH basis convention, L = 0 equals isotropic NBP, the directional forward
model against a straightforward NumPy sum, and a direction-dependent echo that only the SH
field fits."""
import numpy as np
import pytest

from recon import forward as F
from recon import scattering as S
from recon.adam import Adam
from recon.field import NetworkScene, NetworkSettings
from recon.grid import Grid
from sonarsim.errors import InputError
from conftest import TINY_NBP_OPTIONS

SMALL_NET = dict(hash_levels=4, hash_features=2, hash_log2_size=12, hash_base_resolution=4,
                 hash_level_scale=2.0, mlp_width=32, mlp_hidden=1)


def _scipy_real_sh(d: np.ndarray, degree: int) -> np.ndarray:
    """Real orthonormal SH from SciPy's complex ones (the construction of drjit.sh_eval's
    docstring), index l(l+1)+m: [(L+1)², N]."""
    from scipy.special import sph_harm_y
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    rows = []
    for ell in range(degree + 1):
        for m in range(-ell, ell + 1):
            y = sph_harm_y(ell, abs(m), theta, phi)
            rows.append(np.sqrt(2) * y.real if m > 0 else np.sqrt(2) * y.imag if m < 0 else y.real)
    return np.array(rows)


def _unit(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_basis_is_sqrt_4pi_times_scipy_real_harmonics():
    d = _unit(np.random.default_rng(0), 50)
    ours = S.sh_basis_numpy(d, 3)
    assert ours.shape == (16, 50)
    np.testing.assert_allclose(ours, np.sqrt(4 * np.pi) * _scipy_real_sh(d, 3), atol=2e-5)
    assert np.all(ours[0] == 1.0)
    # Ỹ_10 = √3 z (the lobe the fit test uses)
    np.testing.assert_allclose(ours[2], np.sqrt(3) * d[:, 2], atol=1e-5)


@pytest.mark.parametrize("text, degree", [("isotropic", None), ("sh:0", 0), ("sh:2", 2)])
def test_parse_scattering(text, degree):
    assert S.parse_scattering(text) == degree


@pytest.mark.parametrize("text", ["sh", "sh:", "sh:-1", "sh:5", "sh:1.5", "SH:1", "iso", ""])
def test_parse_scattering_refuses_bad_values(text):
    with pytest.raises(InputError, match="scattering"):
        S.parse_scattering(text)


def _geometry():
    """8 pings at 0.85 m around the grid, TX/RX 4 cm apart vertically, 10 range bins."""
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    tx = np.stack([0.85 * np.cos(ang), 0.85 * np.sin(ang), np.full(8, 0.15)], 1)
    rx = tx + np.array([0.0, 0.0, -0.04])
    bore = np.array([0.0, 0.0, 0.05]) - tx
    ranges = np.tile(np.linspace(1.62, 1.78, 10), (8, 1))
    return F.PingGeometry(tx, rx, bore, ranges, bin_width=np.full(8, 0.016))


@pytest.fixture(scope="module")
def grid():
    return Grid(np.array([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.15]]), (20, 20, 15))


def test_look_directions_point_from_the_sample_to_the_array():
    geo = _geometry()
    samples = F.EllipsoidSamples(geo, F.cone_directions(50, 20.0))
    pts = np.array([np.asarray(c) for c in samples.points]).T
    look = np.array([np.asarray(c) for c in samples.look_directions()]).T
    p = np.arange(len(pts)) // (50 * 10)
    v = 0.5 * (geo.tx + geo.rx)[p] - pts
    np.testing.assert_allclose(look, v / np.linalg.norm(v, axis=1, keepdims=True), atol=1e-5)


def test_degree_zero_is_isotropic_nbp_exactly(grid):
    """sh:0 and the isotropic network: same initial parameters from the same seed, and the
    same samples, loss and gradients through the full model (Lambertian normals from AD,
    occlusion): the factor is 1 (Ỹ_00 = 1)."""
    import drjit as dr
    settings = NetworkSettings(**SMALL_NET)
    iso, sh0 = NetworkScene(grid, settings), S.ShNetworkScene(grid, settings, 0)
    p_iso, p_sh = iso.initial(np.random.default_rng(3)), sh0.initial(np.random.default_rng(3))
    assert p_iso.keys() == p_sh.keys()
    for k in p_iso:
        np.testing.assert_array_equal(p_iso[k], p_sh[k])
    rng = np.random.default_rng(4)
    p_iso["grid"] = p_sh["grid"] = rng.uniform(-1, 1, p_iso["grid"].shape).astype(np.float32)
    samples = F.EllipsoidSamples(_geometry(), F.cone_directions(200, 20.0))
    t = rng.standard_normal(samples.n_out).astype(np.float32)
    results = []
    threads = dr.thread_count()
    dr.set_thread_count(1)      # as the solver's deterministic runs: a fixed summation order
    try:
        for scene, p in ((iso, p_iso), (sh0, p_sh)):
            results.append(_loss_and_gradients(scene, p, samples, t))
    finally:
        dr.set_thread_count(threads)
    (y0, l0, g0), (y1, l1, g1) = results
    assert np.abs(y0).max() > 0.1
    np.testing.assert_array_equal(y0, y1)
    assert l0 == l1
    for k in g0:
        assert np.abs(g0[k]).max() > 0
        np.testing.assert_array_equal(g0[k], g1[k])


def _loss_and_gradients(scene, p, samples, t):
    """(samples' real part, loss, parameter gradients) of the full model (Lambertian, occlusion)."""
    import drjit as dr
    m = scene.m
    params = {k: m.Float(v) for k, v in p.items()}
    for v in params.values():
        dr.enable_grad(v)
    y_re, y_im = F.render(scene.bind(params), samples, lambertian_eps=1e-3,
                          occlusion_scale=30.0)
    loss = dr.mean(dr.square(y_re - m.Float(t))) + dr.mean(dr.square(y_im))
    dr.backward(loss)
    return (np.asarray(y_re), float(loss[0]),
            {k: np.asarray(dr.grad(v)) for k, v in params.items()})


def _random_sh2_scene(grid, settings, seed):
    """An sh:2 scene with a random hash table (uniform in ±1, far from the ±1e-4 start, so
    every coefficient is non-zero) and its parameters as Dr.Jit Floats."""
    scene = S.ShNetworkScene(grid, settings, 2)
    rng = np.random.default_rng(seed)
    p = scene.initial(rng)
    p["grid"] = rng.uniform(-1, 1, p["grid"].shape).astype(np.float32)
    return scene, {k: scene.m.Float(v) for k, v in p.items()}


def test_directional_render_equals_a_straightforward_sum(grid):
    """render of an sh:2 field = Σ_j Σ_lm c_lm(x_j) Ỹ_lm(ω_j) over the rays, computed in NumPy
    from the coefficients at the sample points, SciPy's harmonics and look directions from
    the TX/RX positions (no Lambertian factor, no occlusion)."""
    settings = NetworkSettings(**SMALL_NET)
    scene, params = _random_sh2_scene(grid, settings, seed=5)
    m = scene.m
    geo = _geometry()
    J = 60
    samples = F.EllipsoidSamples(geo, F.cone_directions(J, 20.0))
    y_re, y_im = F.render(scene.bind(params), samples)
    got = np.asarray(y_re) + 1j * np.asarray(y_im)

    coeffs = scene.coefficients(params, samples.points)
    c = np.array([np.asarray(re) + 1j * np.asarray(im) for re, im in coeffs])   # [9, lanes]
    pts = np.array([np.asarray(a) for a in samples.points]).T
    lane = np.arange(len(pts))
    p_of = lane // (J * geo.n_bins)
    v = 0.5 * (geo.tx + geo.rx)[p_of] - pts
    basis = np.sqrt(4 * np.pi) * _scipy_real_sh(v / np.linalg.norm(v, axis=1, keepdims=True), 2)
    sigma = np.where(np.asarray(samples.valid), (c * basis).sum(0), 0)
    want = np.zeros(samples.n_out, complex)
    np.add.at(want, np.asarray(samples.out_index), sigma)
    assert np.abs(want).max() > 1.0
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-4 * np.abs(want).max())


class _BoxLobeTarget:
    """σ(x, ω) = 1 + 0.8·ω_z = Ỹ_00 + (0.8/√3)·Ỹ_10 inside the box lo…hi, 0 outside: seen
    from above the box is 1.8× as bright as from the side (sh:1 represents it exactly)."""

    directional = True

    def __init__(self, m, lo, hi):
        self.m, self.lo, self.hi = m, lo, hi

    def scatter_toward(self, points, directions, with_gradient):
        import drjit as dr
        inside = self.m.Bool(True)
        for a in range(3):
            inside &= (points[a] >= float(self.lo[a])) & (points[a] <= float(self.hi[a]))
        one = dr.select(inside, 1.0, 0.0)
        zero = dr.zeros(self.m.Float, dr.width(one))
        return one * (1.0 + 0.8 * directions[2]), zero, one, zero, None


def _lobe_geometry():
    """24 co-located TX/RX pings 0.5 m from the box centre, looking at it from elevations 0°, 40° and
    80°; the bins cover the whole grid box for every ping, so the sum over a ping's bins is
    (to the spreading of the rays, ~10 % here) the integral of σ over the box: an isotropic
    σ gives every ping the same total, the target does not."""
    elev = np.repeat(np.radians([0.0, 40.0, 80.0]), 8)
    az = np.tile(np.linspace(0, 2 * np.pi, 8, endpoint=False), 3) + elev
    c = np.array([0.0, 0.0, 0.05])
    tx = c + 0.5 * np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az),
                             np.sin(elev)], 1)
    ranges = np.tile(np.linspace(0.88, 1.12, 24), (24, 1))
    return F.PingGeometry(tx, tx.copy(), c - tx, ranges)


def _fit(scene, samples, t_re, iterations=120, lr=1e-2):
    """Adam on mean|render − target|²; the final loss over the target's mean energy."""
    import drjit as dr
    m = scene.m
    p = scene.initial(np.random.default_rng(0))
    opt = Adam(p, lr)
    target = m.Float(t_re)
    energy = float(np.mean(t_re ** 2))
    for _ in range(iterations):
        y_re, y_im = F.render(scene.bind(opt.params), samples)
        loss = dr.mean(dr.square(y_re - target)) + dr.mean(dr.square(y_im))
        dr.backward(loss)
        opt.step()
    y_re, y_im = F.render(scene.bind(opt.params), samples)
    return float(np.mean((np.asarray(y_re) - t_re) ** 2 + np.asarray(y_im) ** 2)) / energy


def test_only_the_sh_field_fits_a_direction_dependent_echo():
    """Echoes of a box that is brighter from above: an isotropic field gives every ping about
    the same total echo (the integral of σ over the box), the target does not, so the
    isotropic network cannot fit it; sh:1 can (measured: 0.058 against 0.0052 of the target's
    energy). A coarse field (one hash level, 2 cells per axis) so that neither can fit the
    pings' sample points one by one."""
    from recon._jit import jit
    m = jit()
    grid = Grid(np.array([[-0.04, 0.04], [-0.04, 0.04], [0.01, 0.09]]), (9, 9, 9))
    settings = NetworkSettings(**dict(SMALL_NET, hash_levels=1, hash_base_resolution=2))
    iso, sh1 = NetworkScene(grid, settings), S.ShNetworkScene(grid, settings, 1)
    samples = F.EllipsoidSamples(_lobe_geometry(), F.cone_directions(70, 20.0))
    y_re, _ = F.render(_BoxLobeTarget(m, iso.lo, iso.lo + iso.ext), samples)
    t = np.asarray(y_re)
    totals = t.reshape(24, -1).sum(axis=1)
    assert totals[16:].mean() > 1.3 * totals[:8].mean()      # the top sees more than the side
    iso_misfit = _fit(iso, samples, t, iterations=40, lr=2e-2)
    sh1_misfit = _fit(sh1, samples, t, iterations=40, lr=2e-2)
    assert iso_misfit > 0.03
    assert sh1_misfit < 0.25 * iso_misfit


def test_rms_volume_is_the_rms_over_directions(grid):
    """rms_volume = √(mean over the sphere of |σ(x, ω)|²), the mean by a product quadrature
    exact for |σ|² of an sh:2 field (Gauss–Legendre in cos θ × uniform φ)."""
    settings = NetworkSettings(**SMALL_NET)
    scene, params = _random_sh2_scene(grid, settings, seed=6)
    m = scene.m
    small = Grid(grid.bounds, (4, 4, 3))
    got = scene.rms_volume(params, small).ravel()
    pts = small.points().astype(np.float32)              # [N, 3], the volume's order
    mu, w_mu = np.polynomial.legendre.leggauss(5)
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    mean = np.zeros(len(pts))
    for c, wc in zip(mu, w_mu):
        for f in phi:
            d = np.array([np.sqrt(1 - c * c) * np.cos(f), np.sqrt(1 - c * c) * np.sin(f), c])
            dirs = m.Array3f(*(m.Float(np.full(len(pts), d[a], np.float32)) for a in range(3)))
            re, im = scene.scatter(params, m.Array3f(*(m.Float(pts[:, a].copy()) for a in range(3))),
                                   dirs)
            mean += wc * (2 * np.pi / 8) * (np.asarray(re) ** 2 + np.asarray(im) ** 2) / (4 * np.pi)
    assert got.max() > 0.1
    np.testing.assert_allclose(got, np.sqrt(mean), rtol=2e-4, atol=1e-6)
    c00 = scene.volume(params, small).ravel()
    assert np.all(got >= np.abs(c00) * (1 - 1e-5))


def test_solver_builds_the_sh_scene_from_the_setting(grid):
    from recon import solver
    settings = solver.settings_for("nbp", network=True, scattering="sh:2", **SMALL_NET)
    scene = solver.make_scene(grid, settings, network=True)
    assert isinstance(scene, S.ShNetworkScene) and scene.degree == 2
    assert scene.shapes[-1][0] == 18
    iso = solver.make_scene(grid, solver.settings_for("nbp", network=True, **SMALL_NET), True)
    assert type(iso) is NetworkScene
    # the memory estimate counts the 18 outputs: 32 more weights per extra output
    assert (solver.resources.network_parameters(settings)
            - solver.resources.network_parameters(solver.settings_for("nbp", network=True,
                                                                      **SMALL_NET))) == 16 * 32


@pytest.mark.parametrize("extra", [["--scattering", "sh:9"], ["--scattering", "sh:1", "--occupancy"],
                                   ["--scattering", "sh:1", "--incoherent"]])
def test_cli_refuses_bad_scattering_in_one_line(tmp_path, capsys, extra):
    from recon.cli import main
    rc = main(["nbp", str(tmp_path / "none.h5"), "--out", str(tmp_path / "v.h5"), *extra])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert "scattering" in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_cli_sh_run_exports_c00(point_target_scan, tmp_path, capsys):
    from recon.cli import main
    src = tmp_path / "d.h5"
    point_target_scan.write(src)
    out = tmp_path / "v.h5"
    rc = main(["nbp", str(src), *TINY_NBP_OPTIONS, "--scattering", "sh:1", "--out", str(out),
               "--no-progress"])
    assert rc == 0
    from sonarsim.dataset import Volume
    vol = Volume.read(out)
    assert vol.params["scattering"] == "sh:1" and vol.shape == (9, 9, 9)
    assert np.abs(vol.volume).max() > 0 and np.all(np.isfinite(vol.volume))


def _sh_scene(**overrides):
    """A small sh:1 scene of the solver with SH-SAS's options, its random parameters, and
    the lobe geometry's samples (inside the scene's box)."""
    from recon import solver
    grid = Grid(np.array([[-0.04, 0.04], [-0.04, 0.04], [0.01, 0.09]]), (9, 9, 9))
    settings = solver.settings_for("nbp", network=True, scattering="sh:1", **SMALL_NET,
                                   **overrides)
    scene = solver.make_scene(grid, settings, network=True)
    rng = np.random.default_rng(4)
    p = scene.initial(rng)
    p["grid"] = rng.uniform(-1, 1, p["grid"].shape).astype(np.float32)   # every c_lm non-zero
    params = {k: scene.m.Float(v) for k, v in p.items()}
    samples = F.EllipsoidSamples(_lobe_geometry(), F.cone_directions(70, 20.0))
    return scene, params, settings, samples


def test_sh_start_keeps_the_field_isotropic_until_that_iteration():
    """Before ``sh_start`` σ(x, ω) = c_00(x) from every direction (and the warm start fits
    c_00); from it on the l = 1 terms make σ depend on ω."""
    from recon._jit import jit
    m = jit()
    scene, params, _, _ = _sh_scene(sh_start=5)
    pts = m.Array3f(m.Float([0.01, -0.02]), m.Float([0.0, 0.01]), m.Float([0.05, 0.03]))
    up, side = m.Array3f(0.0, 0.0, 1.0), m.Array3f(1.0, 0.0, 0.0)
    scene.at_iteration(4)
    a, b = np.asarray(scene.scatter(params, pts, up)[0]), np.asarray(scene.scatter(params, pts, side)[0])
    c00 = np.asarray(scene.evaluate(params, pts)[0])
    np.testing.assert_array_equal(a, c00)
    np.testing.assert_array_equal(b, c00)
    np.testing.assert_array_equal(np.asarray(scene.warm_values(params, pts)[0]), c00)
    scene.at_iteration(5)
    a, b = np.asarray(scene.scatter(params, pts, up)[0]), np.asarray(scene.scatter(params, pts, side)[0])
    assert np.abs(a - b).max() > 1e-3 * np.abs(c00).max()


def test_sh_sparsity_is_the_mean_l1_of_the_higher_coefficients():
    """The prior term equals weight × the mean over the valid samples of Σ_{l≥1}|c_lm|,
    computed here in NumPy from the coefficients; without directions (before sh_start) the
    term is absent."""
    from recon._jit import jit
    from recon.solver.priors import loss_terms
    m = jit()
    scene, params, settings, samples = _sh_scene(sh_sparsity=0.3, reg_start=0)
    field = scene.bind(params)
    y_re, y_im, s_re, s_im = F.render(field, samples, lambertian_eps=1e-3, with_sigma=True)
    zero = m.Float(np.zeros(len(np.asarray(y_re)), np.float32))
    terms = loss_terms(m, field, samples, s_re, s_im, y_re, y_im, zero, zero, settings,
                       scene.h, True, None)
    coeffs = scene.coefficients(params, samples.points)
    l1 = sum(np.hypot(np.asarray(re, np.float64), np.asarray(im, np.float64)) for re, im in coeffs[1:])
    valid = np.asarray(samples.valid, bool)
    assert valid.sum() > 100 and l1[valid].max() > 0
    np.testing.assert_allclose(float(terms["sh_sparsity"][0]), 0.3 * l1[valid].mean(), rtol=1e-4)
    scene_off, params_off, settings_off, _ = _sh_scene(sh_sparsity=0.3, reg_start=0, sh_start=9)
    field_off = scene_off.bind(params_off)
    out = F.render(field_off, samples, lambertian_eps=1e-3, with_sigma=True)
    assert "sh_sparsity" not in loss_terms(m, field_off, samples, *out[2:], *out[:2], zero, zero,
                                           settings_off, scene_off.h, True, None)


@pytest.mark.parametrize("options", [dict(sh_start=10), dict(sh_sparsity=0.1),
                                     dict(scattering="sh:0", sh_sparsity=0.1)])
def test_sh_options_need_a_directional_field(options):
    from recon import solver
    with pytest.raises(InputError, match="sh_start / sh_sparsity"):
        solver.settings_for("nbp", network=True, **options)
