"""openSTB interoperability: read and write openSTB's *Zarr baseband pressure* results.

openSTB (github.com/openSTB/simulator, docs ``concepts/result_format.md``) stores a
simulation's result as a Zarr group with

* ``pressure``: complex [pings, receivers, samples], Pa, in the complex baseband;
* ``sample_time`` [samples]: s after the start of the ping's transmission;
* ``ping_start_time`` [pings]: s after the start of the trajectory;
* attributes ``baseband_frequency`` (Hz) and ``sample_rate`` (Hz).

Its baseband convention (``system/signal.py``, ``controller/simple_points.py``): the
analytic passband signal is ``p(t) = pressure(t) · exp(+j2π f_bb t)``, ``t`` = ``sample_time``;
the real pressure is ``Re p(t)``; an echo of travel time τ is ``s_bb(t − τ) · exp(−j2π f_bb τ)``.

The result does **not** store where the sonar was: the geometry lives in the simulation's
configuration (trajectory, transmitter and receivers relative to the vehicle). So

* :func:`write_openstb` (sonarsim → openSTB) adds a group ``sonarsim`` with the positions,
  boresights, pulse and dataset attributes (openSTB's tools ignore it), and
* :func:`read_openstb` (→ sonarsim) takes the geometry from that group, or from the openSTB
  configuration TOML (``config=``; :mod:`sonarsim.importers.openstb_config`).

Mapping: each (ping, receiver) pair becomes one sonarsim row (tx, rx, waveform), ping-major.
The real waveform at ``fs`` = an integer multiple of ``sample_rate`` is the upsampled baseband
(polyphase FIR, SciPy) shifted back to the carrier; the reverse computes the analytic signal
(sonarsim.signals.analytic), shifts it to baseband and decimates. Frames and units are kept
as they are (openSTB's global frame: sonarsim's z-up convention is not imposed). See
docs/importers.md for what is lost in each direction.
"""
from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError

EXTENSION_GROUP = "sonarsim"
EXTENSION_FORMAT = "sonarsim.openstb-extension"
REQUIRED_ARRAYS = ("pressure", "sample_time", "ping_start_time")
REQUIRED_ATTRS = ("baseband_frequency", "sample_rate")
OVERSAMPLE_MARGIN = 2.5      # default fs >= 2.5 x the highest frequency the baseband holds
BLOCK_SAMPLES = 1 << 22      # samples converted at a time (a block of pings, ~100 MB at most)


# ------------------------------------------------------------------------------ reading

def read_openstb(path: str | os.PathLike, *, config: str | os.PathLike | None = None,
                 fs: float | None = None, sound_speed: float | None = None,
                 box=None):
    """The openSTB result at ``path`` (a Zarr directory) as a sonarsim ``SonarDataset``.

    Geometry, pulse and sound speed come from ``config`` (openSTB's simulation TOML) when
    given, else from the ``sonarsim`` group of a file :func:`write_openstb` wrote; a plain
    openSTB result without ``config`` is refused (one line). ``fs``: the sample rate of the
    real waveforms (an integer multiple of ``sample_rate``; default: the ``sonarsim``
    group's, else the smallest multiple >= 2.5 x the highest frequency present).
    ``sound_speed`` overrides the file's or configuration's. ``box``: a SceneBox stored as
    the dataset's scene box.
    """
    from .. import limits
    from ..dataset import SonarDataset
    root = _open_group(path)
    pressure, t, ping_t, f_bb, rate = _checked_result(root, path)   # pressure: lazy
    n_pings, n_rx, n_s = pressure.shape
    ext = _extension(root, path, n_pings, n_rx) if config is None else None
    if config is None and ext is None:
        raise InputError(f"{path}: openSTB results do not store where the sonar was; give "
                         "the simulation's configuration with --config sim.toml")
    if fs is None and ext is not None:       # the rate the waveforms had before export
        factor = _upsampling(ext["fs"], rate, f_bb, path, check_band=False)
    else:
        factor = _upsampling(fs, rate, f_bb, path)
    out_fs = rate * factor
    start = t[0] * out_fs
    if abs(start - round(start)) > 1e-6 * max(1.0, abs(start)):
        raise InputError(f"{path}: sample_time starts at {t[0]:.9g} s, not on the sample grid "
                         f"of fs = {out_fs:g} Hz; choose --fs so that it does")
    limits.check_memory(n_pings * n_rx * n_s * factor * 4 + BLOCK_SAMPLES * 16 * (2 + factor),
                        f"importing {path}", f"{n_pings} pings x {n_rx} receivers x {n_s} "
                        f"samples, x{factor} upsampling", "choose a lower --fs")
    if config is not None:
        from .openstb_config import read_config
        setup = read_config(config, ping_t, n_rx, out_fs)
    else:
        setup = ext
    c = float(sound_speed if sound_speed is not None else setup["sound_speed"] or math.nan)
    if not (math.isfinite(c) and c > 0):
        raise InputError(f"{config}: no sound speed in the configuration ([environment] "
                         "plugin = \"invariant\", sound_speed = ...); give --sound-speed")
    waveforms = _convert_blocks(pressure, path, t[0], rate, f_bb, factor)
    meta = dict(setup.get("meta") or {})
    meta.update({"openstb_baseband_frequency": f_bb, "openstb_sample_rate": rate,
                 "openstb_receivers": n_rx, "openstb_result": str(path)})
    meta.pop("openstb_ping_times", None)
    times = ping_schedule(ping_t)
    if times is not None:
        meta["openstb_ping_times"] = times
    if box is not None:
        meta["box"] = [[float(lo), float(hi)] for lo, hi in zip(box.lo, box.hi)]
    return SonarDataset(
        waveforms=waveforms, tx=setup["tx"].reshape(-1, 3), rx=setup["rx"].reshape(-1, 3),
        boresight=setup["boresight"].reshape(-1, 3),
        rx_boresight=None if setup.get("rx_boresight") is None
        else setup["rx_boresight"].reshape(-1, 3),
        temperatures=None if setup.get("temperatures") is None
        else setup["temperatures"].reshape(-1),
        pulse=setup["pulse"], fs=out_fs, sound_speed=c, source=setup.get("source", "openstb"),
        start_sample=int(round(start)), gt_vertices=setup.get("gt_vertices"),
        gt_faces=setup.get("gt_faces"), snr_db=setup.get("snr_db"), seed=setup.get("seed"),
        meta=meta)


def ping_schedule(ping_t: np.ndarray) -> dict | None:
    """``{'first': s, 'interval': s}`` when the ping start times are evenly spaced (to 1 µs),
    else None: what a dataset keeps of openSTB's ping times (a per-ping array would not fit
    an HDF5 attribute for a full scan)."""
    if len(ping_t) == 1:
        return {"first": float(ping_t[0]), "interval": 0.0}
    step = (ping_t[-1] - ping_t[0]) / (len(ping_t) - 1)
    even = ping_t[0] + step * np.arange(len(ping_t))
    if np.abs(ping_t - even).max() <= 1e-6:
        return {"first": float(ping_t[0]), "interval": float(step)}
    return None


def passband(pressure: np.ndarray, t0: float, rate: float, f_bb: float, factor: int
             ) -> np.ndarray:
    """Real waveforms [R, factor·S] float32 from complex baseband ``pressure`` [R, S]
    sampled at ``rate`` from time ``t0``: upsampled by ``factor`` (polyphase FIR), then
    ``Re(p · exp(j2π f_bb t))`` at ``t = t0 + k / (factor · rate)``."""
    from scipy.signal import resample_poly
    up = resample_poly(pressure, factor, 1, axis=-1) if factor > 1 else pressure
    k = np.arange(up.shape[-1])
    carrier = np.exp(2j * np.pi * f_bb * (t0 + k / (rate * factor)))
    return (up * carrier).real.astype(np.float32)


def _convert_blocks(pressure, path, t0: float, rate: float, f_bb: float, factor: int
                    ) -> np.ndarray:
    """:func:`passband` of the Zarr array ``pressure`` [P, R, S], read a block of pings at a
    time (with progress), as waveforms [P·R, factor·S] float32."""
    from ..progress import progress_bar
    n_pings, n_rx, n_s = pressure.shape
    out = np.empty((n_pings * n_rx, n_s * factor), dtype=np.float32)
    block = max(1, BLOCK_SAMPLES // (n_rx * n_s * factor))
    with progress_bar(n_pings, True, unit="ping", desc="import-openstb") as bar:
        for p0 in range(0, n_pings, block):
            p1 = min(n_pings, p0 + block)
            try:
                chunk = np.asarray(pressure[p0:p1])
            except Exception as exc:          # a damaged chunk: zarr/numcodecs errors vary
                raise FormatError(f"{path}: 'pressure' pings {p0}..{p1 - 1} cannot be read "
                                  f"({type(exc).__name__}: {exc})") from None
            if not np.all(np.isfinite(chunk)):
                raise FormatError(f"{path}: 'pressure' has NaN or infinite values "
                                  f"(pings {p0}..{p1 - 1})")
            out[p0 * n_rx:p1 * n_rx] = passband(chunk.reshape(-1, n_s), t0, rate, f_bb, factor)
            bar.update(p1 - p0)
    return out


def _open_group(path):
    import zarr
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{p}: no such file or directory")
    try:
        return zarr.open_group(str(p), mode="r")
    except Exception as exc:          # zarr raises several kinds for a non-Zarr path
        raise FormatError(f"{p}: not a Zarr group ({type(exc).__name__}: {exc})") from None


def _checked_result(root, path):
    missing = [n for n in REQUIRED_ARRAYS if n not in root]
    if missing:
        raise FormatError(f"{path}: not an openSTB result: missing {', '.join(missing)} "
                          "(expected the Zarr baseband pressure format)")
    for name in REQUIRED_ATTRS:
        if name not in root.attrs:
            raise FormatError(f"{path}: missing attribute '{name}'")
    pressure = root["pressure"]
    try:
        t = np.asarray(root["sample_time"][...], dtype=np.float64)
        ping_t = np.asarray(root["ping_start_time"][...], dtype=np.float64)
        f_bb, rate = float(root.attrs["baseband_frequency"]), float(root.attrs["sample_rate"])
    except Exception as exc:                  # damaged arrays, non-numeric attributes
        raise FormatError(f"{path}: cannot read the result's times and rates "
                          f"({type(exc).__name__}: {exc})") from None
    if not np.issubdtype(pressure.dtype, np.complexfloating):
        raise FormatError(f"{path}: 'pressure' is {pressure.dtype}, expected complex "
                          "(the baseband pressure)")
    if len(pressure.shape) != 3 or 0 in pressure.shape:
        raise FormatError(f"{path}: 'pressure' has shape {pressure.shape}, expected "
                          "(pings, receivers, samples) with none of them 0")
    n_pings, _, n_s = pressure.shape
    if t.shape != (n_s,) or ping_t.shape != (n_pings,):
        raise FormatError(f"{path}: 'sample_time' {t.shape} / 'ping_start_time' "
                          f"{ping_t.shape} do not match 'pressure' {pressure.shape}")
    if not (math.isfinite(rate) and rate > 0 and math.isfinite(f_bb) and f_bb >= 0):
        raise FormatError(f"{path}: sample_rate {rate} / baseband_frequency {f_bb}: "
                          "expected positive finite numbers")
    if n_s > 1 and not np.allclose(np.diff(t), 1.0 / rate, rtol=1e-6, atol=0):
        raise FormatError(f"{path}: 'sample_time' is not evenly spaced at 1/sample_rate")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(ping_t))):
        raise FormatError(f"{path}: NaN or infinite sample or ping times")
    return pressure, t, ping_t, f_bb, rate


def _upsampling(fs, rate: float, f_bb: float, path, check_band: bool = True) -> int:
    """The integer factor from ``rate`` to the real waveforms' sample rate (``check_band``:
    refuse an ``fs`` below twice the top of the baseband's band)."""
    if fs is None:
        top = f_bb + rate / 2.0
        return max(1, math.ceil(OVERSAMPLE_MARGIN * top / rate))
    ratio = float(fs) / rate
    if not (math.isfinite(ratio) and ratio >= 1 and abs(ratio - round(ratio)) < 1e-9 * ratio):
        raise InputError(f"--fs {fs:g}: must be a whole multiple of the result's sample_rate "
                         f"({rate:g} Hz)")
    factor = int(round(ratio))
    if check_band and fs <= 2.0 * (f_bb + rate / 2.0):
        raise InputError(f"--fs {fs:g}: too low for real waveforms of a band up to "
                         f"{f_bb + rate / 2:g} Hz (needs more than {2 * (f_bb + rate / 2):g})")
    return factor


def _extension(root, path, n_pings: int, n_rx: int) -> dict | None:
    """The ``sonarsim`` group of a file :func:`write_openstb` wrote, checked; or None."""
    if EXTENSION_GROUP not in root:
        return None
    g = root[EXTENSION_GROUP]
    if g.attrs.get("format") != EXTENSION_FORMAT:
        return None
    out = {name: np.asarray(g[name][...]) for name in
           ("tx", "rx", "boresight", "rx_boresight", "pulse", "gt_vertices", "gt_faces",
            "temperatures")
           if name in g}
    for name in ("tx", "rx", "boresight"):
        if name not in out or out[name].shape != (n_pings, n_rx, 3):
            raise FormatError(f"{path}: group '{EXTENSION_GROUP}': '{name}' missing or not of "
                              f"shape ({n_pings}, {n_rx}, 3)")
    attrs = json.loads(g.attrs.get("dataset", "{}"))
    out.update(fs=float(g.attrs["fs"]), sound_speed=float(g.attrs["sound_speed"]),
               source=attrs.get("source", "openstb"), snr_db=attrs.get("snr_db"),
               seed=attrs.get("seed"), meta=attrs.get("meta", {}))
    return out


# ------------------------------------------------------------------------------ writing

def write_openstb(dataset, path: str | os.PathLike, *, baseband_frequency: float | None = None,
                  sample_rate: float | None = None, force: bool = False) -> Path:
    """Write a sonarsim ``SonarDataset`` as an openSTB Zarr baseband-pressure result.

    Every row becomes one ping with one receiver (``pressure`` [N, 1, S], complex64).
    ``baseband_frequency``: default the pulse's power-weighted mean frequency (Hz, rounded).
    ``sample_rate``: ``fs`` divided by a whole number (default ``fs``: lossless); refused when
    the pulse's band (99 % of its energy) does not fit in ``f_bb ± sample_rate/2``.
    ``ping_start_time``: the schedule an openSTB import recorded (meta
    ``openstb_ping_times``, one receiver per ping), else nominal times one record length
    apart (sonarsim datasets carry no ping times). The geometry,
    pulse and attributes go to the ``sonarsim`` group. Written to a temporary directory and
    renamed into place; an existing ``path`` needs ``force``.
    """
    import zarr

    if getattr(dataset, "waveform_kind", "real") != "real":
        raise InputError("only datasets of real waveforms can be written as openSTB "
                         "results (this one is pulse-deconvolved)")
    path = Path(path)
    if path.exists() and not force:
        raise InputError(f"--out {path}: exists; pass --force to replace it")
    fs = float(dataset.fs)
    f_bb, factor = _baseband_plan(dataset.pulse, fs, baseband_frequency, sample_rate)
    n, n_t = dataset.waveforms.shape
    t = (dataset.start_sample + np.arange(n_t)) / fs
    times = t[::factor]                    # = the decimated length, ceil(n_t / factor)
    meta = dict(dataset.meta)
    schedule = meta.pop("openstb_ping_times", None)
    if isinstance(schedule, dict) and meta.get("openstb_receivers", 1) == 1:
        ping_t = schedule["first"] + schedule["interval"] * np.arange(n)
    else:                  # nominal: one record length apart
        ping_t = np.arange(n) * (t[-1] + 1.0 / fs)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        root = zarr.open_group(str(tmp), mode="w")
        pressure = root.create_array("pressure", shape=(n, 1, len(times)), dtype=np.complex64,
                                     chunks=(min(n, 256), 1, len(times)))
        _baseband_blocks(dataset.waveforms, pressure, t, f_bb, factor)
        root.create_array("sample_time", data=times)
        root.create_array("ping_start_time", data=ping_t)
        root.attrs.update({"baseband_frequency": f_bb, "sample_rate": fs / factor})
        _write_extension(root, dataset, meta)
        if path.exists():
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def _baseband_blocks(waveforms, pressure, t: np.ndarray, f_bb: float, factor: int) -> None:
    """Fill the Zarr array ``pressure`` [N, 1, S'] with the baseband of real ``waveforms``
    [N, S] (analytic signal, carrier removed, decimated by ``factor``), 256 rows at a time."""
    from scipy.signal import resample_poly

    from ..progress import progress_bar
    from ..signals import analytic
    n = len(waveforms)
    carrier = np.exp(-2j * np.pi * f_bb * t)
    with progress_bar(n, True, unit="ping", desc="export-openstb") as bar:
        for r0 in range(0, n, 256):
            r1 = min(n, r0 + 256)
            bb = analytic(np.asarray(waveforms[r0:r1], dtype=np.float64), axis=-1) * carrier
            if factor > 1:
                bb = resample_poly(bb, 1, factor, axis=-1)
            pressure[r0:r1] = bb[:, None, :].astype(np.complex64)
            bar.update(r1 - r0)


def _write_extension(root, dataset, meta: dict) -> None:
    g = root.create_group(EXTENSION_GROUP)
    rows = lambda a: np.asarray(a, dtype=np.float64)[:, None, :]  # noqa: E731  [N, 1, 3]
    g.create_array("tx", data=rows(dataset.tx))
    g.create_array("rx", data=rows(dataset.rx))
    g.create_array("boresight", data=rows(dataset.boresight))
    if dataset.rx_boresight is not None:
        g.create_array("rx_boresight", data=rows(dataset.rx_boresight))
    g.create_array("pulse", data=np.asarray(dataset.pulse, dtype=np.float64))
    if dataset.temperatures is not None:
        g.create_array("temperatures", data=np.asarray(dataset.temperatures, np.float64)[:, None])
    if dataset.gt_vertices is not None:
        g.create_array("gt_vertices", data=np.asarray(dataset.gt_vertices, np.float64))
        g.create_array("gt_faces", data=np.asarray(dataset.gt_faces, np.int64))
    g.attrs.update({"format": EXTENSION_FORMAT, "format_version": 1, "fs": float(dataset.fs),
                    "sound_speed": float(dataset.sound_speed),
                    "dataset": json.dumps({"source": dataset.source, "snr_db": dataset.snr_db,
                                           "seed": dataset.seed, "meta": _jsonable(meta)})})


def _jsonable(meta: dict) -> dict:
    out = {}
    for k, v in meta.items():
        try:
            out[k] = json.loads(json.dumps(np.asarray(v).tolist() if isinstance(v, np.ndarray)
                                           else v))
        except (TypeError, ValueError):
            out[k] = str(v)
    return out


def pulse_band(pulse, fs: float, fraction: float = 0.99) -> tuple[float, float, float]:
    """(f_lo, f_hi, f_mean) in Hz of a real pulse: the band holding ``fraction`` of its
    energy (equal tails) and the power-weighted mean frequency."""
    p = np.asarray(pulse, dtype=np.float64)
    n = max(4096, 1 << int(np.ceil(np.log2(8 * len(p)))))
    power = np.abs(np.fft.rfft(p, n)) ** 2
    f = np.fft.rfftfreq(n, 1.0 / fs)
    cdf = np.cumsum(power) / power.sum()
    tail = (1.0 - fraction) / 2.0
    lo = f[np.searchsorted(cdf, tail)]
    hi = f[min(np.searchsorted(cdf, 1.0 - tail), len(f) - 1)]
    return float(lo), float(hi), float(np.sum(f * power) / power.sum())


def _baseband_plan(pulse, fs: float, f_bb, sample_rate) -> tuple[float, int]:
    lo, hi, mean = pulse_band(pulse, fs)
    f_bb = float(round(mean)) if f_bb is None else float(f_bb)
    if not (math.isfinite(f_bb) and 0 <= f_bb < fs / 2):
        raise InputError(f"--baseband-frequency {f_bb:g}: must lie in [0, fs/2) = "
                         f"[0, {fs / 2:g}) Hz")
    if sample_rate is None:
        return f_bb, 1
    ratio = fs / float(sample_rate)
    if not (math.isfinite(ratio) and ratio >= 1 and abs(ratio - round(ratio)) < 1e-9 * ratio):
        raise InputError(f"--sample-rate {sample_rate:g}: must be fs ({fs:g} Hz) divided by a "
                         "whole number")
    half = float(sample_rate) / 2.0
    if lo < f_bb - half or hi > f_bb + half:
        raise InputError(f"--sample-rate {sample_rate:g}: the pulse's band {lo:.0f}..{hi:.0f} Hz "
                         f"(99 % of its energy) does not fit in {f_bb:g} ± {half:g} Hz; "
                         "raise --sample-rate or move --baseband-frequency")
    return f_bb, int(round(ratio))
