"""Quick-look pictures of :class:`~sonarsim.dataset.Transients` (``sonarsim render`` output).

:func:`plot_transients` writes into a directory:

- ``transients.png``: one panel per bounce, ping index (rows) × round-trip path length
  (columns, metres; time after transmission on the top axis), energy per bin in dB
  (10·log10) re the maximum over all bounces, floored at −``dynamic_range_db``.
  More than ``MAX_PNG_ROWS`` pings are max-pooled over groups of consecutive pings.
- ``transients_bounce<b>.exr`` (b = 1..B): channel ``Y`` = the stored float32 energies of
  bounce b, row i = ping i, column j = path-length bin j (axis in the EXR ``comments``).
- ``transients_energy.png``: each bounce's share of the total energy (linear axis, the
  energy summed over pings and bins in the labels) and the energy of each ping per bounce
  (dB re the largest).
- ``transients_profiles.png``: energy against path length per bounce for a few pings.

Energies are those of the file (per path-length bin; see docs/formats.md), so the total of
a bounce is a plain sum.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .dataset import Transients
from .errors import InputError
from .figures import MAX_PNG_ROWS, max_pool_rows, ping_group, save_figure, to_db, write_exr

DEFAULT_PROFILE_PINGS = 4
_MAX_PANEL_COLUMNS = 3


def energy_per_ping(tr: Transients) -> np.ndarray:
    """Energy of each ping and bounce summed over path-length bins, float64 [N, B]."""
    return tr.transients.sum(axis=2, dtype=np.float64)


def energy_per_bounce(tr: Transients) -> np.ndarray:
    """Energy of each bounce summed over pings and bins, float64 [B]."""
    return energy_per_ping(tr).sum(axis=0)


def energy_lines(tr: Transients) -> list[str]:
    """One line per bounce: its total energy and share of the total (for the CLI)."""
    energy = energy_per_bounce(tr)
    total = float(energy.sum())
    return [f"bounce {b + 1}: energy {e:.6e} ({100.0 * e / total if total > 0 else 0.0:.2f} %)"
            for b, e in enumerate(energy)]


def default_profile_pings(n_pings: int, count: int = DEFAULT_PROFILE_PINGS) -> np.ndarray:
    """``count`` ping indices spread evenly from the first to the last ping."""
    return np.unique(np.linspace(0, n_pings - 1, min(n_pings, count)).round().astype(int))


def check_profile_pings(pings, n_pings: int) -> np.ndarray:
    """Validated ping indices int [K] for the profile plot (None -> the default choice)."""
    if pings is None:
        return default_profile_pings(n_pings)
    arr = np.asarray(pings).ravel()
    if arr.size == 0 or arr.dtype.kind not in "iu" or arr.min() < 0 or arr.max() >= n_pings:
        raise InputError(f"profile pings must be integers in 0..{n_pings - 1}, "
                         f"got {arr.tolist()}")
    return arr


def _check_transients(tr) -> Transients:
    if not isinstance(tr, Transients):
        raise InputError(f"expected a Transients object (from sonarsim render), "
                         f"got {type(tr).__name__}")
    return tr


def _time_axis(ax, tr: Transients) -> None:
    c = tr.sound_speed
    top = ax.secondary_xaxis("top", functions=(lambda p: p / c * 1e3, lambda t: t * c / 1e3))
    top.set_xlabel("time after transmission [ms]", fontsize=8)


def _panel_columns(n_panels: int) -> int:
    return 2 if n_panels == 4 else min(n_panels, _MAX_PANEL_COLUMNS)


def _panel_grid(fig, n_panels: int):
    cols = _panel_columns(n_panels)
    rows = -(-n_panels // cols)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    return axes[:n_panels]


def _image_figure(tr: Transients, per_bounce: np.ndarray, dynamic_range_db: float,
                  max_rows: int):
    from matplotlib.figure import Figure

    group = ping_group(tr.n_pings, max_rows)
    pooled = np.stack([max_pool_rows(tr.transients[:, b, :], group)
                       for b in range(tr.n_bounces)])
    image_db = to_db(pooled, dynamic_range_db, power=True)    # re the max over all bounces
    del pooled
    total = per_bounce.sum()
    share = per_bounce / total if total > 0 else per_bounce
    cols = _panel_columns(tr.n_bounces)
    fig = Figure(figsize=(4.5 * cols + 1.0, 4.5 * -(-tr.n_bounces // cols) + 0.4),
                 layout="constrained")  # keeps the suptitle clear of the top time axes
    extent = (tr.path_start, tr.path_end, image_db.shape[1] * group - 0.5, -0.5)
    panels = _panel_grid(fig, tr.n_bounces)
    for b, ax in enumerate(panels):
        im = ax.imshow(image_db[b], aspect="auto", origin="upper", cmap="viridis",
                       vmin=-dynamic_range_db, vmax=0.0, interpolation="antialiased",
                       extent=extent)
        ax.set_title(f"bounce {b + 1} ({100 * share[b]:.1f} % of the energy)", fontsize=9)
        ax.set_xlabel("round-trip path length [m]")
        _time_axis(ax, tr)
        if b % cols == 0:
            ax.set_ylabel("ping index" + (f" (max over {group})" if group > 1 else ""))
    fig.colorbar(im, ax=list(panels), label="energy per bin [dB re max over all bounces]")
    fig.suptitle(f"transients: {tr.n_pings} pings, bin {tr.path_bin_width * 1e3:.3g} mm, "
                 f"c = {tr.sound_speed:.2f} m/s", fontsize=10)
    return fig


def _energy_figure(tr: Transients, per_ping: np.ndarray):
    """Left: each bounce's share of the total energy on a linear axis (a log axis would make
    a 1 % bounce look comparable to a 98 % one), annotated with the energy itself. Right: the
    energy of each ping per bounce in dB re the largest, where the spread is the point."""
    from matplotlib.figure import Figure

    per_bounce = per_ping.sum(axis=0)
    bounces = np.arange(1, tr.n_bounces + 1)
    total = float(per_bounce.sum())
    share = 100.0 * per_bounce / total if total > 0 else np.zeros_like(per_bounce)
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax_b, ax_p = fig.subplots(1, 2)
    ax_b.bar(bounces, share, color="tab:blue")
    for b, e, pct in zip(bounces, per_bounce, share):
        ax_b.annotate(f"{pct:.1f} %\n({e:.3g})", (b, pct), ha="center", va="bottom", fontsize=8)
    ax_b.set_ylim(0, 115)
    ax_b.set_xticks(bounces)
    ax_b.set_xlabel("bounce")
    ax_b.set_ylabel("share of the total energy [%] (linear)")
    ax_b.set_title("energy per bounce (in brackets: summed over pings and bins)", fontsize=9)
    pings = np.arange(tr.n_pings)
    reference = float(per_ping.max()) if per_ping.size else 0.0
    for b in range(tr.n_bounces):
        e = per_ping[:, b]
        if np.any(e > 0):
            ax_p.plot(pings, np.where(e > 0, to_db(e, 200.0, power=True, reference=reference),
                                      np.nan), lw=0.8, label=f"bounce {b + 1}")
    if ax_p.lines:
        ax_p.legend(fontsize=8)
    ax_p.set_xlabel("ping index")
    ax_p.set_ylabel("energy summed over bins [dB re the largest]")
    ax_p.set_title("energy per ping", fontsize=9)
    ax_p.grid(True, alpha=0.3)
    return fig


def _profiles_figure(tr: Transients, pings: np.ndarray, dynamic_range_db: float):
    from matplotlib.figure import Figure

    reference = float(tr.transients.max())
    paths = tr.path_lengths()
    cols = _panel_columns(len(pings))
    fig = Figure(figsize=(5.0 * cols, 3.5 * -(-len(pings) // cols)), layout="constrained")
    panels = _panel_grid(fig, len(pings))
    for ping, ax in zip(pings, panels):
        for b in range(tr.n_bounces):
            ax.plot(paths, to_db(tr.transients[ping, b], dynamic_range_db, power=True,
                                 reference=reference), lw=0.8, label=f"bounce {b + 1}")
        ax.set_ylim(-dynamic_range_db - 3, 3)
        ax.set_title(f"ping {ping}", fontsize=9)
        ax.set_xlabel("round-trip path length [m]")
        ax.set_ylabel("energy per bin [dB re max]")
        ax.grid(True, alpha=0.3)
        _time_axis(ax, tr)
    panels[0].legend(fontsize=8)
    return fig


def _exr_note(tr: Transients, bounce: int) -> str:
    return (f"bounce {bounce} transients (energy per path-length bin); rows = pings "
            f"0..{tr.n_pings - 1}; column j = round-trip path [path_start + j*w, "
            f"path_start + (j+1)*w), path_start = {tr.path_start!r} m, w = "
            f"{tr.path_bin_width!r} m; c = {tr.sound_speed!r} m/s, fs = {tr.fs!r} Hz, "
            f"oversample = {tr.oversample}")


def plot_transients(tr: Transients, out_dir: str | Path, *, dynamic_range_db: float = 60.0,
                    pings=None, max_rows: int = MAX_PNG_ROWS) -> list[Path]:
    """Write the transients pictures (see the module docstring) into ``out_dir``.

    ``dynamic_range_db`` (> 0): dB floor of the images and profiles. ``pings``: ping
    indices of the profile plot (default: a few spread over the scan).
    Returns the written paths.
    """
    tr = _check_transients(tr)
    if not (np.isfinite(dynamic_range_db) and dynamic_range_db > 0):
        raise InputError(f"dynamic range must be > 0 dB, got {dynamic_range_db}")
    pings = check_profile_pings(pings, tr.n_pings)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    per_ping = energy_per_ping(tr)
    image = _image_figure(tr, per_ping.sum(axis=0), dynamic_range_db, max_rows)
    written = [save_figure(image, out / "transients.png")]
    written += [write_exr(out / f"transients_bounce{b + 1}.exr", {"Y": tr.transients[:, b, :]},
                          _exr_note(tr, b + 1)) for b in range(tr.n_bounces)]
    written.append(save_figure(_energy_figure(tr, per_ping), out / "transients_energy.png"))
    written.append(save_figure(_profiles_figure(tr, pings, dynamic_range_db),
                               out / "transients_profiles.png"))
    return written
