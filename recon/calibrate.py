"""Calibration by gradient (``recon calibrate``): sound speed, a global time offset and a rig
offset that maximise the focus of the backprojected image.

A scan whose geometry or timing is slightly wrong backprojects into a blurred image: echoes
of one scatterer are summed at slightly wrong delays and do not add up in phase. Autofocus
turns this round (SAR/SAS autofocus by sharpness maximisation, Fienup, JOSA A 20(4), 2003,
"Synthetic-aperture radar autofocus by maximizing sharpness"): the parameters that make the
image sharpest are the best estimate of the true ones, and the objective needs no ground
truth, so it is measurable on a real scan.

Model (per ping i, voxel v, the backprojection of :mod:`recon.backprojection`)::

    t_i = tx_i + F_i·d,   r_i = rx_i + F_i·d                          (rig offset d, metres)
    k_i(v) = ( (|v − t_i| + |v − r_i|) / (c_i + Δc) + δt ) · fs·R − start_sample·R
    I(v) = Σ_i s_i(k_i(v))                                            (s_i: matched-filtered
                                                                       analytic signal, FFT-
                                                                       upsampled by R, Catmull-
                                                                       Rom interpolated)

* ``Δc`` (m/s) is added to every ping's sound speed c_i (per-ping temperatures as the
  backprojector, or the dataset's sound speed);
* ``δt`` (s) is a global time offset: an echo of round-trip path p is *recorded* at p/c + δt
  (AirSAS: the direct arrival is recorded ~13 µs early, i.e. δt ≈ −13 µs if that were a
  global offset, docs/importers.md);
* ``d = (forward, left, up)`` (m) moves TX and RX together in each ping's sonar frame F_i
  (forward = the horizontal part of the TX boresight, up = +z, left = up × forward), i.e. a
  rig mounted off its nominal position; world axes when the dataset has no boresights.

Focus measure: the normalised sharpness ``S = n·Σ|I|⁴ / (Σ|I|²)²`` over the grid's n voxels
(1 for a uniform magnitude, larger when the energy concentrates; scale-free, so the data's
amplitude does not matter). The fit minimises ``−log S`` with SciPy's L-BFGS-B; the gradient
comes from Dr.Jit's reverse-mode AD through the same kernel (:func:`focus_and_gradient`):
one detached pass gives I and ∂S/∂I, then each block of pings is replayed with AD and
``Re⟨∂S/∂I, I_block⟩`` is back-propagated, so memory is one block's, whatever the number of
pings. The interpolation is a Catmull-Rom cubic (C1 in the delay), not the backprojector's
linear one, so that the gradient is continuous; at R = 4 the two images differ by ~1e-3
(relative L2).

Identifiability: for a scene small against its range, Δc, δt and the forward rig offset all
change every delay by nearly the same amount (the scene's range spread is what separates
them), so fitting all of them at once has a nearly flat direction; fit the subset you trust
(``free``) and read :attr:`CalibrationResult.curvature` for the conditioning.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from sonarsim.errors import InputError

from . import measurements
from ._jit import jit
from .grid import Grid

PARAMETERS = ("sound_speed", "time_offset", "rig_forward", "rig_left", "rig_up")
GROUPS = {"sound_speed": ("sound_speed",), "time_offset": ("time_offset",),
          "rig_offset": ("rig_forward", "rig_left", "rig_up"),
          **{name: (name,) for name in ("rig_forward", "rig_left", "rig_up")}}
# Search bounds (Δc m/s, δt s, rig offsets m): generous for a lab rig, tight enough that
# the image stays recognisable (a 20 kHz wavelength in air is 17 mm).
BOUNDS = {"sound_speed": 10.0, "time_offset": 100e-6, "rig_forward": 0.03,
          "rig_left": 0.03, "rig_up": 0.03}
UNITS = {"sound_speed": ("m/s", 1.0), "time_offset": ("us", 1e6), "rig_forward": ("mm", 1e3),
         "rig_left": ("mm", 1e3), "rig_up": ("mm", 1e3)}
RESTARTS = 4                   # L-BFGS-B runs at most (see fit)
LANES_PER_LAUNCH = 1 << 21     # voxel-ping lanes per kernel (AD replay keeps ~30 floats each)
# Per voxel: the float64 centre (24), the complex128 image (16), its float32 copies and the
# ∂S/∂I weights (16), the voxel's part of a launch's outputs (8).
BYTES_PER_VOXEL = 24 + 16 + 16 + 8


@dataclass(frozen=True)
class Calibration:
    """A calibration: ``sound_speed`` Δc (m/s, added to every ping's), ``time_offset`` δt (s,
    echoes are recorded at path/c + δt), ``rig_offset`` (forward, left, up) in metres in each
    ping's sonar frame (see the module docstring)."""

    sound_speed: float = 0.0
    time_offset: float = 0.0
    rig_offset: tuple = (0.0, 0.0, 0.0)

    @classmethod
    def from_vector(cls, theta) -> "Calibration":
        t = [float(x) for x in theta]
        return cls(t[0], t[1], (t[2], t[3], t[4]))

    def vector(self) -> np.ndarray:
        """[Δc, δt, forward, left, up] float64 (SI units), the order of :data:`PARAMETERS`."""
        return np.array([self.sound_speed, self.time_offset, *self.rig_offset], dtype=np.float64)

    def as_dict(self) -> dict:
        return {"sound_speed_delta_m_s": self.sound_speed, "time_offset_s": self.time_offset,
                "rig_offset_m": {"forward": self.rig_offset[0], "left": self.rig_offset[1],
                                 "up": self.rig_offset[2]}}

    def describe(self) -> str:
        f, l, u = (1e3 * x for x in self.rig_offset)
        return (f"sound speed {self.sound_speed:+.3f} m/s, time offset "
                f"{1e6 * self.time_offset:+.2f} us, rig offset forward {f:+.2f} mm, left "
                f"{l:+.2f} mm, up {u:+.2f} mm")


@dataclass
class CalibrationResult:
    """What :func:`fit` found: the calibration, the focus S before and after, the free
    parameters, the L-BFGS-B history [(evaluation, S, θ)], the curvature of −log S in the
    free parameters at the optimum (matrix in the units of :data:`UNITS`, and its eigenvalues)
    and the wall time (s)."""

    calibration: Calibration
    focus_before: float
    focus_after: float
    free: tuple
    history: list = field(default_factory=list)
    curvature: np.ndarray | None = None
    wall_s: float = 0.0
    message: str = ""
    at_bounds: tuple = ()

    def as_dict(self) -> dict:
        out = {"calibration": self.calibration.as_dict(), "describe": self.calibration.describe(),
               "focus_before": self.focus_before, "focus_after": self.focus_after,
               "focus_gain": self.focus_after / self.focus_before, "free": list(self.free),
               "evaluations": len(self.history), "wall_s": self.wall_s,
               "optimizer": self.message, "at_bounds": list(self.at_bounds)}
        if self.curvature is not None:
            out["curvature_units"] = [UNITS[p][0] for p in self.free]
            out["curvature"] = np.asarray(self.curvature).tolist()
            out["curvature_eigenvalues"] = np.linalg.eigvalsh(self.curvature).tolist()
        return out


def sonar_frames(dataset) -> np.ndarray:
    """Per-ping sonar frames [N, 3, 3] float64, columns (forward, left, up): forward = the
    horizontal part of the TX boresight, up = +z, left = up × forward. The identity for pings
    without a usable boresight (none stored, or vertical)."""
    n = len(dataset.waveforms)
    frames = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    b = getattr(dataset, "boresight", None)
    if b is None:
        return frames
    fwd = np.array(b, dtype=np.float64).reshape(n, 3)
    fwd[:, 2] = 0.0
    norm = np.linalg.norm(fwd, axis=1)
    ok = norm > 1e-9
    fwd[ok] /= norm[ok, None]
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, fwd)
    frames[ok] = np.stack([fwd[ok], left[ok], np.broadcast_to(up, fwd[ok].shape)], axis=2)
    return frames


def sharpness(volume) -> float:
    """Normalised sharpness ``n·Σ|I|⁴/(Σ|I|²)²`` of a complex or real volume (1 = uniform)."""
    a2 = np.abs(np.asarray(volume, dtype=np.complex128)) ** 2
    den = float(a2.sum()) ** 2
    if den == 0.0:
        raise InputError("the backprojected image is all zero: nothing to focus "
                         "(check the grid against the scan)")
    return float(a2.size * (a2 ** 2).sum() / den)


class FocusProblem:
    """The backprojection of ``dataset`` onto ``grid`` as a differentiable function of the
    calibration (Dr.Jit, CPU or GPU). ``upsample``: FFT upsampling R of the matched-filtered
    signals (default 4); ``per_ping_sound_speed``: as :func:`recon.backprojection.solve`."""

    def __init__(self, dataset, grid: Grid, *, upsample: int = 4,
                 per_ping_sound_speed: bool = True):
        if not isinstance(grid, Grid):
            raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
        if int(upsample) != upsample or upsample < 1:
            raise InputError(f"upsample must be a positive integer, got {upsample!r}")
        measurements.check_dataset(dataset)
        from sonarsim import signals
        m = self.m = jit()
        self.upsample = int(upsample)
        s = measurements.matched_filtered(dataset)
        if self.upsample > 1:
            s = signals.fft_upsample(s, self.upsample, axis=-1)
        s = np.asarray(s, dtype=np.complex64)
        self.n_pings, self.n_up = s.shape
        self.re = m.Float(np.ascontiguousarray(s.real).ravel())
        self.im = m.Float(np.ascontiguousarray(s.imag).ravel())
        self.c = measurements.sound_speeds(dataset, per_ping_sound_speed)
        self.fs = float(dataset.fs)
        self.start = float(getattr(dataset, "start_sample", 0) or 0)
        frames = sonar_frames(dataset)
        # Geometry and delays in float64: ∂S/∂θ is a residual of per-pair terms ~100x larger,
        # and the float32 round-off of a delay (~1e-4 upsampled samples at 1 000 samples) moved
        # it by a few per cent (measured with linear interpolation against float64 central
        # differences). The signals stay float32.
        f64 = lambda a: m.Float64(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
        self.tx = [f64(dataset.tx[:, j]) for j in range(3)]
        self.rx = [f64(dataset.rx[:, j]) for j in range(3)]
        self.frame = [[f64(frames[:, j, k]) for k in range(3)] for j in range(3)]
        self.c_ping = f64(self.c)
        self.grid = grid
        self.points = grid.points()
        self.n_vox = len(self.points)
        # Pings per launch: as many as fit LANES_PER_LAUNCH lanes, over voxel chunks.
        self.vox_chunk = min(self.n_vox, LANES_PER_LAUNCH)
        self.pings_per_launch = max(1, min(self.n_pings, LANES_PER_LAUNCH // self.vox_chunk))

    # -- kernel ---------------------------------------------------------------------------
    def _params(self, theta, grad: bool):
        m, dr = self.m, _dr()
        # Opaque: the values are kernel inputs, not literals, so one compiled kernel serves
        # every evaluation of a fit.
        p = [dr.opaque(m.Float64, float(x)) for x in theta]
        if grad:
            for x in p:
                dr.enable_grad(x)
        return p

    def _block(self, params, v0: int, v1: int, p0: int, p1: int):
        """Partial image (Re, Im) [v1 − v0] of pings p0..p1 on voxels v0..v1."""
        m, dr = self.m, _dr()
        dc, dt, d_f, d_l, d_u = params
        n_p = p1 - p0
        lane = dr.arange(m.UInt32, (v1 - v0) * n_p)
        vox = lane // n_p
        ping = lane % n_p + p0
        pts = self.points[v0:v1]
        v = [dr.gather(m.Float64, m.Float64(np.ascontiguousarray(pts[:, j])), vox)
             for j in range(3)]
        off = [dr.gather(m.Float64, self.frame[j][0], ping) * d_f
               + dr.gather(m.Float64, self.frame[j][1], ping) * d_l
               + dr.gather(m.Float64, self.frame[j][2], ping) * d_u for j in range(3)]
        dtx = [v[j] - dr.gather(m.Float64, self.tx[j], ping) - off[j] for j in range(3)]
        drx = [v[j] - dr.gather(m.Float64, self.rx[j], ping) - off[j] for j in range(3)]
        path = (dr.sqrt(dtx[0] ** 2 + dtx[1] ** 2 + dtx[2] ** 2)
                + dr.sqrt(drx[0] ** 2 + drx[1] ** 2 + drx[2] ** 2))
        c = dr.gather(m.Float64, self.c_ping, ping) + dc
        rate = self.fs * self.upsample
        k = (path / c + dt) * rate - self.start * self.upsample
        k0 = dr.floor(dr.detach(k))
        w = m.Float(k - k0)
        # Catmull-Rom cubic through s[k0-1 .. k0+2]: C1 in the delay, so the gradient has no
        # jumps where a delay crosses a sample (with linear interpolation it has, and the
        # focus then has kink-made local maxima that stop the fit: measured, a 4 mm rig offset
        # stopped at 3.74 mm). Pairs whose four samples are not all recorded contribute nothing.
        ok = (k0 >= 1) & (k0 < self.n_up - 2)
        base = m.UInt32(dr.select(ok, k0, 1)) + m.UInt32(ping) * self.n_up
        w2 = w * w
        w3 = w2 * w
        weights = (-0.5 * w3 + w2 - 0.5 * w, 1.5 * w3 - 2.5 * w2 + 1.0,
                   -1.5 * w3 + 2.0 * w2 + 0.5 * w, 0.5 * w3 - 0.5 * w2)
        re = dr.zeros(m.Float, dr.width(w))
        im = dr.zeros(m.Float, dr.width(w))
        for j, weight in enumerate(weights):
            index = base + j - 1
            re += weight * dr.gather(m.Float, self.re, index, ok)
            im += weight * dr.gather(m.Float, self.im, index, ok)
        out_re = dr.zeros(m.Float, v1 - v0)
        out_im = dr.zeros(m.Float, v1 - v0)
        dr.scatter_reduce(dr.ReduceOp.Add, out_re, re, vox)
        dr.scatter_reduce(dr.ReduceOp.Add, out_im, im, vox)
        return out_re, out_im

    def _launches(self):
        for v0 in range(0, self.n_vox, self.vox_chunk):
            v1 = min(v0 + self.vox_chunk, self.n_vox)
            for p0 in range(0, self.n_pings, self.pings_per_launch):
                yield v0, v1, p0, min(p0 + self.pings_per_launch, self.n_pings)

    # -- public ---------------------------------------------------------------------------
    def image(self, calibration: Calibration | None = None) -> np.ndarray:
        """Backprojected complex image [nx, ny, nz] complex128 under ``calibration``."""
        theta = (calibration or Calibration()).vector()
        params = self._params(theta, grad=False)
        acc = np.zeros(self.n_vox, dtype=np.complex128)
        for v0, v1, p0, p1 in self._launches():
            re, im = self._block(params, v0, v1, p0, p1)
            acc[v0:v1] += np.asarray(re, dtype=np.float64) + 1j * np.asarray(im, dtype=np.float64)
        return acc.reshape(self.grid.shape)

    def focus(self, calibration: Calibration | None = None) -> float:
        """The sharpness S of :meth:`image`."""
        return sharpness(self.image(calibration))

    def focus_and_gradient(self, calibration: Calibration) -> tuple[float, np.ndarray]:
        """S and ∂S/∂θ [5] (SI units, the order of :data:`PARAMETERS`) by reverse-mode AD."""
        dr = _dr()
        theta = calibration.vector()
        img = self.image(calibration).ravel()
        a2 = np.abs(img) ** 2
        sum2, sum4 = float(a2.sum()), float((a2 ** 2).sum())
        if sum2 == 0.0:
            raise InputError("the backprojected image is all zero: nothing to focus "
                             "(check the grid against the scan)")
        s = self.n_vox * sum4 / sum2 ** 2
        # ∂S/∂Re I = 4·n·Re I·(|I|² − Σ|I|⁴/Σ|I|²)/(Σ|I|²)², the same for Im.
        g = 4.0 * self.n_vox * (a2 - sum4 / sum2) / sum2 ** 2
        g_re, g_im = g * img.real, g * img.imag
        params = self._params(theta, grad=True)
        grad = np.zeros(5)
        for v0, v1, p0, p1 in self._launches():
            re, im = self._block(params, v0, v1, p0, p1)
            loss = dr.sum(re * self.m.Float(g_re[v0:v1].astype(np.float32))
                          + im * self.m.Float(g_im[v0:v1].astype(np.float32)))
            dr.backward(loss)
        grad[:] = [float(dr.grad(x)[0]) for x in params]
        for x in params:
            dr.disable_grad(x)
        return s, grad


def _dr():
    import drjit
    return drjit


def parse_free(names) -> tuple:
    """The free parameters (order of :data:`PARAMETERS`) of names/groups such as
    ``['time_offset', 'rig_offset']``."""
    if isinstance(names, str):
        names = [n for n in names.replace(",", " ").split() if n]
    chosen = set()
    for name in names:
        if name not in GROUPS:
            raise InputError(f"--fit: unknown parameter {name!r} (one of "
                             f"{', '.join(GROUPS)})")
        chosen.update(GROUPS[name])
    if not chosen:
        raise InputError("--fit: name at least one parameter")
    return tuple(p for p in PARAMETERS if p in chosen)


class _OutOfEvaluations(Exception):
    """The search used its ``max_evaluations`` (raised inside scipy's objective)."""


def fit(dataset, grid: Grid, *, free=("sound_speed", "time_offset", "rig_offset"),
        start: Calibration | None = None, upsample: int = 4, per_ping_sound_speed: bool = True,
        max_evaluations: int = 60, curvature: bool = True, log=None) -> CalibrationResult:
    """Maximise the focus S of the backprojection of ``dataset`` on ``grid`` over the ``free``
    parameters (names or groups of :data:`GROUPS`), from ``start`` (default: no correction),
    by L-BFGS-B within :data:`BOUNDS` with the AD gradient. ``curvature``: also the Hessian of
    −log S in the free parameters at the optimum (central differences of the AD gradient,
    2 gradients per parameter). ``log``: a callable taking one line per evaluation."""
    import scipy.optimize
    t_start = time.perf_counter()
    free = parse_free(free)
    if int(max_evaluations) < 1:
        raise InputError(f"--max-evaluations must be >= 1, got {max_evaluations}")
    problem = FocusProblem(dataset, grid, upsample=upsample,
                           per_ping_sound_speed=per_ping_sound_speed)
    theta0 = (start or Calibration()).vector()
    idx = [PARAMETERS.index(p) for p in free]
    # Optimise in display units (m/s, µs, mm), in which steps of one unit move echoes by
    # comparable amounts, with −log S divided by its largest gradient component at the start:
    # within bounds L-BFGS-B's first trial step is the gradient itself, so the parameter that
    # matters most moves by one unit. Unnormalised, a flat start (the real scan at z = 0.2 m:
    # 4e-4 per µs) took steps of 0.0004 µs and could stop there ("relative reduction of f")
    # or not, depending on round-off (docs/differentiable.md "Variants").
    scale = np.array([UNITS[p][1] for p in free])
    history: list = []
    norm = [1.0]

    def theta_of(x):
        theta = theta0.copy()
        theta[idx] = np.asarray(x) / scale
        return theta

    def objective(x):
        if len(history) >= int(max_evaluations):
            raise _OutOfEvaluations        # scipy's maxfun is not a hard limit (line searches)
        theta = theta_of(x)
        s, g = problem.focus_and_gradient(Calibration.from_vector(theta))
        history.append((len(history), s, theta.tolist()))
        if log is not None:
            log(f"evaluation {len(history)}: focus {s:.5f}; "
                f"{Calibration.from_vector(theta).describe()}")
        return -math.log(s) / norm[0], -g[idx] / s / scale / norm[0]

    x0 = theta0[idx] * scale
    first = objective(x0)
    norm[0] = float(np.max(np.abs(first[1]))) or 1.0
    cached = {tuple(x0): (first[0] / norm[0], first[1] / norm[0])}

    def objective_once(x):
        """:func:`objective`, the start's evaluation reused once (L-BFGS-B asks for it first)."""
        hit = cached.pop(tuple(np.asarray(x, np.float64)), None)
        return hit if hit is not None else objective(x)

    bounds = [(x - BOUNDS[p] * u, x + BOUNDS[p] * u) for x, p, u in zip(x0, free, scale)]
    focus_before = problem.focus(Calibration.from_vector(theta0))
    # The linear interpolation makes S piecewise smooth: its gradient jumps a little where a
    # (ping, voxel) delay crosses a sample, which spoils L-BFGS-B's curvature pairs and can
    # stop it early (measured: a 4 mm rig offset stopped at 3.74 mm). Restarting from the
    # result with a fresh curvature memory until a restart no longer improves S fixes that.
    x, f_best, message = x0, math.inf, ""
    for _ in range(RESTARTS):
        left = int(max_evaluations) - len(history)
        if left < 2:
            break
        try:
            res = scipy.optimize.minimize(objective_once, x, jac=True, method="L-BFGS-B",
                                          bounds=bounds,
                                          options={"maxfun": left, "ftol": 1e-7, "gtol": 1e-6})
        except _OutOfEvaluations:
            _, s, theta = max(history, key=lambda h: h[1])        # the best focus evaluated
            if -math.log(s) / norm[0] < f_best:
                x, f_best = np.asarray(theta)[idx] * scale, -math.log(s) / norm[0]
            message = f"stopped after --max-evaluations {int(max_evaluations)}"
            break
        improved = f_best - float(res.fun)
        if float(res.fun) < f_best:
            x, f_best, message = res.x, float(res.fun), str(res.message)
        if improved * norm[0] < 1e-6:             # in −log S
            break
    best = Calibration.from_vector(theta_of(x))
    # A parameter that ends on its search bound was not determined by the focus (it kept
    # rising): measured on the single-height real scan, see docs/differentiable.md.
    at_bounds = tuple(p for p, xi, (lo, hi) in zip(free, x, bounds)
                      if min(xi - lo, hi - xi) < 1e-3 * (hi - lo))
    hess = None
    if curvature:
        hess = _curvature(problem, best, idx, scale)
    return CalibrationResult(best, focus_before, problem.focus(best), free, history, hess,
                             time.perf_counter() - t_start, message, at_bounds)


def _curvature(problem: FocusProblem, at: Calibration, idx, scale) -> np.ndarray:
    """Hessian of −log S in the free parameters (display units) by central differences of the
    AD gradient (steps of 0.05 display units: 0.05 m/s, 0.05 µs, 0.05 mm)."""
    theta = at.vector()
    h = 0.05
    rows = []
    for i, j in enumerate(idx):
        grads = []
        for sign in (1.0, -1.0):
            t = theta.copy()
            t[j] += sign * h / scale[i]
            s, g = problem.focus_and_gradient(Calibration.from_vector(t))
            grads.append(-g[idx] / s / scale)
        rows.append((grads[0] - grads[1]) / (2 * h))
    hess = np.array(rows)
    return 0.5 * (hess + hess.T)


def apply(dataset, calibration: Calibration):
    """A copy of ``dataset`` corrected by ``calibration``: TX/RX moved by the rig offset, the
    sound speed (and per-ping temperatures, through 331.4 + 0.6·T) raised by Δc, and the
    waveforms delayed by −δt (FFT fractional delay, :func:`sonarsim.signals.fractional_delay`),
    so that any ``recon`` method images the corrected scan."""
    from sonarsim import signals
    frames = sonar_frames(dataset)
    off = frames @ np.asarray(calibration.rig_offset, dtype=np.float64)
    temps = dataset.temperatures
    if temps is not None:
        temps = np.asarray(temps, dtype=np.float64) + calibration.sound_speed / 0.6
    w = dataset.waveforms
    if calibration.time_offset != 0.0:
        w = signals.fractional_delay(w, -calibration.time_offset * float(dataset.fs), axis=-1)
        w = np.asarray(w, dtype=dataset.waveforms.dtype)
    meta = dict(dataset.meta or {})
    meta["calibration"] = calibration.describe()
    return dataclasses.replace(dataset, waveforms=w, tx=np.asarray(dataset.tx) + off,
                               rx=np.asarray(dataset.rx) + off, temperatures=temps,
                               sound_speed=float(dataset.sound_speed) + calibration.sound_speed,
                               meta=meta, transients=None)
