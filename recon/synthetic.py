"""Reference data: analytic point-scatterer datasets, for the tests, the benchmarks and sanity
checks of reconstructors. Not used by the package itself (like :mod:`recon.straightforward`;
tests/test_layout.py checks it); it lives in the package because the benchmarks use it too.

Each ping's waveform is the sum over scatterers of ``amplitude · pulse`` delayed by the
round-trip time (|p − tx| + |p − rx|)/c, built with :func:`sonarsim.signals.fractional_delay`
and honouring ``start_sample`` (sample k is at time (start_sample + k)/fs). No spreading
loss, beam pattern or occlusion: the ideal single-scattering model that every
reconstructor here should invert.
"""
from __future__ import annotations

import numpy as np

from sonarsim.errors import InputError
from sonarsim.signals import AIRSAS_FS


def circular_poses(n_angles: int, radius: float = 0.85, heights=(0.1,),
                   offset=(0.0, -0.013, -0.038), target=(0.0, 0.0, 0.1)):
    """A turntable-like trajectory: ``n_angles`` TX positions on a circle of ``radius`` at each
    of ``heights`` (height-major, N = n_angles·len(heights)), RX displaced by ``offset`` in
    the rotating rig frame (defaults mimic AirSAS: 13 mm further out, 38 mm lower),
    boresights at ``target``. Returns (tx, rx, boresight), each [N, 3]."""
    heights = np.atleast_1d(np.asarray(heights, dtype=np.float64))
    ang = np.tile(np.linspace(0.0, 2 * np.pi, n_angles, endpoint=False), len(heights))
    z = np.repeat(heights, n_angles)
    c, s = np.cos(ang), np.sin(ang)
    radial = np.stack([c, s, np.zeros_like(c)], axis=1)
    tangent = np.stack([-s, c, np.zeros_like(c)], axis=1)
    tx = radial * radius + z[:, None] * np.array([0.0, 0.0, 1.0])
    rx = tx + radial * (-offset[1]) + tangent * offset[0] + np.array([0.0, 0.0, offset[2]])
    b = np.asarray(target, dtype=np.float64) - tx
    return tx, rx, b / np.linalg.norm(b, axis=1, keepdims=True)


def point_echoes(points, amplitudes, tx, rx, pulse, fs: float, sound_speed: float,
                 n_samples: int, start_sample: int = 0) -> np.ndarray:
    """Waveforms [N, n_samples] float32 of point scatterers ``points`` [P,3] (``amplitudes`` [P])."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    amplitudes = np.broadcast_to(np.asarray(amplitudes, dtype=np.float64), len(points))
    pulse = np.asarray(pulse, dtype=np.float64)
    from sonarsim import signals
    # Delay in a record long enough that the circular shift never wraps into the window.
    n_fft = int(start_sample + n_samples + 2 * len(pulse))
    base = np.zeros(n_fft)
    base[:len(pulse)] = pulse
    out = np.zeros((len(tx), n_samples))
    for p, a in zip(points, amplitudes):
        path = np.linalg.norm(p - tx, axis=1) + np.linalg.norm(p - rx, axis=1)
        delay = path / sound_speed * fs
        if np.any(delay >= n_fft - len(pulse)):
            raise InputError("point_echoes: echo arrives after the record; increase n_samples")
        echoes = signals.fractional_delay(np.tile(base, (len(tx), 1)), delay, axis=-1)
        out += a * echoes[:, start_sample:start_sample + n_samples]
    return out.astype(np.float32)


def point_dataset(points, amplitudes=1.0, n_pings: int = 90, *, heights=(0.1,), pulse=None, fs: float = AIRSAS_FS,
                  sound_speed: float = 343.0, n_samples: int | None = None,
                  start_sample: int | None = None, poses=None, scene_box=None):
    """A :class:`sonarsim.dataset.SonarDataset` of point scatterers on a circular scan
    (``n_pings`` angles at each of ``heights``).

    Defaults: the reference's 20 kHz LFM, a cropped window that covers the scene
    (``start_sample`` > 0, so the time origin is exercised). ``scene_box`` (a SceneBox or
    [3, 2] bounds) is stored as meta ``box`` = [[x0, x1], [y0, y1], [z0, z1]], as the importers do.
    """
    from sonarsim import signals
    from sonarsim.dataset import SonarDataset
    if pulse is None:
        pulse = signals.named_pulse("lfm-20k", fs)
    tx, rx, bore = circular_poses(n_pings, heights=heights) if poses is None else poses
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    paths = (np.linalg.norm(pts[None] - tx[:, None], axis=2)
             + np.linalg.norm(pts[None] - rx[:, None], axis=2))
    if start_sample is None:
        start_sample = max(int(np.floor((paths.min() - 0.3) / sound_speed * fs)), 0)
    if n_samples is None:
        n_samples = int(np.ceil((paths.max() + 0.3) / sound_speed * fs)) + len(pulse) - start_sample
    w = point_echoes(pts, amplitudes, tx, rx, pulse, fs, sound_speed, n_samples, start_sample)
    meta = {"scene": "analytic point scatterers", "points": pts.tolist()}
    if scene_box is not None:
        lo, hi = (np.asarray(scene_box.lo), np.asarray(scene_box.hi)) if hasattr(scene_box, "lo") \
            else np.asarray(scene_box, dtype=np.float64).T
        meta["box"] = np.stack([np.asarray(lo, float), np.asarray(hi, float)], axis=1).tolist()
    return SonarDataset(waveforms=w, tx=tx, rx=rx, boresight=bore,
                        pulse=np.asarray(pulse, dtype=np.float64), fs=float(fs),
                        sound_speed=float(sound_speed), source="synthetic:point",
                        start_sample=int(start_sample), meta=meta)
