"""What a sonarsim file holds and what the readers would refuse in it: a human summary of a
transients, dataset or volume file, and its problems (``sonarsim info``).

Large arrays (transients, waveforms, volume) are read in slabs, so the summary of a
multi-gigabyte file needs little memory. The problems are exactly what the readers refuse
(:func:`describe_and_check` validates a file as they do, also an unfinished ``.partial``
file, which every reader refuses as incomplete).
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from ..errors import InputError
from . import any_kind
from .h5io import INCOMPLETE, KIND_DATASET, KIND_NAMES, KIND_TRANSIENTS, KIND_VOLUME
from .sonar_dataset import SonarDataset
from .transients import Transients
from .volume import Volume, voxel_spacing

_SLAB_BYTES = 64 * 2**20


def describe(path: Path | str) -> list[str]:
    """The summary lines for ``path`` (FormatError if its schema cannot be read)."""
    return describe_and_check(path)[0]


def describe_and_check(path: Path | str) -> tuple[list[str], list[str]]:
    """(summary lines, problems) of ``path``; the problems are what the readers refuse
    (FormatError if not even the schema can be read)."""
    with any_kind.inspect(path, allow_partial=True) as (kind, fields), \
            np.errstate(all="ignore"):
        head = (f"{path}: {KIND_NAMES[kind]} ({kind}, "
                f"format version {fields['format_version']})")
        problems: list[str] = []
        body = {KIND_TRANSIENTS: _transients, KIND_DATASET: _dataset,
                KIND_VOLUME: _volume}[kind](fields, problems)
        problems[:0] = _constructor_problems(kind, fields)
        if not fields["complete"]:
            done = fields.get("pings_done")
            body.insert(0, ("status", "INCOMPLETE: partial output of an unfinished run" + (
                "" if done is None else f", {done} pings written so far")))
            problems.insert(0, INCOMPLETE)
        return [head] + [f"  {key:<22} {value}" for key, value in body], problems


_LARGE = ("waveforms", "transients", "volume")


def _stub(fields: dict) -> dict:
    """The constructor arguments with the large arrays replaced by tiny ones of the same
    dtype and leading size (the constructors then check everything but those values)."""
    out = {}
    for key, value in fields.items():
        if key in ("format_version", "complete", "pings_done"):
            continue
        if key in _LARGE and hasattr(value, "shape"):
            shape = (value.shape[0],) + (1,) * (len(value.shape) - 1)
            value = np.zeros(shape, dtype=value.dtype)
        out[key] = value
    return out


def _constructor_problems(kind: str, fields: dict) -> list[str]:
    """What the typed constructors (as used by every reader) refuse, as one line each."""
    classes = {KIND_TRANSIENTS: Transients, KIND_DATASET: SonarDataset, KIND_VOLUME: Volume}
    args = _stub(fields)
    problems = []
    if kind == KIND_DATASET and args.get("transients") is not None:
        try:
            args["transients"] = Transients(**_stub(args["transients"]))
        except (InputError, TypeError, ValueError) as exc:
            problems.append(f"transients: {exc}")
            args["transients"] = None
    try:
        classes[kind](**args)
    except (InputError, TypeError, ValueError) as exc:
        problems.append(str(exc))
    return problems


# ---- pieces

def _slabs(dset: h5py.Dataset) -> Iterator[np.ndarray]:
    """The dataset in slabs along its first axis, each about _SLAB_BYTES."""
    row = max(1, int(np.prod(dset.shape[1:])) * dset.dtype.itemsize)
    step = max(1, _SLAB_BYTES // row)
    for start in range(0, dset.shape[0], step):
        yield dset[start:start + step]


def _range(values: np.ndarray, unit: str = "m", digits: int = 3) -> str:
    return f"{values.min():.{digits}f} .. {values.max():.{digits}f} {unit}"


def _extent(points: np.ndarray) -> str:
    if len(points) == 0:
        return "(none)"
    lo, hi = points.min(axis=0), points.max(axis=0)
    radius = np.hypot(points[:, 0], points[:, 1])
    axes = "  ".join(f"{a} [{l:+.3f}, {h:+.3f}]" for a, l, h in zip("xyz", lo, hi))
    return f"{axes} m; distance from z axis {_range(radius)}"


def _meta(meta: dict, prefix: str = "meta.") -> list[tuple[str, str]]:
    return [(f"{prefix}{key}", _short(value)) for key, value in sorted(meta.items())]


def _short(value, limit: int = 70) -> str:
    text = np.array2string(value, threshold=8) if isinstance(value, np.ndarray) else repr(value)
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _pulse_band(pulse: np.ndarray, fs: float) -> str:
    """Band where the pulse spectrum is within 6 dB of its peak."""
    n = max(4096, 8 * len(pulse))
    spectrum = np.abs(np.fft.rfft(pulse, n))
    if spectrum.max() <= 0:
        return "all zero"
    freqs = np.fft.rfftfreq(n, 1.0 / fs)
    inside = np.flatnonzero(spectrum >= 0.5 * spectrum.max())
    peak = freqs[np.argmax(spectrum)]
    return (f"-6 dB band {freqs[inside[0]] / 1e3:.2f} .. {freqs[inside[-1]] / 1e3:.2f} kHz, "
            f"peak {peak / 1e3:.2f} kHz")


def _nonfinite(name: str, count: int, first: int | None, problems: list) -> None:
    if count:
        problems.append(f"dataset '{name}' contains {count} NaN or inf values "
                        f"(first in ping {first})")


def _transient_lines(f: dict, problems: list, label: str = "") -> list[tuple[str, str]]:
    data: h5py.Dataset = f["transients"]
    n, b, t = data.shape
    w, c = np.float64(f["path_bin_width"]), np.float64(f["sound_speed"])
    start, end = f["path_start"], f["path_start"] + t * w
    energy = np.zeros(b)
    bad, first, row = 0, None, 0
    for slab in _slabs(data):
        finite = np.isfinite(slab)
        if not finite.all():
            bad += int((~finite).sum())
            first = row + int(np.argmin(finite.reshape(len(slab), -1).all(axis=1))) \
                if first is None else first
        energy += np.where(finite, slab, 0).sum(axis=(0, 2), dtype=np.float64)
        row += len(slab)
    _nonfinite(label + "transients", bad, first, problems)
    energies = ", ".join(f"{i + 1}: {e:.4g}" for i, e in enumerate(energy))
    return [
        (label + "shape", f"N = {n} pings x B = {b} bounces x T = {t} bins (float32)"),
        (label + "path length", f"{start:.4f} .. {end:.4f} m round trip "
                                f"({start / c * 1e3:.3f} .. {end / c * 1e3:.3f} ms)"),
        (label + "bins", f"width {w * 1e3:.4f} mm = c / (fs x {f['oversample']}), "
                         f"fs = {f['fs']:g} Hz, c = {c:g} m/s"),
        (label + "energy/bounce", energies),
    ] + [(label + key, value) for key, value in _meta(f["meta"])]


def _transients(f: dict, problems: list) -> list[tuple[str, str]]:
    return _transient_lines(f, problems) + [("tx positions", _extent(f["tx"])),
                                  ("rx positions", _extent(f["rx"]))]


def _dataset(f: dict, problems: list) -> list[tuple[str, str]]:
    wf: h5py.Dataset = f["waveforms"]
    n, t = wf.shape
    fs, c, k0 = np.float64(f["fs"]), np.float64(f["sound_speed"]), f["start_sample"]
    t0, t1 = k0 / fs, (k0 + t - 1) / fs
    peak, square = 0.0, 0.0
    bad, first, row = 0, None, 0
    for slab in _slabs(wf):
        finite = np.isfinite(slab)
        if not finite.all():
            bad += int((~finite).sum())
            first = row + int(np.argmin(finite.all(axis=1))) if first is None else first
            slab = np.where(finite, slab, 0)
        peak = max(peak, float(np.abs(slab).max(initial=0.0)))
        square += float(np.square(np.abs(slab), dtype=np.float64).sum())
        row += len(slab)
    _nonfinite("waveforms", bad, first, problems)
    rms = np.sqrt(square / max(1, n * t))
    pulse = f["pulse"]
    finite_note = f" over the finite samples ({bad} NaN/inf)" if bad else ""
    lines = [
        ("source", f["source"]),
        ("waveforms", f"N = {n} pings x T = {t} samples ({wf.dtype}); peak |x| {peak:.4g}, "
                      f"rms {rms:.4g}{finite_note}"),
        ("sampling", f"fs = {fs:g} Hz, c = {c:g} m/s"),
        ("time span", f"samples {k0} .. {k0 + t - 1}: {t0 * 1e3:.3f} .. {t1 * 1e3:.3f} ms "
                      f"(round-trip path {t0 * c:.3f} .. {t1 * c:.3f} m)"),
        ("tx positions", _extent(f["tx"])),
        ("rx positions", _extent(f["rx"])),
        ("boresight", "separate tx and rx" if f["rx_boresight"] is not None
         else "shared by tx and rx"),
        ("pulse", f"{len(pulse)} samples ({len(pulse) / fs * 1e3:.3f} ms), "
                  f"{_pulse_band(pulse, fs)}"),
        ("noise", "none added" if f["snr_db"] is None else f"SNR {f['snr_db']:g} dB"),
        *_fidelity(f["meta"]),
        ("seed", "none" if f["seed"] is None else str(f["seed"])),
    ]
    if not np.any(pulse):
        problems.append("dataset 'pulse' is all zero: matched filtering would zero every echo "
                        "(recon refuses it)")
    if f["temperatures"] is not None:
        lines.append(("temperature", _range(f["temperatures"], "degC", 2)))
    if f["gt_vertices"] is not None:
        v = f["gt_vertices"]
        lines.append(("ground truth", f"mesh of {len(v)} vertices, {len(f['gt_faces'])} faces"
                                      + (f", {_extent(v).split(';')[0]}" if len(v) else "")))
    lines += _meta(f["meta"])
    if f["transients"] is not None:
        lines += _transient_lines(f["transients"], problems, "transients.")
    else:
        lines.append(("transients", "not stored"))
    return lines


def _fidelity(meta: dict) -> list[tuple[str, str]]:
    """The measured fidelity of a simulated dataset (docs/simulation.md), if recorded."""
    lines = []
    if "mc_snr_db" in meta:
        target = meta.get("mc_snr_target_db")
        lines.append(("Monte-Carlo SNR", f"{meta['mc_snr_db']:.1f} dB after matched filtering "
                      f"(measured from two half-estimates"
                      + (f"; target {target:g} dB)" if target is not None else ")")))
    if "effective_snr_db" in meta:
        lines.append(("effective SNR", f"{meta['effective_snr_db']:.1f} dB (Monte-Carlo and "
                      f"added noise together, in the --snr-db definition)"))
    return lines


def _volume(f: dict, problems: list) -> list[tuple[str, str]]:
    vol: h5py.Dataset = f["volume"]
    bounds = f["bounds"]
    shape = vol.shape
    size = voxel_spacing(bounds, shape)
    peak, argmax, offset = 0.0, None, 0
    bad, first = 0, None
    for slab in _slabs(vol):
        mag = np.abs(slab)
        finite = np.isfinite(mag)
        if not finite.all():
            bad += int((~finite).sum())
            first = offset + int(np.argmin(finite.reshape(len(slab), -1).all(axis=1))) \
                if first is None else first
            mag = np.where(finite, mag, 0)
        i = int(np.argmax(mag))
        if mag.flat[i] > peak or argmax is None:
            peak, argmax = float(mag.flat[i]), offset * mag[0].size + i
        offset += len(slab)
    where = np.unravel_index(argmax, shape)
    centres = [np.linspace(lo, hi, k)[j] for (lo, hi), k, j in zip(bounds, shape, where)]
    if bad:
        problems.append(f"dataset 'volume' contains {bad} NaN or inf values "
                        f"(first in x slice {first})")
    lines = [
        ("method", f["method"]),
        ("shape", " x ".join(map(str, shape)) + f" voxels (complex64, {vol.size} total)"),
        ("bounds", "  ".join(f"{a} [{lo:+.4f}, {hi:+.4f}]" for a, (lo, hi) in
                             zip("xyz", bounds)) + " m (voxel centres)"),
        ("voxel size", " x ".join("-" if np.isnan(s) else f"{s * 1e3:.3f}" for s in size)
         + " mm"),
        ("|v| max", f"{peak:.4g} at voxel {tuple(int(j) for j in where)} = "
                    f"({centres[0]:+.4f}, {centres[1]:+.4f}, {centres[2]:+.4f}) m"),
    ]
    return lines + _meta(f["params"], "params.")
