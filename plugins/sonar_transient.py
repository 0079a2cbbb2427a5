"""Mitsuba integrator ``sonar_transient``: per-bounce energy histograms over round-trip path length.

Physics (intensity mode, DESIGN §4). The transmitter (TX) is a point source of radiant
intensity ``b_T(ω)``; the receiver (RX) is a point that reports ``∫ b_R(ω) L(ω) dω``
(no receiver cosine). Surfaces are two-sided Lambertian with the albedo ρ of each shape's
(diffuse) BSDF. A surface element dA seen directly by both ends contributes

    b_T · b_R · ρ/π · cosθ_i · cosθ_o / (r_T² r_R²) dA     at path length r_T + r_R,

and bounce k adds k − 1 further diffuse reflections before the connection to the RX.

Estimator. A TX direction is sampled from the beam (uniform in the cone's solid angle,
uniform on the sphere for ``isotropic``, a cone/hemisphere mixture for ``piston``), so the
path throughput starts at ``b_T/pdf``; at every vertex the path is connected to the RX with
a shadow ray (next-event estimation; its value is stored in the histogram of that bounce);
the path continues by cosine-weighted sampling (throughput × ρ), its ray started a hair along
its own direction so that it is the sampled line; path lengths are summed from the vertex
positions (docs/transient_rendering.md). The poses of a call and all their paths run as
wavefront Dr.Jit kernels of up to 2²⁴ lanes, each pose's paths sorted by their first TX
direction so that neighbouring lanes trace coherent rays (a path's random numbers do not
depend on its lane); every per-call scalar enters the kernel as an opaque value, so new
poses, windows or seeds reuse the compiled kernel.

Binning. Bin j covers round-trip path lengths [path_start + j·w, path_start + (j+1)·w).
A contribution at path length L is split linearly (tent) between the two bins whose centres
enclose L. The histogram equals the restriction of an unbounded histogram to bins 0…T−1:
parts of a tent that fall outside the window are dropped, never piled into the edge bins.

Randomness. Lane (pose p, path k) draws from a PCG32 stream seeded by a hash of
(seed, pose_offset + p, k), so a pose receives the same random numbers whatever chunk it is
rendered in. Threads add into the histogram in a varying order; accumulating in float64
(default ``accumulator='float64'``) and rounding to float32 at the end makes results
identical from run to run and for any chunking, except for a rare 1-ulp difference when a
sum falls on a float32 rounding boundary. ``accumulator='float32'`` halves the buffer
memory but is reproducible only to about 1e-6 relative.

A coherent mode (seed Eq. (1): amplitude 1/(r_T r_R), fixed random phase per surface
point) would change only the per-vertex weight and splat complex values; sampling,
visibility, binning and seeding stay as they are (docs/transient_rendering.md).

This module depends on mitsuba and drjit (and numpy for the returned array) only. Like
Mitsuba's own Python integrators it needs a variant to be set before it is imported; the
class is defined at module level and registered under ``sonar_transient`` on import, so
after ``sonarsim.runtime.mitsuba()`` it can be loaded with
``mi.load_dict({"type": "sonar_transient", ...})``, read and subclassed.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._beams import BEAM_KINDS, Beam, piston_ka  # noqa: F401  (re-exported)
from ._cone_tracer import ConeTracer
from ._path_vertex import PathVertices
from ._path_vertex import AdjointSink, HistogramSink
from ._surface_estimator import StrataLanes, SurfaceEstimator

PLUGIN_NAME = "sonar_transient"
VARIANT = mi.variant()   # the variant this module's class was built for
MAX_BOUNCES_LIMIT = 64
AMPLITUDES = ("intensity", "pressure", "coherent")
BOUNCE1_ESTIMATORS = ("surface", "cone")
DEFAULT_SURFACE_SPACING = 8e-3     # m: longest edge of the bounce-1 quadrature's facets
DEFAULT_VERTEX_SPREAD = 0.0        # m: disk radius over which bounce >= 2 vertices spread
DEFAULT_GUIDE_FRACTION = 0.5      # share of continuations aimed at the objects' bounding sphere
DEFAULT_PATH_SAMPLES = 16          # path-length quantiles splatted per facet
DEFAULT_SPECKLE_SPACING = 3e-3     # m: scatterer cells of the 'coherent' amplitude


class SonarTransientIntegrator(mi.SamplingIntegrator):
    """Transient sonar integrator; use :meth:`render_transients` (not ``mi.render``).

    Properties (validated here, once, with a one-line ``ValueError``):
    ``max_bounces`` (int in 1..64, default 3), ``tx_beam``/``rx_beam``
    ('cone' | 'isotropic' | 'piston', default 'cone'), ``tx_beamwidth``/``rx_beamwidth``
    (full beamwidth in degrees, default 30; for 'piston' the half-power width),
    ``shading_normals`` (bool, default True: cosines use interpolated mesh normals),
    ``accumulator`` ('float64' | 'float32', default 'float64': the histogram buffer type),
    ``bounce1`` ('surface' | 'cone', default 'surface': the bounce-1 estimator),
    ``amplitude`` ('intensity' | 'pressure' | 'coherent', default 'intensity'),
    ``surface_spacing`` (m in [1e-5, 10], default 8e-3: longest edge of the surface
    quadrature's strata), ``path_samples`` (int in 1..64, default 16: path-length quantiles
    splatted per facet), ``facet_paths`` (int in 1..16, default 1: continuations per surface
    point for bounces >= 2), ``guide_fraction`` (in [0, 1), default 0.5: share of
    continuations aimed at the objects' bounding sphere), ``vertex_spread`` (m, default 0:
    disk radius over which the vertices of bounces >= 2 are spread in path length),
    ``speckle_spacing`` (m in [1e-5, 10], default 3e-3: scatterer cell of 'coherent'),
    ``speckle_seed`` (int in [0, 2^32), default 0: the phases of 'coherent').
    """

    def __init__(self, props):
        super().__init__(props)
        self.max_bounces = int(props.get("max_bounces", 3))
        if not 1 <= self.max_bounces <= MAX_BOUNCES_LIMIT:
            raise ValueError(f"sonar_transient: max_bounces must be in 1..{MAX_BOUNCES_LIMIT}, "
                             f"got {self.max_bounces}")
        self.tx_beam = Beam(str(props.get("tx_beam", "cone")),
                             float(props.get("tx_beamwidth", 30.0)), "tx")
        self.rx_beam = Beam(str(props.get("rx_beam", "cone")),
                             float(props.get("rx_beamwidth", 30.0)), "rx")
        self.shading_normals = bool(props.get("shading_normals", True))
        accumulator = str(props.get("accumulator", "float64"))
        if accumulator not in ("float64", "float32"):
            raise ValueError("sonar_transient: accumulator must be 'float64' or 'float32', "
                             f"got {accumulator!r}")
        self.float64 = accumulator == "float64"
        if "mode" in props:
            raise ValueError("sonar_transient: the property 'mode' is now called 'amplitude'")
        self.amplitude = str(props.get("amplitude", "intensity"))
        if self.amplitude not in AMPLITUDES:
            raise ValueError(f"sonar_transient: amplitude must be one of {AMPLITUDES}, "
                             f"got {self.amplitude!r}")
        self.bounce1 = str(props.get("bounce1", "surface"))
        if self.bounce1 not in BOUNCE1_ESTIMATORS:
            raise ValueError(f"sonar_transient: bounce1 must be one of {BOUNCE1_ESTIMATORS}, "
                             f"got {self.bounce1!r}")
        self.surface_spacing = float(props.get("surface_spacing", DEFAULT_SURFACE_SPACING))
        self.speckle_spacing = float(props.get("speckle_spacing", DEFAULT_SPECKLE_SPACING))
        for name, value in (("surface_spacing", self.surface_spacing),
                            ("speckle_spacing", self.speckle_spacing)):
            if not (math.isfinite(value) and 1e-5 <= value <= 10.0):
                raise ValueError(f"sonar_transient: {name} must be in [1e-5, 10] m, got {value}")
        self.path_samples = int(props.get("path_samples", DEFAULT_PATH_SAMPLES))
        if not 1 <= self.path_samples <= 64:
            raise ValueError(f"sonar_transient: path_samples must be in 1..64, "
                             f"got {self.path_samples}")
        self.vertex_spread = float(props.get("vertex_spread", DEFAULT_VERTEX_SPREAD))
        self.facet_paths = int(props.get("facet_paths", 1))
        if not 1 <= self.facet_paths <= 16:
            raise ValueError(f"sonar_transient: facet_paths must be in 1..16, got {self.facet_paths}")
        self.guide_fraction = float(props.get("guide_fraction", DEFAULT_GUIDE_FRACTION))
        if not 0.0 <= self.guide_fraction < 1.0:
            raise ValueError(f"sonar_transient: guide_fraction must be in [0, 1), "
                             f"got {self.guide_fraction}")
        self.speckle_seed = int(props.get("speckle_seed", 0))
        if not 0 <= self.speckle_seed < 2**32:
            raise ValueError(f"sonar_transient: speckle_seed must be in [0, 2^32), "
                             f"got {self.speckle_seed}")
        self._strata_cache: dict = {}

    @property
    def complex_output(self) -> bool:
        """True if histograms are complex64 ('coherent'), else float32."""
        return self.amplitude == "coherent"

    def to_string(self):
        return (f"SonarTransientIntegrator[max_bounces={self.max_bounces}, "
                f"tx_beam={self.tx_beam.describe()}, rx_beam={self.rx_beam.describe()}, "
                f"bounce1={self.bounce1}, amplitude={self.amplitude}]")

    # ------------------------------------------------------------------ mi.render
    def render(self, scene, sensor=None, seed=0, spp=0, develop=True, evaluate=True):
        """The histograms of a ``sonar`` sensor (``mi.render``): TensorXf (B, T) for one pose,
        (N, B, T) for a sensor holding N poses; a last axis [real, imag] for 'coherent'.

        B = ``max_bounces``, T = the ``sonar_film``'s ``temporal_bins``. Same estimator and
        random numbers as :meth:`render_transients` with ``seed`` and ``pose_offset=0``.
        ``spp``: TX-cone paths per pose (0: the sensor's sampler ``sample_count``); used by
        bounce1='cone' only. Gradients: through ``mi.render(scene, params)``
        (:meth:`render_backward`, :meth:`render_forward`); this primal tracks none.
        """
        sensor = _sonar_sensor(scene, sensor)
        with dr.suspend_grad():
            ctx, roi, paths = self._sensor_context(scene, sensor, seed, spp)
            buf_type = mi.Float64 if self.float64 else mi.Float
            hists = [dr.zeros(buf_type, ctx["n_hist"]) for _ in range(ctx["parts"])]
            self._histograms(scene, HistogramSink(hists, ctx), ctx, roi, paths)
            out = self._tensor(ctx, [mi.Float(h) for h in hists])
            if evaluate:
                dr.eval(out)
        sensor.film().histogram = out
        return out if develop else mi.TensorXf()

    def render_forward(self, scene, params=None, sensor=0, seed=0, spp=0):
        """Forward-mode derivative of :meth:`render` (the gradients set on the scene's
        parameters, propagated to the histograms): a TensorXf shaped as ``render``'s."""
        sensor = _sonar_sensor(scene, sensor)
        with dr.resume_grad():
            ctx, roi, paths = self._sensor_context(scene, sensor, seed, spp)
            buf_type = mi.Float64 if self.float64 else mi.Float
            hists = [dr.zeros(buf_type, ctx["n_hist"]) for _ in range(ctx["parts"])]
            ctx["reduce_mode"] = dr.ReduceMode.Auto
            self._histograms(scene, HistogramSink(hists, ctx), ctx, roi, paths)
            out = self._tensor(ctx, [mi.Float(h) for h in hists])
            dr.forward_to(out)
            return mi.TensorXf(dr.grad(out))

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Reverse-mode derivative of :meth:`render` by path replay: every path of the
        primal is traced again with the same random numbers, and each contribution,
        weighted by ``grad_in`` (shaped as ``render``'s output) at its tent bins, is
        back-propagated into the scene parameters launch by launch
        (:class:`._path_vertex.AdjointSink`; docs/differentiable.md)."""
        sensor = _sonar_sensor(scene, sensor)
        with dr.resume_grad():
            ctx, roi, paths = self._sensor_context(scene, sensor, seed, spp)
            flat = mi.Float(dr.detach(grad_in).array)
            if ctx["parts"] == 2:      # [..., T, 2]: real and imaginary parts interleaved
                half = dr.arange(mi.UInt32, ctx["n_hist"]) * 2
                grads = [dr.gather(mi.Float, flat, half), dr.gather(mi.Float, flat, half + 1)]
            else:
                grads = [flat]
            self._histograms(scene, AdjointSink(grads, ctx), ctx, roi, paths)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        raise RuntimeError("sonar_transient has no image mode: render a 'sonar' sensor "
                           "(mi.render) or call render_transients()")

    def _sensor_context(self, scene, sensor, seed, spp):
        """(context, region of interest, TX-cone paths per pose) of a ``sonar`` sensor."""
        tx, rx, tx_dir, rx_dir, n = sensor.pose_vectors()
        film = sensor.film()
        start, width, n_bins = film.window()
        paths = int(spp) if spp else int(sensor.sampler().sample_count())
        seed = _as_seed(seed)
        self._check_launch(n, paths, n_bins, False)
        beams = (sensor.tx_beam or self.tx_beam, sensor.rx_beam or self.rx_beam)
        ctx = self._context_arrays(tx, rx, tx_dir, rx_dir, n, start, width, n_bins, seed, 0,
                                   False, dr.ReduceMode.Local, beams)
        roi = None
        if self.bounce1 == "surface":
            arrays = [np.asarray(dr.detach(v), np.float64).reshape(3, -1).T
                      for v in (ctx["tx"], ctx["rx"], ctx["tx_dir"], ctx["rx_dir"])]
            arrays[2:] = [a / np.linalg.norm(a, axis=1, keepdims=True) for a in arrays[2:]]
            end = float(dr.detach(start)[0]) + (n_bins + 1) * float(dr.detach(width)[0])
            roi = self._region(*arrays, end, beams)
        return ctx, roi, paths

    def _tensor(self, ctx, hists):
        """The histograms [N·B·T] (one per part) as render()'s TensorXf."""
        n, shape = ctx["n_poses"], (self.max_bounces, int(ctx["n_bins_value"]))
        shape = shape if n == 1 else (n,) + shape
        if len(hists) == 1:
            return mi.TensorXf(hists[0], shape)
        both = dr.zeros(mi.Float, 2 * ctx["n_hist"])
        index = dr.arange(mi.UInt32, ctx["n_hist"]) * 2
        dr.scatter(both, hists[0], index)
        dr.scatter(both, hists[1], index + 1)
        return mi.TensorXf(both, shape + (2,))

    def _histograms(self, scene, sink, ctx, roi, paths_per_pose, ray_stats=None):
        """Every contribution of the poses of ``ctx`` into ``sink``: the surface estimator
        (bounce 1, and bounces >= 2 from its points) or the TX-cone tracer."""
        if self.bounce1 == "surface":
            self._surface(scene, sink, ctx, roi)
        else:
            self._trace(scene, sink, ctx, paths_per_pose, ray_stats)

    def _check_launch(self, n, paths_per_pose, n_bins, halves):
        n_hist = (2 if halves else 1) * n * self.max_bounces * n_bins
        if n * paths_per_pose >= 2**32 or n_hist >= 2**32:
            raise ValueError("sonar_transient: too many lanes or bins for one launch "
                             "(< 2^32 each); render fewer poses at a time")

    # ------------------------------------------------------------------ public API
    def surface_strata(self, scene, roi=None):
        """The surface quadrature of ``scene``: (strata, Dr.Jit arrays), built once per scene,
        geometry and settings; ``roi`` [2, 3] (m) limits large triangles to the strata near
        that box (a cached set whose box contains ``roi`` is reused). The strata's topology
        is rebuilt when a shape's vertices or extent change (e.g. after
        ``SceneParameters.update()``); their positions are always the shapes' current ones."""
        from . import _surface_samples
        speckle = self.speckle_spacing if self.amplitude == "coherent" else None
        key = (id(scene), self.surface_spacing, speckle, self.speckle_seed,
               _geometry_fingerprint(scene))
        entry = self._strata_cache.get(key)
        if entry is not None and roi is not None and entry[0].roi is not None:
            cached = entry[0].roi
            if np.any(roi[0] < cached[0]) or np.any(roi[1] > cached[1]):
                entry = None
                roi = np.stack([np.minimum(roi[0], cached[0]), np.maximum(roi[1], cached[1])])
        if entry is None or (roi is None and entry[0].roi is not None):
            strata = _surface_samples.build(mi, scene, self.surface_spacing, speckle,
                                            self.speckle_seed, roi)
            # one entry; holding the scene keeps its id from being reused meanwhile
            entry = (strata, StrataLanes(strata), scene)
            self._strata_cache = {key: entry}
        return entry[0], entry[1]

    def _region(self, tx, rx, tx_dir, rx_dir, path_end: float, beams) -> np.ndarray:
        """A box [2, 3] (m) holding every point that can reach the window of some pose:
        path length ≤ path_end (an ellipsoid's box) and inside both cone beams
        (``beams``: the TX and RX :class:`._beams.Beam`)."""
        half = path_end / 2.0
        mid = (tx + rx) / 2.0
        lo, hi = mid - half, mid + half
        for beam, apex, axis in ((beams[0], tx, tx_dir), (beams[1], rx, rx_dir)):
            if beam.kind != "cone" or beam.beamwidth_deg >= 120.0:
                continue
            radius = path_end * math.tan(math.radians(beam.beamwidth_deg) / 2.0)
            end = apex + path_end * axis
            extent = radius * np.sqrt(np.maximum(0.0, 1.0 - axis * axis))
            lo = np.maximum(lo, np.minimum(apex, end - extent))
            hi = np.minimum(hi, np.maximum(apex, end + extent))
        pad = 2.0 * max(self.surface_spacing, self.speckle_spacing)
        return np.stack([lo.min(axis=0) - pad, hi.max(axis=0) + pad])

    def render_transients(self, scene, tx, rx, tx_dir, rx_dir, path_start: float,
                          bin_width: float, n_bins: int, paths_per_pose: int,
                          seed: int = 0, *, pose_offset: int = 0, halves: bool = False,
                          reduce_mode=None, ray_stats: dict | None = None) -> np.ndarray:
        """Histograms for N poses: [N, max_bounces, n_bins], or [2, N, max_bounces, n_bins]
        with ``halves=True`` (two independent half-estimates whose mean is the full one).

        float32 for amplitude 'intensity' (energy) and 'pressure' (real pressure), complex64
        for 'coherent' (the phase-carrying pressure; the waveform is the real part of the
        histogram convolved with the analytic pulse). ``tx``, ``rx``: positions [N, 3] (m);
        ``tx_dir``, ``rx_dir``: boresights [N, 3] (normalised here). ``path_start``,
        ``bin_width``: round-trip path length (m) of the window start and of one bin.
        ``paths_per_pose``: TX-cone paths (bounces ≥ 2, and bounce 1 with bounce1='cone');
        paths of even index form half 0, odd ones half 1 (``halves`` needs ≥ 2 paths when
        paths are traced). ``seed`` (0 ≤ seed < 2³²) and ``pose_offset`` (global index of
        pose 0, which makes results independent of chunking) select the random numbers.
        N · paths_per_pose, N · 2 · surface strata and 2 · N · bounces · n_bins must be < 2³².
        ``ray_stats``: if a dict, the numbers of intersection and shadow rays traced by
        the path tracer are added to its keys 'intersect' and 'shadow' (slower: splits the
        kernel; for benchmarks).
        """
        tx, rx, tx_dir, rx_dir = (_as_vectors(a, name) for a, name in (
            (tx, "tx"), (rx, "rx"), (tx_dir, "tx_dir"), (rx_dir, "rx_dir")))
        n = tx.shape[0]
        if not all(a.shape[0] == n for a in (rx, tx_dir, rx_dir)):
            raise ValueError("sonar_transient: tx, rx, tx_dir, rx_dir need the same length")
        n_bins, paths_per_pose, seed, pose_offset = (int(n_bins), int(paths_per_pose),
                                                      int(seed), int(pose_offset))
        if n_bins < 1 or paths_per_pose < 1:
            raise ValueError("sonar_transient: n_bins and paths_per_pose must be >= 1")
        if not (math.isfinite(path_start) and math.isfinite(bin_width) and bin_width > 0):
            raise ValueError("sonar_transient: path_start must be finite and bin_width > 0")
        if not (0 <= seed < 2**32 and 0 <= pose_offset and pose_offset + n <= 2**32):
            raise ValueError("sonar_transient: seed must be in [0, 2^32), pose indices < 2^32")
        traces = self.bounce1 == "cone"     # else bounces >= 2 start at the surface points
        if halves and traces and paths_per_pose < 2:
            raise ValueError("sonar_transient: halves=True needs paths_per_pose >= 2")
        self._check_launch(n, paths_per_pose, n_bins, halves)
        shape = ((2,) if halves else ()) + (n, self.max_bounces, n_bins)
        dtype = np.complex64 if self.complex_output else np.float32
        if n == 0:
            return np.zeros(shape, dtype)
        ctx = self._context(tx, rx, tx_dir, rx_dir, float(path_start), float(bin_width),
                            n_bins, seed, pose_offset, halves,
                            dr.ReduceMode.Local if reduce_mode is None else reduce_mode)
        buf_type = mi.Float64 if self.float64 else mi.Float
        hists = [dr.zeros(buf_type, ctx["n_hist"]) for _ in range(ctx["parts"])]
        roi = None
        if not traces:
            roi = self._region(tx, rx, tx_dir / np.linalg.norm(tx_dir, axis=1, keepdims=True),
                               rx_dir / np.linalg.norm(rx_dir, axis=1, keepdims=True),
                               float(path_start) + (n_bins + 1) * float(bin_width),
                               (self.tx_beam, self.rx_beam))
        self._histograms(scene, HistogramSink(hists, ctx), ctx, roi, paths_per_pose, ray_stats)
        out = []
        for h in hists:
            if self.float64:
                h = mi.Float(h)        # round in Dr.Jit: much faster than NumPy's astype
            dr.eval(h)
            out.append(h.numpy())
        if self.complex_output:
            result = np.empty(ctx["n_hist"], np.complex64)
            result.real, result.imag = out
        else:
            result = out[0]
        return result.reshape(shape)

    # ------------------------------------------------------------------ shared set-up
    def _context(self, tx, rx, tx_dir, rx_dir, path_start, bin_width, n_bins, seed,
                 pose_offset, halves, reduce_mode) -> dict:
        """The kernel context of poses given as NumPy arrays [N, 3] (see :meth:`_context_arrays`)."""
        def vec(a):
            if a.shape[0] == 1:   # as _context_arrays' widen(), without an extra kernel
                a = np.repeat(a, 2, axis=0)
            return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, i], np.float32))
                                 for i in range(3)))

        return self._context_arrays(vec(tx), vec(rx), vec(tx_dir), vec(rx_dir), tx.shape[0],
                                    dr.opaque(mi.Float, path_start),
                                    dr.opaque(mi.Float, bin_width), n_bins, seed, pose_offset,
                                    halves, reduce_mode, (self.tx_beam, self.rx_beam))

    def _context_arrays(self, tx, rx, tx_dir, rx_dir, n, start, width, n_bins, seed,
                        pose_offset, halves, reduce_mode, beams) -> dict:
        """Everything a launch reads: the N poses (Dr.Jit vectors of width N or 1, m;
        boresights of any length > 0, normalised per lane), the window (``start``, ``width``: Dr.Jit Floats, m of
        round-trip path; differentiable), seeds, buffer strides, the beams. Every per-call
        scalar is an opaque value, so new poses, windows or seeds reuse compiled kernels."""
        def widen(v):
            v = mi.Vector3f(v)
            # Dr.Jit compiles 1-element sources differently per call: keep width >= 2.
            if dr.width(v) == 1:
                v = dr.gather(mi.Vector3f, v, dr.zeros(mi.UInt32, max(n, 2)))
            return v

        stride = self.max_bounces * n_bins
        tx_beam, rx_beam = beams
        return dict(
            n_poses=n, halves=halves, reduce_mode=reduce_mode,
            n_hist=(2 if halves else 1) * n * stride, parts=2 if self.complex_output else 1,
            tx=widen(tx), rx=widen(rx), tx_dir=widen(tx_dir), rx_dir=widen(rx_dir),
            seed=dr.opaque(mi.UInt32, seed), pose_offset=dr.opaque(mi.UInt32, pose_offset),
            start=start, inv_width=1.0 / width, margin=width,
            end=start + dr.opaque(mi.Float, n_bins) * width,
            n_bins=dr.opaque(mi.Int32, n_bins), n_bins_value=n_bins,
            pose_stride=dr.opaque(mi.UInt32, stride),
            half_stride=dr.opaque(mi.UInt32, n * stride),
            n_bins_u=dr.opaque(mi.UInt32, n_bins),
            tx_beam=tx_beam, rx_beam=rx_beam, tx_c=tx_beam.opaque(), rx_c=rx_beam.opaque(),
            speckle_key=dr.opaque(mi.UInt32, self.speckle_seed),
            inv_speckle=dr.opaque(mi.Float, 1.0 / self.speckle_spacing))


def _sonar_sensor(scene, sensor):
    """The ``sonar`` sensor that ``sensor`` (index, sensor or None) names in ``scene``."""
    if sensor is None or isinstance(sensor, int):
        sensors = scene.sensors()
        index = sensor or 0
        if not 0 <= index < len(sensors):
            raise ValueError(f"sonar_transient: the scene has {len(sensors)} sensors; "
                             f"no sensor {index}")
        sensor = sensors[index]
    if not hasattr(sensor, "pose_vectors"):
        raise ValueError(f"sonar_transient renders 'sonar' sensors, not {type(sensor).__name__}")
    return sensor


def _as_seed(seed) -> int:
    value = int(seed) if isinstance(seed, (int, np.integer)) else int(np.asarray(seed).ravel()[0])
    if not 0 <= value < 2**32:
        raise ValueError(f"sonar_transient: seed must be in [0, 2^32), got {value}")
    return value


def _geometry_fingerprint(scene) -> tuple:
    """What the surface strata's topology depends on: each shape's vertex positions (a hash)
    and face count, or its bounding box."""
    out = []
    for shape in scene.shapes():
        if shape.is_mesh():
            v = np.asarray(dr.detach(shape.vertex_positions_buffer()))
            out.append((hash(v.tobytes()), int(shape.face_count())))
        else:
            bb = shape.bbox()
            out.append(tuple(np.asarray(bb.min, np.float64)) + tuple(np.asarray(bb.max, np.float64)))
    return tuple(out)


def _include(cls, *parts) -> None:
    """Give ``cls`` the methods of the helper classes ``parts`` (nanobind classes take a
    single base, so the estimator's parts are attached rather than inherited)."""
    for part in parts:
        for name, value in vars(part).items():
            if not name.startswith("__"):
                setattr(cls, name, value)


_include(SonarTransientIntegrator, SurfaceEstimator, ConeTracer, PathVertices)
mi.register_integrator(PLUGIN_NAME, lambda props: SonarTransientIntegrator(props))


def _as_vectors(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"sonar_transient: {name} must have shape [N, 3], got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"sonar_transient: {name} contains NaN or infinite values")
    if name.endswith("_dir"):
        norm = np.linalg.norm(arr, axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError(f"sonar_transient: {name} contains a zero-length boresight")
    return arr
