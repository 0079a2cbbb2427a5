"""Checks every reconstruction path makes before any large array exists.

The command line (``recon backproject|pfa|gd|nbp``), ``sonarsim batch``'s reconstruction
steps (:mod:`recon.batch_step`) and the Python API call the same functions:

* :func:`check_grid_memory` refuses a grid whose voxels alone cannot fit (a memory estimate
  in the style of :mod:`sonarsim.limits`; a solver module may declare its own
  ``BYTES_PER_VOXEL``, see :func:`bytes_per_voxel_of`);
* :func:`check_signal` refuses a dataset whose pulse is all zero (matched filtering would zero
  every echo) and warns about all-zero waveforms;
* :func:`check_grid_sees_data` refuses a grid that no ping's recorded window reaches
  (``--bounds`` far from the scan, a wrong ``start_sample``).

Each of these used to give an all-zero volume with exit 0.
"""
from __future__ import annotations

import sys
from typing import Callable

import numpy as np

from sonarsim.errors import InputError

from .grid import Grid

BYTES_PER_VOXEL = 16   # the least any solver needs: the complex64 result and its copy
GRID_HINT = "use a coarser --voxel-size, a smaller --shape or tighter --bounds"


def bytes_per_voxel_of(module) -> float:
    """The bytes per voxel a solver module declares (``BYTES_PER_VOXEL``), else the least any
    solver needs (:data:`BYTES_PER_VOXEL`)."""
    return float(getattr(module, "BYTES_PER_VOXEL", BYTES_PER_VOXEL))


def check_grid_memory(grid: Grid, bytes_per_voxel: float = BYTES_PER_VOXEL, extra: float = 0,
                      what: str = "the volume", detail: str = "",
                      hint: str = GRID_HINT) -> None:
    """Refuse a grid whose estimated memory exceeds the limit (one line, before allocating)."""
    from sonarsim import limits
    nx, ny, nz = grid.shape
    voxels = nx * ny * nz            # Python ints: no overflow for absurd shapes
    need = voxels * bytes_per_voxel + extra
    limits.check_memory(need, what, detail or f"{nx} x {ny} x {nz} voxels x "
                                              f"{bytes_per_voxel:g} bytes", hint)


def check_signal(ds, label, warn: Callable[[str], None] | None = None,
                 refuse_silence: str | None = None) -> None:
    """Refuse an all-zero pulse (InputError); warn (``warn``, default stderr) about all-zero
    waveforms, or refuse them with ``refuse_silence`` as the reason (commands that fit the
    waveforms, for which silence leaves nothing to do)."""
    from . import measurements
    deconvolved = getattr(measurements, "is_deconvolved", lambda d: False)(ds)
    if not deconvolved and not np.any(np.asarray(ds.pulse)):
        raise InputError(f"{label}: the dataset's pulse is all zero; matched filtering would "
                         "turn every echo into zeros (fix the pulse of the dataset)")
    if not np.any(np.asarray(ds.waveforms)):
        if refuse_silence:
            raise InputError(f"{label}: every waveform sample is zero; {refuse_silence}")
        message = f"warning: {label}: every waveform sample is zero; the volume will be all zero"
        (warn or (lambda m: print(m, file=sys.stderr)))(message)


def _distance_to_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance [N] from points [N, 3] to the axis-aligned box [lo, hi] (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)


def _farthest_corner(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance [N] from points [N, 3] to the farthest corner of the box [lo, hi]."""
    return np.linalg.norm(np.maximum(np.abs(points - lo), np.abs(points - hi)), axis=1)


def check_grid_sees_data(ds, grid: Grid) -> None:
    """Refuse a grid that lies outside every ping's recorded window (InputError).

    For each ping the round-trip paths tx -> voxel -> rx over the grid's box lie within
    [d(tx, box) + d(rx, box), far(tx) + far(rx)]; sample k of a waveform is the path
    c·(start_sample + k)/fs. If these intervals are disjoint for every ping, no voxel can
    receive anything and the result would be an all-zero volume.
    """
    lo, hi = grid.bounds[:, 0], np.where(np.asarray(grid.shape) > 1, grid.bounds[:, 1],
                                         grid.bounds[:, 0])
    check_box_sees_data(ds, lo, hi, "no voxel of the grid", "check --bounds and the dataset's "
                        "start_sample (the volume would be all zero)")


def check_box_sees_data(ds, lo, hi, what: str = "nothing in the box", hint: str = "") -> None:
    """Refuse an axis-aligned box [lo, hi] (m) that lies outside every ping's recorded window
    (InputError starting with ``what``, ending with ``hint``); see :func:`check_grid_sees_data`."""
    from . import measurements
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    tx, rx = np.asarray(ds.tx, float), np.asarray(ds.rx, float)
    near = _distance_to_box(tx, lo, hi) + _distance_to_box(rx, lo, hi)
    far = _farthest_corner(tx, lo, hi) + _farthest_corner(rx, lo, hi)
    c = measurements.sound_speeds(ds)
    k0, t = int(ds.start_sample), np.asarray(ds.waveforms).shape[1]
    first, last = c * k0 / ds.fs, c * (k0 + t - 1) / ds.fs
    if np.any((near <= last) & (far >= first)):
        return
    raise InputError(
        f"{what} lies within what any ping recorded: round-trip paths to it are "
        f"{near.min():.3f} .. {far.max():.3f} m, the waveforms cover "
        f"{first.min():.3f} .. {last.max():.3f} m (samples {k0} .. {k0 + t - 1} at "
        f"{ds.fs:g} Hz); {hint}")


def check_grid(ds, grid: Grid, bytes_per_voxel: float = BYTES_PER_VOXEL) -> Grid:
    """Both grid checks (memory, then data coverage); returns ``grid``."""
    check_grid_memory(grid, bytes_per_voxel)
    check_grid_sees_data(ds, grid)
    return grid
