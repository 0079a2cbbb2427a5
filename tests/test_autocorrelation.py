"""The matched-filter model's convolution (recon.solver.autocorrelation.convolve_rendered):
values and gradients against a straightforward NumPy loop, and one compiled kernel reused
across iterations (no recompilation from where NumPy happens to place each iteration's
index arrays)."""
import numpy as np

from recon._jit import jit
from recon._jit import aligned_upload
from recon.solver.autocorrelation import convolve_rendered, expand_bins

TAPS, N_T = 6, 200


def _draw(rng, pings=4, bins=4):
    """One iteration's drawn bins [pings, bins] -> (render_bins, positions) as the solver
    makes them."""
    drawn = np.sort(rng.choice(N_T, size=(pings, bins)), axis=1)
    return expand_bins(drawn, TAPS, N_T)


def _acf(rng):
    return rng.standard_normal(2 * TAPS + 1) + 1j * rng.standard_normal(2 * TAPS + 1)


def test_convolution_and_its_gradient_match_a_numpy_loop():
    """out[k] = Σ_m acf[m]·ŷ(pos[k, m]) (complex), and the reverse pass gives the adjoint:
    for the loss Σ w_re·out_re + w_im·out_im, ∂/∂ŷ_re[i] = Σ_{pos = i} w_re·a_re + w_im·a_im and
    ∂/∂ŷ_im[i] = Σ_{pos = i} w_im·a_re − w_re·a_im, accumulated over every (k, m) that reads i."""
    import drjit as dr
    m = jit()
    rng = np.random.default_rng(4)
    render, pos = _draw(rng)
    acf = _acf(rng)
    y = rng.standard_normal(render.size) + 1j * rng.standard_normal(render.size)
    w = rng.standard_normal((2, pos.shape[0] * pos.shape[1]))
    y_re, y_im = m.Float(y.real), m.Float(y.imag)
    dr.enable_grad(y_re, y_im)
    out_re, out_im = convolve_rendered(m, y_re, y_im, pos, acf)
    dr.backward(dr.sum(m.Float(w[0]) * out_re + m.Float(w[1]) * out_im))

    flat = pos.reshape(-1, pos.shape[2])
    expected = np.zeros(len(flat), dtype=complex)
    g_re, g_im = np.zeros(render.size), np.zeros(render.size)
    for k, row in enumerate(flat):
        for j, i in enumerate(row):
            expected[k] += acf[j] * y[i]
            g_re[i] += w[0, k] * acf[j].real + w[1, k] * acf[j].imag
            g_im[i] += w[1, k] * acf[j].real - w[0, k] * acf[j].imag
    np.testing.assert_allclose(out_re.numpy() + 1j * out_im.numpy(), expected, rtol=1e-5,
                               atol=1e-5)
    np.testing.assert_allclose(dr.grad(y_re).numpy(), g_re, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dr.grad(y_im).numpy(), g_im, rtol=1e-5, atol=1e-5)


def test_iterations_reuse_the_compiled_kernels():
    """Each iteration draws new bins (new index arrays, fresh NumPy allocations); after the
    first iteration the forward and backward kernels come from the in-process kernel cache.
    With the index arrays handed to Dr.Jit as NumPy allocated them, the 13 lags' alignments
    changed the kernel's hash: 2-3 new kernels nearly every iteration (0.25 CPU-s each in the
    GD loop)."""
    import drjit as dr
    m = jit()
    rng = np.random.default_rng(5)
    acf = _acf(rng)
    compiled = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for _ in range(8):
            dr.kernel_history()
            render, pos = _draw(rng)
            y_re = aligned_upload(m.Float, rng.standard_normal(render.size).astype(np.float32))
            y_im = aligned_upload(m.Float, rng.standard_normal(render.size).astype(np.float32))
            dr.enable_grad(y_re, y_im)
            out_re, out_im = convolve_rendered(m, y_re, y_im, pos, acf)
            dr.backward(dr.sum(out_re * out_re + out_im * out_im))
            dr.eval(dr.grad(y_re), dr.grad(y_im))
            compiled.append(sum(1 for k in dr.kernel_history()
                                if k["type"] == dr.KernelType.JIT and not k["cache_hit"]))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert sum(compiled[2:]) == 0, compiled


def test_aligned_upload_keeps_the_values():
    m = jit()
    values = np.arange(1, 38, dtype=np.uint32)[1:]
    arr = aligned_upload(m.UInt32, values.reshape(4, 9))
    np.testing.assert_array_equal(arr.numpy(), values)
