"""recon.interp: the tent (linear) delay-interpolation convention, NumPy and Dr.Jit."""
import numpy as np
import pytest

from recon import interp, straightforward


def test_tent_reproduces_linear_signals_and_is_zero_outside_the_window():
    n = 7
    s = 2.0 + 0.5 * np.arange(n) - 1j * np.arange(n)       # linear in k: the tent is exact
    u = np.array([0.0, 0.25, 3.5, 5.999, 6.0, -1e-6, 6.0 + 1e-6, -3.0, 40.0])
    got = interp.tent_gather(s[None], u[None])[0]
    inside = (u >= 0) & (u <= n - 1)
    np.testing.assert_allclose(got[inside], 2.0 + 0.5 * u[inside] - 1j * u[inside], rtol=1e-12)
    assert np.all(got[~inside] == 0)


def test_tent_nodes_convention():
    k, f, valid = interp.tent_nodes([2.75, 0.0, 4.0, -0.5], 5)
    assert k.tolist() == [2, 0, 4, 0] and valid.tolist() == [True, True, True, False]
    np.testing.assert_allclose(f, [0.75, 0.0, 0.0, 0.0])


def test_fractional_index_of_a_path():
    # 1.5 m of round trip at 300 m/s and 1 kHz: 5 ms = sample 5 after transmission, index 3.
    assert interp.fractional_index(1.5, 1e3, 300.0, start_sample=2) == pytest.approx(3.0)


def test_scatter_is_the_adjoint_of_gather():
    rng = np.random.default_rng(1)
    n, p, m = 11, 3, 20
    s = rng.standard_normal((p, n)) + 1j * rng.standard_normal((p, n))
    u = rng.uniform(-2, n + 1, (p, m))
    u[0, :3] = [0.0, n - 1.0, 4.0]                        # window edges and a node
    v = rng.standard_normal((p, m)) + 1j * rng.standard_normal((p, m))
    lhs = np.vdot(v, interp.tent_gather(s, u))             # <v, G s>
    rhs = np.vdot(interp.tent_scatter(u, v, n), s)         # <G^H v, s>
    assert abs(lhs - rhs) < 1e-12 * abs(lhs)


@pytest.mark.parametrize("mode", interp.MODES)
def test_jit_gather_matches_numpy(mode):
    import drjit as dr
    from recon._jit import jit
    m = jit()
    rng = np.random.default_rng(2)
    n, p, lanes = 9, 2, 64
    s = (rng.standard_normal((p, n)) + 1j * rng.standard_normal((p, n))).astype(np.complex64)
    u = rng.uniform(-1.5, n + 0.5, lanes).astype(np.float32)
    u[:4] = [0.0, n - 1, n - 1.4, n - 0.6]
    sig = rng.integers(0, p, lanes)
    buf = m.Float(straightforward.packed_buffer(s).ravel())
    re, im = straightforward.tent_gather_jit(m, buf, m.UInt32(sig * n), m.Float(u), n, mode)
    dr.eval(re, im)
    got = np.asarray(re) + 1j * np.asarray(im)
    uu = u.astype(np.float64)
    if mode == "nearest":
        uu = np.floor(uu + 0.5)
    if mode == "floor":
        k, _, valid = interp.tent_nodes(uu, n)
        want = np.where(valid, s[sig, k], 0)
    else:
        want = interp.tent_gather(s[sig][:, :], uu[:, None])[:, 0]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_aligned_empty_and_diff_buffer_layout():
    a = interp.aligned_empty((3, 5, 4))
    assert a.shape == (3, 5, 4) and a.dtype == np.float32 and a.ctypes.data % interp.ALIGNMENT == 0
    rng = np.random.default_rng(3)
    s = (rng.standard_normal((2, 6)) + 1j * rng.standard_normal((2, 6))).astype(np.complex64)
    buf = interp.packed_diff_buffer(s)
    assert buf.ctypes.data % interp.ALIGNMENT == 0
    np.testing.assert_array_equal(buf[..., 0] + 1j * buf[..., 1], s)
    nxt = np.concatenate([s[:, 1:], np.zeros((2, 1), np.complex64)], axis=1)   # s[n] = 0
    diff = nxt.astype(np.complex128) - s
    np.testing.assert_allclose(buf[..., 2] + 1j * buf[..., 3], diff, rtol=1e-7, atol=0)


@pytest.mark.parametrize("mode", interp.MODES)
def test_jit_diff_gather_matches_numpy(mode):
    """The difference-buffer read agrees with the NumPy tent (float32 round-off), including
    the window edges u = 0 and u = n - 1, just outside them, and masked lanes."""
    import drjit as dr
    from recon._jit import jit
    m = jit()
    rng = np.random.default_rng(4)
    n, p, lanes = 9, 3, 96
    s = (rng.standard_normal((p, n)) + 1j * rng.standard_normal((p, n))).astype(np.complex64)
    u = rng.uniform(-1.5, n + 0.5, lanes).astype(np.float32)
    u[:8] = [0.0, n - 1, n - 1.4, n - 0.6, np.nextafter(np.float32(n - 1), np.float32(n)),
             -1e-7, np.float32(-0.5), np.float32(n - 1.5)]
    sig = rng.integers(0, p, lanes)
    active = rng.random(lanes) > 0.2
    buf = m.Float(interp.packed_diff_buffer(s).ravel())
    re, im = interp.tent_gather_diff_jit(m, buf, m.UInt32(sig * n), m.Float(u), n, mode,
                                         m.Bool(active))
    dr.eval(re, im)
    got = np.asarray(re) + 1j * np.asarray(im)
    uu = u.astype(np.float64)
    if mode == "nearest":
        uu = np.floor(uu + 0.5)
    if mode == "linear":
        want = interp.tent_gather(s[sig], uu[:, None])[:, 0]
    else:
        k, _, valid = interp.tent_nodes(uu, n)
        want = np.where(valid, s[sig, k], 0)
    want = np.where(active, want, 0)
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert np.all(got[(uu < 0) | (uu > n - 1) | ~active] == 0)
