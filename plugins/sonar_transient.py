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

PLUGIN_NAME = "sonar_transient"
VARIANT = mi.variant()   # the variant this module's class was built for
BEAM_KINDS = ("cone", "isotropic", "piston")
MAX_BOUNCES_LIMIT = 64
# Piston pattern: |2 J1(x)/x|² = 1/2 at x = 1.6163 (half-power), first null at x = 3.8317.
_PISTON_HALF_POWER_X = 1.616339948
_PISTON_FIRST_NULL_X = 3.831705970
_PISTON_MAIN_LOBE_FRACTION = 0.9   # share of TX samples drawn inside the main lobe
AMPLITUDES = ("intensity", "pressure", "coherent")
BOUNCE1_ESTIMATORS = ("surface", "cone")
DEFAULT_SURFACE_SPACING = 8e-3     # m: longest edge of the bounce-1 quadrature's facets
DEFAULT_VERTEX_SPREAD = 0.0        # m: disk radius over which bounce >= 2 vertices spread
DEFAULT_GUIDE_FRACTION = 0.5      # share of continuations aimed at the objects' bounding sphere
DEFAULT_PATH_SAMPLES = 16          # path-length quantiles splatted per facet
DEFAULT_SPECKLE_SPACING = 3e-3     # m: scatterer cells of the 'coherent' amplitude
# TX-cone tracer: lanes per launch (its lane order takes about 8 bytes per lane), the
# fewest paths per pose for which sorting them by TX direction pays, and the paths per
# direction cell of that sort (see SonarTransientIntegrator._coherent_order).
_TRACE_BATCH = 2**24
_ORDER_MIN_PATHS = 64
_ORDER_PER_CELL = 16.0


def piston_ka(beamwidth_deg: float) -> float:
    """Piston ``k·a`` (wavenumber × radius) whose full half-power beamwidth is ``beamwidth_deg``."""
    return _PISTON_HALF_POWER_X / math.sin(math.radians(beamwidth_deg) / 2.0)


def _bessel_j1_over_x(x):
    """J1(x)/x for x >= 0 (Abramowitz & Stegun 9.4.4 and 9.4.6, |error| < 1e-7)."""
    y = (x * (1.0 / 3.0)) ** 2
    small = 0.5 + y * (-0.56249985 + y * (0.21093573 + y * (-0.03954289 + y * (
        0.00443319 + y * (-0.00031761 + y * 0.00001109)))))
    xs = dr.maximum(x, 3.0)
    z = 3.0 / xs
    f1 = 0.79788456 + z * (0.00000156 + z * (0.01659667 + z * (0.00017105 + z * (
        -0.00249511 + z * (0.00113653 + z * -0.00020033)))))
    t1 = xs - 2.35619449 + z * (0.12499612 + z * (0.00005650 + z * (-0.00637879 + z * (
        0.00074348 + z * (0.00079824 + z * -0.00029166)))))
    large = f1 * dr.cos(t1) / (xs * dr.sqrt(xs))
    return dr.select(x <= 3.0, small, large)


class _Beam:
    """A beam pattern: intensity gain ``b(θ)`` and pressure gain ``a(θ)`` (both 1 on the
    axis) and, for the TX, direction sampling.

    Per-call constants are made opaque when the kernel is built (:meth:`opaque`), so the
    beamwidth never forces a recompilation.
    """

    def __init__(self, kind: str, beamwidth_deg: float, role: str):
        if kind not in BEAM_KINDS:
            raise ValueError(f"sonar_transient: {role}_beam must be one of {BEAM_KINDS}, "
                             f"got {kind!r}")
        if kind != "isotropic" and not (0.0 < beamwidth_deg < 180.0):
            raise ValueError(f"sonar_transient: {role}_beamwidth must be in (0, 180) degrees, "
                             f"got {beamwidth_deg}")
        self.kind = kind
        self.beamwidth_deg = float(beamwidth_deg)
        half = math.radians(self.beamwidth_deg) / 2.0
        if kind == "cone":
            self.cos_cut = math.cos(half)        # cone edge
            self.ka = 0.0
        elif kind == "piston":
            self.ka = piston_ka(self.beamwidth_deg)
            s = _PISTON_FIRST_NULL_X / self.ka
            self.cos_cut = math.sqrt(1.0 - s * s) if s < 1.0 else 0.0   # main-lobe edge
        else:
            self.cos_cut = -1.0
            self.ka = 0.0

    def describe(self) -> str:
        return "isotropic" if self.kind == "isotropic" else f"{self.kind} {self.beamwidth_deg:g}°"

    def opaque(self) -> dict:
        return {"cos_cut": dr.opaque(mi.Float, self.cos_cut), "ka": dr.opaque(mi.Float, self.ka)}

    def amplitude(self, cos_theta, c):
        """Pressure gain for a direction at angle θ from the boresight (``cos_theta``):
        1/0 for the cone, 1 for isotropic, the signed 2·J1(ka sinθ)/(ka sinθ) in front of
        a baffled piston (its square is :meth:`gain`)."""
        if self.kind == "isotropic":
            return dr.full(mi.Float, 1.0, dr.width(cos_theta))
        if self.kind == "cone":
            return dr.select(cos_theta >= c["cos_cut"], 1.0, 0.0)
        sin_theta = dr.safe_sqrt(1.0 - cos_theta * cos_theta)
        return dr.select(cos_theta > 0.0, 2.0 * _bessel_j1_over_x(c["ka"] * sin_theta), 0.0)

    def gain(self, cos_theta, c):
        """Intensity gain for a direction at angle θ from the boresight (``cos_theta``)."""
        if self.kind == "piston":   # |2 J1(ka sinθ)/(ka sinθ)|² in front, nothing behind
            a = self.amplitude(cos_theta, c)
            return a * a
        return self.amplitude(cos_theta, c)

    def sample(self, u_pick, u2, c):
        """Local direction (z = boresight) and 1/pdf (sr) for uniform numbers."""
        if self.kind == "isotropic":
            return mi.warp.square_to_uniform_sphere(u2), dr.full(mi.Float, 4.0 * math.pi,
                                                                  dr.width(u_pick))
        cone_solid_angle = 2.0 * math.pi * (1.0 - c["cos_cut"])
        if self.kind == "cone":
            return mi.warp.square_to_uniform_cone(u2, c["cos_cut"]), cone_solid_angle
        # Piston: mixture of the main-lobe cone (fraction q) and the front hemisphere,
        # which keeps side lobes (unbiased) while spending most samples in the main lobe.
        q = _PISTON_MAIN_LOBE_FRACTION
        in_lobe = u_pick < q
        d_cone = mi.warp.square_to_uniform_cone(u2, c["cos_cut"])
        d_hemi = mi.warp.square_to_uniform_hemisphere(u2)
        d = dr.select(in_lobe, d_cone, d_hemi)
        pdf = (1.0 - q) / (2.0 * math.pi) + dr.select(d.z >= c["cos_cut"],
                                                       q / cone_solid_angle, 0.0)
        return d, 1.0 / pdf


class SonarTransientIntegrator(mi.SamplingIntegrator):
    """Transient sonar integrator; use :meth:`render_transients` (not ``mi.render``).

    Properties: ``max_bounces`` (int, default 3), ``tx_beam``/``rx_beam``
    ('cone' | 'isotropic' | 'piston', default 'cone'), ``tx_beamwidth``/``rx_beamwidth``
    (full beamwidth in degrees, default 30; for 'piston' the half-power width),
    ``shading_normals`` (bool, default True: cosines use interpolated mesh normals),
    ``accumulator`` ('float64' | 'float32', default 'float64': the histogram buffer type),
    ``bounce1`` ('surface' | 'cone', default 'surface': the bounce-1 estimator),
    ``amplitude`` ('intensity' | 'pressure' | 'coherent', default 'intensity'),
    ``surface_spacing`` (m, default 1.5e-3: size of the surface quadrature's strata),
    ``speckle_spacing`` (m, default 3e-3: scatterer cell of 'coherent'),
    ``speckle_seed`` (int, default 0: the phases of 'coherent').
    """

    def __init__(self, props):
        super().__init__(props)
        self.max_bounces = int(props.get("max_bounces", 3))
        if not 1 <= self.max_bounces <= MAX_BOUNCES_LIMIT:
            raise ValueError(f"sonar_transient: max_bounces must be in 1..{MAX_BOUNCES_LIMIT}, "
                             f"got {self.max_bounces}")
        self.tx_beam = _Beam(str(props.get("tx_beam", "cone")),
                             float(props.get("tx_beamwidth", 30.0)), "tx")
        self.rx_beam = _Beam(str(props.get("rx_beam", "cone")),
                             float(props.get("rx_beamwidth", 30.0)), "rx")
        self.shading_normals = bool(props.get("shading_normals", True))
        accumulator = str(props.get("accumulator", "float64"))
        if accumulator not in ("float64", "float32"):
            raise ValueError("sonar_transient: accumulator must be 'float64' or 'float32', "
                             f"got {accumulator!r}")
        self.float64 = accumulator == "float64"
        # 'mode' is the former name of 'amplitude'
        self.amplitude = str(props.get("amplitude", props.get("mode", "intensity")))
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

    def render(self, scene, sensor=None, seed=0, spp=0, develop=True, evaluate=True):
        raise RuntimeError("sonar_transient renders histograms: call "
                           "integrator.render_transients(scene, tx, rx, ...)")

    def sample(self, scene, sampler, ray, medium=None, active=True):
        raise RuntimeError("sonar_transient has no image mode; use render_transients()")

    # ------------------------------------------------------------------ public API
    def surface_strata(self, scene, roi=None):
        """The surface quadrature of ``scene``: (strata, Dr.Jit arrays), built once per scene
        and settings; ``roi`` [2, 3] (m) limits large triangles to the strata near that box
        (a cached set whose box contains ``roi`` is reused)."""
        from . import _surface_samples
        speckle = self.speckle_spacing if self.amplitude == "coherent" else None
        key = (id(scene), self.surface_spacing, speckle, self.speckle_seed)
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
            entry = (strata, _StrataArrays(strata), scene)
            self._strata_cache = {key: entry}
        return entry[0], entry[1]

    def _region(self, tx, rx, tx_dir, rx_dir, path_end: float) -> np.ndarray:
        """A box [2, 3] (m) holding every point that can reach the window of some pose:
        path length ≤ path_end (an ellipsoid's box) and inside both cone beams."""
        half = path_end / 2.0
        mid = (tx + rx) / 2.0
        lo, hi = mid - half, mid + half
        for beam, apex, axis in ((self.tx_beam, tx, tx_dir), (self.rx_beam, rx, rx_dir)):
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
        n_slots = 2 if halves else 1
        n_hist = n_slots * n * self.max_bounces * n_bins
        if n * paths_per_pose >= 2**32 or n_hist >= 2**32:
            raise ValueError("sonar_transient: too many lanes or bins for one launch "
                             "(< 2^32 each); render fewer poses at a time")
        shape = ((2,) if halves else ()) + (n, self.max_bounces, n_bins)
        dtype = np.complex64 if self.complex_output else np.float32
        if n == 0:
            return np.zeros(shape, dtype)
        buf_type = mi.Float64 if self.float64 else mi.Float
        parts = 2 if self.complex_output else 1
        hists = [dr.zeros(buf_type, n_hist) for _ in range(parts)]
        ctx = self._context(tx, rx, tx_dir, rx_dir, float(path_start), float(bin_width),
                            n_bins, seed, pose_offset, halves,
                            dr.ReduceMode.Local if reduce_mode is None else reduce_mode)
        if self.bounce1 == "surface":
            roi = self._region(tx, rx, tx_dir, rx_dir,
                               float(path_start) + (n_bins + 1) * float(bin_width))
            self._surface(scene, hists, ctx, roi)
        if traces:
            self._trace(scene, hists, ctx, paths_per_pose, ray_stats)
        out = []
        for h in hists:
            if self.float64:
                h = mi.Float(h)        # round in Dr.Jit: much faster than NumPy's astype
            dr.eval(h)
            out.append(h.numpy())
        if self.complex_output:
            result = np.empty(n_hist, np.complex64)
            result.real, result.imag = out
        else:
            result = out[0]
        return result.reshape(shape)

    # ------------------------------------------------------------------ shared set-up
    def _context(self, tx, rx, tx_dir, rx_dir, path_start, bin_width, n_bins, seed,
                 pose_offset, halves, reduce_mode) -> dict:
        n = tx.shape[0]

        def vec(a):
            if a.shape[0] == 1:   # Dr.Jit compiles 1-element sources differently per call
                a = np.repeat(a, 2, axis=0)
            return mi.Vector3f(*(mi.Float(a[:, i].astype(np.float32)) for i in range(3)))

        stride = self.max_bounces * n_bins
        return dict(
            n_poses=n, halves=halves, reduce_mode=reduce_mode,
            tx=vec(tx), rx=vec(rx), tx_dir=vec(tx_dir), rx_dir=vec(rx_dir),
            seed=dr.opaque(mi.UInt32, seed), pose_offset=dr.opaque(mi.UInt32, pose_offset),
            start=dr.opaque(mi.Float, path_start), inv_width=dr.opaque(mi.Float, 1.0 / bin_width),
            end=dr.opaque(mi.Float, path_start + n_bins * bin_width),
            margin=dr.opaque(mi.Float, bin_width),
            n_bins=dr.opaque(mi.Int32, n_bins), pose_stride=dr.opaque(mi.UInt32, stride),
            half_stride=dr.opaque(mi.UInt32, n * stride),
            n_bins_u=dr.opaque(mi.UInt32, n_bins),
            tx_c=self.tx_beam.opaque(), rx_c=self.rx_beam.opaque(),
            speckle_key=dr.opaque(mi.UInt32, self.speckle_seed),
            inv_speckle=dr.opaque(mi.Float, 1.0 / self.speckle_spacing))

    # ------------------------------------------------------------------ bounce 1: surface
    def _surface(self, scene, hists, ctx, roi):
        """Bounce 1 by stratified area quadrature: one jittered point per stratum and half."""
        strata, arrays = self.surface_strata(scene, roi)
        if arrays.n_tri:
            self._surface_lanes(scene, hists, ctx, arrays.n_tri, arrays.triangle_points,
                                lambda k: dr.gather(mi.UInt32, arrays.tri["sid"], k))
        for index, item in enumerate(arrays.parametric):
            self._surface_lanes(scene, hists, ctx, len(item[0]),
                                lambda k, u, it=item: _parametric_points(it, k, u),
                                lambda k, i=index: k ^ mi.UInt32((0x7F4A7C15 * (i + 1)) & 0xFFFFFFFF))

    def _surface_lanes(self, scene, hists, ctx, n_strata, points, stable_id):
        """Launch the lanes (pose, half, stratum), in batches of < 2³¹ lanes."""
        per_batch = max(1, (2**31) // (2 * n_strata))
        for first in range(0, ctx["n_poses"], per_batch):
            count = min(per_batch, ctx["n_poses"] - first)
            self._surface_batch(scene, hists, ctx, n_strata, points, stable_id, first, count)

    def _surface_batch(self, scene, hists, ctx, n_strata, points, stable_id, first, count):
        UInt32, Float = mi.UInt32, mi.Float
        m = dr.opaque(UInt32, n_strata)
        lane = dr.arange(UInt32, count * 2 * n_strata)
        pair = lane // m                  # pose * 2 + half
        k = lane - pair * m               # stratum
        pose = (pair >> 1) + dr.opaque(UInt32, first)
        half = pair & 1
        key = mi.sample_tea_32(ctx["seed"], (pose + ctx["pose_offset"]) * 2 + half)[0]
        sid = stable_id(k)
        r1, r2 = mi.sample_tea_32(key, sid)
        u = mi.Point2f(Float(r1 >> 8) * (1.0 / 16777216.0), Float(r2 >> 8) * (1.0 / 16777216.0))
        p, n_geo, n_sh, rho, area, phase, corners = points(k, u)
        if not self.shading_normals:
            n_sh = n_geo
        p_tx = mi.Point3f(dr.gather(mi.Vector3f, ctx["tx"], pose))
        p_rx = mi.Point3f(dr.gather(mi.Vector3f, ctx["rx"], pose))
        b_tx = dr.gather(mi.Vector3f, ctx["tx_dir"], pose)
        b_rx = dr.gather(mi.Vector3f, ctx["rx_dir"], pose)
        to_tx, to_rx = p_tx - p, p_rx - p
        r_t, r_r = dr.norm(to_tx), dr.norm(to_rx)
        w_t, w_r = to_tx / r_t, to_rx / r_r
        length = r_t + r_r
        # Two-sided surfaces: orient the normals towards the TX's side.
        flip = dr.select(dr.dot(n_geo, w_t) < 0.0, -1.0, 1.0)
        n_geo, n_sh = n_geo * flip, n_sh * flip
        cos_i = dr.dot(n_geo, w_t)                      # geometric, as the TX-cone sampling
        cos_o = dr.maximum(dr.dot(n_sh, w_r), 0.0)
        active = (cos_i > 0.0) & (dr.dot(n_geo, w_r) > 0.0) & (cos_o > 0.0)
        ls = None
        if corners is None:
            lo_len = hi_len = length
        else:   # path lengths at the facet's corners: a ≤ c ≤ b
            ls = [dr.norm(p_tx - q) + dr.norm(p_rx - q) for q in corners]
            lo_len = dr.minimum(dr.minimum(ls[0], ls[1]), ls[2])
            hi_len = dr.maximum(dr.maximum(ls[0], ls[1]), ls[2])
        active &= (hi_len > ctx["start"] - ctx["margin"]) & (lo_len < ctx["end"] + ctx["margin"])
        ct, cr = -dr.dot(w_t, b_tx), -dr.dot(w_r, b_rx)
        weight = area * (1.0 if ctx["halves"] else 0.5)
        if self.amplitude == "intensity":
            g_t = self.tx_beam.gain(ct, ctx["tx_c"])
            value = (g_t * self.rx_beam.gain(cr, ctx["rx_c"])
                     * rho * dr.inv_pi * cos_i * cos_o / (r_t * r_t * r_r * r_r))
        else:   # the seed's Eq. (1): b_T b_R σ / (2π r_T r_R), σ = sqrt(ρ cosθ_i cosθ_o)
            g_t = self.tx_beam.amplitude(ct, ctx["tx_c"])
            value = (g_t * self.rx_beam.amplitude(cr, ctx["rx_c"])
                     * dr.sqrt(rho * cos_i * cos_o) * (0.5 * dr.inv_pi) / (r_t * r_r))
        value = value * weight
        active &= value != 0.0
        # Visibility: shadow rays from the point (offset along the oriented normal). The TX
        # ray also serves the paths of bounces >= 2 that start at this point.
        lit = (cos_i > 0.0) & (g_t != 0.0)
        lit = (active | lit) if self.max_bounces > 1 else active
        scale = dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
        origin = p + n_geo * ((1.0 + scale) * mi.math.RayEpsilon)
        for target in (p_tx, p_rx):
            ray = mi.Ray3f(origin, target - origin)
            ray.maxt = Float(1.0 - mi.math.ShadowEpsilon)
            if target is p_tx:
                lit &= ~scene.ray_test(ray, lit)
                active &= lit
            else:
                active &= ~scene.ray_test(ray, active)
        if self.max_bounces > 1:
            k = self.facet_paths
            for j in range(k):   # k continuations per point, the first direction stratified
                self._facet_paths(scene, hists, ctx, pose, half, p, n_geo, n_sh, rho, cos_i,
                                  r_t, g_t * (weight / k), phase, corners, lit,
                                  key ^ (0x632BE5AB * j & 0xFFFFFFFF), sid, p_tx, p_rx, b_rx,
                                  (j, k))
        slot = half if ctx["halves"] else UInt32(0)
        values = [value]
        if self.complex_output:
            values = [value * dr.cos(phase), value * dr.sin(phase)]
        if corners is None:           # analytic shapes: a point splat
            for h, v in zip(hists, values):
                self._splat(h, v, length, pose, slot, 0, ctx, active)
            return
        # Flat facets: path length is linear over the facet to within s²/(2r); the
        # facet's area maps to the triangular density of L between its corners' lengths
        # a ≤ c ≤ b. Spread the value over m stratified quantiles of that density (one
        # random shift per lane), so the facet's echo is smooth in time, not a spike.
        m = self.path_samples
        shift = Float(mi.sample_tea_32(key, sid ^ 0x80000000)[0] >> 8) * (1.0 / 16777216.0)
        values = [v * (1.0 / m) for v in values]
        for li in self._quantiles(ls, shift, m):
            for h, v in zip(hists, values):
                self._splat(h, v, li, pose, slot, 0, ctx, active)

    # ------------------------------------------------------------------ bounces >= 2
    def _facet_paths(self, scene, hists, ctx, pose, half, p, n_geo, n_sh, albedo, cos_in, r_t,
                     tx_weight, phase, corners, active, key, sid, p_tx, p_rx, b_rx,
                     stratum=(0, 1)):
        """Bounces 2…B from the surface points: one path per lit stratum point x₁.

        x₁ carries the TX's transfer b_T cosθ_i dA / r_T² (intensity; a_T dA / r_T for
        pressure: the TX-cone tracer's weight with dω = cosθ_i dA / r_T²); the path goes on
        by cosine/guide sampling with next-event connections to the RX, as the tracer.
        For facets, the first two legs |TX − x₁| + |x₁ − x₂| are spread over the facet
        (triangular density between the corners' values) like bounce 1.
        """
        Float = mi.Float
        intensity = self.amplitude == "intensity"
        active = mi.Bool(active)          # a copy: the in-place &= below must not reach the caller
        rng = mi.PCG32(1, mi.sample_tea_64(key, sid), mi.sample_tea_64(sid, key ^ 0x5bd1e995))
        slot = half if ctx["halves"] else mi.UInt32(0)
        guide = self._guide(scene)
        throughput = tx_weight * (cos_in / (r_t * r_t) if intensity else 1.0 / r_t)
        prev_p, length, quantiles = p, Float(0.0), None
        n_geo_v, n_sh_v = n_geo, n_sh
        ray_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        m = self.path_samples
        for bounce in range(1, self.max_bounces):
            u_pick = rng.next_float32()
            u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
            if bounce == 1 and stratum[1] > 1:
                u2.x = (stratum[0] + u2.x) * (1.0 / stratum[1])
            d_new, inv_pdf = self._continuation(prev_p, n_sh_v, u_pick, u2, guide)
            cos_new = dr.dot(d_new, n_sh_v)
            active &= (dr.dot(d_new, n_geo_v) > 0.0) & (cos_new > 0.0)
            if intensity:
                throughput *= albedo * dr.inv_pi * cos_new * inv_pdf
            else:
                throughput *= dr.sqrt(albedo * cos_in * cos_new) * (0.5 * dr.inv_pi) * inv_pdf
            ray = self._continue_ray(prev_p, d_new)
            si = scene.ray_intersect(ray, ray_flags, dr.opaque(mi.Bool, False), active)
            active &= si.is_valid()
            seg = dr.norm(si.p - prev_p)
            if bounce == 1:
                if corners is not None:
                    lc = [dr.norm(p_tx - q) + dr.norm(q - si.p) for q in corners]
                    quantiles = self._quantiles(lc, rng.next_float32(), m)
                else:
                    quantiles = [r_t + seg]
            else:
                length += seg
            prev_p = si.p
            n_geo_v, n_sh_v, albedo = self._arrival(si, ray, active)
            if not intensity:
                cos_in = -dr.dot(n_geo_v, ray.d)
                active &= cos_in > 1e-6
                throughput = throughput * seg / cos_in
                if self.amplitude == "coherent":
                    phase = phase + self._voxel_phase(si.p, bounce, ctx)
            value, dist, w_rx, connect = self._connect_rx(
                scene, si, p_rx, b_rx, n_sh_v, n_geo_v, throughput, albedo, cos_in, active,
                intensity, ctx)
            values = [value * (1.0 / len(quantiles))]
            if self.complex_output:
                values = [values[0] * dr.cos(phase), values[0] * dr.sin(phase)]
            rest = length + dist
            offsets = [0.0] * len(quantiles)
            scales = [1.0] * len(quantiles)
            if self.vertex_spread > 0.0 and len(quantiles) > 1:
                # Spread x_k over a disk of radius vertex_spread in its tangent plane: the
                # semicircle density of L along the tangential gradient of the last two
                # legs, at stratified points paired with the quantiles by a permutation.
                grad = ray.d - w_rx
                grad = grad - dr.dot(grad, n_geo_v) * n_geo_v
                half_span = dr.norm(grad) * self.vertex_spread
                n_q = len(quantiles)
                shift = rng.next_float32()
                ts = [2.0 * ((i * 5) % n_q + shift) / n_q - 1.0 for i in range(n_q)]
                ws = [dr.safe_sqrt(1.0 - t * t) for t in ts]
                total = dr.maximum(sum(ws[1:], ws[0]), 1e-12)
                offsets = [t * half_span for t in ts]
                scales = [w * (n_q / total) for w in ws]
            for q, off, sc in zip(quantiles, offsets, scales):
                for h, v in zip(hists, values):
                    self._splat(h, v * sc, q + rest + off, pose, slot, bounce, ctx, connect)

    @staticmethod
    def _quantiles(ls, shift, m):
        """m stratified quantiles (i + shift)/m of the triangular density between the
        three corner values ``ls`` (a linear function's image of a uniform triangle)."""
        a = dr.minimum(dr.minimum(ls[0], ls[1]), ls[2])
        b = dr.maximum(dr.maximum(ls[0], ls[1]), ls[2])
        c = ls[0] + ls[1] + ls[2] - a - b
        span = dr.maximum(b - a, 1e-12)
        f_c = (c - a) / span
        out = []
        for i in range(m):
            q = (i + shift) * (1.0 / m)
            lo = a + dr.safe_sqrt(q * span * (c - a))
            hi = b - dr.safe_sqrt((1.0 - q) * span * (b - c))
            out.append(dr.select(q < f_c, lo, hi))
        return out

    # ------------------------------------------------------------------ TX-cone paths
    def _trace(self, scene, hists, ctx, paths_per_pose, ray_stats=None):
        """The TX-cone paths of every pose, in launches of at most _TRACE_BATCH lanes:
        whole poses, or (beyond _TRACE_BATCH paths per pose) part of one pose's paths."""
        n_poses, P = ctx["n_poses"], paths_per_pose
        if P <= _TRACE_BATCH:
            per = max(1, _TRACE_BATCH // P)
            batches = [(p0, min(per, n_poses - p0), 0, P) for p0 in range(0, n_poses, per)]
        else:
            batches = [(p0, 1, a, min(_TRACE_BATCH, P - a))
                       for p0 in range(n_poses) for a in range(0, P, _TRACE_BATCH)]
        for pose0, n_batch_poses, path0, n_paths in batches:
            batch = {"pose0": dr.opaque(mi.UInt32, pose0), "path0": dr.opaque(mi.UInt32, path0),
                     "n_paths": dr.opaque(mi.UInt32, n_paths)}
            order = self._coherent_order(ctx, batch, n_batch_poses, n_paths, P)
            self._trace_lanes(scene, hists, ctx, paths_per_pose, batch, n_batch_poses * n_paths,
                              order, ray_stats)

    @staticmethod
    def _path_rng(ctx, pose, path):
        """The PCG32 stream of path ``path`` of pose ``pose`` (index in this call), seeded
        by a hash of (seed, global pose index, path): independent of chunking and order."""
        stream_key = mi.sample_tea_32(ctx["seed"], pose + ctx["pose_offset"])[0]
        return mi.PCG32(1, mi.sample_tea_64(stream_key, path), mi.sample_tea_64(path, stream_key))

    @staticmethod
    def _direction_cell(ctx, batch, index, level):
        """(pose, path, Morton cell of the first TX sample square at ``level``) of lane
        ``index`` of a batch: the cell's 4^level squares tile [0, 1)² (the beam warps
        map nearby points of the square to nearby directions)."""
        UInt32 = mi.UInt32
        pose = batch["pose0"] + index // batch["n_paths"]
        path = batch["path0"] + index % batch["n_paths"]
        rng = SonarTransientIntegrator._path_rng(ctx, pose, path)
        rng.next_float32()                                   # u_pick
        side = mi.Float(UInt32(1) << level)
        x = dr.minimum(UInt32(rng.next_float32() * side), (UInt32(1) << level) - 1)
        y = dr.minimum(UInt32(rng.next_float32() * side), (UInt32(1) << level) - 1)
        return pose, path, _interleave(x) | (_interleave(y) << 1)

    def _coherent_order(self, ctx, batch, n_batch_poses, n_paths, P):
        """The order in which a batch's lanes are traced: UInt32 [n_batch_poses·n_paths],
        lane i traces path order[i] (index into the batch, pose-major), or None (the
        identity) for fewer than _ORDER_MIN_PATHS paths per pose.

        Each path keeps its own random numbers (they depend on pose and path index
        only), so results are the same in any order; the order only decides which paths
        share a SIMD packet. Each pose's paths (of this batch) are sorted by the Morton
        cell of their first TX sample (4^L cells, about 16 paths per cell, L <= 8),
        stably (by index within a cell): neighbouring lanes then leave the TX in nearby
        directions, hit nearby points and send nearby shadow rays, so Embree's 16-ray
        packets stay coherent (docs/transient_rendering.md, "Performance design"). The
        sort is Dr.Jit's per-block stable counting sort (``drjit.detail.block_mkperm``,
        on which ``drjit.argsort`` is built; deterministic, a few ns per lane); with a
        Dr.Jit that lacks it, lanes stay in index order.
        """
        mkperm = getattr(getattr(dr, "detail", None), "block_mkperm", None)
        if P < _ORDER_MIN_PATHS or mkperm is None:
            return None
        level = max(0, min(8, int(math.log(n_paths / _ORDER_PER_CELL, 4.0))))
        index = dr.arange(mi.UInt32, n_batch_poses * n_paths)
        cell = self._direction_cell(ctx, batch, index, dr.opaque(mi.UInt32, level))[2]
        dr.eval(cell)
        order = mkperm(cell, n_paths, 4 ** level)     # blocks: the poses of the batch
        dr.eval(order)
        return order

    def _trace_lanes(self, scene, hists, ctx, paths_per_pose, batch, n_lanes, order,
                     ray_stats=None):
        """Trace the ``n_lanes`` paths of one batch, lane i taking batch path ``order[i]``
        (pose-major index into the batch; None: lane i takes path i)."""
        UInt32, Float = mi.UInt32, mi.Float
        index = dr.arange(UInt32, n_lanes)
        if order is not None:
            index = dr.gather(UInt32, order, index)
        pose = batch["pose0"] + index // batch["n_paths"]
        path = batch["path0"] + index % batch["n_paths"]
        rng = self._path_rng(ctx, pose, path)
        # Half h = paths of parity h; weights make the full estimate the mean of the halves.
        half = path & 1
        n0, n1 = (paths_per_pose + 1) // 2, paths_per_pose // 2
        if ctx["halves"]:
            w0, w1 = 1.0 / n0, 1.0 / n1
        elif paths_per_pose == 1:
            w0 = w1 = 1.0
        else:
            w0, w1 = 0.5 / n0, 0.5 / n1
        weight = dr.select(half == 0, dr.opaque(Float, w0), dr.opaque(Float, w1))
        slot = half if ctx["halves"] else UInt32(0)

        p_tx = mi.Point3f(dr.gather(mi.Vector3f, ctx["tx"], pose))
        p_rx = mi.Point3f(dr.gather(mi.Vector3f, ctx["rx"], pose))
        b_tx = dr.gather(mi.Vector3f, ctx["tx_dir"], pose)
        b_rx = dr.gather(mi.Vector3f, ctx["rx_dir"], pose)
        intensity = self.amplitude == "intensity"
        guide = self._guide(scene) if self.max_bounces > 1 else None

        # Bounce 0: leave the TX in a direction drawn from its beam.
        u_pick = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        d_local, inv_pdf = self.tx_beam.sample(u_pick, u2, ctx["tx_c"])
        beam = (self.tx_beam.gain if intensity else self.tx_beam.amplitude)(d_local.z, ctx["tx_c"])
        ray = mi.Ray3f(p_tx, mi.Frame3f(b_tx).to_world(d_local))
        # intensity: b_T/pdf; pressure: a_T/pdf, completed by r/cosθ_i at the vertex
        throughput = beam * inv_pdf * weight
        length = Float(0.0)
        phase = Float(0.0)
        prev_p = p_tx
        active = dr.full(mi.Bool, True, n_lanes)

        # Position, normals, UV (for textured albedo); no partial derivatives.
        ray_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        for bounce in range(self.max_bounces):    # unrolled: faster than a loop for few bounces
            if ray_stats is not None:
                ray_stats["intersect"] = ray_stats.get("intersect", 0) + int(dr.count(active)[0])
            si = scene.ray_intersect(ray, ray_flags, dr.opaque(mi.Bool, False), active)
            active &= si.is_valid()
            # Length between the vertices themselves (the ray starts a little past
            # the previous vertex, see below).
            seg = dr.norm(si.p - prev_p)
            length += seg
            prev_p = si.p
            n_geo, n_shade, albedo = self._arrival(si, ray, active)
            cos_in = None                                  # used by the pressure models only
            if not intensity:
                cos_in = -dr.dot(n_geo, ray.d)
                active &= cos_in > 1e-6
                throughput = throughput * seg / cos_in          # dA = r²/cosθ_i dω (÷ r: Eq. (1))
                if self.amplitude == "coherent":
                    phase += self._voxel_phase(si.p, bounce, ctx)

            if bounce > 0 or self.bounce1 == "cone":
                # Next-event connection to the point receiver.
                value, dist, w_rx, connect = self._connect_rx(
                    scene, si, p_rx, b_rx, n_shade, n_geo, throughput, albedo, cos_in, active,
                    intensity, ctx, ray_stats)
                values = [value]
                if self.complex_output:
                    values = [value * dr.cos(phase), value * dr.sin(phase)]
                if bounce == 0 or self.vertex_spread <= 0.0:
                    for h, v in zip(hists, values):
                        self._splat(h, v, length + dist, pose, slot, bounce, ctx, connect)
                else:
                    # Spread over a disk of radius ρ_s around the vertex in its tangent
                    # plane: L varies along the tangential gradient g of the last two
                    # legs; a uniform disk maps to the semicircle density of L over
                    # [−ρ_s|g|, ρ_s|g|], taken at m stratified points with weights.
                    grad = ray.d - w_rx                    # ∂(|x−x_prev| + |x−rx|)/∂x
                    grad = grad - dr.dot(grad, n_geo) * n_geo
                    half_span = dr.norm(grad) * self.vertex_spread
                    m = self.path_samples
                    shift = rng.next_float32()
                    ts = [(2.0 * (i + shift) / m) - 1.0 for i in range(m)]
                    ws = [dr.safe_sqrt(1.0 - t * t) for t in ts]
                    norm = 1.0 / dr.maximum(sum(ws[1:], ws[0]), 1e-12)
                    for t, wt in zip(ts, ws):
                        for h, v in zip(hists, values):
                            self._splat(h, v * wt * norm, length + dist + t * half_span, pose,
                                        slot, bounce, ctx, connect)

            if bounce + 1 < self.max_bounces:
                u_pick = rng.next_float32()
                u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
                d_new, inv_pdf = self._continuation(si.p, n_shade, u_pick, u2, guide)
                cos_new = dr.dot(d_new, n_shade)
                active &= (dr.dot(d_new, n_geo) > 0.0) & (cos_new > 0.0)
                if intensity:                              # (ρ/π · cosθ_o) / pdf
                    throughput *= albedo * dr.inv_pi * cos_new * inv_pdf
                else:   # σ/(2π) / pdf with σ = sqrt(ρ cosθ_i cosθ_o)
                    throughput *= dr.sqrt(albedo * cos_in * cos_new) * (0.5 * dr.inv_pi) * inv_pdf
                ray = self._continue_ray(si.p, d_new)

    def _arrival(self, si, ray, active):
        """(geometric normal, shading normal, albedo) at the vertex a ray arrives at; the
        surfaces are two-sided, so both normals face the side the ray comes from."""
        flip = dr.select(dr.dot(si.n, ray.d) > 0.0, -1.0, 1.0)
        n_shade = (si.sh_frame.n if self.shading_normals else si.n) * flip
        return si.n * flip, n_shade, si.bsdf().eval_diffuse_reflectance(si, active)[0]

    def _connect_rx(self, scene, si, p_rx, b_rx, n_shade, n_geo, throughput, albedo, cos_in,
                    active, intensity: bool, ctx, ray_stats=None):
        """Next-event connection of vertex ``si`` to the point receiver: (value, |x − rx|,
        unit direction to the receiver, connected mask). Intensity: throughput·ρ/π·cosθ_o·b_R/r²; pressure/coherent:
        throughput·√(ρ cosθ_i cosθ_o)/(2π)·a_R/r (supplemental Eq. (1)). Shadow ray included."""
        to_rx = p_rx - si.p
        dist2 = dr.squared_norm(to_rx)
        dist = dr.sqrt(dist2)
        w_rx = to_rx / dist
        cos_out = dr.maximum(dr.dot(n_shade, w_rx), 0.0)
        c_rx = -dr.dot(w_rx, b_rx)
        if intensity:
            value = (throughput * albedo * dr.inv_pi * cos_out
                     * self.rx_beam.gain(c_rx, ctx["rx_c"]) / dist2)
        else:
            value = (throughput * dr.sqrt(albedo * cos_in * cos_out) * (0.5 * dr.inv_pi)
                     * self.rx_beam.amplitude(c_rx, ctx["rx_c"]) / dist)
        connect = active & (dr.dot(n_geo, w_rx) > 0.0) & (value != 0.0)
        if ray_stats is not None:
            ray_stats["shadow"] = ray_stats.get("shadow", 0) + int(dr.count(connect)[0])
        connect &= ~scene.ray_test(si.spawn_ray_to(p_rx), connect)
        return value, dist, w_rx, connect

    def _guide(self, scene):
        """Bounding sphere (centre, radius) of the scene's non-flat shapes, or None."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for shape in scene.shapes():
            bb = shape.bbox()
            a, b = np.array(bb.min, np.float64), np.array(bb.max, np.float64)
            if np.all(b - a > 1e-6):
                lo, hi = np.minimum(lo, a), np.maximum(hi, b)
        if not np.all(np.isfinite(lo)) or self.guide_fraction <= 0.0:
            return None
        centre = (lo + hi) / 2.0
        return {"centre": mi.Point3f(*(dr.opaque(mi.Float, float(v)) for v in centre)),
                "radius2": dr.opaque(mi.Float, float(np.sum((hi - lo) ** 2) / 4.0)),
                "q": dr.opaque(mi.Float, self.guide_fraction)}

    @staticmethod
    def _continuation(p, n, u_pick, u2, guide):
        """A continuation direction and 1/pdf (sr): cosine-weighted about ``n``, or (one-sample
        MIS, probability q) uniform in the cone towards the guide sphere when ``p`` is
        outside it; pdf = q·[in cone]/Ω + (1 − q)·cos⁺/π, unbiased for any q."""
        frame = mi.Frame3f(n)
        d_cos = frame.to_world(mi.warp.square_to_cosine_hemisphere(u2))
        if guide is None:
            return d_cos, dr.pi / dr.maximum(dr.dot(d_cos, n), 1e-12)
        to_c = guide["centre"] - p
        dist2 = dr.squared_norm(to_c)
        outside = dist2 > guide["radius2"] * 1.0001
        cos_max = dr.safe_sqrt(1.0 - guide["radius2"] / dr.maximum(dist2, 1e-30))
        axis = to_c * dr.rsqrt(dr.maximum(dist2, 1e-30))
        d_cone = mi.Frame3f(axis).to_world(mi.warp.square_to_uniform_cone(u2, cos_max))
        q = dr.select(outside, guide["q"], 0.0)
        d = dr.select(u_pick < q, d_cone, d_cos)
        solid = 2.0 * dr.pi * dr.maximum(1.0 - cos_max, 1e-12)
        in_cone = outside & (dr.dot(d, axis) >= cos_max)
        pdf = dr.select(in_cone, q / solid, 0.0) + (1.0 - q) * dr.maximum(dr.dot(d, n), 0.0) * dr.inv_pi
        return d, dr.select(pdf > 0.0, 1.0 / pdf, 0.0)

    @staticmethod
    def _voxel_phase(p, bounce, ctx):
        """Phase (rad) of the world-space speckle cell (cube of side speckle_spacing) at p,
        for the vertices of paths with ≥ 2 bounces (a stream independent of bounce 1's)."""
        q = mi.Vector3i(dr.floor(p * ctx["inv_speckle"]))
        h = mi.sample_tea_32(mi.UInt32(q.x), mi.UInt32(q.y) ^ (ctx["speckle_key"] * 2 + 1))[0]
        h = mi.sample_tea_32(h, mi.UInt32(q.z) ^ 0x9E3779B9)[0]
        return mi.Float(h >> 8) * (2.0 * math.pi / 16777216.0)

    @staticmethod
    def _continue_ray(p, d):
        """The ray leaving vertex ``p`` in direction ``d``, started ε = (1 + max|p|)·9e-5 m
        along ``d`` itself to avoid re-hitting the surface at p.

        ``si.spawn_ray`` offsets the origin along the *normal* instead; the traced ray
        then misses the sampled line near grazing directions, which lengthens paths
        systematically (inside a hollow sphere of radius 1 cm, mean bounce-2 length
        +4.6e-5 m from si.t, +1.1e-4 m from vertex distances; now 0 within 5e-6 m).
        Along ``d`` the ray is the sampled line; only geometry within ε of p is skipped.
        """
        scale = dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
        eps = (1.0 + scale) * mi.math.RayEpsilon
        return mi.Ray3f(p + eps * d, d)

    @staticmethod
    def _splat(hist, value, length, pose, slot, bounce, ctx, active):
        """Tent-splat ``value`` at ``length`` into the bins of (slot, pose, bounce)."""
        u = (length - ctx["start"]) * ctx["inv_width"] - 0.5   # in bin-centre units
        u = dr.clip(u, -2.0, mi.Float(ctx["n_bins"]) + 1.0)   # keep the int cast defined
        j0f = dr.floor(u)
        frac = u - j0f
        j0 = mi.Int32(j0f)
        base = slot * ctx["half_stride"] + pose * ctx["pose_stride"] + bounce * ctx["n_bins_u"]
        for j, w in ((j0, 1.0 - frac), (j0 + 1, frac)):
            ok = active & (j >= 0) & (j < ctx["n_bins"])
            dr.scatter_reduce(dr.ReduceOp.Add, hist, type(hist)(value * w), base + mi.UInt32(j),
                              ok, mode=ctx["reduce_mode"])


class _StrataArrays:
    """The strata of :mod:`._surface_samples` as Dr.Jit arrays (gathered per lane)."""

    def __init__(self, strata):
        t = strata.triangles
        self.n_tri = 0 if t is None else len(t)
        if self.n_tri:
            v = lambda a: mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, i])) for i in range(3)))
            self.tri = {key: v(getattr(t, key)) for key in
                        ("p0", "e1", "e2", "n_geo", "n0", "dn1", "dn2")}
            self.tri["rho"] = mi.Float(t.rho)
            self.tri["area"] = mi.Float(t.area)
            self.tri["sid"] = mi.UInt32(t.sid)
            self.tri["phase"] = mi.Float(t.phase if t.phase is not None
                                         else np.zeros(1, np.float32))
        self.parametric = []
        for ps in strata.parametric:
            phase = ps.phase if ps.phase is not None else np.zeros(1, np.float32)
            self.parametric.append((range(len(ps)), ps.shape, dr.opaque(mi.UInt32, ps.n_v),
                                    dr.opaque(mi.Float, 1.0 / ps.n_u),
                                    dr.opaque(mi.Float, 1.0 / ps.n_v),
                                    dr.opaque(mi.Float, 1.0 / (ps.n_u * ps.n_v)),
                                    dr.opaque(mi.Float, ps.rho), mi.Float(phase),
                                    ps.phase is not None))

    def triangle_points(self, k, u):
        t = self.tri
        g = lambda key: dr.gather(mi.Vector3f, t[key], k)
        b = mi.warp.square_to_uniform_triangle(u)
        p = mi.Point3f(g("p0") + b.x * g("e1") + b.y * g("e2"))
        n_sh = dr.normalize(g("n0") + b.x * g("dn1") + b.y * g("dn2"))
        phase = dr.gather(mi.Float, t["phase"], k) if len(t["phase"]) > 1 else mi.Float(0.0)
        p0 = mi.Point3f(g("p0"))
        corners = (p0, p0 + g("e1"), p0 + g("e2"))
        return (p, g("n_geo"), n_sh, dr.gather(mi.Float, t["rho"], k),
                dr.gather(mi.Float, t["area"], k), phase, corners)


def _parametric_points(item, k, u):
    """A point of stratum k of an analytic shape: ``shape.sample_position`` of the cell."""
    _, shape, n_v, inv_nu, inv_nv, inv_cells, rho, phases, has_phase = item
    iu = k // n_v
    iv = k - iu * n_v
    uv = mi.Point2f((mi.Float(iu) + u.x) * inv_nu, (mi.Float(iv) + u.y) * inv_nv)
    ps = shape.sample_position(0.0, uv)
    area = inv_cells / ps.pdf                 # cell measure / area density of the map
    phase = dr.gather(mi.Float, phases, k) if has_phase else mi.Float(0.0)
    return ps.p, ps.n, ps.n, mi.Float(rho), area, phase, None


def _interleave(x):
    """The bits of UInt32 ``x`` < 2^16 spread to the even bit positions (Morton code)."""
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    return (x | (x << 1)) & 0x55555555


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
        arr = arr / norm
    return arr
