"""Time-domain coherent backprojection (delay-and-sum) on Dr.Jit.

For every voxel v and ping i (the reference code's baseline, ``beamformer.py``,
``backproject_all_airsas_measurements``)::

    scene(v) += s_i( (|v - tx_i| + |v - rx_i|) / c_i )

where s_i is the matched-filtered analytic signal of ping i (complex), upsampled by an
FFT factor R (default 5, as the reference) and then *linearly interpolated* at the exact
delay (the tent rule of :mod:`recon.interp`). The reference instead truncates the delay to
the lower upsampled sample (a bias of half an upsampled sample, ≈ 0.34 mm of round-trip path
at R = 5); ``interpolation='floor'`` reproduces that, ``'nearest'`` rounds. Sample k of a
waveform is at time ``(start_sample + k)/fs``; delays outside the recorded window contribute
nothing.

Options: ``incoherent`` sums |s|; ``tx_beam_mask`` (full cone angle, degrees) only lets a ping
contribute to voxels inside its TX cone around the boresight; per-ping sound speed from
per-ping temperatures (``sonarsim.signals.sound_speed_air``).

Kernel (one fused kernel per voxel chunk and group of pings): each SIMD lane owns one voxel,
loops over the pings and accumulates Re/Im in registers; the per-ping constants and the
upsampled signals are read from compact arrays, and nothing of size voxels × pings is ever
stored. Per voxel-ping: two distances as ``sqrt(|v|² − 2v·t + |t|²)`` (three FMAs each,
:func:`kernel_constants`), the fractional index, one unsigned window test, one 16-byte
packet gather of ``(s[k], s[k+1] − s[k])`` (64-byte aligned buffer, or Dr.Jit falls back to
four per-float gathers) and two FMAs. The packet gather bounds the CPU kernel: on AVX-512 it
is 16 pointer extractions, 16 loads and ~20 shuffles per 16 lanes, about 60 % of the
instructions (``docs/reconstruction.md``). Lanes are ordered in 4×4×4 voxel bricks so that
the 16 lanes of a vector and the next vectors read nearby signal samples. The lane order
changes no result. Two loop forms over the pings (``loop``):

* ``'unrolled'`` (default on the CPU): 16 pings per launch, unrolled, their constants passed
  as kernel parameters (opaque scalars: one compiled kernel for every launch); only the
  accumulators go to memory between launches (8 bytes per voxel per 16 pings).
* ``'symbolic'`` (default on CUDA): a ``drjit.while_loop`` over a block of pings; the loop
  index is the lane's ping, whose constants are gathered from a [N·12] array. On the CPU the
  three extra packet gathers per voxel-ping of the constants cost more than they save.

Signal preparation (matched filter, FFT upsampling, packing) runs in NumPy on the host for
blocks of up to 256 pings while the asynchronous kernels of the previous block run (the
first blocks have 32, 64, ... pings, so little preparation precedes the first launch); at
most two blocks of signals are alive (≈ 15 MB each for 718-sample pings at R = 5).
"""
from __future__ import annotations

import math

import numpy as np

from sonarsim.errors import InputError
from sonarsim.progress import progress_bar

from . import interp, measurements
from ._jit import jit
from .grid import Grid

PINGS_PER_LAUNCH = 16          # unrolled pings per kernel (8, 16, 32 measured alike)
LOOP_PINGS_PER_LAUNCH = 64     # pings per symbolic-loop launch on the CPU (cache-sized)
PINGS_PER_BLOCK = 256          # pings whose signals are prepared and uploaded together
                               # (~15 MB at 718 samples, R = 5: below glibc's largest mmap
                               # threshold, so the blocks' memory is reused rather than
                               # mapped and page-faulted anew: half the preparation time)
FIRST_BLOCK = 32               # the first block; the next ones double up to PINGS_PER_BLOCK
MAX_VOXELS_PER_LAUNCH = 1 << 23
BRICK = (4, 4, 4)              # lane order: voxel bricks (None = C order, the pre-brick layout)
INTERPOLATIONS = interp.MODES
LOOPS = ("auto", "unrolled", "symbolic")
# Peak bytes of a run (see memory_estimate): per voxel, the Dr.Jit coordinates, |v|² and
# accumulators (6 float32), the real/imaginary results, their complex128 sum and the
# complex64 volume; per upsampled sample of a ping block, the upsampled complex128 signal and
# its spectrum, the complex64 copy, the 4-float interpolation buffer and its Dr.Jit copy
# (on the CPU up to four blocks are alive: two prepared ahead, the running one, the last).
BYTES_PER_VOXEL = 24 + 8 + 16 + 8
BYTES_PER_UPSAMPLED_SAMPLE = 16 + 16 + 8 + 16 + 2 * 16


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


def kernel_constants(consts: np.ndarray) -> np.ndarray:
    """The kernel's per-ping constants [N, 16] float32 (computed in float64) from
    :func:`ping_constants` [N, 12]: the squared distances are expanded as
    ``|v − t|² = |v|² − 2v·t + |t|²`` with ``|v|²`` per voxel, three FMAs each instead of three
    subtractions, a product and two FMAs (same float32 round-off class: the terms are of the
    size of the result). Columns: −2·tx (3), |tx|², −2·rx (3), |rx|², scale, offset,
    cos(beam/2), −tx·b, b (3), 0 (the beam test is ``v·b − tx·b ≥ cos·|v − tx|``)."""
    c = np.asarray(consts, dtype=np.float64).reshape(-1, 12)
    k = np.zeros((len(c), 16))
    k[:, 0:3], k[:, 3] = -2.0 * c[:, 0:3], np.einsum("ij,ij->i", c[:, 0:3], c[:, 0:3])
    k[:, 4:7], k[:, 7] = -2.0 * c[:, 3:6], np.einsum("ij,ij->i", c[:, 3:6], c[:, 3:6])
    k[:, 8:11] = c[:, [6, 7, 11]]
    k[:, 11] = -np.einsum("ij,ij->i", c[:, 0:3], c[:, 8:11])
    k[:, 12:15] = c[:, 8:11]
    return k.astype(np.float32)


def _ping(m, voxels, q, masked: bool):
    """Fractional upsampled-sample index u and beam mask of one ping at the lanes' voxels
    ``(x, y, z, |v|²)``. ``q``: the ping's :func:`kernel_constants` (12 used, 15 masked)."""
    import drjit as dr
    vx, vy, vz, r2 = voxels
    d1 = dr.sqrt(dr.fma(vx, q[0], dr.fma(vy, q[1], dr.fma(vz, q[2], r2 + q[3]))))
    d2 = dr.sqrt(dr.fma(vx, q[4], dr.fma(vy, q[5], dr.fma(vz, q[6], r2 + q[7]))))
    u = dr.fma(d1 + d2, q[8], q[9])
    mask = True
    if masked:
        mask = dr.fma(vx, q[12], dr.fma(vy, q[13], dr.fma(vz, q[14], q[11]))) >= q[10] * d1
    return u, mask


def _kernel_unrolled(m, voxels, acc, buf, consts, row0, n_up, interpolation: str, masked: bool):
    """Add PINGS_PER_LAUNCH pings (constants: opaque scalars ``consts[p][c]``, signals at
    packet rows ``row0 + p·n_up`` of ``buf``) to the accumulators (lazy, not evaluated)."""
    are, aim = acc
    for p, q in enumerate(consts):
        u, mask = _ping(m, voxels, q, masked)
        re, im = interp.tent_gather_diff_jit(m, buf, row0 + p * n_up, u, n_up, interpolation, mask)
        are, aim = are + re, aim + im
    return are, aim


def _kernel_symbolic(m, voxels, acc, buf, cbuf, p0, p1, b0, n_up, interpolation: str,
                     masked: bool):
    """Add pings p0 … p1−1 (opaque UInt32 scalars) in a ``drjit.while_loop``: constants
    gathered from ``cbuf`` (flat [N·16] :func:`kernel_constants`), signal of ping i at packet
    row (i − b0)·n_up."""
    import drjit as dr
    width = dr.width(voxels[0])

    def body(i, are, aim):
        q = []
        for j in range(4 if masked else 3):
            q.extend(dr.gather(m.Array4f, cbuf, i * 4 + j))
        u, mask = _ping(m, voxels, q, masked)
        re, im = interp.tent_gather_diff_jit(m, buf, (i - b0) * n_up, u, n_up, interpolation, mask)
        return i + 1, are + re, aim + im

    i0 = p0 + dr.zeros(m.UInt32, width)
    _, are, aim = dr.while_loop((i0, acc[0], acc[1]), lambda i, are, aim: i < p1, body)
    return are, aim


def brick_order(shape, brick=BRICK) -> np.ndarray:
    """Flat C-order voxel indices [nx·ny·nz] of a grid ``shape`` in lane order: bricks of
    ``brick`` voxels (x-major over bricks, then x-major inside a brick); ``None`` = C order.
    int32 when the padded grid has fewer than 2³¹ voxels, else int64."""
    shape = tuple(int(n) for n in shape)
    b = [1, 1, 1] if brick is None else [min(int(k), n) for k, n in zip(brick, shape)]
    nb = [-(-n // k) for n, k in zip(shape, b)]
    dtype = np.int32 if math.prod(nb) * math.prod(b) < 2 ** 31 else np.int64
    if brick is None:
        return np.arange(math.prod(shape), dtype=dtype)

    def axis(a):  # voxel index along axis a, broadcast over (bx, by, bz, ox, oy, oz)
        sh = [1] * 6
        sh[a] = nb[a]
        outer = (np.arange(nb[a], dtype=dtype) * b[a]).reshape(sh)
        sh = [1] * 6
        sh[a + 3] = b[a]
        return outer + np.arange(b[a], dtype=dtype).reshape(sh)

    ix, iy, iz = axis(0), axis(1), axis(2)
    flat = (ix * shape[1] + iy) * shape[2] + iz
    valid = (ix < shape[0]) & (iy < shape[1]) & (iz < shape[2])
    flat, valid = np.broadcast_arrays(flat, valid)
    return flat[valid]


def _lane_voxels(m, grid: Grid, flat: np.ndarray) -> list:
    """Dr.Jit voxel-centre coordinates (x, y, z) and |v|² (evaluated) of the flat C-order
    voxel indices ``flat``."""
    import drjit as dr
    _, ny, nz = grid.shape
    rest, iz = np.divmod(flat, flat.dtype.type(nz))
    ix, iy = np.divmod(rest, flat.dtype.type(ny))
    del rest
    x, y, z = [m.Float(np.asarray(a, dtype=np.float32)[i]) for a, i in zip(grid.axes(), (ix, iy, iz))]
    r2 = dr.fma(x, x, dr.fma(y, y, z * z))
    dr.eval(r2)
    return [x, y, z, r2]


def memory_estimate(n_pings: int, n_samples: int, grid: Grid, upsample: int
                    ) -> tuple[int, str]:
    """(peak bytes, how they are made up) of backprojecting n_pings x n_samples onto grid."""
    block = min(n_pings, 4 * PINGS_PER_BLOCK)
    nx, ny, nz = grid.shape
    per_block = block * n_samples * int(upsample) * BYTES_PER_UPSAMPLED_SAMPLE
    need = nx * ny * nz * BYTES_PER_VOXEL + per_block
    detail = (f"{nx} x {ny} x {nz} voxels x {BYTES_PER_VOXEL} bytes + {block} pings x "
              f"{n_samples} samples x upsample {upsample} x {BYTES_PER_UPSAMPLED_SAMPLE} bytes")
    return need, detail


def check_options(grid: Grid, dataset=None, *, upsample: int = 5,
                  interpolation: str = "linear", tx_beam_mask: float | None = None,
                  **_ignored) -> None:
    """The checks the command line, ``sonarsim batch`` and :func:`solve` make before any
    work (InputError, one line): the option ranges, and with ``dataset`` the memory estimate
    of :func:`memory_estimate` against the limit (:mod:`sonarsim.limits`)."""
    from sonarsim import limits
    limits.check_upsample(upsample)
    _validate(grid, upsample, interpolation, tx_beam_mask)
    if dataset is not None:
        n_pings, n_t = np.asarray(dataset.waveforms).shape
        need, detail = memory_estimate(n_pings, n_t, grid, upsample)
        limits.check_memory(need, "backprojection", detail,
                            "use a smaller grid, a smaller --upsample or fewer --pings")


def _backend_is_cuda(m) -> bool:
    return m.__name__.startswith("drjit.cuda")


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
    if tx_beam_mask is not None and not np.any(volume) and np.any(dataset.waveforms):
        raise InputError(f"--beam-mask {float(tx_beam_mask):g}: no voxel centre of the grid lies "
                         "inside any ping's TX cone, the volume would be all zero (widen the "
                         "cone, or check the boresights and the grid)")
    params = {"upsample": int(upsample), "interpolation": interpolation,
              "incoherent": bool(incoherent),
              "tx_beam_mask_deg": float(tx_beam_mask) if tx_beam_mask is not None else -1.0,
              "per_ping_sound_speed": bool(per_ping_sound_speed),
              "n_pings": int(len(dataset.waveforms))}
    return Volume(volume=volume, bounds=np.asarray(grid.bounds, dtype=np.float64),
                  method="backprojection", params=params)


def backproject(dataset, grid: Grid, *, upsample: int = 5, interpolation: str = "linear",
                incoherent: bool = False, tx_beam_mask: float | None = None,
                per_ping_sound_speed: bool = True, progress: bool = True,
                loop: str = "auto", brick=BRICK) -> np.ndarray:
    """Backprojected complex volume [nx, ny, nz] complex64 (see :func:`solve`; ``loop`` and
    ``brick``: the kernel form and lane order of :func:`delay_and_sum`)."""
    _validate(grid, upsample, interpolation, tx_beam_mask)
    measurements.check_dataset(dataset)
    upsample = int(upsample)
    n_pings, n_t = np.asarray(dataset.waveforms).shape
    consts = ping_constants(dataset, upsample, per_ping_sound_speed, tx_beam_mask)

    def ranges():
        # Blocks of 32, 64, ... up to PINGS_PER_BLOCK pings: only the first block's preparation
        # precedes the kernels; the next ones are prepared while the previous blocks' run.
        b0, size = 0, FIRST_BLOCK
        while b0 < n_pings:
            b1 = min(b0 + size, n_pings)
            yield np.arange(b0, b1)
            b0, size = b1, min(2 * size, PINGS_PER_BLOCK)

    prepare = lambda pings: upsampled_signals(dataset, pings, upsample, incoherent)  # noqa: E731
    with _Prefetch(prepare, ranges(), _preparation_threads(jit())) as blocks:
        return delay_and_sum(blocks, consts, grid, n_t * upsample, interpolation=interpolation,
                             masked=tx_beam_mask is not None, progress=progress, loop=loop,
                             brick=brick)


def _preparation_threads(m) -> int:
    """Threads that prepare signal blocks (NumPy/SciPy FFTs release the GIL). On the CPU the
    kernels already use every core: one thread, which overlaps the preparation with the
    launches that the main thread traces. With CUDA the host's cores are free: all but one
    (up to 16); a GPU kernel outruns one preparation thread by 10-100x."""
    if not _backend_is_cuda(m):
        return 1
    import os
    return max(1, min(16, (os.cpu_count() or 2) - 1))


class _Prefetch:
    """Iterate ``fn(item)`` for the items in order, computed ahead by ``threads`` worker
    threads (at most ``threads + 1`` results pending)."""

    def __init__(self, fn, items, threads: int):
        from concurrent.futures import ThreadPoolExecutor
        self.fn, self.items, self.depth = fn, iter(items), threads + 1
        self.pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="bp-prepare")
        self.pending = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for f in self.pending:
            f.cancel()
        self.pool.shutdown(wait=True)
        self.pending = []

    def __iter__(self):
        while True:
            while len(self.pending) < self.depth:
                item = next(self.items, None)
                if item is None:
                    break
                self.pending.append(self.pool.submit(self.fn, item))
            if not self.pending:
                return
            yield self.pending.pop(0).result()


def interpolation_buffer(s: np.ndarray) -> np.ndarray:
    """Packed buffer [n, T, 4] float32 of signals s [n, T], the layout :func:`delay_and_sum`
    reads: ``(Re s[k], Im s[k], Re Δ[k], Im Δ[k])``, Δ[k] = s[k+1] − s[k], 64-byte aligned
    (:func:`recon.interp.packed_diff_buffer`)."""
    return interp.packed_diff_buffer(s)


def _device_buffer(m, host: np.ndarray):
    """Flat ``m.Float`` of an interpolation buffer. The LLVM backend maps a NumPy array
    without copying; unless its data is 64-byte aligned, Dr.Jit then reads it with four
    separate gathers per packet instead of one packet gather (half the kernel's speed)."""
    flat = np.ascontiguousarray(host, dtype=np.float32).reshape(-1)
    if flat.ctypes.data % interp.ALIGNMENT:
        aligned = interp.aligned_empty(flat.shape, np.float32)
        aligned[...] = flat
        flat = aligned
    return m.Float(flat)


def delay_and_sum(blocks, consts: np.ndarray, grid: Grid, n_up: int, *,
                  interpolation: str = "linear", masked: bool = False,
                  progress: bool = False, loop: str = "auto", brick=BRICK) -> np.ndarray:
    """The fused Dr.Jit delay-and-sum: ``blocks`` yields interpolation buffers [n_b, n_up, 4]
    (see :func:`interpolation_buffer`) of consecutive pings, ``consts`` [N, 12] their
    :func:`ping_constants`. ``loop``: 'unrolled', 'symbolic' or 'auto' (unrolled on the CPU,
    symbolic on CUDA; see the module docstring); ``brick``: lane order (:func:`brick_order`).
    Returns the complex volume [nx, ny, nz] complex64."""
    import drjit as dr
    m = jit()
    if loop not in LOOPS:
        raise InputError(f"loop: choose one of {', '.join(LOOPS)}, got {loop!r}")
    if loop == "auto":
        loop = "symbolic" if _backend_is_cuda(m) else "unrolled"
    consts = kernel_constants(consts)
    n_used = 15 if masked else 12
    n_pings = len(consts)
    order = brick_order(grid.shape, brick)
    chunks = []
    for v0 in range(0, grid.size, MAX_VOXELS_PER_LAUNCH):
        voxels = _lane_voxels(m, grid, order[v0:v0 + MAX_VOXELS_PER_LAUNCH])
        n = dr.width(voxels[0])
        chunks.append((voxels, [dr.zeros(m.Float, n), dr.zeros(m.Float, n)]))
    n_up_o = dr.opaque(m.UInt32, n_up)  # opaque: a new window length must not recompile
    if loop == "symbolic":
        cbuf = m.Float(consts.ravel())
        per_launch = PINGS_PER_BLOCK if _backend_is_cuda(m) else LOOP_PINGS_PER_LAUNCH
    else:
        per_launch = PINGS_PER_LAUNCH
        # A padding ping never contributes: scale 0, offset -1 -> u = -1 is outside the window.
        pad_ping = np.zeros(16, dtype=np.float32)
        pad_ping[9], pad_ping[10] = -1.0, -2.0
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
        buf = _device_buffer(m, host)
        del host
        for l0 in range(0, n_b, per_launch):
            l1 = min(l0 + per_launch, n_b)
            if loop == "symbolic":
                args = (cbuf, dr.opaque(m.UInt32, b0 + l0), dr.opaque(m.UInt32, b0 + l1),
                        dr.opaque(m.UInt32, b0), n_up_o)
            else:
                c = consts[b0 + l0:b0 + l1]
                if len(c) < per_launch:
                    c = np.concatenate([c, np.tile(pad_ping, (per_launch - len(c), 1))])
                q = [[dr.opaque(m.Float, float(v)) for v in row[:n_used]] for row in c]
                args = (q, dr.opaque(m.UInt32, l0) * n_up_o, n_up_o)
            for voxels, acc in chunks:
                if loop == "symbolic":
                    acc[:] = _kernel_symbolic(m, voxels, acc, buf, *args, interpolation, masked)
                else:
                    acc[:] = _kernel_unrolled(m, voxels, acc, buf, *args, interpolation, masked)
                dr.eval(acc)
            bar.update(l1 - l0)
        del buf
        b0 += n_b
    bar.close()
    out = np.empty(grid.size, dtype=np.complex64)
    v0 = 0
    while chunks:
        voxels, (are, aim) = chunks.pop(0)
        del voxels
        lanes = np.empty(dr.width(are), dtype=np.complex64)
        lanes.real, lanes.imag = np.asarray(are), np.asarray(aim)
        del are, aim
        out[order[v0:v0 + len(lanes)]] = lanes
        v0 += len(lanes)
    return out.reshape(grid.shape)
