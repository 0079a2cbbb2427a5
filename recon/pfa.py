"""Polar formatting (PFA): 3-D Fourier-domain reconstruction for bistatic SAS.

The reference names a PFA baseline in its Table 2 but released no code for it (Reed et
al. 2023, Table 2; reference code ``evaluate/predefined_configs.py`` lists ``*_pfa``
experiments only). This is a standard far-field polar-format algorithm for the AirSAS
bistatic geometry:

1. **Spectrum of each ping.** The complex measurement s_i (matched-filtered analytic
   signal, or the stored analytic signal of a deconvolved dataset, :mod:`recon.measurements`)
   is Fourier transformed over its record (sample k at
   time (start_sample + k)/fs); only the pulse's band is kept (bins whose pulse power is
   within ``band_db`` of the peak).
2. **Reference point (motion compensation).** Each spectrum is multiplied by
   exp(+j2πf·L0_i/c_i) with L0_i = |x0 − tx_i| + |x0 − rx_i| the exact round-trip path to the
   reference point x0 (default: the grid centre): a scatterer at x0 then has zero phase
   at every frequency and ping, whatever the geometry.
3. **Polar raster.** Sample (i, f) sits at the wavenumber vector
   k = (2πf/c_i)·(û_TX + û_RX), û the unit vectors from x0 towards TX and RX. This is the
   plane-wave (far-field) approximation about x0: L(x) − L0 ≈ −(û_TX + û_RX)·(x − x0), so the
   phase-referenced spectrum of a scatterer at x is ≈ exp(+j k·(x − x0)).
4. **Weights and window.** With ``weights='density'`` each sample is weighted
   by |k|^D·ΔΩ_i (the Jacobian of the polar raster: D = 2 for a 3-D aperture such as the
   cylindrical scan, D = 1 for one circle; ΔΩ_i the aperture area per ping, estimated from
   nearest neighbours of the look directions): the classical inverse of the polar raster,
   which sharpens the image along the range direction. ``weights='uniform'`` weights every
   sample alike, the matched-filter sum: with no taper, a wide band and the reference
   point at the voxel it is then the same sum as backprojection (:mod:`recon.backprojection`),
   evaluated in the Fourier domain. Either way a Tukey window over the band (``taper``).
   Defaults: uniform weights, the band to −40 dB, no window (:data:`DEFAULT_WEIGHTS` ...;
   the low frequencies they keep carry the object's body, docs/reconstruction.md "Defaults").
5. **Cartesian grid and inverse FFT.** image(x_l) = Σ_j w_j S_j exp(−j k_j·(x_l − x0)) on the
   voxel centres x_l of a :class:`~recon.grid.Grid`, computed as one type-1 non-uniform FFT
   (``finufft``): finufft spreads the polar samples onto an oversampled Cartesian k-grid
   with its exponential-of-semicircle kernel, takes the 3-D FFT and corrects the kernel's
   roll-off, which is exactly the interpolation + inverse FFT of classical PFA, but with a
   controlled error (``eps``) instead of a polynomial interpolator's.

The far-field step 3 is the only approximation besides ``eps``: it is exact at x0 and
degrades with |x − x0|²/R (R ≈ 0.85 m for AirSAS); docs/reconstruction.md quantifies it.
The output scale is chosen so that a unit point scatterer at x0 images to magnitude ≈ 1.
"""
from __future__ import annotations

import math

import numpy as np

from sonarsim.errors import InputError
from sonarsim.progress import progress_bar

from . import measurements
from .grid import Grid

MAX_POINTS_PER_NUFFT = 4_000_000   # polar samples per finufft call (bounds memory)
# Peak bytes per voxel: finufft's 2x-oversampled complex128 fine grid (8 x 16), its complex128
# result and our accumulator (2 x 16), the complex64 volume (8).
BYTES_PER_VOXEL = 8 * 16 + 2 * 16 + 8
_NEIGHBOURS = (12, 200)            # nearest look directions for the aperture-area estimate
WEIGHTS = ("density", "uniform")   # polar-sample weighting (module docstring, step 4)
# Defaults (chosen on full-size scans of the bunny, cube, cylinder, sphere and tabletop scenes;
# docs/reconstruction.md "Polar formatting", "Defaults"): every polar sample alike, the
# pulse's band to -40 dB and no extra window, i.e. backprojection's sum of the same data.
DEFAULT_WEIGHTS = "uniform"
DEFAULT_BAND_DB = -40.0
DEFAULT_TAPER = 0.0


def _validate(grid, band_db, taper, eps, reference_point, weights=DEFAULT_WEIGHTS):
    if weights not in WEIGHTS:
        raise InputError(f"weights: expected one of {', '.join(WEIGHTS)}, got {weights!r}")
    if not isinstance(grid, Grid):
        raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
    if not (np.isfinite(band_db) and band_db < 0):
        raise InputError(f"band_db: must be a negative number of dB, got {band_db}")
    if not (0.0 <= float(taper) <= 1.0):
        raise InputError(f"taper: Tukey ratio must lie in [0, 1], got {taper}")
    if not (1e-15 < float(eps) < 1e-1):
        raise InputError(f"eps: NUFFT tolerance must lie in (1e-15, 0.1), got {eps}")
    if reference_point is not None:
        p = np.asarray(reference_point, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError(f"reference_point: expected three finite numbers, got {reference_point!r}")


def check_options(grid: Grid, dataset=None, *, reference_point=None,
                  band_db: float = DEFAULT_BAND_DB, taper: float = DEFAULT_TAPER,
                  eps: float = 1e-6, patches=1, weights: str = DEFAULT_WEIGHTS,
                  **_ignored) -> None:
    """The checks the command line, ``sonarsim batch`` and :func:`solve` make before any work
    (InputError, one line): the option ranges and the grid's memory."""
    from .checks import check_grid_memory
    _validate(grid, band_db, taper, eps, reference_point, weights)
    _patch_counts(patches, reference_point)
    check_grid_memory(grid, BYTES_PER_VOXEL, what="polar formatting")


def complex_measurements(dataset, pings) -> np.ndarray:
    """Complex measurements [n, T] of the selected pings: the matched-filtered analytic signal,
    or, for a deconvolved dataset, its stored analytic signals (both through
    :func:`recon.measurements.matched_filtered`)."""
    return measurements.matched_filtered(dataset, pings)


def is_deconvolved(dataset) -> bool:
    """True for datasets of deconvolved analytic signals (see :mod:`recon.measurements`)."""
    return bool(getattr(measurements, "is_deconvolved", lambda d: False)(dataset))


def fft_length(dataset, x0: np.ndarray, grid: Grid, c: np.ndarray) -> int:
    """FFT length (samples) of each ping: at least the record, and long enough that the
    periodic replicas of the image (period c·n_fft/fs in round-trip path) stay off the grid."""
    import scipy.fft
    n_t = np.asarray(dataset.waveforms).shape[1]
    corners = np.array(np.meshgrid(*grid.bounds, indexing="ij")).reshape(3, -1).T  # [8, 3]
    tx, rx = np.asarray(dataset.tx, float), np.asarray(dataset.rx, float)
    path = (np.linalg.norm(corners[None] - tx[:, None], axis=2)
            + np.linalg.norm(corners[None] - rx[:, None], axis=2))          # [N, 8]
    path0 = np.linalg.norm(x0 - tx, axis=1) + np.linalg.norm(x0 - rx, axis=1)
    spread = float(np.max(np.abs(path - path0[:, None])))
    need = 2 * spread / float(np.min(c)) * float(dataset.fs) + 2 * len(dataset.pulse)
    return int(scipy.fft.next_fast_len(max(n_t, int(math.ceil(need)))))


def band(dataset, n_fft: int, band_db: float) -> tuple[np.ndarray, np.ndarray]:
    """(FFT bin indices [F] of the pulse's band, pulse power |P(f)|² [F]).

    The band is the contiguous range of positive-frequency bins from the first to the last
    one whose power is within ``band_db`` of the peak.
    """
    p = np.fft.rfft(np.asarray(dataset.pulse, dtype=np.float64), n=n_fft)
    power = np.abs(p) ** 2
    power[0] = 0.0                      # DC carries no range information (and no phase)
    if not power.max() > 0:
        raise InputError("dataset pulse: has no energy at positive frequencies")
    ok = np.nonzero(power >= power.max() * 10 ** (band_db / 10))[0]
    bins = np.arange(ok[0], ok[-1] + 1)
    if len(bins) < 2:
        raise InputError(f"dataset pulse: its band ({band_db:g} dB) holds fewer than 2 "
                         f"frequency bins of a {n_fft}-sample FFT; too short a record")
    return bins, power[bins]


def aperture_weights(look: np.ndarray, areas: bool = True) -> tuple[np.ndarray, int]:
    """(aperture area per ping ΔΩ_i [N] (mean 1), dimension D of the aperture: 1 or 2).

    ``look`` [N, 3] unit look directions. D = 1 when they lie on one plane (a circle or an
    arc: one height of a turntable, a straight track), else 2. ΔΩ_i ∝ d_k^D, d_k the
    distance to the k-th nearest look direction (k ≈ 2√N, beyond the spacing of both axes
    of an anisotropic raster such as the cylindrical scan's 1° in azimuth × 0.3° in
    elevation), clipped to 2× the median so that pings on the edge of the aperture
    (half-neighbourhoods) are not overweighted. A rough estimate; exact for uniform rasters.
    ``areas=False``: D only, ΔΩ all 1 (the k-th neighbours, most of the cost, are not searched).
    """
    n = len(look)
    if n < 4:
        return np.ones(n), 1
    from scipy.spatial import cKDTree
    k = min(max(_NEIGHBOURS[0], int(2 * math.sqrt(n))), _NEIGHBOURS[1], n - 2)
    # column 0 of k=1 would be the point itself
    d, _ = cKDTree(look).query(look, k=[2, k + 1] if areas else [2])
    spacing = float(np.median(d[:, 0]))
    off_plane = np.linalg.svd(look - look.mean(axis=0), compute_uv=False)[-1] / math.sqrt(n)
    dim = 1 if off_plane <= 0.25 * max(spacing, 1e-12) else 2
    if not areas:
        return np.ones(n), dim
    area = np.maximum(d[:, 1], 1e-12) ** dim
    area = np.minimum(area, 2 * float(np.median(area)))
    return area / area.mean(), dim


def tukey(u: np.ndarray, ratio: float) -> np.ndarray:
    """Tukey window of u ∈ [0, 1] (ratio 0 = rectangular, 1 = Hann)."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    if ratio <= 0:
        return np.ones_like(u)
    w = np.ones_like(u)
    a = ratio / 2
    lo, hi = u < a, u > 1 - a
    w[lo] = 0.5 * (1 - np.cos(np.pi * u[lo] / a))
    w[hi] = 0.5 * (1 - np.cos(np.pi * (1 - u[hi]) / a))
    return w


def polar_samples(dataset, grid: Grid, *, reference_point=None,
                  band_db: float = DEFAULT_BAND_DB, taper: float = DEFAULT_TAPER,
                  per_ping_sound_speed: bool = True,
                  weights: str = DEFAULT_WEIGHTS) -> dict:
    """The polar raster without the measurements: everything :func:`pfa` needs per ping.

    Returns a dict: ``x0`` [3], ``n_fft``, ``bins`` [F], ``freqs`` [F] (Hz), ``c`` [N],
    ``path0`` [N] (m), ``look_sum`` [N, 3] (û_TX + û_RX), ``weights`` [N, F] (density ×
    window, or the window alone for ``weights='uniform'``), ``response`` [F] (spectrum of a
    unit echo's measurement), ``dim``.
    """
    measurements.check_dataset(dataset)
    x0 = (grid.bounds.mean(axis=1) if reference_point is None
          else np.asarray(reference_point, dtype=np.float64))
    c = measurements.sound_speeds(dataset, per_ping_sound_speed)
    tx, rx = np.asarray(dataset.tx, float), np.asarray(dataset.rx, float)
    to_tx, to_rx = tx - x0, rx - x0
    r_tx, r_rx = np.linalg.norm(to_tx, axis=1), np.linalg.norm(to_rx, axis=1)
    if np.any(r_tx < 1e-6) or np.any(r_rx < 1e-6):
        raise InputError("dataset pings: a transmitter or receiver sits at the reference point "
                         f"{x0.tolist()}; polar formatting needs it at a distance")
    look_sum = to_tx / r_tx[:, None] + to_rx / r_rx[:, None]
    norm = np.linalg.norm(look_sum, axis=1)
    if np.any(norm < 1e-6):
        raise InputError("dataset pings: transmitter and receiver on opposite sides of the "
                         "reference point (forward scatter); no monostatic-like wavenumber")
    n_fft = fft_length(dataset, x0, grid, c)
    bins, power = band(dataset, n_fft, band_db)
    freqs = bins * float(dataset.fs) / n_fft
    area, dim = aperture_weights(look_sum / norm[:, None], areas=weights == "density")
    kmag = 2 * np.pi * freqs[None, :] / c[:, None] * norm[:, None]      # [N, F]
    window = tukey((freqs - freqs[0]) / max(freqs[-1] - freqs[0], 1e-300), float(taper))
    if weights == "uniform":
        sample_weights = np.broadcast_to(window[None, :], kmag.shape).copy()
    else:
        sample_weights = kmag ** dim * area[:, None] * window[None, :]
    # Spectrum of the measurement of a unit echo: the matched filter of two analytic signals
    # carries 4|P|² at positive frequencies; a deconvolved analytic impulse carries 2.
    response = np.full(len(bins), 2.0) if is_deconvolved(dataset) else 4.0 * power
    return {"x0": x0, "n_fft": n_fft, "bins": bins, "freqs": freqs, "c": c,
            "path0": r_tx + r_rx, "look_sum": look_sum, "weights": sample_weights,
            "response": response, "dim": dim}


def phase_referenced(dataset, raster: dict, pings: np.ndarray) -> np.ndarray:
    """Weighted, phase-referenced spectra [n, F] complex128 of the selected pings:
    w·S_i(f)·exp(+j2πf(L0_i/c_i − start_sample/fs))."""
    s = complex_measurements(dataset, pings)
    spec = np.fft.fft(np.asarray(s, dtype=np.complex128), n=raster["n_fft"], axis=1)
    spec = spec[:, raster["bins"]]
    delay = raster["path0"][pings] / raster["c"][pings] \
        - float(getattr(dataset, "start_sample", 0) or 0) / float(dataset.fs)
    spec *= np.exp(2j * np.pi * raster["freqs"][None, :] * delay[:, None])
    return spec * raster["weights"][pings]


def wavenumbers(raster: dict, pings: np.ndarray) -> np.ndarray:
    """Wavenumber vectors k [n, F, 3] (rad/m) of the selected pings' band."""
    scale = 2 * np.pi * raster["freqs"][None, :] / raster["c"][pings, None]      # [n, F]
    return scale[:, :, None] * raster["look_sum"][pings, None, :]


def pfa(dataset, grid: Grid, *, reference_point=None, band_db: float = DEFAULT_BAND_DB,
        taper: float = DEFAULT_TAPER, eps: float = 1e-6, per_ping_sound_speed: bool = True,
        progress: bool = True, weights: str = DEFAULT_WEIGHTS) -> tuple[np.ndarray, dict]:
    """Polar-format image (complex64 [nx, ny, nz]) and the raster's summary (see :func:`solve`)."""
    import finufft
    _validate(grid, band_db, taper, eps, reference_point, weights)
    raster = polar_samples(dataset, grid, reference_point=reference_point, band_db=band_db,
                           taper=taper, per_ping_sound_speed=per_ping_sound_speed,
                           weights=weights)
    n_pings, n_f = raster["weights"].shape
    spacing = grid.spacing
    # Mode m' of finufft (index i = m' + floor(n/2)) is the voxel at centre + m'·Δ.
    centre = grid.bounds[:, 0] + np.floor(np.asarray(grid.shape) / 2) * spacing
    shift = centre - raster["x0"]
    plan = finufft.Plan(1, grid.shape, eps=float(eps), isign=-1, dtype="complex128")
    image = np.zeros(grid.shape, dtype=np.complex128)
    per_chunk = max(1, MAX_POINTS_PER_NUFFT // n_f)
    bar = progress_bar(n_pings, progress, unit="ping", desc="pfa", leave=False)
    for p0 in range(0, n_pings, per_chunk):
        pings = np.arange(p0, min(p0 + per_chunk, n_pings))
        k = wavenumbers(raster, pings).reshape(-1, 3)
        strengths = phase_referenced(dataset, raster, pings).reshape(-1)
        strengths = strengths * np.exp(-1j * (k @ shift))
        # points k·Δ: finufft folds them into [-π, π), which leaves e^{-i k·Δ m'} unchanged
        pts = [np.ascontiguousarray(np.mod(k[:, a] * spacing[a] + np.pi, 2 * np.pi) - np.pi)
               for a in range(3)]
        plan.setpts(*pts)
        image += plan.execute(strengths)
        bar.update(len(pings))
    bar.close()
    image /= float(np.sum(raster["weights"] * raster["response"][None, :]))
    info = {"reference_point": raster["x0"].tolist(), "n_fft": int(raster["n_fft"]),
            "band_hz": [float(raster["freqs"][0]), float(raster["freqs"][-1])],
            "n_frequencies": int(n_f), "aperture_dim": int(raster["dim"]), "weights": weights,
            "n_polar_samples": int(n_pings * n_f)}
    return image.astype(np.complex64), info


def _patch_counts(patches, reference_point=None) -> tuple[int, int, int]:
    """Blocks per axis of ``patches`` (one-line InputError for a bad value, or for blocks
    together with a ``reference_point``: each block has its own)."""
    counts = (patches,) * 3 if np.ndim(patches) == 0 else tuple(patches)
    if len(counts) != 3 or not all(isinstance(c, (int, np.integer)) and not isinstance(c, bool)
                                   and 1 <= c <= 16 for c in counts):
        raise InputError(f"patches: must be an integer in [1, 16] (blocks per axis) or three "
                         f"of them, got {patches!r}")
    if max(counts) > 1 and reference_point is not None:
        raise InputError("patches: each block has its own reference point; "
                         "give either patches or reference_point")
    return tuple(int(c) for c in counts)


def patch_grids(grid: Grid, patches) -> list[tuple[tuple[slice, slice, slice], Grid]]:
    """The grid cut into ``patches`` blocks per axis (an int, or one per axis; as equal as
    the voxel counts allow): [(index slices into the grid, the block's own Grid)], every
    voxel in exactly one block."""
    axes = grid.axes()
    cuts = [np.array_split(np.arange(n), min(c, n))
            for n, c in zip(grid.shape, _patch_counts(patches))]
    out = []
    for ix in cuts[0]:
        for iy in cuts[1]:
            for iz in cuts[2]:
                idx = (ix, iy, iz)
                bounds = [[axes[a][i[0]], axes[a][i[-1]]] for a, i in enumerate(idx)]
                out.append((tuple(slice(i[0], i[-1] + 1) for i in idx),
                            Grid(np.asarray(bounds), tuple(len(i) for i in idx))))
    return out


def solve(dataset, grid: Grid, *, reference_point=None, band_db: float = DEFAULT_BAND_DB,
          taper: float = DEFAULT_TAPER, eps: float = 1e-6, per_ping_sound_speed: bool = True,
          progress: bool = True, patches: int = 1, weights: str = DEFAULT_WEIGHTS):
    """Polar-format reconstruction of ``dataset`` on ``grid``.

    reference_point: [3] metres, the phase (motion-compensation) centre; default the grid
        centre. The far-field approximation is exact there and degrades away from it.
    band_db: keep the frequencies whose pulse power is within this many dB of the peak.
    taper: Tukey ratio of the window over the band (0 = none, 1 = Hann).
    eps: finufft tolerance. per_ping_sound_speed: as in backprojection.
    patches: sub-patch processing: the grid is cut into this many blocks per axis (an int or
        one per axis) and each
        block imaged with its own reference point (its centre), so the far-field error grows
        with the distance from the nearest block centre rather than from the grid's centre
        (cost: one non-uniform FFT of all samples per block). Excludes ``reference_point``.
    weights: 'density' (|k|^D·ΔΩ, the polar raster's Jacobian) or 'uniform' (every polar
        sample alike: backprojection's sum); module docstring, step 4.
    Returns a :class:`~sonarsim.dataset.Volume` (complex64 [nx, ny, nz], method 'pfa').
    """
    from sonarsim.dataset import Volume
    counts = _patch_counts(patches, reference_point)
    if max(counts) == 1:
        image, info = pfa(dataset, grid, reference_point=reference_point, band_db=band_db,
                          taper=taper, eps=eps, per_ping_sound_speed=per_ping_sound_speed,
                          progress=progress, weights=weights)
    else:
        _validate(grid, band_db, taper, eps, None, weights)
        image = np.zeros(grid.shape, dtype=np.complex64)
        blocks = patch_grids(grid, patches)
        for index, block in blocks:
            image[index], info = pfa(dataset, block, band_db=band_db, taper=taper, eps=eps,
                                     per_ping_sound_speed=per_ping_sound_speed,
                                     progress=progress, weights=weights)
        info = {**info, "reference_point": None, "patches": list(counts),
                "n_blocks": len(blocks)}
    params = {"band_db": float(band_db), "taper": float(taper), "eps": float(eps),
              "per_ping_sound_speed": bool(per_ping_sound_speed),
              "n_pings": int(len(dataset.waveforms)), **info}
    return Volume(volume=image, bounds=np.asarray(grid.bounds, dtype=np.float64),
                  method="pfa", params=params)
