"""AirSAS rig geometry: transducer positions, sonar poses, trajectories, crop window.

All positions are float64 NumPy arrays in metres, in the world frame of
docs/frames.md: z up, the turntable plane is z = 0, the turntable rotates about +z.
Distances called ``dist`` are *round-trip* path lengths |x - tx| + |x - rx|.

Sources (docs/references.md): the rig constants from the AirSAS ``SysParams.csv``; the
trajectories from Reed et al. 2023 (supplemental) and the reference code
(``airsas/utils.py::resample_cylindrical``); the crop window from the reference code
(``sas_utils.crop_wfm``).
"""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import FormatError, InputError

# --- Rig constants (from the AirSAS SysParams.csv), rig frame, metres.
TX_RIG = np.array([0.0, -0.8485, 0.285])      # speaker
RX_RIG = np.array([0.0, -0.8615, 0.247])      # microphone 1 (the one used)
MIC2_RIG = np.array([0.0, -0.8615, 0.216])    # microphone 2 (unused by the reference)
RIG_CENTER = np.array([0.0, 0.0, 0.1775])     # rig-frame point that becomes the world origin

# --- The reference cylindrical scan (Reed et al. 2023 supp.): 360 angles x 150 heights.
CYLINDRICAL_ANGLES = 360
CYLINDRICAL_HEIGHTS = 150
HEIGHT_STEP = 0.005          # metres between height levels
FIRST_HEIGHT = 0.005         # metres, height of level 0
HELIX_PITCH_LEVELS = 20      # height levels per helix turn (reference code)
POSE_HEADER = ("tx_x", "tx_y", "tx_z", "rx_x", "rx_y", "rx_z")
BORESIGHT_HEADER = ("b_x", "b_y", "b_z")
TWO_BORESIGHT_HEADER = ("btx_x", "btx_y", "btx_z", "brx_x", "brx_y", "brx_z")


def _vec3(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise InputError(f"{name}: expected 3 values, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinity")
    return arr


def _points(value, name: str) -> np.ndarray:
    """Validate an [N, 3] float64 array of finite values (N >= 1)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise InputError(f"{name}: expected shape [N, 3] with N >= 1, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinity")
    return arr


def _unit(vectors: np.ndarray, name: str) -> np.ndarray:
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise InputError(f"{name}: zero-length direction vector")
    # Leave vectors that are unit to rounding alone, so that save/load round trips are exact.
    return np.where(np.abs(norm - 1.0) < 1e-14, vectors, vectors / norm)


@dataclass(frozen=True, eq=False)
class SceneBox:
    """Axis-aligned box (metres) that holds the scene; ``lo`` and ``hi`` are [3] corners."""

    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self) -> None:
        lo, hi = _vec3(self.lo, "box lo"), _vec3(self.hi, "box hi")
        if np.any(hi <= lo):
            raise InputError(f"box: hi {hi.tolist()} must exceed lo {lo.tolist()} on every axis")
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    @classmethod
    def from_bounds(cls, bounds) -> "SceneBox":
        """Box from ``bounds`` [3, 2] = [[x0, x1], [y0, y1], [z0, z1]] (the Volume convention)."""
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape != (3, 2):
            raise InputError(f"bounds: expected shape [3, 2], got {b.shape}")
        return cls(b[:, 0], b[:, 1])

    @property
    def bounds(self) -> np.ndarray:
        """[3, 2] array [[x0, x1], [y0, y1], [z0, z1]]."""
        return np.stack([self.lo, self.hi], axis=1)

    @property
    def center(self) -> np.ndarray:
        """[3] centre of the box (= mean of the 8 corners, as the reference's scene centre)."""
        return 0.5 * (self.lo + self.hi)

    @property
    def size(self) -> np.ndarray:
        return self.hi - self.lo

    def corners(self) -> np.ndarray:
        """[8, 3] corners; corner k takes hi on axis a where bit a of k is set."""
        bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1
        return np.where(bits == 1, self.hi, self.lo)

    def contains(self, points, tol: float = 0.0) -> np.ndarray:
        """[M] bool: which of ``points`` [M, 3] lie in the box (inclusive, widened by tol)."""
        p = np.asarray(points, dtype=np.float64)
        return np.all((p >= self.lo - tol) & (p <= self.hi + tol), axis=-1)

    def __eq__(self, other) -> bool:
        if not isinstance(other, SceneBox):
            return NotImplemented
        return bool(np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi))

    def __hash__(self) -> int:
        return hash((tuple(self.lo), tuple(self.hi)))

    def __repr__(self) -> str:
        return f"SceneBox(lo={self.lo.tolist()}, hi={self.hi.tolist()})"


SIM_BOX = SceneBox((-0.2, -0.2, 0.0), (0.2, 0.2, 0.3))               # reference code geometry.py
AIRSAS_REAL_BOX = SceneBox((-0.125, -0.125, 0.0), (0.125, 0.125, 0.2))  # reference code geometry.py


@dataclass(frozen=True, eq=False)
class Poses:
    """N sonar pings: TX and RX positions [N, 3] (m) and unit boresights [N, 3].

    Boresights are normalised on construction.
    """

    tx: np.ndarray
    rx: np.ndarray
    tx_boresight: np.ndarray
    rx_boresight: np.ndarray

    def __post_init__(self) -> None:
        tx, rx = _points(self.tx, "tx"), _points(self.rx, "rx")
        tb = _points(self.tx_boresight, "tx_boresight")
        rb = _points(self.rx_boresight, "rx_boresight")
        n = tx.shape[0]
        for name, arr in (("rx", rx), ("tx_boresight", tb), ("rx_boresight", rb)):
            if arr.shape[0] != n:
                raise InputError(f"{name}: {arr.shape[0]} rows but tx has {n}")
        object.__setattr__(self, "tx", tx)
        object.__setattr__(self, "rx", rx)
        object.__setattr__(self, "tx_boresight", _unit(tb, "tx_boresight"))
        object.__setattr__(self, "rx_boresight", _unit(rb, "rx_boresight"))

    @classmethod
    def pointing_at(cls, tx, rx, target, boresight=None) -> "Poses":
        """Poses whose beams point from each transducer at ``target`` [3] (m).

        If ``boresight`` ([N, 3] or [3]) is given it is used for both TX and RX instead.
        """
        tx, rx = _points(tx, "tx"), _points(rx, "rx")
        if boresight is not None:
            b = np.broadcast_to(np.asarray(boresight, dtype=np.float64), tx.shape)
            return cls(tx, rx, b, b)
        target = _vec3(target, "target")
        return cls(tx, rx, _unit(target - tx, "tx_boresight"), _unit(target - rx, "rx_boresight"))

    def __len__(self) -> int:
        return self.tx.shape[0]

    def __getitem__(self, index) -> "Poses":
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        sel = [np.asarray(a[index]).reshape(-1, 3) for a in
               (self.tx, self.rx, self.tx_boresight, self.rx_boresight)]
        if sel[0].shape[0] == 0:
            raise InputError("pose selection is empty")
        return Poses(*sel)

    def round_trip(self, points) -> np.ndarray:
        """[N, M] round-trip path lengths |p - tx| + |p - rx| (m) to ``points`` [M, 3]."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return (np.linalg.norm(p[None] - self.tx[:, None], axis=-1)
                + np.linalg.norm(p[None] - self.rx[:, None], axis=-1))


def rotation_z(angle_deg) -> np.ndarray:
    """[N, 3, 3] rotations about +z by ``angle_deg`` (counter-clockwise seen from +z)."""
    a = np.deg2rad(np.atleast_1d(np.asarray(angle_deg, dtype=np.float64)))
    c, s = np.cos(a), np.sin(a)
    zero, one = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, zero], -1),
                     np.stack([s, c, zero], -1),
                     np.stack([zero, zero, one], -1)], axis=-2)


def rig_positions(angles_deg, heights_m, rig_point=TX_RIG, rig_center=RIG_CENTER) -> np.ndarray:
    """[N, 3] world positions R_z(angle) · rig_point − rig_center + [0, 0, height].

    The one home of the AirSAS pose formula (Reed et al. 2023, the AirSAS rig; the reference
    code's pose computation): the turntable turns the object by ``angle`` about +z, which
    is the same as turning the rig by ``angle`` about the object; ``rig_center`` is the rig
    point that becomes the world origin (metres).
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    heights = np.asarray(heights_m, dtype=np.float64)
    if angles.ndim > 1 or heights.ndim > 1:
        raise InputError("angles and heights must be scalars or 1-D arrays")
    try:
        angles, heights = np.broadcast_arrays(np.atleast_1d(angles), np.atleast_1d(heights))
    except ValueError:
        raise InputError(f"angles ({angles.size}) and heights ({heights.size}) differ in length") from None
    if angles.size == 0:
        raise InputError("angles/heights are empty")
    if not (np.all(np.isfinite(angles)) and np.all(np.isfinite(heights))):
        raise InputError("angles/heights contain NaN or infinity")
    rig = _vec3(rig_point, "rig_point")
    pos = rotation_z(angles) @ rig - _vec3(rig_center, "rig_center")
    pos[:, 2] += heights
    return pos


def rig_poses(angles_deg, heights_m, box: SceneBox = SIM_BOX, *, tx_rig=TX_RIG, rx_rig=RX_RIG,
              rig_center=RIG_CENTER) -> Poses:
    """AirSAS poses for turntable ``angles_deg`` [N] (degrees) and track ``heights_m`` [N] (m).

    ``tx_rig``, ``rx_rig``, ``rig_center``: the speaker, the microphone and the centre in the
    rig frame (m; default: the AirSAS constants above, a real scan passes its SysParams).
    Boresights point from each transducer at ``box.center`` (the reference's
    ``--point_at_center``).
    """
    tx = rig_positions(angles_deg, heights_m, tx_rig, rig_center)
    rx = rig_positions(angles_deg, heights_m, rx_rig, rig_center)
    return Poses.pointing_at(tx, rx, box.center)


def cylindrical_grid(n_angles: int = CYLINDRICAL_ANGLES, n_heights: int = CYLINDRICAL_HEIGHTS
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(angles_deg [A·H], heights_m [A·H]) of a cylindrical scan, height-major.

    Angles are ``k·360/A`` degrees, heights ``FIRST_HEIGHT + j·HEIGHT_STEP``; ping
    ``j·A + k`` is angle k at height j (as the reference code orders them).
    """
    if n_angles < 1 or n_heights < 1:
        raise InputError(f"cylindrical scan needs >= 1 angle and height, got {n_angles}x{n_heights}")
    angles = np.arange(n_angles) * (360.0 / n_angles)
    heights = FIRST_HEIGHT + np.arange(n_heights) * HEIGHT_STEP
    return np.tile(angles, n_heights), np.repeat(heights, n_angles)


def helical_indices(n_angles: int = CYLINDRICAL_ANGLES, n_heights: int = CYLINDRICAL_HEIGHTS,
                    pitch_levels: int = HELIX_PITCH_LEVELS) -> np.ndarray:
    """Indices into the cylindrical grid that approximate a helix (reference code
    ``airsas/utils.py::resample_cylindrical``).

    The helix rises ``pitch_levels`` height levels per turn and is sampled at
    ``n_angles · n_heights`` points over ceil(height span / pitch) turns. Each point snaps
    to the measured pose at its nearest height level and nearest measured angle;
    duplicates are removed, keeping the order along the helix. Points above the top
    level (the last partial turn) are dropped, as in the reference. A level spans
    360°/pitch_levels of azimuth, which snaps to about that many + 1 distinct angles
    (19 at 1° steps and 20 levels per turn: 2 841 of the 54 000 poses).
    """
    if pitch_levels < 1:
        raise InputError(f"helix pitch must be >= 1 level per turn, got {pitch_levels}")
    span_levels = max(n_heights - 1, 1)
    turns = math.ceil(span_levels / pitch_levels)
    t = 2 * np.pi * np.linspace(0.0, turns, n_angles * n_heights)   # helix parameter (rad)
    level = np.rint(t / (2 * np.pi) * pitch_levels).astype(np.int64)
    angle_idx = np.rint(np.mod(t, 2 * np.pi) / (2 * np.pi) * n_angles).astype(np.int64) % n_angles
    keep = level < n_heights
    flat = level[keep] * n_angles + angle_idx[keep]
    _, first = np.unique(flat, return_index=True)
    return flat[np.sort(first)]


def _positive_int(text: str, spec: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise InputError(f"trajectory '{spec}': '{text}' is not an integer") from None
    if value < 1:
        raise InputError(f"trajectory '{spec}': {value} must be >= 1")
    return value


TRAJECTORY_HELP = ("'cylindrical' (360 angles x 150 heights), 'cylindrical:A:H', 'helical', "
                   "'helical:P' (P levels per turn), 'sparse:N' (every N-th cylindrical pose), "
                   "or a .csv/.npy pose file")


def trajectory(spec: str | os.PathLike, box: SceneBox = SIM_BOX) -> Poses:
    """Poses for a trajectory spec (see ``TRAJECTORY_HELP``) or a pose file path."""
    text = os.fspath(spec)
    name, *args = text.split(":") if not text.lower().endswith((".csv", ".npy")) else (text,)
    name = name.strip().lower()
    if name == "cylindrical" and len(args) in (0, 2):
        a, h = ((_positive_int(args[0], text), _positive_int(args[1], text)) if args
                else (CYLINDRICAL_ANGLES, CYLINDRICAL_HEIGHTS))
        return rig_poses(*cylindrical_grid(a, h), box=box)
    if name == "helical" and len(args) in (0, 1):
        pitch = _positive_int(args[0], text) if args else HELIX_PITCH_LEVELS
        angles, heights = cylindrical_grid()
        idx = helical_indices(pitch_levels=pitch)
        return rig_poses(angles[idx], heights[idx], box=box)
    if name == "sparse" and len(args) == 1:
        step = _positive_int(args[0], text)
        angles, heights = cylindrical_grid()
        return rig_poses(angles[::step], heights[::step], box=box)
    if text.lower().endswith((".csv", ".npy")):
        return load_poses(text, box=box)
    raise InputError(f"unknown trajectory '{text}': expected {TRAJECTORY_HELP}")


# --- Pose files -------------------------------------------------------------------------

def _poses_from_table(table: np.ndarray, box: SceneBox, where: str) -> Poses:
    if table.ndim == 1 and table.size in (6, 9, 12):
        table = table[None, :]
    if table.ndim != 2 or table.shape[1] not in (6, 9, 12) or table.shape[0] == 0:
        raise InputError(f"{where}: expected rows of 6 (tx, rx), 9 (+ boresight) or 12 "
                         f"(+ tx and rx boresights) values, got shape {table.shape}")
    if not np.all(np.isfinite(table)):
        bad = int(np.argwhere(~np.all(np.isfinite(table), axis=1))[0, 0])
        raise InputError(f"{where}: pose {bad} contains NaN or infinity")
    tx, rx = table[:, 0:3], table[:, 3:6]
    if table.shape[1] == 6:
        return Poses.pointing_at(tx, rx, box.center)
    tb = table[:, 6:9]
    rb = table[:, 9:12] if table.shape[1] == 12 else tb
    for name, b in (("boresight", tb), ("rx boresight", rb)):
        if np.any(np.linalg.norm(b, axis=1) < 1e-12):
            raise InputError(f"{where}: {name} of zero length")
    return Poses(tx, rx, tb, rb)


def _read_csv_table(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not a UTF-8 text (CSV) file") from None
    rows, header_allowed = [], True
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f for f in (s.strip() for s in line.replace(",", " ").split()) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if header_allowed:       # a non-numeric first row is a header
                header_allowed = False
                continue
            raise InputError(f"{path} line {lineno}: non-numeric value in '{line[:60]}'") from None
        header_allowed = False
        if rows and len(values) != len(rows[0]):
            raise InputError(f"{path} line {lineno}: {len(values)} values, "
                             f"earlier rows have {len(rows[0])}")
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no pose rows")
    return np.array(rows, dtype=np.float64)


def load_poses(path: str | os.PathLike, box: SceneBox = SIM_BOX) -> Poses:
    """Read poses from a .csv (optional header row) or .npy file with 6, 9 or 12 columns.

    Columns: tx_x, tx_y, tx_z, rx_x, rx_y, rx_z [, b_x, b_y, b_z] (metres). A boresight
    column applies to TX and RX; without one, each beam points at ``box.center``.
    12 columns (tx boresight, then rx boresight) is sonarsim's lossless extension.
    """
    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: pose file not found")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            table = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise FormatError(f"{p}: not a readable .npy array ({exc})") from None
        if not np.issubdtype(table.dtype, np.number) or np.iscomplexobj(table):
            raise InputError(f"{p}: expected a real numeric array, got dtype {table.dtype}")
        table = table.astype(np.float64)
    elif suffix == ".csv":
        table = _read_csv_table(p)
    else:
        raise FormatError(f"{p}: pose files must end in .csv or .npy")
    return _poses_from_table(table, box, str(p))


def save_poses(path: str | os.PathLike, poses: Poses, boresight: str = "auto") -> None:
    """Write ``poses`` to .csv (with header) or .npy, atomically.

    ``boresight``: 'none' (6 columns; readers re-derive beams pointing at the box centre),
    'shared' (9 columns, the TX boresight), 'both' (12 columns), or 'auto' = 'shared' when
    TX and RX boresights agree, else 'both' (so that a round trip is exact).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".csv", ".npy"):
        raise InputError(f"{p}: pose files must end in .csv or .npy")
    if boresight == "auto":
        boresight = "shared" if np.allclose(poses.tx_boresight, poses.rx_boresight,
                                            rtol=0, atol=1e-15) else "both"
    parts = {"none": [poses.tx, poses.rx],
             "shared": [poses.tx, poses.rx, poses.tx_boresight],
             "both": [poses.tx, poses.rx, poses.tx_boresight, poses.rx_boresight]}
    if boresight not in parts:
        raise InputError(f"boresight: expected auto|none|shared|both, got '{boresight}'")
    table = np.concatenate(parts[boresight], axis=1)
    header = {"none": POSE_HEADER, "shared": POSE_HEADER + BORESIGHT_HEADER,
              "both": POSE_HEADER + TWO_BORESIGHT_HEADER}[boresight]
    with atomic_path(p, keep_suffix=False) as tmp, open(tmp, "wb") as f:
        if suffix == ".npy":
            np.save(f, table)
        else:
            buf = io.StringIO()
            writer = csv.writer(buf, lineterminator="\n")
            writer.writerow(header)
            writer.writerows([[repr(float(v)) for v in row] for row in table])
            f.write(buf.getvalue().encode("utf-8"))


# --- Crop window ------------------------------------------------------------------------

@dataclass(frozen=True)
class CropWindow:
    """Samples [min_sample, min_sample + num_samples) at fs cover the scene for all poses.

    ``min_dist`` = min_sample·c/fs and ``max_dist`` = (min_sample + num_samples)·c/fs are
    round-trip path lengths (m).
    """

    min_sample: int
    num_samples: int
    min_dist: float
    max_dist: float

    def path_lengths(self, sound_speed: float, fs: float) -> np.ndarray:
        """[num_samples] round-trip path length (m) of each sample in the window."""
        return (self.min_sample + np.arange(self.num_samples)) * (sound_speed / fs)


def crop_window(poses: Poses, box: SceneBox, sound_speed: float, fs: float,
                pulse_samples: int = 100, pad: float = 0.05) -> CropWindow:
    """Sample window that holds every echo from ``box`` (reference code ``sas_utils.crop_wfm``).

    Over all poses and the 8 box corners, the round-trip distance range is widened by
    ``pad`` (m) plus the pulse length ``pulse_samples·c/fs`` (the reference uses
    min(len(pulse), 100) samples), then snapped outward to whole samples.
    """
    if not (math.isfinite(sound_speed) and sound_speed > 0):
        raise InputError(f"sound_speed must be positive, got {sound_speed}")
    if not (math.isfinite(fs) and fs > 0):
        raise InputError(f"fs must be positive, got {fs}")
    if pulse_samples < 0 or not math.isfinite(pad) or pad < 0:
        raise InputError(f"pulse_samples ({pulse_samples}) and pad ({pad}) must be >= 0")
    dist = poses.round_trip(box.corners())
    margin = pad + pulse_samples * sound_speed / fs
    min_dist = float(dist.min()) - margin
    max_dist = float(dist.max()) + margin
    min_sample = max(int(math.floor(min_dist * fs / sound_speed)), 0)
    min_dist = min_sample * sound_speed / fs
    num_samples = int(math.ceil((max_dist - min_dist) * fs / sound_speed))
    max_dist = (min_sample + num_samples) * sound_speed / fs
    return CropWindow(min_sample, num_samples, min_dist, max_dist)
