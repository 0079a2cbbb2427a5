"""Straightforward reference implementations: what the fast reconstruction code is tested
and benchmarked against. Not used by the package itself.

* :func:`backproject_numpy`: delay-and-sum in float64 NumPy, one vectorised pass over every
  voxel per ping (:func:`recon.backprojection.backproject`'s conventions and options);
* :func:`pfa_direct`: the polar-format image by direct summation over every voxel
  (:func:`recon.pfa.pfa`'s raster and weights);
* :func:`packed_buffer`, :func:`tent_gather_jit`: the plain ``(s[k], s[k+1])`` packed buffer
  and its Dr.Jit tent read, against which :func:`recon.interp.tent_gather_diff_jit` is tested.
"""
from __future__ import annotations

import numpy as np

from . import interp, measurements
from .backprojection import PINGS_PER_BLOCK, _validate, ping_constants, upsampled_signals
from .grid import Grid
from .interp import MODES
from .pfa import phase_referenced, polar_samples, wavenumbers


def backproject_numpy(dataset, grid: Grid, *, upsample: int = 5, interpolation: str = "linear",
                      incoherent: bool = False, tx_beam_mask: float | None = None,
                      per_ping_sound_speed: bool = True) -> np.ndarray:
    """Straightforward vectorised NumPy delay-and-sum in float64 (one pass over all voxels per
    ping; reference implementation for tests and benchmarks; same conventions and options as
    :func:`backproject`, the tent rule of :func:`recon.interp.tent_gather`)."""
    _validate(grid, upsample, interpolation, tx_beam_mask)
    measurements.check_dataset(dataset)
    n_pings, n_t = np.asarray(dataset.waveforms).shape
    n_up = n_t * upsample
    consts = ping_constants(dataset, upsample, per_ping_sound_speed, tx_beam_mask).astype(np.float64)
    pts = grid.points()
    acc = np.zeros(len(pts), dtype=np.complex128)
    for b0 in range(0, n_pings, PINGS_PER_BLOCK):
        pings = np.arange(b0, min(b0 + PINGS_PER_BLOCK, n_pings))
        buf = upsampled_signals(dataset, pings, upsample, incoherent)
        sig = buf[..., 0].astype(np.float64) + 1j * buf[..., 1]
        for j, i in enumerate(pings):
            q = consts[i]
            d1 = np.linalg.norm(pts - q[0:3], axis=1)
            u = (d1 + np.linalg.norm(pts - q[3:6], axis=1)) * q[6] + q[7]
            if interpolation == "nearest":
                u = np.floor(u + 0.5)
            if interpolation == "linear":
                val = interp.tent_gather(sig[j], u)
            else:
                k, _, valid = interp.tent_nodes(u, n_up)
                val = np.where(valid, sig[j, k], 0)
            if tx_beam_mask is not None:
                val = np.where((pts - q[0:3]) @ q[8:11] >= q[11] * d1, val, 0)
            acc += val
    return acc.astype(np.complex64).reshape(grid.shape)


def pfa_direct(dataset, grid: Grid, **options) -> np.ndarray:
    """The same image by direct summation Σ_j w_j S_j exp(−j k_j·(x_l − x0)) over every voxel
    (NumPy, O(voxels × samples): small grids only; the reference for tests)."""
    raster = polar_samples(dataset, grid, **options)
    pings = np.arange(len(raster["c"]))
    k = wavenumbers(raster, pings).reshape(-1, 3)
    s = phase_referenced(dataset, raster, pings).reshape(-1)
    x = grid.points() - raster["x0"]
    out = np.exp(-1j * (x @ k.T)) @ s
    out /= float(np.sum(raster["weights"] * raster["response"][None, :]))
    return out.reshape(grid.shape).astype(np.complex64)


def packed_buffer(s) -> np.ndarray:
    """Packed buffer [P, n, 4] float32 ``(Re s[k], Im s[k], Re s[k+1], Im s[k+1])`` of complex
    signals ``s`` [P, n] (``s[n]`` = 0), read by :func:`tent_gather_jit`."""
    s = np.asarray(s, dtype=np.complex64)
    pairs = np.ascontiguousarray(s).view(np.float32).reshape(s.shape + (2,))
    buf = np.empty(s.shape + (4,), dtype=np.float32)
    buf[..., 0:2] = pairs
    buf[:, :-1, 2:4] = pairs[:, 1:]
    buf[:, -1, 2:4] = 0.0
    return buf


def tent_gather_jit(m, buf, row, u, n, mode: str = "linear", active=True):
    """Dr.Jit tent read of one signal per lane: ``buf`` a flat ``m.Float`` view of a
    :func:`packed_buffer`, ``row`` (``m.UInt32``) the signal's first packet index (signal
    number × n), ``u`` (``m.Float``) the fractional index, ``n`` the samples per signal
    (int or ``m.UInt32``). Returns ``(re, im)``, 0 outside the window or where not ``active``.
    ``mode``: 'linear' (the tent), 'nearest' or 'floor' (see the module docstring)."""
    import drjit as dr
    if mode not in MODES:
        raise ValueError(f"mode: choose one of {MODES}, got {mode!r}")
    if mode == "nearest":
        u = dr.floor(u + 0.5)
    valid = active & (u >= 0) & (u <= m.Float(n - 1))
    fl = dr.floor(u)
    s = dr.gather(m.Array4f, buf, row + m.UInt32(m.Int32(fl)), valid)
    if mode != "linear":
        return s[0], s[1]
    f = u - fl
    return dr.fma(f, s[2] - s[0], s[0]), dr.fma(f, s[3] - s[1], s[1])
