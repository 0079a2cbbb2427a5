"""Quick-look pictures of a :class:`~sonarsim.dataset.SonarDataset`.

:func:`plot_dataset` writes into a directory:

- ``echo_raw.png`` / ``echo_raw.exr``: the echo image, ping (rows) × time sample (columns).
  The PNG shows the envelope |analytic(waveform)| in dB re its maximum; the EXR keeps the
  raw float32 waveform samples (channel ``Y``).
- ``echo_mf.png`` / ``echo_mf.exr``: the same for the matched-filtered analytic signal
  (:func:`sonarsim.signals.matched_filter`, the same linear filter the reconstructions use); EXR channel ``Y`` = magnitude (plus ``re``, ``im`` with
  ``complex_exr``).
- ``pulse.png``: the pulse against time and its spectrum in dB.
- ``trajectory.png``: TX and RX positions seen from above (x, y) and from the side (distance
  from the rotation axis, z), each at equal scale on both axes, with the scene box, a few TX
  boresights and the ground-truth mesh when the dataset has one.
- for a dataset that keeps its transients, the pictures of :mod:`sonarsim.plot_transients`.

PNG echo images of more than ``MAX_PNG_ROWS`` pings show the maximum over groups of
consecutive pings (the axis stays in ping index). Horizontal axes of the echo images are the
**one-way range c·t/2** (metres), with the round-trip path c·t on the top axis;
t = (start_sample + k)/fs is the time after transmission.
In the EXR files row i is ping i and column k is sample k (its time is in the header).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import geometry, signals
from .errors import InputError
from .figures import MAX_PNG_ROWS, max_pool_rows, ping_group, save_figure, to_db, write_exr
from .plot_transients import check_profile_pings, plot_transients

_MF_CHUNK = 2048        # pings per matched-filter FFT batch (bounds memory for big scans)
_MAX_TRAJECTORY_POINTS = 4000


def echo_images(waveforms: np.ndarray, pulse: np.ndarray, max_rows: int = MAX_PNG_ROWS,
                keep_complex: bool = False) -> dict[str, np.ndarray]:
    """Envelopes and matched-filter outputs of ``waveforms`` [N, T], computed in ping batches.

    Complex ``waveforms`` are already pulse-compressed analytic signals (a deconvolved
    dataset): they are shown as they are, not matched-filtered again.
    Returns ``raw_rows`` and ``mf_rows`` (float32 [R, T], R <= max_rows): the envelope
    |analytic(waveform)| and the matched-filter magnitude, each max-pooled over groups of
    ceil(N / max_rows) consecutive pings (for the PNGs); ``mf`` (float32 [N, T]) the full
    matched-filter magnitude; with ``keep_complex`` also ``mf_re``/``mf_im`` [N, T].
    """
    n, t = waveforms.shape
    group = ping_group(n, max_rows)
    rows = -(-n // group)
    chunk = group * max(1, _MF_CHUNK // group)
    pulse = np.asarray(pulse, dtype=np.float64)[:t]
    out = {"raw_rows": np.empty((rows, t), np.float32), "mf_rows": np.empty((rows, t), np.float32),
           "mf": np.empty((n, t), np.float32)}
    if keep_complex:
        out["mf_re"] = np.empty((n, t), np.float32)
        out["mf_im"] = np.empty((n, t), np.float32)

    compressed = np.iscomplexobj(waveforms)   # deconvolved analytic signals: no second filter
    for start in range(0, n, chunk):
        if compressed:
            block = waveforms[start:start + chunk].astype(np.complex128)
            envelope, mf = np.abs(block), block
        else:
            block = waveforms[start:start + chunk].astype(np.float64)
            envelope = np.abs(signals.analytic(block))
            mf = signals.matched_filter(block, pulse)
        r0, r1 = start // group, -(-(start + len(block)) // group)
        out["raw_rows"][r0:r1] = max_pool_rows(envelope, group)
        mag = np.abs(mf).astype(np.float32)
        out["mf"][start:start + len(block)] = mag
        out["mf_rows"][r0:r1] = max_pool_rows(mag, group)
        if keep_complex:
            out["mf_re"][start:start + len(block)] = mf.real
            out["mf_im"][start:start + len(block)] = mf.imag
    out["group"] = group
    return out


def _range_axis(ds) -> tuple[float, float]:
    """One-way range (m) at the first and last sample: c·(start_sample + k)/fs / 2."""
    n = ds.waveforms.shape[1]
    first = ds.start_sample * ds.sound_speed / ds.fs / 2.0
    last = (ds.start_sample + n - 1) * ds.sound_speed / ds.fs / 2.0
    return first, last


def _echo_figure(image_db: np.ndarray, ds, title: str, dynamic_range_db: float, group: int):
    from matplotlib.figure import Figure

    r0, r1 = _range_axis(ds)
    half_bin = 0.25 * ds.sound_speed / ds.fs
    n = image_db.shape[0] * group
    fig = Figure(figsize=(8, 6))
    ax = fig.add_subplot()
    im = ax.imshow(image_db, aspect="auto", origin="upper", cmap="viridis",
                   vmin=-dynamic_range_db, vmax=0.0, interpolation="antialiased",
                   extent=(r0 - half_bin, r1 + half_bin, n - 0.5, -0.5))
    ax.set_xlabel("one-way range c·t/2 [m]  (t after transmission)")
    ax.set_ylabel("ping index" + (f" (max over groups of {group})" if group > 1 else ""))
    top = ax.secondary_xaxis("top", functions=(lambda r: 2.0 * r, lambda p: 0.5 * p))
    top.set_xlabel("round-trip path c·t [m]")
    ax.set_title(f"{title}\n{ds.source}, c = {ds.sound_speed:.2f} m/s, fs = {ds.fs / 1e3:g} kHz",
                 fontsize=9)
    fig.colorbar(im, ax=ax, label="dB re max")
    fig.tight_layout()
    return fig


def _pulse_figure(pulse: np.ndarray, fs: float):
    from matplotlib.figure import Figure

    p = np.asarray(pulse, dtype=np.float64)
    fig = Figure(figsize=(10, 4))
    ax_t, ax_f = fig.subplots(1, 2)
    ax_t.plot(np.arange(p.size) / fs * 1e3, p, lw=1)
    ax_t.set_xlabel("time [ms]")
    ax_t.set_ylabel("amplitude")
    ax_t.set_title(f"pulse ({p.size} samples at {fs / 1e3:g} kHz)")
    n_fft = max(4096, int(2 ** np.ceil(np.log2(p.size))))
    spectrum = np.abs(np.fft.rfft(p, n_fft))
    freq = np.fft.rfftfreq(n_fft, 1.0 / fs)
    ax_f.plot(freq / 1e3, to_db(spectrum, 80.0), lw=1)
    ax_f.set_xlabel("frequency [kHz]")
    ax_f.set_ylabel("magnitude [dB re max]")
    ax_f.set_ylim(-80, 3)
    ax_f.set_title("spectrum")
    ax_f.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _trajectory_figure(ds, box: "geometry.SceneBox"):
    """Top view (x, y) and side view (distance from the rotation axis, z), both at equal
    scale on the two axes: a 3-D view at true scale flattens the scan's few centimetres of
    height against its 1.7 m diameter, and one with stretched z misstates the geometry."""
    from matplotlib.figure import Figure

    n = ds.tx.shape[0]
    step = max(1, n // _MAX_TRAJECTORY_POINTS)
    tx, rx = ds.tx[::step], ds.rx[::step]
    radius = lambda p: np.hypot(p[..., 0], p[..., 1])          # noqa: E731
    lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
    fig = Figure(figsize=(12, 5.5), layout="constrained")
    ax_top, ax_side = fig.subplots(1, 2, width_ratios=[1, 1.3])

    ax_top.scatter(tx[:, 0], tx[:, 1], s=3, c="tab:red", label="TX")
    ax_top.scatter(rx[:, 0], rx[:, 1], s=3, c="tab:blue", label="RX")
    ax_top.add_patch(_rectangle(lo[:2], hi[:2]))
    ax_side.scatter(radius(tx), tx[:, 2], s=3, c="tab:red", label="TX")
    ax_side.scatter(radius(rx), rx[:, 2], s=3, c="tab:blue", label="RX")
    corner = np.max(np.abs(np.stack([lo[:2], hi[:2]])), axis=0)
    r_box = float(np.hypot(*corner))
    ax_side.add_patch(_rectangle([0.0, lo[2]], [r_box, hi[2]]))

    arrows = np.linspace(0, n - 1, min(n, 12)).astype(int)
    length = 0.25 * float(np.linalg.norm(ds.tx[0] - np.asarray(box.center)))
    b = ds.boresight[arrows] * length
    ax_top.quiver(ds.tx[arrows, 0], ds.tx[arrows, 1], b[:, 0], b[:, 1], color="tab:orange",
                  angles="xy", scale_units="xy", scale=1, width=0.004, label="TX boresight")
    # In the side view the boresight's horizontal part points at the axis (radius shrinks).
    b_r = np.sum(ds.boresight[arrows, :2] * ds.tx[arrows, :2], axis=1) / np.maximum(
        radius(ds.tx[arrows]), 1e-12) * length
    ax_side.quiver(radius(ds.tx[arrows]), ds.tx[arrows, 2], b_r, b[:, 2], color="tab:orange",
                   angles="xy", scale_units="xy", scale=1, width=0.004, label="TX boresight")
    if getattr(ds, "gt_vertices", None) is not None and len(ds.gt_vertices):
        v = np.asarray(ds.gt_vertices)
        v = v[:: max(1, len(v) // 3000)]
        ax_top.scatter(v[:, 0], v[:, 1], s=1, c="0.4", label="ground-truth mesh")
        ax_side.scatter(radius(v), v[:, 2], s=1, c="0.4", label="ground-truth mesh")
    ax_side.axhline(0.0, c="0.6", lw=0.8, ls=":", label="turntable z = 0")

    for ax in (ax_top, ax_side):
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    ax_side.legend(loc="best", fontsize=8)          # the same symbols in both views
    ax_top.set_xlabel("x [m]")
    ax_top.set_ylabel("y [m]")
    ax_top.set_title(f"top view: {n} pings, the scene box (black)", fontsize=9)
    ax_side.set_xlabel("horizontal distance from the rotation axis (z axis) [m]")
    ax_side.set_ylabel("z [m]")
    heights = np.unique(np.round(ds.tx[:, 2], 6))
    ax_side.set_title(f"side view, same scale on both axes: TX at {len(heights)} height(s) "
                      f"{heights.min():.3f} .. {heights.max():.3f} m; box z "
                      f"{lo[2]:g} .. {hi[2]:g} m", fontsize=9)
    return fig


def _rectangle(lo, hi):
    from matplotlib.patches import Rectangle
    return Rectangle(tuple(lo), float(hi[0] - lo[0]), float(hi[1] - lo[1]), fill=False,
                     ec="k", lw=0.9, label="scene box")


def default_box(ds) -> "geometry.SceneBox":
    """The scene box recorded in ``ds.meta['box']``, else the usual box of its source kind."""
    from .dataset import declared_scene_box
    fallback = geometry.AIRSAS_REAL_BOX if str(ds.source).startswith("airsas") \
        else geometry.SIM_BOX
    return declared_scene_box(ds, fallback)


def plot_dataset(ds, out_dir: str | Path, *, box: "geometry.SceneBox | None" = None,
                 dynamic_range_db: float = 60.0, complex_exr: bool = False,
                 profile_pings=None) -> list[Path]:
    """Write the echo images, pulse and trajectory pictures of ``ds`` into ``out_dir``.

    Returns the written paths. ``dynamic_range_db`` (> 0) sets the PNG colour range;
    ``complex_exr`` adds the matched filter's real and imaginary parts to ``echo_mf.exr``.
    A dataset that keeps its transients also gets the pictures of
    :func:`sonarsim.plot_transients.plot_transients` (``profile_pings`` passed on).
    """
    if getattr(ds, "transients", None) is not None:
        check_profile_pings(profile_pings, ds.transients.n_pings)
    if not (np.isfinite(dynamic_range_db) and dynamic_range_db > 0):
        raise InputError(f"dynamic range must be > 0 dB, got {dynamic_range_db}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    box = default_box(ds) if box is None else box
    waveforms = np.asarray(ds.waveforms)
    waveforms = waveforms.astype(np.complex64 if np.iscomplexobj(waveforms) else np.float32)
    r0, r1 = _range_axis(ds)
    axis_note = (f"rows = pings 0..{waveforms.shape[0] - 1}; column k = sample start_sample+k "
                 f"(start_sample {ds.start_sample}) at t = (start_sample+k)/fs, fs = {ds.fs} Hz, "
                 f"c = {ds.sound_speed} m/s; one-way range {r0:.6g}..{r1:.6g} m")
    images = echo_images(waveforms, ds.pulse, keep_complex=complex_exr)
    group = images["group"]
    written = [
        save_figure(_echo_figure(to_db(images.pop("raw_rows"), dynamic_range_db), ds,
                                 "raw waveforms: envelope", dynamic_range_db, group),
                    out / "echo_raw.png"),
        write_exr(out / "echo_raw.exr", {"Y": waveforms.real},
                  ("real part of the deconvolved analytic waveforms" if np.iscomplexobj(waveforms)
                   else "raw waveforms") + f"; {axis_note}"),
        save_figure(_echo_figure(to_db(images.pop("mf_rows"), dynamic_range_db), ds,
                                 "deconvolved analytic signal" if np.iscomplexobj(waveforms)
                                 else "matched-filtered analytic signal", dynamic_range_db, group),
                    out / "echo_mf.png"),
    ]
    channels = {"Y": images.pop("mf")}
    if complex_exr:
        channels.update(re=images.pop("mf_re"), im=images.pop("mf_im"))
    written.append(write_exr(out / "echo_mf.exr", channels,
                             "matched-filtered analytic signal (Y = magnitude"
                             + (", re/im = complex value" if complex_exr else "")
                             + f"); {axis_note}"))
    del images, channels

    written.append(save_figure(_pulse_figure(ds.pulse, ds.fs), out / "pulse.png"))
    written.append(save_figure(_trajectory_figure(ds, box), out / "trajectory.png"))
    if getattr(ds, "transients", None) is not None:
        written += plot_transients(ds.transients, out, dynamic_range_db=dynamic_range_db,
                                   pings=profile_pings)
    return written
