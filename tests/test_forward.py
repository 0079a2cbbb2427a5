"""recon.forward: ellipsoid geometry, adjoint identity, AD gradient, Lambertian, occlusion."""
import numpy as np
import pytest

from recon import forward as F
from recon.grid import Grid
from sonarsim.errors import InputError


def _geometry(n_pings=3, n_bins=6, seed=1):
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n_pings)
    tx = np.stack([0.85 * np.cos(ang), 0.85 * np.sin(ang), rng.uniform(0.0, 0.2, n_pings)], 1)
    rx = tx + np.array([0.0, 0.0, -0.038])
    bore = np.array([0.0, 0.0, 0.1]) - tx
    ranges = np.sort(rng.uniform(1.6, 1.85, (n_pings, n_bins)), axis=1)
    return F.PingGeometry(tx, rx, bore, ranges)


def random_complex(shape, rng: np.random.Generator) -> np.ndarray:
    """Standard complex normal array of ``shape`` (complex128)."""
    return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)


def adjoint_mismatch(op, seed: int = 0) -> float:
    """|⟨A x, y⟩ − ⟨x, Aᴴ y⟩| / (‖A x‖‖y‖) for random complex x, y (0 for an exact adjoint;
    normalised by the Cauchy–Schwarz bound, so float32 kernels give ~1e-6)."""
    rng = np.random.default_rng(seed)
    x = random_complex(op.ishape, rng)
    y = random_complex(op.oshape, rng)
    ax = op.forward(x)
    ahy = op.adjoint(y)
    lhs = np.vdot(y, ax)          # ⟨Ax, y⟩ = yᴴ A x
    rhs = np.vdot(ahy, x)         # ⟨x, Aᴴy⟩ = (Aᴴy)ᴴ x
    scale = np.linalg.norm(ax) * np.linalg.norm(y)
    return float(abs(lhs - rhs) / scale) if scale > 0 else float(abs(lhs - rhs))


class DelayOperator(F.LinearOperator):
    """Voxel-driven linear delay model D: complex voxels [nx, ny, nz] → samples [N, T],
    ``y[i, k] = Σ_v x_v · h(k − u_iv)`` (h the linear-interpolation tent, u_iv the voxel's
    fractional sample index). Its adjoint is the Dr.Jit delay-and-sum kernel of
    :mod:`recon.backprojection` without upsampling; the forward direction is a NumPy scatter."""

    def __init__(self, dataset, grid: Grid):
        from recon import backprojection
        self.grid = grid
        self.consts = backprojection.ping_constants(dataset, 1, True)
        n, t = np.asarray(dataset.waveforms).shape
        self.ishape, self.oshape = tuple(grid.shape), (n, t)

    def _forward(self, x):
        from recon import interp
        n, t = self.oshape
        pts = self.grid.points()
        flat = np.asarray(x, dtype=np.complex128).ravel()
        y = np.zeros((n, t), dtype=np.complex128)
        for i, q in enumerate(self.consts.astype(np.float64)):
            path = np.linalg.norm(pts - q[0:3], axis=1) + np.linalg.norm(pts - q[3:6], axis=1)
            y[i] = interp.tent_scatter(path * q[6] + q[7], flat, t)
        return y

    def _adjoint(self, y):
        from recon import backprojection
        y = np.asarray(y, dtype=np.complex64)
        step = backprojection.PINGS_PER_BLOCK
        blocks = (backprojection.interpolation_buffer(y[b:b + step]) for b in range(0, len(y), step))
        return backprojection.delay_and_sum(blocks, self.consts, self.grid, self.oshape[1])


def test_cone_directions_are_unit_and_fill_the_cone():
    d = F.cone_directions(500, 30.0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    ang = np.degrees(np.arccos(d[:, 2]))
    assert ang.max() <= 15.0 + 1e-9 and ang.max() > 14.0
    # Uniform in solid angle: half the rays within the half-solid-angle cone.
    half = np.degrees(np.arccos(1 - (1 - np.cos(np.radians(15))) / 2))
    assert abs(np.mean(ang < half) - 0.5) < 0.01
    with pytest.raises(InputError):
        F.cone_directions(0, 30.0)


def test_boresight_frames_are_rotations_with_boresight_as_third_column():
    b = np.array([[0.0, 0.0, 1.0], [0.3, -0.4, 0.1], [0.0, 0.0, -2.0]])
    f = F.boresight_frames(b)
    for fi, bi in zip(f, b):
        np.testing.assert_allclose(fi.T @ fi, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(fi), 1.0, atol=1e-12)
        np.testing.assert_allclose(fi[:, 2], bi / np.linalg.norm(bi), atol=1e-12)


def test_samples_lie_on_their_ellipsoids_inside_the_cone():
    geo = _geometry()
    dirs = F.cone_directions(64, 30.0)
    s = F.EllipsoidSamples(geo, dirs)
    P, J, K = s.shape
    pts = np.array(s.points).T.reshape(P, J, K, 3)
    valid = np.array(s.valid).reshape(P, J, K)
    assert valid.all()
    for p in range(P):
        path = (np.linalg.norm(pts[p] - geo.tx[p], axis=-1)
                + np.linalg.norm(pts[p] - geo.rx[p], axis=-1))
        np.testing.assert_allclose(path, np.broadcast_to(geo.ranges[p], (J, K)), atol=2e-6)
        b = geo.boresight[p] / np.linalg.norm(geo.boresight[p])
        v = pts[p] - geo.tx[p]
        cos = (v @ b) / np.linalg.norm(v, axis=-1)
        assert cos.min() >= np.cos(np.radians(15)) - 1e-5


def test_generic_adjoint_test_detects_a_wrong_adjoint():
    class Wrong(F.LinearOperator):
        def __init__(self, mat):
            self.mat, self.ishape, self.oshape = mat, (mat.shape[1],), (mat.shape[0],)

        def _forward(self, x):
            return self.mat @ x

        def _adjoint(self, y):
            return self.mat.T @ y          # transpose without conjugation: wrong for complex

    rng = np.random.default_rng(3)
    mat = random_complex((7, 5), rng)
    assert adjoint_mismatch(Wrong(mat)) > 1e-2
    right = Wrong(mat)
    right._adjoint = lambda y: mat.conj().T @ y
    assert adjoint_mismatch(right) < 1e-12


@pytest.mark.parametrize("shape, zrange", [((9, 8, 7), (0.0, 0.2)), ((12, 10, 1), (0.1, 0.1))])
def test_ellipsoid_operator_adjoint_identity(shape, zrange):
    g = Grid([[-0.1, 0.1], [-0.1, 0.1], list(zrange)], shape)
    op = F.EllipsoidOperator(g, _geometry(), n_rays=400, beamwidth_deg=30.0)
    y = op.forward(random_complex(op.ishape, np.random.default_rng(0)))
    assert np.abs(y).max() > 0                       # the rays do meet the grid
    assert adjoint_mismatch(op, seed=0) < 1e-5
    assert adjoint_mismatch(op.H, seed=1) < 1e-5
    with pytest.raises(InputError):
        op.forward(np.zeros((2, 2, 2)))


def test_ad_gradient_equals_explicit_adjoint():
    import drjit as dr
    g = Grid([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]], (8, 8, 8))
    op = F.EllipsoidOperator(g, _geometry(), n_rays=300)
    m = op.field.m
    rng = np.random.default_rng(5)
    x = random_complex(op.ishape, rng).ravel().astype(np.complex64)
    t = random_complex(op.oshape, rng).ravel().astype(np.complex64)
    re, im = m.Float(x.real.copy()), m.Float(x.imag.copy())
    dr.enable_grad(re, im)
    y_re, y_im = op.forward_jit(re, im)
    loss = dr.sum(dr.square(y_re - m.Float(t.real.copy())) + dr.square(y_im - m.Float(t.imag.copy())))
    dr.backward(loss)
    grad = np.asarray(dr.grad(re)) + 1j * np.asarray(dr.grad(im))
    # d/d(re) + i d/d(im) of ||Ax - t||^2 = 2 A^H (Ax - t)
    expected = 2 * op.adjoint(op.forward(x.reshape(op.ishape)) - t.reshape(op.oshape)).ravel()
    np.testing.assert_allclose(grad, expected, atol=2e-5 * np.abs(expected).max())


def test_occlusion_transmittance_closed_form_for_constant_medium():
    # One ray, constant sigma0: T_k = exp(-2 s sigma0 (t_k - t_0)) because the along-ray
    # steps telescope; y_k = sigma0 * T_k.
    geo = _geometry(n_pings=1, n_bins=8)
    s = F.EllipsoidSamples(geo, np.array([[0.0, 0.0, 1.0]]))
    m = s.m
    sigma0, scale = 0.7, 3.0

    def field(points):
        import drjit as dr
        return dr.full(m.Float, sigma0, dr.width(points)), dr.zeros(m.Float, dr.width(points))

    y_re, y_im = F.render(field, s, occlusion_scale=scale)
    t = np.asarray(s.t)
    expected = sigma0 * np.exp(-2 * scale * sigma0 * (t - t[0]))
    np.testing.assert_allclose(np.asarray(y_re), expected, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(y_im), 0.0, atol=1e-7)


def test_lambertian_factor_matches_analytic_normal():
    # |sigma| = Gaussian blob around c: n = (x - c)/|x - c| (outward); factor = max(0, <n, -d>).
    geo = _geometry(n_pings=2, n_bins=5)
    dirs = F.cone_directions(50, 20.0)
    s = F.EllipsoidSamples(geo, dirs)
    m = s.m
    c = np.array([0.01, -0.02, 0.1])
    width = 0.2

    def field(points):
        import drjit as dr
        d2 = dr.squared_norm(points - m.Array3f(*(float(v) for v in c)))
        mag = dr.exp(-d2 / width ** 2)
        return mag * 0.6, mag * 0.8               # |sigma| = mag

    lam = np.asarray(F.lambertian(field, s.points, s.dirs, 1e-4))
    pts = np.array(s.points).T
    d = np.array(s.dirs).T
    n = (pts - c) / np.linalg.norm(pts - c, axis=1, keepdims=True)
    expected = np.maximum(0.0, np.sum(n * -d, axis=1))
    np.testing.assert_allclose(lam, expected, atol=2e-2)
    assert expected.max() > 0.5


def test_exact_voxel_normals_match_finite_differences():
    g = Grid([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]], (21, 21, 21))
    pts = g.points()
    blob = np.exp(-np.sum((pts - [0.01, -0.02, 0.1]) ** 2, axis=1) / 0.05 ** 2)
    vals = (blob * np.exp(1j * 40 * pts[:, 0])).astype(np.complex64)
    op = F.EllipsoidOperator(g, _geometry(n_pings=2, n_bins=5), n_rays=200)
    m = op.field.m
    bound = op.field.field(m.Float(vals.real.copy()), m.Float(vals.imag.copy()))
    s = op.samples
    _, _, grad = bound.gradient_of_magnitude(s.points)
    exact = np.asarray(F.lambertian(bound, s.points, s.dirs, 1e-4, grad))
    fd = np.asarray(F.lambertian(lambda p: bound(p), s.points, s.dirs, 1e-5))
    inside = np.asarray(s.valid) & (np.abs(np.array(s.points)).max(axis=0) < 0.095)
    diff = np.abs(exact - fd)[inside]
    assert inside.sum() > 100 and exact[inside].max() > 0.5
    assert np.median(diff) < 1e-3 and np.mean(diff < 2e-2) > 0.95


def test_delay_operator_adjoint_is_the_backprojection_kernel():
    from recon import backprojection as bp
    from recon import measurements, synthetic
    ds = synthetic.point_dataset([[0.01, 0.02, 0.1]], n_pings=12, heights=(0.05, 0.15))
    g = Grid([[-0.05, 0.05], [-0.04, 0.06], [0.08, 0.12]], (9, 10, 5))
    op = DelayOperator(ds, g)
    assert op.oshape == ds.waveforms.shape
    assert adjoint_mismatch(op, seed=2) < 1e-5
    # Independent NumPy delay-and-sum: per ping, linear interpolation of the matched-filtered
    # signal at each voxel's fractional sample index (zero outside the record).
    mf = measurements.matched_filtered(ds).astype(np.complex128)
    pts = g.points()
    ref = np.zeros(len(pts), complex)
    n_t = mf.shape[1]
    for i in range(ds.n_pings):
        path = np.linalg.norm(pts - ds.tx[i], axis=1) + np.linalg.norm(pts - ds.rx[i], axis=1)
        u = path / ds.sound_speed * ds.fs - ds.start_sample
        k = np.arange(n_t)
        ref += (np.interp(u, k, mf[i].real, left=0, right=0)
                + 1j * np.interp(u, k, mf[i].imag, left=0, right=0))
    got = bp.backproject(ds, g, upsample=1, progress=False).ravel()
    assert np.abs(ref).max() > 0
    np.testing.assert_allclose(got, ref, atol=2e-4 * np.abs(ref).max())
    np.testing.assert_allclose(op.adjoint(mf.astype(np.complex64)).ravel(), ref,
                               atol=2e-4 * np.abs(ref).max())


def test_voxel_lookup_adjoint_matches_ad_of_plain_gathers():
    """The packed lookup's explicit adjoint (interpolant and its spatial gradient) equals
    Dr.Jit AD through 8 plain gathers per lane, for a loss nonlinear in both (the Lambertian
    and occlusion terms of the full model depend on them this way); z-edge cells included."""
    import drjit as dr
    g = Grid([[-0.1, 0.1], [-0.1, 0.1], [0.05, 0.15]], (7, 6, 5))
    vf = F.VoxelField(g)
    m = vf.m
    rng = np.random.default_rng(7)
    x = random_complex(g.shape, rng).ravel().astype(np.complex64)
    pts = rng.uniform([-0.12, -0.12, 0.03], [0.12, 0.12, 0.17], (4000, 3)).T   # some outside
    p = m.Array3f(*(m.Float(a.astype(np.float32)) for a in pts))
    w = [m.Float(rng.standard_normal(4000).astype(np.float32)) for _ in range(8)]

    def loss(vals):
        s_re, s_im, g_re, g_im = vals
        mag = dr.sqrt(s_re * s_re + s_im * s_im + 1e-20)
        gm = (g_re * s_re + g_im * s_im) / mag
        return dr.sum(w[0] * s_re + w[1] * s_im * mag + w[2] * gm[0] + w[3] * gm[1] * gm[2]
                      + w[4] * g_re[2] + w[5] * g_im[0] + w[6] * dr.square(g_im[1]))

    def plain(re, im):
        """Trilinear value and gradient by AD-differentiable gathers at the 8 corners."""
        s_re, s_im = dr.zeros(m.Float, 4000), dr.zeros(m.Float, 4000)
        d_re = [dr.zeros(m.Float, 4000) for _ in range(3)]
        d_im = [dr.zeros(m.Float, 4000) for _ in range(3)]
        u = [(p[a] - float(vf.lo[a])) / float(vf.h[a]) for a in range(3)]
        f = [ua - dr.floor(ua) for ua in u]
        for (idx, wt, inside), c in zip(vf.corners(p), np.ndindex(2, 2, 2)):
            v_re = dr.gather(m.Float, re, idx, inside)
            v_im = dr.gather(m.Float, im, idx, inside)
            s_re += wt * v_re
            s_im += wt * v_im
            lin = [f[a] if c[a] else 1.0 - f[a] for a in range(3)]
            for a in range(3):
                dw = (1.0 if c[a] else -1.0) / float(vf.h[a])
                for b in range(3):
                    if b != a:
                        dw = dw * lin[b]
                d_re[a] += dw * v_re
                d_im[a] += dw * v_im
        return s_re, s_im, m.Array3f(*d_re), m.Array3f(*d_im)

    grads = []
    for fn in (plain, lambda re, im: vf.sample_with_gradient(re, im, p)):
        re, im = m.Float(x.real.copy()), m.Float(x.imag.copy())
        dr.enable_grad(re, im)
        vals = fn(re, im)
        dr.backward(loss(vals))
        grads.append(np.asarray(dr.grad(re)) + 1j * np.asarray(dr.grad(im)))
        grads.append(np.concatenate([np.ravel(np.asarray(v)) for v in vals]))
    np.testing.assert_allclose(grads[3], grads[1], atol=1e-5 * np.abs(grads[1]).max())
    assert np.abs(grads[0]).max() > 1.0
    np.testing.assert_allclose(grads[2], grads[0], atol=1e-5 * np.abs(grads[0]).max())


def test_occupancy_render_hides_what_lies_behind_the_first_occupied_sample():
    """render_occupancy against a straightforward NumPy sum: w_k = o_k Π_{i<k}(1 − o_i)
    along each ray, ŷ = Σ_j a·w. A slab z > z0 is solid (o = 0.9); in front o = 0.05."""
    geo = _geometry(n_pings=2, n_bins=7)
    dirs = F.cone_directions(30, 20.0)
    s = F.EllipsoidSamples(geo, dirs)
    m = s.m
    pts = np.array(s.points).T
    z0 = float(np.median(pts[:, 2]))
    a = (0.3, -0.4)

    class Field:
        def occupancy_and_amplitude(self, points):
            import drjit as dr
            o = dr.select(points[2] > z0, 0.9, 0.05)
            n = dr.width(points)
            return o, dr.full(m.Float, a[0], n), dr.full(m.Float, a[1], n)

    y_re, y_im, _, _ = F.render_occupancy(Field(), s)
    P, J, K = s.shape
    o = np.where(pts[:, 2] > z0, 0.9, 0.05) * np.asarray(s.valid)
    o = o.reshape(P, J, K)
    trans = np.cumprod(np.concatenate([np.ones((P, J, 1)), 1 - o[:, :, :-1]], axis=2), axis=2)
    w = (o * trans).sum(axis=1).ravel()
    np.testing.assert_allclose(np.asarray(y_re), a[0] * w, rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(y_im), a[1] * w, rtol=2e-4, atol=1e-6)
    # without occlusion every occupied sample scatters: the deepest bins are far brighter
    y_all, _, _, _ = F.render_occupancy(Field(), s, occlusion=False)
    deep = np.asarray(y_all).reshape(P, K)[:, -1]
    assert np.all(deep > 3 * np.asarray(y_re).reshape(P, K)[:, -1])
