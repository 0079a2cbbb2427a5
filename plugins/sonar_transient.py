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
positions (docs/transient_rendering.md). All poses of a call and all
their paths run as one wavefront Dr.Jit kernel; every per-call scalar enters the kernel as an
opaque value, so new poses, windows or seeds reuse the compiled kernel.

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


def piston_ka(beamwidth_deg: float) -> float:
    """Piston ``k·a`` (wavenumber × radius) whose full half-power beamwidth is ``beamwidth_deg``."""
    return _PISTON_HALF_POWER_X / math.sin(math.radians(beamwidth_deg) / 2.0)


def _bessel_j1_over_x(dr, mi, x):
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
    """A beam pattern: gain ``b(θ)`` (1 on the axis) and, for the TX, direction sampling.

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

    def opaque(self, dr, mi) -> dict:
        return {"cos_cut": dr.opaque(mi.Float, self.cos_cut), "ka": dr.opaque(mi.Float, self.ka)}

    def gain(self, dr, mi, cos_theta, c):
        """Intensity gain for a direction at angle θ from the boresight (``cos_theta``)."""
        if self.kind == "isotropic":
            return dr.full(mi.Float, 1.0, dr.width(cos_theta))
        if self.kind == "cone":
            return dr.select(cos_theta >= c["cos_cut"], 1.0, 0.0)
        # Baffled circular piston: |2 J1(ka sinθ)/(ka sinθ)|² in front, nothing behind.
        sin_theta = dr.safe_sqrt(1.0 - cos_theta * cos_theta)
        d = 2.0 * _bessel_j1_over_x(dr, mi, c["ka"] * sin_theta)
        return dr.select(cos_theta > 0.0, d * d, 0.0)

    def sample(self, dr, mi, u_pick, u2, c):
        """Local direction (z = boresight) and the weight gain/pdf for uniform numbers."""
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
        return d, self.gain(dr, mi, d.z, c) / pdf


class SonarTransientIntegrator(mi.SamplingIntegrator):
    """Transient sonar integrator; use :meth:`render_transients` (not ``mi.render``).

    Properties: ``max_bounces`` (int, default 3), ``tx_beam``/``rx_beam``
    ('cone' | 'isotropic' | 'piston', default 'cone'), ``tx_beamwidth``/``rx_beamwidth``
    (full beamwidth in degrees, default 30; for 'piston' the half-power width),
    ``shading_normals`` (bool, default True: cosines use interpolated mesh normals),
    ``accumulator`` ('float64' | 'float32', default 'float64': the histogram buffer type),
    ``mode`` ('intensity'; reserved for a later coherent mode).
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
        self.mode = str(props.get("mode", "intensity"))
        if self.mode != "intensity":
            raise ValueError(f"sonar_transient: mode must be 'intensity', got {self.mode!r}")

    def to_string(self):
        return (f"SonarTransientIntegrator[max_bounces={self.max_bounces}, "
                f"tx_beam={self.tx_beam.describe()}, rx_beam={self.rx_beam.describe()}]")

    def render(self, scene, sensor=None, seed=0, spp=0, develop=True, evaluate=True):
        raise RuntimeError("sonar_transient renders histograms: call "
                           "integrator.render_transients(scene, tx, rx, ...)")

    def sample(self, scene, sampler, ray, medium=None, active=True):
        raise RuntimeError("sonar_transient has no image mode; use render_transients()")

    # ------------------------------------------------------------------ public API
    def render_transients(self, scene, tx, rx, tx_dir, rx_dir, path_start: float,
                          bin_width: float, n_bins: int, paths_per_pose: int,
                          seed: int = 0, *, pose_offset: int = 0,
                          reduce_mode=None, ray_stats: dict | None = None) -> np.ndarray:
        """Energy histograms for N poses, float32 [N, max_bounces, n_bins].

        ``tx``, ``rx``: positions [N, 3] (m); ``tx_dir``, ``rx_dir``: boresights [N, 3]
        (normalised here). ``path_start``, ``bin_width``: round-trip path length (m) of
        the window start and of one bin. ``seed`` (0 ≤ seed < 2³²) and ``pose_offset``
        (global index of pose 0, which makes results independent of chunking) select
        the random numbers. N · paths_per_pose and N · bounces · n_bins must be < 2³².
        ``ray_stats``: if a dict, the numbers of intersection and shadow rays traced are
        added to its keys 'intersect' and 'shadow' (slower: splits the kernel; for
        benchmarks).
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
        n_hist = n * self.max_bounces * n_bins
        if n * paths_per_pose >= 2**32 or n_hist >= 2**32:
            raise ValueError("sonar_transient: too many lanes or bins for one launch "
                             "(< 2^32 each); render fewer poses at a time")
        if n == 0:
            return np.zeros((0, self.max_bounces, n_bins), np.float32)
        hist = dr.zeros(mi.Float64 if self.float64 else mi.Float, n_hist)
        self._trace(scene, hist, tx, rx, tx_dir, rx_dir, float(path_start),
                    float(bin_width), n_bins, paths_per_pose, seed, pose_offset,
                    dr.ReduceMode.Local if reduce_mode is None else reduce_mode, ray_stats)
        if self.float64:
            hist = mi.Float(hist)        # round in Dr.Jit: much faster than NumPy's astype
        dr.eval(hist)
        return hist.numpy().reshape(n, self.max_bounces, n_bins)

    # ------------------------------------------------------------------ kernel
    def _trace(self, scene, hist, tx, rx, tx_dir, rx_dir, path_start, bin_width, n_bins,
               paths_per_pose, seed, pose_offset, reduce_mode, ray_stats=None):
        UInt32, Float = mi.UInt32, mi.Float
        n_poses = tx.shape[0]
        n_paths = UInt32(dr.opaque(UInt32, paths_per_pose))
        lane = dr.arange(UInt32, n_poses * paths_per_pose)
        pose = lane // n_paths           # lanes are pose-major: coherent rays per pose
        path = lane - pose * n_paths
        pose_global = pose + dr.opaque(UInt32, pose_offset)
        stream_key = mi.sample_tea_32(dr.opaque(UInt32, seed), pose_global)[0]
        rng = mi.PCG32(1, mi.sample_tea_64(stream_key, path),
                       mi.sample_tea_64(path, stream_key))

        def gather3(a):
            if a.shape[0] == 1:   # Dr.Jit compiles 1-element sources differently per call
                a = np.repeat(a, 2, axis=0)
            src = mi.Vector3f(*(Float(a[:, i].astype(np.float32)) for i in range(3)))
            return dr.gather(mi.Vector3f, src, pose)

        p_tx, p_rx = mi.Point3f(gather3(tx)), mi.Point3f(gather3(rx))
        b_tx, b_rx = gather3(tx_dir), gather3(rx_dir)
        tx_c = self.tx_beam.opaque(dr, mi)
        rx_c = self.rx_beam.opaque(dr, mi)
        bins = dict(start=dr.opaque(Float, path_start),
                    inv_width=dr.opaque(Float, 1.0 / bin_width),
                    n_bins=dr.opaque(mi.Int32, n_bins),
                    pose_stride=dr.opaque(UInt32, self.max_bounces * n_bins),
                    n_bins_u=dr.opaque(UInt32, n_bins))

        # Bounce 0: leave the TX in a direction drawn from its beam.
        u_pick = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        d_local, throughput = self.tx_beam.sample(dr, mi, u_pick, u2, tx_c)
        ray = mi.Ray3f(p_tx, mi.Frame3f(b_tx).to_world(d_local))
        throughput = throughput * dr.opaque(Float, 1.0 / paths_per_pose)   # MC average
        length = Float(0.0)
        prev_p = p_tx
        active = dr.full(mi.Bool, True, n_poses * paths_per_pose)

        # Position, normals, UV (for textured albedo); no partial derivatives.
        ray_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        for bounce in range(self.max_bounces):    # unrolled: faster than a loop for few bounces
            if ray_stats is not None:
                ray_stats["intersect"] = ray_stats.get("intersect", 0) + int(dr.count(active)[0])
            si = scene.ray_intersect(ray, ray_flags, dr.opaque(mi.Bool, False), active)
            active &= si.is_valid()
            # Length between the vertices themselves (the ray starts a little past
            # the previous vertex, see below).
            length += dr.norm(si.p - prev_p)
            prev_p = si.p
            # Two-sided surfaces: orient the normals towards the side the path arrives from.
            flip = dr.select(dr.dot(si.n, ray.d) > 0.0, -1.0, 1.0)
            n_geo = si.n * flip
            n_shade = (si.sh_frame.n if self.shading_normals else si.n) * flip
            albedo = si.bsdf().eval_diffuse_reflectance(si, active)[0]

            # Next-event connection to the point receiver.
            to_rx = p_rx - si.p
            dist2 = dr.squared_norm(to_rx)
            dist = dr.sqrt(dist2)
            w_rx = to_rx / dist
            cos_out = dr.dot(n_shade, w_rx)
            gain_rx = self.rx_beam.gain(dr, mi, -dr.dot(w_rx, b_rx), rx_c)
            value = throughput * albedo * dr.inv_pi * dr.maximum(cos_out, 0.0) * gain_rx / dist2
            connect = active & (dr.dot(n_geo, w_rx) > 0.0) & (value > 0.0)
            if ray_stats is not None:
                ray_stats["shadow"] = ray_stats.get("shadow", 0) + int(dr.count(connect)[0])
            connect &= ~scene.ray_test(si.spawn_ray_to(p_rx), connect)
            self._splat(hist, value, length + dist, pose, bounce, bins, connect, reduce_mode)

            if bounce + 1 < self.max_bounces:
                u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
                d_new = mi.Frame3f(n_shade).to_world(mi.warp.square_to_cosine_hemisphere(u2))
                active &= dr.dot(d_new, n_geo) > 0.0   # shading normal may point under the surface
                throughput *= albedo                   # (ρ/π · cos) / (cos/π)
                ray = self._continue_ray(si.p, d_new)

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
    def _splat(hist, value, length, pose, bounce, bins, active, reduce_mode):
        """Tent-splat ``value`` at ``length`` into the bins of (pose, bounce)."""
        u = (length - bins["start"]) * bins["inv_width"] - 0.5   # in bin-centre units
        u = dr.clip(u, -2.0, mi.Float(bins["n_bins"]) + 1.0)   # keep the int cast defined
        j0f = dr.floor(u)
        frac = u - j0f
        j0 = mi.Int32(j0f)
        base = pose * bins["pose_stride"] + bounce * bins["n_bins_u"]
        for j, w in ((j0, 1.0 - frac), (j0 + 1, frac)):
            ok = active & (j >= 0) & (j < bins["n_bins"])
            dr.scatter_reduce(dr.ReduceOp.Add, hist, type(hist)(value * w), base + mi.UInt32(j), ok,
                              mode=reduce_mode)


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
