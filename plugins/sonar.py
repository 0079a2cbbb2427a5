"""Mitsuba sensor ``sonar``: the pose(s) of a sonar for ``mi.render`` with ``sonar_transient``.

A pose is a transmitter (TX) and a receiver (RX) position (m, world frame) and their
boresights. ``mi.render(scene)`` with the ``sonar_transient`` integrator returns the pose's
per-bounce histograms over round-trip path length, on the axis of the sensor's
``sonar_film`` (docs/differentiable.md).

Properties: ``tx_origin`` [3] (m, required), ``rx_origin`` [3] (default: ``tx_origin``, a
monostatic sonar), ``tx_boresight`` [3] (required; normalised), ``rx_boresight`` [3]
(default: ``tx_boresight``); optionally the beam of either end, which then replaces the
integrator's: ``tx_beam``/``rx_beam`` ('cone' | 'isotropic' | 'piston') with
``tx_beamwidth``/``rx_beamwidth`` (full width in degrees; piston: half-power width; default
30); a ``film`` (``sonar_film``) and a ``sampler`` whose ``sample_count`` is the number of
TX-cone paths per pose (used by ``bounce1='cone'`` only).

Several poses: a scene may hold several ``sonar`` sensors (``mi.render(scene, sensor=i)``),
or one sensor may hold N poses (batch form): set its parameters to Dr.Jit vectors of width
N (each of width N or 1, which is broadcast), e.g.
``params['sensor.tx_origin'] = mi.Point3f(x, y, z)``, or all four from [N, 3] arrays with
:func:`set_poses`; ``params.update()``; ``mi.render``
then returns (N, B, T), pose i's histograms equal to those of a one-pose sensor with the
same seed and pose offset i (see ``sonar_transient.render_transients``).

The four vectors are differentiable parameters (``mi.traverse``). Depends on mitsuba and
drjit only.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ._beams import BEAM_KINDS, Beam

PLUGIN_NAME = "sonar"
VARIANT = mi.variant()   # the variant this module's class was built for
_VECTORS = ("tx_origin", "rx_origin", "tx_boresight", "rx_boresight")


def _vector(props, name: str, default=None):
    if name not in props:
        if default is None:
            raise ValueError(f"sonar: property {name!r} is required")
        return mi.Point3f(default)
    value = props.get(name)
    try:
        x, y, z = (float(value[i]) for i in range(3))
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"sonar: {name} must be three numbers, got {value!r}") from None
    return mi.Point3f(x, y, z)


def _beam(props, end: str):
    """The ``end`` ('tx' | 'rx') beam the properties set, or None (the integrator's)."""
    kind, width = props.get(f"{end}_beam", None), props.get(f"{end}_beamwidth", None)
    if kind is None and width is None:
        return None
    kind = "cone" if kind is None else str(kind)
    if kind not in BEAM_KINDS:
        raise ValueError(f"sonar: {end}_beam must be one of {BEAM_KINDS}, got {kind!r}")
    return Beam(kind, 30.0 if width is None else float(width), end)


class SonarSensor(mi.Sensor):
    """TX/RX poses for ``sonar_transient`` (see the module doc)."""

    def __init__(self, props):
        super().__init__(props)
        self.tx_origin = _vector(props, "tx_origin")
        self.rx_origin = _vector(props, "rx_origin", self.tx_origin)
        self.tx_boresight = _vector(props, "tx_boresight")
        self.rx_boresight = _vector(props, "rx_boresight", self.tx_boresight)
        self.tx_beam, self.rx_beam = _beam(props, "tx"), _beam(props, "rx")
        if not hasattr(self.film(), "window"):
            raise ValueError("sonar: the film must be a 'sonar_film'")
        self._check()

    def _check(self) -> None:
        widths = {name: dr.width(getattr(self, name)) for name in _VECTORS}
        n = max(widths.values())
        if any(w not in (1, n) for w in widths.values()) or min(widths.values()) < 1:
            raise ValueError(f"sonar: the pose vectors need width N or 1, got {widths}")
        for name in _VECTORS:
            v = dr.detach(getattr(self, name))
            if not dr.all(dr.isfinite(v.x) & dr.isfinite(v.y) & dr.isfinite(v.z)):
                raise ValueError(f"sonar: {name} contains NaN or infinite values")
            if name.endswith("boresight") and dr.any(dr.squared_norm(v) == 0):
                raise ValueError(f"sonar: {name} contains a zero-length boresight")

    def pose_count(self) -> int:
        """N: the number of poses the sensor holds."""
        return max(dr.width(getattr(self, name)) for name in _VECTORS)

    def pose_vectors(self):
        """(tx, rx, tx_boresight, rx_boresight, N): Dr.Jit vectors of width N or 1 (m),
        carrying gradients where enabled."""
        return (self.tx_origin, self.rx_origin, self.tx_boresight, self.rx_boresight,
                self.pose_count())

    def traverse(self, callback):
        for name in _VECTORS:
            callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)
        callback.put("film", self.film(), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        # The parameters were updated in place: they must stay the very arrays that
        # mi.traverse holds (gradients accumulate there), so they are only checked.
        self._check()

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        raise RuntimeError("sonar: a sonar sensor has no rays; render it with sonar_transient")

    def to_string(self):
        return f"SonarSensor[poses={self.pose_count()}, film={self.film()}]"


mi.register_sensor(PLUGIN_NAME, lambda props: SonarSensor(props))


def set_poses(params, tx, tx_boresight, rx=None, rx_boresight=None, *, sensor: str = "sensor"):
    """Load N poses into the batch form of the ``sonar`` sensor ``sensor`` of ``params``.

    ``params``: ``mi.traverse(scene)``. ``tx``, ``rx``: [N, 3] positions (m, world frame);
    ``tx_boresight``, ``rx_boresight``: [N, 3] directions (normalised by the sensor); any
    array indexable as ``a[:, i]`` (NumPy). ``rx`` defaults to ``tx`` (monostatic) and
    ``rx_boresight`` to ``tx_boresight``. Sets the four parameters to ``Point3f`` of width N;
    the caller calls ``params.update()`` (after its other changes).
    """
    rx = tx if rx is None else rx
    rx_boresight = tx_boresight if rx_boresight is None else rx_boresight
    for name, value in zip(_VECTORS, (tx, rx, tx_boresight, rx_boresight)):
        params[f"{sensor}.{name}"] = mi.Point3f(*(mi.Float(value[:, i]) for i in range(3)))
