"""Linear ("tent") interpolation of sampled signals at fractional sample indices.

The one home of the delay-interpolation convention of the reconstructors: delay-and-sum
backprojection *reads* a signal at a delay (:func:`tent_gather`, :func:`tent_gather_diff_jit`);
the voxel-driven delay model *spreads* a value onto the two neighbouring samples
(:func:`tent_scatter`, the exact adjoint of :func:`tent_gather`).

Convention
----------
* A signal ``s`` has ``n`` samples; sample ``k`` is at time ``(start_sample + k) / fs``
  after transmission (``fs`` in Hz; for a signal upsampled by an integer factor R, use
  ``fs·R`` and ``start_sample·R``).
* A round-trip path length L (metres) with sound speed c (m/s) is at the fractional sample
  index (dimensionless, in samples) ``u = L·fs/c − start_sample`` (:func:`fractional_index`);
  kernels precompute ``scale = fs/c`` and ``offset = −start_sample`` so that ``u = L·scale + offset``.
* The interpolated value is ``s(u) = Σ_k s[k]·h(u − k)`` with the tent ``h(x) = max(0, 1 − |x|)``,
  i.e. ``(1 − f)·s[k] + f·s[k+1]`` with ``k = floor(u)``, ``f = u − k ∈ [0, 1)``.
* The window is ``0 ≤ u ≤ n − 1``: outside it the value is 0 (no clamping, no extrapolation).
  At ``u = n − 1`` exactly, ``f = 0`` and the missing ``s[n]`` counts as 0.

Two variants of the rule exist only as options of backprojection: ``'nearest'`` (value of
the sample ``floor(u + 0.5)``, window tested after rounding) and ``'floor'`` (value of
``s[floor(u)]``, the reference code's truncation of the delay to the lower sample).

Dr.Jit kernels read from a packed buffer (:func:`packed_diff_buffer`): per sample ``k`` the
four float32 ``(Re s[k], Im s[k], Re Δ[k], Im Δ[k])`` with ``Δ[k] = s[k+1] − s[k]``, so one
16-byte packet gather fetches both interpolation nodes and the tent is one fused
multiply-add per component, ``s[k] + f·Δ[k]`` (read by :func:`tent_gather_diff_jit`; the
plain-pair form it replaced is kept as a test reference in :mod:`recon.straightforward`).

Dr.Jit turns a packet gather into separate per-float gathers (about half as fast on the CPU)
when the source array is not 64-byte aligned, which a NumPy array mapped into the LLVM
backend often is not: :func:`aligned_empty` allocates host arrays that are.
"""
from __future__ import annotations

import numpy as np

MODES = ("linear", "nearest", "floor")


def fractional_index(path, fs: float, sound_speed, start_sample: float = 0.0):
    """Fractional sample index ``u = path·fs/c − start_sample`` (samples) of round-trip
    ``path`` (metres, any shape) at sample rate ``fs`` (Hz) and sound speed ``c`` (m/s)."""
    return np.asarray(path) * (float(fs) / np.asarray(sound_speed)) - float(start_sample)


def tent_nodes(u, n: int):
    """Nodes and weights of the tent at fractional indices ``u`` (any shape) for ``n`` samples.

    Returns ``(k, f, valid)``: lower node ``k = floor(u)`` (int64, 0 where not valid), weight
    ``f = u − k`` of node ``k + 1`` (``1 − f`` of node ``k``; 0 where not valid) and
    ``valid = 0 ≤ u ≤ n − 1`` (bool). Node ``k + 1 = n`` only occurs with ``f = 0``.
    """
    u = np.asarray(u, dtype=np.float64)
    valid = (u >= 0) & (u <= n - 1)
    k = np.floor(np.where(valid, u, 0.0))
    f = np.where(valid, u - k, 0.0)
    return k.astype(np.int64), f, valid


def tent_gather(s, u):
    """Signal values at fractional indices: ``s`` [..., n] (real or complex), ``u`` [..., m]
    with the same leading shape → [..., m] (0 outside the window)."""
    s = np.asarray(s)
    n = s.shape[-1]
    k, f, valid = tent_nodes(u, n)
    padded = np.concatenate([s, np.zeros(s.shape[:-1] + (1,), s.dtype)], axis=-1)
    lo = np.take_along_axis(padded, k, axis=-1)
    hi = np.take_along_axis(padded, k + 1, axis=-1)
    return np.where(valid, (1 - f) * lo + f * hi, 0)


def tent_scatter(u, values, n: int):
    """Adjoint of :func:`tent_gather`: spread ``values`` [..., m] at fractional indices ``u``
    [..., m] onto ``n`` samples → [..., n] (complex128 for complex values, else float64)."""
    u = np.asarray(u, dtype=np.float64)
    values = np.asarray(values)
    lead = u.shape[:-1]
    k, f, valid = tent_nodes(u, n)
    rows = np.arange(int(np.prod(lead, dtype=np.int64))).reshape(lead + (1,)) * (n + 1)
    size = (n + 1) * int(np.prod(lead, dtype=np.int64))

    def spread(v):
        v = np.where(valid, v, 0.0)
        out = (np.bincount((rows + k).ravel(), ((1 - f) * v).ravel(), size)
               + np.bincount((rows + k + 1).ravel(), (f * v).ravel(), size))
        return out.reshape(lead + (n + 1,))[..., :n]

    if np.iscomplexobj(values):
        return spread(values.real.astype(np.float64)) + 1j * spread(values.imag.astype(np.float64))
    return spread(values.astype(np.float64))


ALIGNMENT = 64   # bytes; what Dr.Jit's LLVM backend needs to read a mapped array in packets


def aligned_empty(shape, dtype=np.float32, alignment: int = ALIGNMENT) -> np.ndarray:
    """Uninitialised C-contiguous array whose data starts at a multiple of ``alignment`` bytes."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape, dtype=np.int64))
    raw = np.empty(n * dtype.itemsize + alignment, dtype=np.uint8)
    start = (-raw.ctypes.data) % alignment
    return raw[start:start + n * dtype.itemsize].view(dtype).reshape(shape)


def packed_diff_buffer(s) -> np.ndarray:
    """Packed buffer [P, n, 4] float32 ``(Re s[k], Im s[k], Re Δ[k], Im Δ[k])``, ``Δ[k] =
    s[k+1] − s[k]`` (rounded once from the exact difference; ``s[n]`` = 0), of complex signals
    ``s`` [P, n], 64-byte aligned; read by :func:`tent_gather_diff_jit`."""
    s = np.asarray(s, dtype=np.complex64)
    buf = aligned_empty(s.shape + (4,), np.float32)
    pairs = buf.view(np.complex64)                  # [P, n, 2]: (s[k], Δ[k]); 7x faster than
    pairs[..., 0] = s                               # writing float pairs
    np.subtract(s[:, 1:], s[:, :-1], out=pairs[:, :-1, 1])    # IEEE: rounded once
    np.negative(s[:, -1], out=pairs[:, -1, 1])
    return buf


def tent_gather_diff_jit(m, buf, row, u, n, mode: str = "linear", active=True):
    """Dr.Jit tent read of one signal per lane from a :func:`packed_diff_buffer`: ``buf`` its
    flat ``m.Float`` view, ``row`` (``m.UInt32``) the signal's first packet index (signal
    number × n), ``u`` (``m.Float``) the fractional index, ``n`` the samples per signal (int or
    ``m.UInt32``). Returns ``(re, im)`` = ``s[k] + f·Δ[k]``, 0 outside the window or where not
    ``active``; ``mode``: 'linear' (the tent), 'nearest' or 'floor' (module docstring). The window test ``0 ≤ u ≤ n − 1`` is
    one unsigned comparison of the float's bits (for u ≥ +0 the bit patterns order like the
    values, and a negative u has the sign bit set); u is never −0 here."""
    import drjit as dr
    if mode not in MODES:
        raise ValueError(f"mode: choose one of {MODES}, got {mode!r}")
    if mode == "nearest":
        u = dr.floor(u + 0.5)
    last = dr.reinterpret_array(m.UInt32, m.Float(n - 1))
    valid = active & (dr.reinterpret_array(m.UInt32, u) <= last)
    fl = dr.floor(u)
    s = dr.gather(m.Array4f, buf, row + m.UInt32(m.Int32(fl)), valid)
    if mode != "linear":
        return s[0], s[1]
    f = u - fl
    return dr.fma(f, s[2], s[0]), dr.fma(f, s[3], s[1])
