"""The geometry, pulse and sound speed of an openSTB simulation, from its configuration TOML.

openSTB's result (:mod:`sonarsim.importers.openstb`) holds the pressures and the ping start
times; where the sonar was and what it sent are in the simulation's configuration. This
module evaluates the parts of it that define them, following openSTB's definitions
(openSTB/simulator ``system/trajectory.py``, ``system/transducer.py``,
``travel_time/stop_and_hop.py``, ``system/signal.py``, ``system/signal_windows.py``):

* ``[trajectory]``: ``linear`` (``start_position``, ``end_position``, ``speed``; the vehicle's
  x axis turned onto the direction of travel by the shortest rotation) or ``circular``
  (``centre``, ``radius``, ``speed``, ``clockwise``, ``start_angle`` in degrees; heading
  tangent to the circle);
* ``[system]`` ``generic`` with a ``transmitter`` and ``receivers``, each ``generic`` with a
  ``position`` (m, vehicle frame) and an ``orientation`` quaternion [w, x, y, z] of its
  boresight relative to the vehicle's x axis;
* stop and hop: at a ping's start time t the transducers are at ``p(t) + R(t)·position``
  (p, R: the vehicle's position and orientation); boresight = ``(q_transducer · q(t))``
  applied to x, as openSTB's travel-time plugin composes them;
* ``[system.signal]``: ``lfm_chirp`` or ``hfm_chirp`` (``f_start``, ``f_stop``, ``duration``,
  ``rms_spl``, ``rms_after_window``, ``window`` = tukey, hann, hamming, blackman,
  blackman_harris or nuttall): the real pulse ``Re s(t)`` in Pa at the output rate;
* ``[environment]`` ``invariant``: ``sound_speed``.

Other plugins are refused in one line naming them. The plugin name is read from ``plugin``
(or the older ``name``).
"""
from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import FormatError, InputError

COSINE_WINDOWS = {          # generalised cosine coefficients a_k (Harris 1978; Nuttall 1981)
    "hann": [0.5, 0.5],
    "blackman": [0.42, 0.5, 0.08],
    "blackman_harris": [0.35875, 0.48829, 0.14128, 0.01168],
    "nuttall": [0.3635819, 0.4891775, 0.1365995, 0.0106411],
}
HAMMING_A0 = {"optimal": 0.53836, "original": 25 / 46, "scipy": 0.54}


def read_config(path: str | os.PathLike, ping_times: np.ndarray, n_receivers: int,
                fs: float) -> dict:
    """``tx``, ``rx``, ``boresight``, ``rx_boresight`` [pings, receivers, 3], ``pulse`` [L]
    (Pa, at ``fs``), ``sound_speed`` (m/s or None) and ``meta`` of the simulation configured
    in ``path``, at the result's ``ping_times`` [pings] (s)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise FormatError(f"{path}: no such configuration file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: not a valid TOML configuration ({exc})") from None
    cfg = _Config(path, doc)
    system = cfg.table(doc, "system", "generic")
    receivers = system.get("receivers")
    if not isinstance(receivers, list) or len(receivers) != n_receivers:
        raise cfg.error("system.receivers", f"expected {n_receivers} receivers (the result's), "
                        f"got {len(receivers) if isinstance(receivers, list) else 'none'}")
    traj = trajectory(cfg, cfg.table(doc, "trajectory"))
    veh_pos = traj.position(ping_times)                   # [P, 3]
    veh_rot = traj.orientation(ping_times)                # P rotations
    tx_t = cfg.table(system, "transmitter", "generic", "system.transmitter")
    tx_pos, tx_rot = cfg.vector(tx_t, "position", "system.transmitter"), \
        cfg.quaternion(tx_t, "system.transmitter")
    tx = veh_pos + veh_rot.apply(tx_pos)
    bore = (tx_rot * veh_rot).apply([1.0, 0.0, 0.0])
    rx, rx_bore = [], []
    for r, table in enumerate(receivers):
        where = f"system.receivers[{r}]"
        table = cfg.check_plugin(table, "generic", where)
        rx.append(veh_pos + veh_rot.apply(cfg.vector(table, "position", where)))
        rx_bore.append((cfg.quaternion(table, where) * veh_rot).apply([1.0, 0.0, 0.0]))
    n = len(ping_times)
    stack = lambda a: np.stack(a, axis=1)                 # noqa: E731  [P, R, 3]
    return {
        "tx": np.repeat(tx[:, None, :], n_receivers, axis=1), "rx": stack(rx),
        "boresight": np.repeat(bore.reshape(n, 1, 3), n_receivers, axis=1),
        "rx_boresight": stack([b.reshape(n, 3) for b in rx_bore]),
        "pulse": pulse(cfg, cfg.table(system, "signal", None, "system.signal"), fs),
        "sound_speed": sound_speed(cfg, doc.get("environment")),
        "source": "openstb",
        "meta": {"openstb_config": str(path), "amplitude_model": "pressure"},
    }


class _Config:
    """Typed access to a configuration document with one-line errors naming the key."""

    def __init__(self, path: Path, doc: dict):
        self.path, self.doc = path, doc

    def error(self, key: str, message: str) -> FormatError:
        return FormatError(f"{self.path}: {key}: {message}")

    def check_plugin(self, table, expected: str | None, where: str) -> dict:
        if not isinstance(table, dict):
            raise self.error(where, "expected a table")
        name = table.get("plugin", table.get("name"))
        if expected is not None and name != expected:
            raise self.error(f"{where}.plugin", f"{name!r} is not supported here (supported: "
                             f"{expected!r})")
        return table

    def table(self, parent: dict, key: str, expected: str | None = None,
              where: str | None = None) -> dict:
        where = where or key
        if key not in parent:
            raise self.error(where, "missing")
        return self.check_plugin(parent[key], expected, where)

    def number(self, table: dict, key: str, where: str, default=None) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise self.error(f"{where}.{key}", f"expected a number, got {value!r}")
        return float(value)

    def vector(self, table: dict, key: str, where: str, size: int = 3) -> np.ndarray:
        value = table.get(key)
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (size,) or not np.all(np.isfinite(arr)):
            raise self.error(f"{where}.{key}", f"expected {size} numbers, got {value!r}")
        return arr

    def quaternion(self, table: dict, where: str) -> Rotation:
        q = self.vector(table, "orientation", where, 4)      # [w, x, y, z]
        if not np.linalg.norm(q) > 0:
            raise self.error(f"{where}.orientation", "a zero quaternion is no rotation")
        return Rotation.from_quat(q, scalar_first=True)


# --------------------------------------------------------------------------- trajectory

class _Linear:
    def __init__(self, start, end, speed: float):
        self.start, self.speed = start, speed
        diff = end - start
        self.length = float(np.linalg.norm(diff))
        self.direction = diff / self.length
        self.rotation = shortest_rotation(np.array([1.0, 0.0, 0.0]), self.direction)

    def position(self, t):
        return self.start + np.asarray(t, float)[:, None] * self.speed * self.direction

    def orientation(self, t):
        return Rotation.from_quat(np.tile(self.rotation.as_quat(), (len(t), 1)))


class _Circular:
    def __init__(self, centre, radius: float, speed: float, clockwise: bool, start_deg: float):
        self.centre, self.radius, self.speed = centre, radius, speed
        self.sign = 1.0 if clockwise else -1.0
        self.start = math.radians(start_deg)

    def _angle(self, t):
        return self.start + self.sign * np.asarray(t, float) * self.speed / self.radius

    def position(self, t):
        a = self._angle(t)
        return self.centre + self.radius * np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)

    def orientation(self, t):
        heading = self._angle(t) + self.sign * math.pi / 2
        return Rotation.from_euler("z", heading)


def shortest_rotation(reference: np.ndarray, target: np.ndarray) -> Rotation:
    """The rotation turning unit vector ``reference`` onto ``target`` about their common
    normal (about z when they are parallel or opposite), as openSTB orients a linear
    trajectory."""
    dot = float(np.clip(np.dot(reference, target), -1.0, 1.0))
    axis = np.cross(reference, target)
    if np.isclose(abs(dot), 1.0):
        axis = np.array([0.0, 0.0, 1.0])
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.acos(dot))


def trajectory(cfg: _Config, table: dict):
    kind = table.get("plugin", table.get("name"))
    if kind == "linear":
        start = cfg.vector(table, "start_position", "trajectory")
        end = cfg.vector(table, "end_position", "trajectory")
        speed = cfg.number(table, "speed", "trajectory")
        if not (speed > 0 and np.linalg.norm(end - start) > 0):
            raise cfg.error("trajectory", "needs a positive speed and distinct end points")
        return _Linear(start, end, speed)
    if kind == "circular":
        speed = cfg.number(table, "speed", "trajectory")
        radius = cfg.number(table, "radius", "trajectory")
        clockwise = table.get("clockwise")
        if not isinstance(clockwise, bool) or not (speed > 0 and radius > 0):
            raise cfg.error("trajectory", "circular needs radius > 0, speed > 0 and "
                            "clockwise = true|false")
        return _Circular(cfg.vector(table, "centre", "trajectory"), radius, speed, clockwise,
                         cfg.number(table, "start_angle", "trajectory", 0.0))
    raise cfg.error("trajectory.plugin", f"{kind!r} is not supported here (supported: "
                    "'linear', 'circular')")


# -------------------------------------------------------------------------------- pulse

def window(cfg: _Config, spec, t: np.ndarray, duration: float) -> np.ndarray:
    """openSTB's signal window ``spec`` at times ``t`` in [0, duration]."""
    spec = {"plugin": spec} if isinstance(spec, str) else spec
    kind = cfg.check_plugin(spec, None, "system.signal.window").get(
        "plugin", spec.get("name"))
    if kind == "tukey":
        alpha = cfg.number(spec, "alpha", "system.signal.window")
        if not 0 <= alpha <= 1:
            raise cfg.error("system.signal.window.alpha", f"must be in [0, 1], got {alpha}")
        taper = duration * alpha / 2.0
        w = np.ones_like(t)
        if taper > 0:
            rise, fall = t < taper, t > duration - taper
            w[rise] = 0.5 * (1 + np.cos(np.pi * (t[rise] / taper - 1)))
            w[fall] = 0.5 * (1 + np.cos(np.pi * (t[fall] - (duration - taper)) / taper))
        return w
    if kind == "hamming":
        a0 = HAMMING_A0.get(spec.get("mode", "optimal"))
        if a0 is None:
            raise cfg.error("system.signal.window.mode", f"unknown {spec.get('mode')!r}")
        coefficients = [a0, 1 - a0]
    elif kind in COSINE_WINDOWS:
        coefficients = COSINE_WINDOWS[kind]
    elif kind == "generalised_cosine":
        coefficients = [float(a) for a in spec.get("coefficients", [])]
    else:
        raise cfg.error("system.signal.window.plugin", f"{kind!r} is not supported here")
    arg = 2 * np.pi * t / duration
    return sum((-1) ** k * a * np.cos(k * arg) for k, a in enumerate(coefficients))


def pulse(cfg: _Config, table: dict, fs: float) -> np.ndarray:
    """The real transmitted pulse ``Re s(t)`` (Pa) at ``t = k / fs`` over its duration."""
    kind = table.get("plugin", table.get("name"))
    if kind not in ("lfm_chirp", "hfm_chirp"):
        raise cfg.error("system.signal.plugin", f"{kind!r} is not supported here "
                        "(supported: 'lfm_chirp', 'hfm_chirp')")
    f0 = cfg.number(table, "f_start", "system.signal")
    f1 = cfg.number(table, "f_stop", "system.signal")
    duration = cfg.number(table, "duration", "system.signal")
    spl = cfg.number(table, "rms_spl", "system.signal")
    if not (duration > 0 and f0 > 0 and f1 > 0):
        raise cfg.error("system.signal", "needs positive frequencies and duration")
    if duration * fs > 1e7:
        raise InputError(f"{cfg.path}: system.signal.duration {duration:g} s is more than "
                         "10^7 samples at the output rate")
    t = np.arange(int(math.floor(duration * fs)) + 1) / fs
    if kind == "lfm_chirp":
        s = np.exp(1j * np.pi * t * (2 * f0 + (f1 - f0) / duration * t))
    else:
        b = (1 / f1 - 1 / f0) / duration
        s = np.exp(2j * np.pi * np.log1p(b * f0 * t) / b)
    level = 10 ** (spl / 20) * 1e-6
    win = table.get("window")
    after = bool(table.get("rms_after_window", True)) and win is not None
    if win is not None:
        s = s * window(cfg, win, t, duration)
    s = s * (level / np.sqrt(np.mean(np.abs(s) ** 2)) if after else level)
    return s.real


def sound_speed(cfg: _Config, table) -> float | None:
    if table is None:
        return None
    table = cfg.check_plugin(table, "invariant", "environment")
    return cfg.number(table, "sound_speed", "environment") if "sound_speed" in table else None
