"""Time-domain coherent backprojection (delay-and-sum) on Dr.Jit.

For every voxel v and ping i (REFERENCE_SPEC §5.1)::

    scene(v) += s_i( (|v - tx_i| + |v - rx_i|) / c_i )

where s_i is the matched-filtered analytic signal of ping i (complex), upsampled by an
FFT factor R (default 5, as the reference) and then *linearly interpolated* at the exact
delay. The reference instead truncates the delay to the lower upsampled sample (a bias of
half an upsampled sample, ≈ 0.34 mm of round-trip path at R = 5); ``interpolation='floor'``
reproduces that, ``'nearest'`` rounds. Sample k of a waveform is at time
``(start_sample + k)/fs``; delays outside the recorded window contribute nothing.

Options: ``incoherent`` sums |s| (REFERENCE_SPEC §5.1 item 5); ``tx_beam_mask`` (full cone
angle, degrees) only lets a ping contribute to voxels inside its TX cone around the boresight;
per-ping sound speed from per-ping temperatures (``sonarsim.signals.sound_speed_air``).

Kernel layout: one launch covers all voxels (lanes) of a voxel chunk and a fixed number of
pings (Python-unrolled; each ping's constants are size-1 opaque variables, so every launch
reuses one compiled kernel). The signal buffer holds, per upsampled sample k, the four floats
(Re s[k], Im s[k], Re s[k+1], Im s[k+1]) so that one packet gather fetches both
interpolation nodes. Memory: 5 floats per voxel plus two blocks of pings' signals.
"""
from __future__ import annotations

import math

import numpy as np

from sonarsim.errors import InputError
from sonarsim.progress import progress_bar

from . import measurements
from ._jit import jit
from .grid import Grid

PINGS_PER_LAUNCH = 16          # unrolled pings per kernel (8, 16, 32 measured alike)
PINGS_PER_BLOCK = 1024         # pings whose signals are prepared and uploaded together
MAX_VOXELS_PER_LAUNCH = 1 << 23
INTERPOLATIONS = ("linear", "nearest", "floor")


def _validate(grid, upsample, interpolation, tx_beam_mask):
    if not isinstance(grid, Grid):
        raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
    if int(upsample) != upsample or upsample < 1:
        raise InputError(f"upsample: must be a positive integer, got {upsample}")
    if interpolation not in INTERPOLATIONS:
        raise InputError(f"interpolation: choose one of {', '.join(INTERPOLATIONS)}, got {interpolation!r}")
    if tx_beam_mask is not None and not (0 < float(tx_beam_mask) <= 360):
        raise InputError(f"tx_beam_mask: full cone angle must be in (0, 360] degrees, got {tx_beam_mask}")


def upsampled_signals(dataset, pings, upsample: int, incoherent: bool) -> np.ndarray:
    """Interpolation buffer [n, T*R, 4] float32 of the selected pings (see module docstring)."""
    from sonarsim import signals
    s = measurements.matched_filtered(dataset, pings)
    if upsample > 1:
        s = signals.fft_upsample(s, upsample, axis=-1)
    s = np.abs(s).astype(np.complex64) if incoherent else np.asarray(s, dtype=np.complex64)
    return interpolation_buffer(s)


def ping_constants(dataset, upsample: int, per_ping_sound_speed: bool = True,
                   tx_beam_mask: float | None = None) -> np.ndarray:
    """Per-ping kernel constants [N, 12] float32.

    Columns: tx (3), rx (3), scale = fs·R/c_i (upsampled samples per metre of path),
    offset = −start_sample·R, boresight (3, unit), cos(beam/2) (−2 = no mask).
    """
    c = measurements.sound_speeds(dataset, per_ping_sound_speed)
    n = len(c)
    out = np.zeros((n, 12), dtype=np.float64)
    out[:, 0:3] = np.asarray(dataset.tx, dtype=np.float64)
    out[:, 3:6] = np.asarray(dataset.rx, dtype=np.float64)
    out[:, 6] = float(dataset.fs) * upsample / c
    out[:, 7] = -float(getattr(dataset, "start_sample", 0) or 0) * upsample
    b = getattr(dataset, "boresight", None)
    if b is None:
        b = np.zeros((n, 3))
    b = np.asarray(b, dtype=np.float64)
    norm = np.linalg.norm(b, axis=1, keepdims=True)
    out[:, 8:11] = np.divide(b, norm, out=np.zeros_like(b), where=norm > 0)
    out[:, 11] = -2.0 if tx_beam_mask is None else math.cos(math.radians(float(tx_beam_mask)) / 2)
    if tx_beam_mask is not None and np.any(norm == 0):
        raise InputError("dataset pings/boresight: zero vector, cannot apply a TX beam mask")
    return out.astype(np.float32)


def _kernel(m, voxels, acc, buf, consts, block_offset, n_up, interpolation: str,
            masked: bool):
    """Add PINGS_PER_LAUNCH pings to the accumulators of one voxel chunk (lazy, not evaluated)."""
    import drjit as dr
    vx, vy, vz = voxels
    are, aim = acc
    u_max = m.Float(n_up - 1)
    for p in range(PINGS_PER_LAUNCH):
        q = consts[p]
        dx, dy, dz = vx - q[0], vy - q[1], vz - q[2]
        d1 = dr.sqrt(dr.fma(dx, dx, dr.fma(dy, dy, dz * dz)))
        ex, ey, ez = vx - q[3], vy - q[4], vz - q[5]
        d2 = dr.sqrt(dr.fma(ex, ex, dr.fma(ey, ey, ez * ez)))
        u = dr.fma(d1 + d2, q[6], q[7])
        if interpolation == "nearest":
            u = dr.floor(u + 0.5)
        valid = (u >= 0) & (u <= u_max)
        if masked:
            valid &= dr.fma(dx, q[8], dr.fma(dy, q[9], dz * q[10])) >= q[11] * d1
        fl = dr.floor(u)
        k = m.UInt32(m.Int32(fl)) + (block_offset + p) * n_up
        s = dr.gather(m.Array4f, buf, k, valid)
        if interpolation == "linear":
            f = u - fl
            are += dr.fma(f, s[2] - s[0], s[0])
            aim += dr.fma(f, s[3] - s[1], s[1])
        else:
            are += s[0]
            aim += s[1]
    return are, aim


def solve(dataset, grid: Grid, *, upsample: int = 5, interpolation: str = "linear",
          incoherent: bool = False, tx_beam_mask: float | None = None,
          per_ping_sound_speed: bool = True, progress: bool = True):
    """Backproject a :class:`~sonarsim.dataset.SonarDataset` onto ``grid``.

    upsample: FFT upsampling factor R of the matched-filtered signal (1 = none).
    interpolation: 'linear' (default), 'nearest' or 'floor' (the reference's truncation).
    incoherent: sum magnitudes instead of complex values.
    tx_beam_mask: full TX cone angle in degrees (None = every ping sees every voxel).
    per_ping_sound_speed: use sound_speed_air(T_i) per ping when the dataset has temperatures.
    Returns a :class:`~sonarsim.dataset.Volume` with complex64 [nx, ny, nz], method
    'backprojection' and the parameters used.
    """
    from sonarsim.dataset import Volume
    volume = backproject(dataset, grid, upsample=upsample, interpolation=interpolation,
                         incoherent=incoherent, tx_beam_mask=tx_beam_mask,
                         per_ping_sound_speed=per_ping_sound_speed, progress=progress)
    params = {"upsample": int(upsample), "interpolation": interpolation,
              "incoherent": bool(incoherent),
              "tx_beam_mask_deg": float(tx_beam_mask) if tx_beam_mask is not None else -1.0,
              "per_ping_sound_speed": bool(per_ping_sound_speed),
              "n_pings": int(len(dataset.waveforms))}
    return Volume(volume=volume, bounds=np.asarray(grid.bounds, dtype=np.float64),
                  method="backprojection", params=params)


def backproject(dataset, grid: Grid, *, upsample: int = 5, interpolation: str = "linear",
                incoherent: bool = False, tx_beam_mask: float | None = None,
                per_ping_sound_speed: bool = True, progress: bool = True) -> np.ndarray:
    """Backprojected complex volume [nx, ny, nz] complex64 (see :func:`solve`)."""
    _validate(grid, upsample, interpolation, tx_beam_mask)
    measurements.check_dataset(dataset)
    upsample = int(upsample)
    n_pings, n_t = np.asarray(dataset.waveforms).shape
    consts = ping_constants(dataset, upsample, per_ping_sound_speed, tx_beam_mask)

    def blocks():
        for b0 in range(0, n_pings, PINGS_PER_BLOCK):
            pings = np.arange(b0, min(b0 + PINGS_PER_BLOCK, n_pings))
            yield upsampled_signals(dataset, pings, upsample, incoherent)

    return delay_and_sum(blocks(), consts, grid, n_t * upsample, interpolation=interpolation,
                         masked=tx_beam_mask is not None, progress=progress)


def interpolation_buffer(s: np.ndarray) -> np.ndarray:
    """Buffer [n, T, 4] float32 (Re s[k], Im s[k], Re s[k+1], Im s[k+1]) of signals s [n, T]."""
    s = np.asarray(s, dtype=np.complex64)
    pairs = np.ascontiguousarray(s).view(np.float32).reshape(s.shape + (2,))
    buf = np.empty(s.shape + (4,), dtype=np.float32)
    buf[..., 0:2] = pairs
    buf[:, :-1, 2:4] = pairs[:, 1:]
    buf[:, -1, 2:4] = 0.0
    return buf


def delay_and_sum(blocks, consts: np.ndarray, grid: Grid, n_up: int, *,
                  interpolation: str = "linear", masked: bool = False,
                  progress: bool = False) -> np.ndarray:
    """The Dr.Jit delay-and-sum loop: ``blocks`` yields interpolation buffers [n_b, n_up, 4]
    (see :func:`interpolation_buffer`) of consecutive pings, ``consts`` [N, 12] their
    :func:`ping_constants`. Returns the complex volume [nx, ny, nz] complex64."""
    import drjit as dr
    m = jit()
    n_pings = len(consts)
    chunks = []
    for v0 in range(0, grid.size, MAX_VOXELS_PER_LAUNCH):
        p = grid.points_range(v0, v0 + MAX_VOXELS_PER_LAUNCH).astype(np.float32)
        chunks.append(([m.Float(p[:, j]) for j in range(3)],
                       [dr.zeros(m.Float, len(p)), dr.zeros(m.Float, len(p))]))
    # A padding ping never contributes: scale 0, offset -1 -> u = -1 is outside the window.
    pad_ping = np.zeros(12, dtype=np.float32)
    pad_ping[7], pad_ping[11] = -1.0, -2.0
    n_up_o = dr.opaque(m.UInt32, n_up)  # opaque: a new window length must not recompile
    bar = progress_bar(n_pings, progress, unit="ping", desc="backprojection", leave=False)
    b0 = 0
    for host in blocks:
        n_b = len(host)
        if host.shape[1:] != (n_up, 4) or b0 + n_b > n_pings:
            raise InputError(f"delay_and_sum: block of shape {host.shape} does not fit "
                             f"{n_pings} pings x {n_up} samples")
        # Launches are asynchronous: wait for the previous block before queuing this one, so
        # that at most two signal blocks are alive (the NumPy preparation of this block
        # still overlapped with the previous block's kernels).
        dr.sync_thread()
        buf = m.Float(np.ascontiguousarray(host, dtype=np.float32).reshape(-1))
        del host
        for l0 in range(0, n_b, PINGS_PER_LAUNCH):
            c = consts[b0 + l0:b0 + min(l0 + PINGS_PER_LAUNCH, n_b)]
            if len(c) < PINGS_PER_LAUNCH:
                c = np.concatenate([c, np.tile(pad_ping, (PINGS_PER_LAUNCH - len(c), 1))])
            q = [[dr.opaque(m.Float, float(v)) for v in row] for row in c]
            offset = dr.opaque(m.UInt32, l0)
            for voxels, acc in chunks:
                acc[:] = _kernel(m, voxels, acc, buf, q, offset, n_up_o, interpolation, masked)
                dr.eval(acc)
            bar.update(min(PINGS_PER_LAUNCH, n_b - l0))
        del buf
        b0 += n_b
    bar.close()
    re = np.concatenate([np.asarray(acc[0]) for _, acc in chunks])
    im = np.concatenate([np.asarray(acc[1]) for _, acc in chunks])
    return (re + 1j * im).astype(np.complex64).reshape(grid.shape)


def backproject_numpy(dataset, grid: Grid, *, upsample: int = 5, incoherent: bool = False,
                      per_ping_sound_speed: bool = True) -> np.ndarray:
    """Straightforward vectorised NumPy delay-and-sum with linear interpolation (reference
    implementation for tests and benchmarks; same conventions as :func:`backproject`)."""
    measurements.check_dataset(dataset)
    n_pings, n_t = np.asarray(dataset.waveforms).shape
    n_up = n_t * upsample
    consts = ping_constants(dataset, upsample, per_ping_sound_speed).astype(np.float64)
    pts = grid.points()
    acc = np.zeros(len(pts), dtype=np.complex128)
    for b0 in range(0, n_pings, PINGS_PER_BLOCK):
        pings = np.arange(b0, min(b0 + PINGS_PER_BLOCK, n_pings))
        buf = upsampled_signals(dataset, pings, upsample, incoherent)
        sig = buf[..., 0] + 1j * buf[..., 1]
        for j, i in enumerate(pings):
            q = consts[i]
            path = np.linalg.norm(pts - q[0:3], axis=1) + np.linalg.norm(pts - q[3:6], axis=1)
            u = path * q[6] + q[7]
            ok = (u >= 0) & (u <= n_up - 1)
            k = np.floor(u[ok]).astype(np.int64)
            f = u[ok] - k
            nxt = np.where(k + 1 < n_up, sig[j, np.minimum(k + 1, n_up - 1)], 0)
            acc[ok] += (1 - f) * sig[j, k] + f * nxt
    return acc.astype(np.complex64).reshape(grid.shape)
