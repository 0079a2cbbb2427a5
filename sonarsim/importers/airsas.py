"""Import a real AirSAS scan from the rig's LabVIEW CSV folder (the reference code's
``airsas/reconstruct_airsas_scene.py``; docs/importers.md).

A scan folder holds

- ``SysParams.csv``: ``key,value`` rows; rig positions in metres (``Speaker x``, ``Mic1 y``,
  ``Center z``, ...), ``Fs`` in Hz, ``Group Delay`` in samples;
- ``WaveformParams.csv``: one row per waveform, e.g.
  ``LFM_2.25E+4Hz_1.75E+4Hz_1.00E-3s_5.00E-1V_tukeywin_1.00E-1``
  (f_start, f_stop, duration, amplitude, window, window ratio);
- ``Waveforms.csv``: the commanded waveforms at fs, one column per waveform;
- ``Coordinates.csv``: header ``Flight #,Angle,Height,Temp,Waveform``; angle in degrees,
  height in millimetres, temperature in °C, waveform index;
- ``Flight-NNNNNN.csv``: one row per sample, column 0 = Mic1 (used), column 1 = Mic2.

The import (:func:`import_airsas`) keeps column 0 of the flights of one waveform, subtracts
the background scan (same flight numbers), removes the DAQ group delay by a fractional
circular advance (so sample k is at k/fs after transmission, DESIGN §3), computes the poses
``R_z(angle)·RIG − CENTER + [0, 0, height]`` with boresights at the scene-box centre, and the
sound speed ``331.4 + 0.6·mean(T)`` m/s from the per-ping temperatures (kept in the dataset).
"""
from __future__ import annotations

import re
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import geometry, signals
from ..errors import FormatError, InputError

SYS_PARAMS = "SysParams.csv"
WAVEFORM_PARAMS = "WaveformParams.csv"
WAVEFORMS = "Waveforms.csv"
COORDINATES = "Coordinates.csv"
FLIGHT_PATTERN = "Flight-{:06d}.csv"

#: Number of leading samples of a measured pulse file used as the reference pulse, as the
#: reference does (``np.load(...)[0:100]``, 1 ms at 100 kHz; the tail is ringing).
DEFAULT_PULSE_SAMPLES = 100

_COORD_COLUMNS = {"flight": "flight", "flight#": "flight", "flightnumber": "flight",
                  "angle": "angle", "height": "height", "temp": "temp",
                  "temperature": "temp", "waveform": "waveform"}
_DEFAULT_COORD_ORDER = ("flight", "angle", "height", "temp", "waveform")
_NUMBER_UNIT = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z]*)\s*$")


# --------------------------------------------------------------------------- CSV reading
def _read_lines(path: Path) -> list[str]:
    """Lines of a text file without line ends; trailing blank lines dropped."""
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[:exc.start].count(b"\n") + 1
        raise FormatError(f"{path}: line {line}: not UTF-8/ASCII text") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror})") from None
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    return lines


def _delimiter(line: str) -> str:
    for sep in (",", "\t", ";"):
        if sep in line:
            return sep
    return ","


def _parse_float(text: str, path: Path, line: int, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FormatError(f"{path}: line {line}: {what} {text.strip()!r} is not a number") \
            from None
    if not np.isfinite(value):
        raise FormatError(f"{path}: line {line}: {what} is {text.strip()!r}")
    return value


def read_numeric_table(path: Path, *, skip_header: bool = False,
                       min_columns: int = 1) -> tuple[np.ndarray, list[str] | None]:
    """Read a comma-separated table of numbers.

    Returns ``(values [rows, columns] float64, header)``; ``header`` is the list of the first
    row's names when ``skip_header`` and that row is not numeric, else ``None``. Blank lines
    are not allowed inside the table. Any bad line raises :class:`FormatError` naming the file
    and the 1-based line number.
    """
    lines = _read_lines(path)
    if not lines:
        raise FormatError(f"{path}: line 1: file is empty")
    sep = _delimiter(lines[-1])
    first = 0
    header = None
    if skip_header:
        cells = lines[0].split(sep)
        try:
            [float(c) for c in cells]
        except ValueError:
            header = [c.strip() for c in cells]
            first = 1
    rows = [ln.split(sep) for ln in lines[first:]]
    if not rows:
        raise FormatError(f"{path}: line {first + 1}: no data rows (only a header)")
    try:
        values = np.array(rows, dtype=np.float64)
        if values.ndim != 2:
            raise ValueError
    except ValueError:
        values = None
    if values is None or values.shape[1] < min_columns or not np.isfinite(values).all():
        _raise_first_bad_line(path, rows, first, min_columns)
    if values.shape[0] == 0:
        raise FormatError(f"{path}: line {first + 1}: no data rows")
    return values, header


def _raise_first_bad_line(path: Path, rows: list[list[str]], first: int, min_columns: int):
    width = Counter(len(r) for r in rows).most_common(1)[0][0]
    width = max(width, min_columns)
    for i, cells in enumerate(rows):
        line = first + i + 1
        if not "".join(cells).strip():
            raise FormatError(f"{path}: line {line}: empty line inside the table")
        if len(cells) != width:
            raise FormatError(f"{path}: line {line}: {len(cells)} field(s), expected {width}"
                              + (" (truncated file?)" if i == len(rows) - 1 else ""))
        for cell in cells:
            _parse_float(cell, path, line, "value")
    raise FormatError(f"{path}: unreadable table")  # not reached for well-formed input


def read_sys_params(path: Path) -> dict[str, float | str]:
    """``SysParams.csv`` as ``{key: value}``; numeric values as float (SI units as stored)."""
    params: dict[str, float | str] = {}
    for number, line in enumerate(_read_lines(path), start=1):
        if not line.strip():
            continue
        key, sep, value = line.partition(_delimiter(line))
        if not sep or not key.strip():
            raise FormatError(f"{path}: line {number}: expected 'key,value', got {line!r}")
        value = value.strip()
        try:
            params[key.strip()] = float(value)
        except ValueError:
            params[key.strip()] = value
    return params


def _number(params: dict, key: str, path: Path) -> float:
    if key not in params:
        raise FormatError(f"{path}: missing field {key!r}")
    value = params[key]
    if not isinstance(value, float) or not np.isfinite(value):
        raise FormatError(f"{path}: field {key!r} = {value!r} is not a number")
    return value


@dataclass(frozen=True)
class LfmParams:
    """One row of ``WaveformParams.csv`` (SI units)."""
    f_start: float
    f_stop: float
    duration: float
    amplitude: float
    window: str
    window_ratio: float
    text: str


def read_waveform_params(path: Path) -> list[LfmParams]:
    """All rows of ``WaveformParams.csv`` (non-blank row index = waveform index)."""
    out = []
    for number, line in enumerate(_read_lines(path), start=1):
        text = line.strip().strip(",")
        if not text:
            continue
        tokens = text.split("_")
        if not tokens or tokens[0].upper() != "LFM" or len(tokens) < 7:
            raise FormatError(f"{path}: line {number}: expected "
                              f"'LFM_<f0>Hz_<f1>Hz_<T>s_<A>V_<window>_<ratio>', got {text!r}")
        nums = []
        for token, unit in zip(tokens[1:5] + tokens[6:7], ("hz", "hz", "s", "v", "")):
            m = _NUMBER_UNIT.match(token)
            if not m or m.group(2).lower() not in (unit, ""):
                raise FormatError(f"{path}: line {number}: bad field {token!r} in {text!r}")
            nums.append(float(m.group(1)))
        out.append(LfmParams(nums[0], nums[1], nums[2], nums[3], tokens[5], nums[4], text))
    if not out:
        raise FormatError(f"{path}: line 1: no waveform rows")
    return out


@dataclass(frozen=True)
class Coordinates:
    """``Coordinates.csv``: per-flight arrays (length M, file order)."""
    flight: np.ndarray       # int
    angle_deg: np.ndarray
    height_mm: np.ndarray
    temp_c: np.ndarray
    waveform: np.ndarray     # int
    line: np.ndarray         # 1-based line number of each row in the file


def read_coordinates(path: Path) -> Coordinates:
    values, header = read_numeric_table(path, skip_header=True, min_columns=4)
    if header is None:
        names = _DEFAULT_COORD_ORDER[:values.shape[1]]
        first_line = 1
    else:
        names = [_COORD_COLUMNS.get(re.sub(r"[\s_]", "", h).lower()) for h in header]
        first_line = 2
        for need in ("flight", "angle", "height", "temp"):
            if need not in names:
                raise FormatError(f"{path}: line 1: header {header} has no {need!r} column")
        if len(header) != values.shape[1]:
            raise FormatError(f"{path}: line 1: header has {len(header)} columns, "
                              f"data rows have {values.shape[1]}")
    cols = {n: values[:, i] for i, n in enumerate(names) if n is not None}
    lines = np.arange(values.shape[0]) + first_line
    for name in ("flight", "waveform"):
        if name in cols and not np.all(cols[name] == np.round(cols[name])):
            bad = int(np.argmax(cols[name] != np.round(cols[name])))
            raise FormatError(f"{path}: line {lines[bad]}: {name} {cols[name][bad]} "
                              "is not an integer")
    flight = cols["flight"].astype(np.int64)
    if np.any(flight < 0):
        bad = int(np.argmax(flight < 0))
        raise FormatError(f"{path}: line {lines[bad]}: negative flight number")
    uniq, counts = np.unique(flight, return_counts=True)
    if np.any(counts > 1):
        dup = uniq[counts > 1][0]
        bad = int(np.nonzero(flight == dup)[0][1])
        raise FormatError(f"{path}: line {lines[bad]}: flight {dup} listed twice")
    waveform = cols.get("waveform", np.zeros(len(flight))).astype(np.int64)
    return Coordinates(flight, cols["angle"], cols["height"], cols["temp"], waveform, lines)


def read_flight(path: Path) -> np.ndarray:
    """One ``Flight-NNNNNN.csv`` as [samples, channels] float64 (column 0 = Mic1)."""
    return read_numeric_table(path)[0]


# --------------------------------------------------------------------------- import
@dataclass(frozen=True)
class RigConstants:
    """Rig-frame positions (metres) from ``SysParams.csv`` or :mod:`sonarsim.geometry`."""
    tx: np.ndarray
    rx: np.ndarray
    center: np.ndarray
    from_file: bool


def rig_constants(params: dict, path: Path) -> RigConstants:
    """Speaker, Mic1 and Center from SysParams; the geometry constants when all are absent."""
    keys = {"tx": "Speaker", "rx": "Mic1", "center": "Center"}
    names = [f"{k} {a}" for k in keys.values() for a in "xyz"]
    present = [n in params for n in names]
    if not any(present):
        return RigConstants(np.asarray(geometry.TX_RIG, float), np.asarray(geometry.RX_RIG, float),
                            np.asarray(geometry.RIG_CENTER, float), False)
    vec = {k: np.array([_number(params, f"{p} {a}", path) for a in "xyz"])
           for k, p in keys.items()}
    return RigConstants(vec["tx"], vec["rx"], vec["center"], True)


def rig_poses(angles_deg: np.ndarray, heights_m: np.ndarray, rig: RigConstants,
              box: "geometry.SceneBox") -> "geometry.Poses":
    """The scan's poses by :func:`sonarsim.geometry.rig_poses` with this rig's constants.

    ``angles_deg`` [N] degrees, ``heights_m`` [N] metres; positions [N, 3] in metres; both
    beams point at ``box.center``.
    """
    return geometry.rig_poses(angles_deg, heights_m, box, tx_rig=rig.tx, rx_rig=rig.rx,
                              rig_center=rig.center)


def _select_waveform(coords: Coordinates, waveform_index: int | None, path: Path) -> np.ndarray:
    present = sorted(set(coords.waveform.tolist()))
    if waveform_index is None:
        if len(present) > 1:
            raise InputError(f"{path}: the scan interleaves waveforms {present}; "
                             "choose one with --waveform-index")
        waveform_index = present[0]
    keep = coords.waveform == waveform_index
    if not keep.any():
        raise InputError(f"{path}: no flight uses waveform {waveform_index} (present: {present})")
    return keep


def _load_pulse(scan_dir: Path, pulse: str | Path | None, waveform_index: int, fs: float,
                pulse_samples: int | None) -> tuple[np.ndarray, str]:
    """The reference pulse [L] at fs and a description of where it came from."""
    if pulse is None or str(pulse) == "lfm":
        rows = read_waveform_params(scan_dir / WAVEFORM_PARAMS)
        if waveform_index >= len(rows):
            raise FormatError(f"{scan_dir / WAVEFORM_PARAMS}: no row for waveform "
                              f"{waveform_index} ({len(rows)} row(s))")
        p = rows[waveform_index]
        if p.window.lower() not in ("tukeywin", "tukey", "rectwin", "rect", "none"):
            raise FormatError(f"{scan_dir / WAVEFORM_PARAMS}: line {waveform_index + 1}: "
                              f"window {p.window!r} is not supported (Tukey or rectangular)")
        ratio = p.window_ratio if p.window.lower().startswith("tukey") else 0.0
        return signals.lfm(p.f_start, p.f_stop, p.duration, fs, window_ratio=ratio), \
            f"lfm:{p.text}"
    if str(pulse) == "commanded":
        path = scan_dir / WAVEFORMS
        table, _ = read_numeric_table(path, skip_header=True)
        if waveform_index >= table.shape[1]:
            raise FormatError(f"{path}: no column for waveform {waveform_index}")
        return table[:, waveform_index], f"commanded:{WAVEFORMS}[{waveform_index}]"
    if str(pulse).strip().lower() in signals.NAMED_PULSES:
        return signals.named_pulse(str(pulse), fs), f"named:{str(pulse).strip().lower()}"
    path = Path(pulse)
    samples = DEFAULT_PULSE_SAMPLES if pulse_samples is None else pulse_samples
    return signals.load_pulse(path, max_samples=samples or None), \
        f"file:{path.name}[:{samples or 'all'}]"


def _read_flights(scan_dir: Path, background_dir: Path | None, flights: np.ndarray,
                  progress: bool) -> tuple[list[np.ndarray | None], list, list]:
    """Mic1 (column 0) of each flight minus its background, as float32 [T] arrays.

    Returns (differences, scan row counts, background row counts); a difference is None
    where the two files differ in length (reported by :func:`_check_lengths`).
    """
    from ..progress import progress_bar

    data, scan_counts, bg_counts = [], [], []
    with progress_bar(len(flights), progress, unit="flight", desc=f"reading {scan_dir.name}",
                      leave=False) as bar:
        for f in flights:
            name = FLIGHT_PATTERN.format(int(f))
            ping = read_flight(scan_dir / name)[:, 0]
            scan_counts.append(ping.size)
            if background_dir is not None:
                empty = read_flight(background_dir / name)[:, 0]
                bg_counts.append(empty.size)
                ping = ping - empty if empty.size == ping.size else None
            data.append(None if ping is None else ping.astype(np.float32))
            bar.update(1)
    return data, scan_counts, bg_counts


def _check_lengths(folders_counts: list[tuple[Path, np.ndarray, list[int]]]) -> int:
    all_counts = [c for _, _, counts in folders_counts for c in counts]
    expected = Counter(all_counts).most_common(1)[0][0]
    for folder, flights, counts in folders_counts:
        for f, c in zip(flights, counts):
            if c != expected:
                path = folder / FLIGHT_PATTERN.format(int(f))
                if c < expected:
                    raise FormatError(f"{path}: line {c + 1}: file ends after {c} samples, "
                                      f"the other flights have {expected} (truncated file?)")
                raise FormatError(f"{path}: line {expected + 1}: {c} samples, "
                                  f"the other flights have {expected}")
    return expected


def import_airsas(scan_dir: str | Path, background_dir: str | Path | None = None, *,
                  pulse: str | Path | None = None, pulse_samples: int | None = None,
                  waveform_index: int | None = None, box: "geometry.SceneBox | None" = None,
                  progress: bool | None = None):
    """Read an AirSAS CSV scan folder into a :class:`sonarsim.dataset.SonarDataset`.

    ``pulse``: ``None``/``'lfm'`` = the LFM of ``WaveformParams.csv`` generated at fs;
    ``'commanded'`` = the column of ``Waveforms.csv``; a named pulse (``'lfm-5k'``, ...); or a
    ``.npy`` file of a measured pulse at fs, of which the first ``pulse_samples`` (default 100, 0 = all) are kept.
    ``waveform_index`` selects the flights of one waveform (``Waveform`` column) when a scan
    interleaves two. ``box`` (default ``AIRSAS_REAL_BOX``) is where the beams point.
    Waveforms [N, T] float32 are Mic1 minus background, group delay removed; start_sample 0.
    """
    from ..dataset import SonarDataset

    scan_dir = Path(scan_dir)
    if not scan_dir.is_dir():
        raise FormatError(f"{scan_dir}: not a directory")
    box = geometry.AIRSAS_REAL_BOX if box is None else box
    if progress is None:       # progress_bar decides: a bar on a terminal, else log lines
        progress = True

    sys_path = scan_dir / SYS_PARAMS
    params = read_sys_params(sys_path)
    fs = _number(params, "Fs", sys_path)
    group_delay = _number(params, "Group Delay", sys_path)
    if fs <= 0:
        raise FormatError(f"{sys_path}: field 'Fs' = {fs} must be positive")
    rig = rig_constants(params, sys_path)

    coord_path = scan_dir / COORDINATES
    coords = read_coordinates(coord_path)
    keep = _select_waveform(coords, waveform_index, coord_path)
    chosen_waveform = int(coords.waveform[keep][0])
    flights = coords.flight[keep]

    background_meta = ""
    if background_dir is not None:
        background_dir = Path(background_dir)
        if not background_dir.is_dir():
            raise FormatError(f"{background_dir}: background is not a directory")
        bg_params = read_sys_params(background_dir / SYS_PARAMS)
        bg_fs = _number(bg_params, "Fs", background_dir / SYS_PARAMS)
        if bg_fs != fs:
            raise FormatError(f"{background_dir / SYS_PARAMS}: Fs {bg_fs} differs from the "
                              f"scan's {fs}")
        bg_gd = _number(bg_params, "Group Delay", background_dir / SYS_PARAMS)
        if bg_gd != group_delay:
            warnings.warn(f"background group delay {bg_gd} differs from the scan's "
                          f"{group_delay}; using the scan's", stacklevel=2)
        bg_coords = read_coordinates(background_dir / COORDINATES)
        _check_same_flights(coords, keep, bg_coords, scan_dir, background_dir)
        background_meta = str(background_dir.resolve())

    pings, scan_counts, bg_counts = _read_flights(scan_dir, background_dir, flights, progress)
    to_check = [(scan_dir, flights, scan_counts)]
    if background_dir is not None:
        to_check.append((background_dir, flights, bg_counts))
    n_samples = _check_lengths(to_check)
    if not abs(group_delay) < n_samples:
        raise FormatError(f"{sys_path}: field 'Group Delay' = {group_delay:g} samples is not "
                          f"shorter than the {n_samples}-sample recordings; expected the DAQ's "
                          "delay in samples (e.g. 62.3)")

    raw = np.stack(pings)
    del pings
    # Sample k was recorded at (k + group delay)/fs after transmission: advance by the delay.
    waveforms = np.empty(raw.shape, dtype=np.float32)
    for start in range(0, len(raw), 4096):
        waveforms[start:start + 4096] = signals.fractional_delay(
            raw[start:start + 4096].astype(np.float64), -group_delay, axis=-1)
    del raw

    temps = coords.temp_c[keep].astype(np.float64)
    sound_speed = float(signals.sound_speed_air(float(np.mean(temps))))
    heights_m = coords.height_mm[keep] / 1000.0
    angles = coords.angle_deg[keep]
    poses = rig_poses(angles, heights_m, rig, box)
    pulse_wave, pulse_source = _load_pulse(scan_dir, pulse, chosen_waveform, fs, pulse_samples)

    meta = {
        "scan_dir": str(scan_dir.resolve()),
        "background_dir": background_meta,
        "group_delay_samples": float(group_delay),
        "waveform_index": chosen_waveform,
        "pulse_source": pulse_source,
        "raw_samples": int(n_samples),
        "rig_constants_from": "SysParams.csv" if rig.from_file else "sonarsim.geometry",
        "rig_tx": rig.tx.tolist(), "rig_rx": rig.rx.tolist(), "rig_center": rig.center.tolist(),
        # [[x0, x1], [y0, y1], [z0, z1]] m, the layout of Volume bounds
        "box": np.stack([np.asarray(box.lo, float), np.asarray(box.hi, float)], axis=1).tolist(),
        # Per-ping angles/heights are not kept: HDF5 attributes are limited to 64 KiB and
        # the poses already encode them.
        "n_flights": int(len(flights)),
        "first_flight": int(flights[0]), "last_flight": int(flights[-1]),
        "sound_speed_formula": "331.4 + 0.6 * mean(temperatures)",
        "amplitude_model": "pressure",   # microphone voltage; simulate writes "intensity"
    }
    return SonarDataset(
        waveforms=waveforms, tx=poses.tx, rx=poses.rx, boresight=poses.tx_boresight,
        rx_boresight=poses.rx_boresight,
        pulse=np.asarray(pulse_wave, dtype=np.float64), fs=float(fs), sound_speed=sound_speed,
        source=f"airsas:{scan_dir.resolve().name}", start_sample=0, temperatures=temps,
        meta=meta)


def _check_same_flights(coords: Coordinates, keep: np.ndarray, bg: Coordinates,
                        scan_dir: Path, bg_dir: Path) -> None:
    """The background must hold every selected flight; warn when its positions differ."""
    index = {int(f): i for i, f in enumerate(bg.flight)}
    wanted = coords.flight[keep]
    missing = [int(f) for f in wanted if int(f) not in index]
    if missing:
        raise FormatError(
            f"{bg_dir / COORDINATES}: background lacks {len(missing)} of the {len(wanted)} "
            f"flights of {scan_dir.name} (first missing: {missing[:5]}); "
            "background subtraction needs the same flight numbers")
    rows = np.array([index[int(f)] for f in wanted])
    if np.any(bg.waveform[rows] != coords.waveform[keep]):
        bad = int(wanted[np.argmax(bg.waveform[rows] != coords.waveform[keep])])
        raise FormatError(f"{bg_dir / COORDINATES}: flight {bad} used a different waveform "
                          f"than in {scan_dir.name}")
    d_angle = np.abs((bg.angle_deg[rows] - coords.angle_deg[keep] + 180.0) % 360.0 - 180.0)
    d_height = np.abs(bg.height_mm[rows] - coords.height_mm[keep])
    if d_angle.max() > 0.5 or d_height.max() > 1.0:
        warnings.warn(f"background positions differ from the scan's by up to "
                      f"{d_angle.max():.2f} deg / {d_height.max():.1f} mm", stacklevel=3)
