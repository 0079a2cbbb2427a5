"""The neural scene of neural backprojection: a complex field σ(x) = MLP(hash-grid(x))
(Reed et al. 2023, §4.1; reference ``inr_reconstruction/network.py``) on ``drjit.nn``.

- Coordinates: x (metres) → u = (x − lo)/(hi − lo) over the grid box widened by one voxel
  pitch on every side; σ = 0 outside that box (as the voxel scene), so both representations
  share one domain. The reference scales by 1/(4 max|x|) and relies on tcnn's index
  wrap-around instead.
- Encoding: multiresolution hash grid (``drjit.nn.HashGridEncoding``: levels, 2 features per
  level, 2^log2 entries per level, base resolution, per-level scale), float32.
- MLP: bias-free Linear layers with ReLU between them, width × hidden layers, 2 outputs
  (Re σ, Im σ; 1 output for the incoherent ablation), evaluated in tensor mode (GEMM): on
  the LLVM backend this trains 4–5× faster than cooperative vectors.
- Normals for the Lambertian factor: ∇ₓ|σ| by Dr.Jit reverse-mode AD with respect to the
  sample points (weights held constant): the normal is a *constant* in the weight gradient,
  whereas the reference differentiates through it (``create_graph=True``); Dr.Jit has no
  second-order AD through the hash grid.

Parameters are flat float32 arrays in a dict ('grid', 'w0', 'w1', …) so that one Adam and
one checkpoint format serve voxels and network alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonarsim.errors import InputError

from ._jit import jit
from .grid import Grid

MAX_FINEST_RESOLUTION = 2 ** 24      # hash-grid cells per axis: float32 keeps integers exact
MAX_MLP_WIDTH = 1024
MAX_MLP_HIDDEN = 16
MAX_HASH_FEATURES = 8


@dataclass
class NetworkSettings:
    """The hash grid + MLP of a neural field (one home for these seven settings: the
    solver's :class:`recon.solver.SolverSettings` and the deconvolution's INR inherit them)."""

    hash_levels: int = 14
    hash_features: int = 2
    hash_log2_size: int = 15
    hash_base_resolution: int = 16
    hash_level_scale: float = 1.5
    mlp_width: int = 128
    mlp_hidden: int = 3

    def validate_network(self) -> None:
        """Ranges of the network settings (one-line InputError): levels whose finest
        resolution base·scale^(levels − 1) stays ≤ 2^24 cells per axis (beyond, the level
        indices overflow and training turns to NaN), 1–8 features per level, table sizes
        2^8–2^26, widths 1–1024, 0–16 hidden layers."""
        for name in ("hash_levels", "hash_features", "hash_base_resolution", "mlp_width"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if int(self.mlp_hidden) < 0:
            raise InputError(f"mlp_hidden: must be >= 0, got {self.mlp_hidden}")
        for name, top in (("mlp_width", MAX_MLP_WIDTH), ("mlp_hidden", MAX_MLP_HIDDEN),
                          ("hash_features", MAX_HASH_FEATURES)):
            if int(getattr(self, name)) > top:
                raise InputError(f"{name}: must be <= {top}, got {getattr(self, name)}")
        if not 8 <= self.hash_log2_size <= 26:
            raise InputError(f"hash_log2_size: must be in [8, 26], got {self.hash_log2_size}")
        if not (np.isfinite(self.hash_level_scale) and self.hash_level_scale >= 1):
            raise InputError(f"hash_level_scale: must be >= 1, got {self.hash_level_scale}")
        finest = self.finest_resolution()
        if not finest <= MAX_FINEST_RESOLUTION:
            raise InputError(
                f"hash_levels: the finest level would have {finest:.3g} cells per axis "
                f"(hash_base_resolution {self.hash_base_resolution} × hash_level_scale "
                f"{self.hash_level_scale}^(levels − 1)), more than {MAX_FINEST_RESOLUTION}; "
                "use fewer levels or a smaller scale")

    def finest_resolution(self) -> float:
        try:
            return float(self.hash_base_resolution) * float(self.hash_level_scale) ** (
                int(self.hash_levels) - 1)
        except OverflowError:
            return float("inf")

    def n_features(self) -> int:
        """Encoding outputs (the MLP's input width)."""
        return int(self.hash_levels) * int(self.hash_features)

    def network_parameters(self, n_out: int = 2) -> int:
        """Hash-table entries × features (every level counted at the table size: an upper
        bound) plus the MLP's weights (bias-free)."""
        table = int(self.hash_levels) * 2 ** int(self.hash_log2_size) * int(self.hash_features)
        widths = [self.n_features()] + [int(self.mlp_width)] * int(self.mlp_hidden) + [n_out]
        return table + sum(a * b for a, b in zip(widths[:-1], widths[1:]))


class NetworkScene:
    """Hash grid + MLP complex field over a :class:`~recon.grid.Grid`'s box.

    settings: :class:`NetworkSettings` (e.g. a :class:`recon.solver.SolverSettings`).
    """

    kind = "network"

    def __init__(self, grid: Grid, settings, incoherent: bool = False):
        import drjit.nn as nn
        m = jit()
        self.m, self.grid, self.incoherent = m, grid, incoherent
        sp = grid.spacing
        pitch = float(np.mean(sp[sp > 0])) if np.any(sp > 0) else 0.01
        self.h = np.where(sp > 0, sp, pitch)
        self.lo = grid.bounds[:, 0] - self.h
        self.ext = grid.bounds[:, 1] + self.h - self.lo
        self.enc = nn.HashGridEncoding(
            m.Float, 3, n_levels=int(settings.hash_levels),
            n_features_per_level=int(settings.hash_features),
            hashmap_size=2 ** int(settings.hash_log2_size),
            base_resolution=int(settings.hash_base_resolution),
            per_level_scale=float(settings.hash_level_scale))
        n_in = self.enc.n_output_features
        n_out = self.n_outputs(incoherent)
        self.layers = [int(settings.mlp_width)] * int(settings.mlp_hidden)
        self.shapes = [(o, i) for i, o in zip([n_in] + self.layers, self.layers + [n_out])]

    @staticmethod
    def n_outputs(incoherent: bool) -> int:
        return 1 if incoherent else 2

    # parameters --------------------------------------------------------------------
    def initial(self, rng: np.random.Generator, x0=None) -> dict:
        """Hash table uniform in ±1e-4 (tcnn's init), weights uniform in ±1/√fan_in
        (PyTorch's default for Linear), from the run's NumPy generator."""
        p = {"grid": rng.uniform(-1e-4, 1e-4, self.enc.n_params).astype(np.float32)}
        for i, (o, n) in enumerate(self.shapes):
            p[f"w{i}"] = rng.uniform(-1, 1, o * n).astype(np.float32) / np.float32(np.sqrt(n))
        return p

    @property
    def n_params(self) -> int:
        return int(self.enc.n_params + sum(o * i for o, i in self.shapes))

    # evaluation --------------------------------------------------------------------
    def outputs(self, params: dict, points):
        """(raw MLP outputs [n_out] Float, inside Bool) at ``points`` Array3f (metres);
        differentiable in the parameters and the points."""
        import drjit as dr
        m = self.m
        u = m.Array3f(*((points[a] - float(self.lo[a])) * float(1.0 / self.ext[a])
                        for a in range(3)))
        inside = (u[0] >= 0) & (u[0] <= 1) & (u[1] >= 0) & (u[1] <= 1) & (u[2] >= 0) & (u[2] <= 1)
        self.enc.data = params["grid"]
        x = m.TensorXf(self.enc(u))
        for i, (o, n) in enumerate(self.shapes):
            x = m.TensorXf(params[f"w{i}"], shape=(o, n)) @ x
            if i + 1 < len(self.shapes):
                x = dr.maximum(x, 0.0)
        return [x[i].array for i in range(self.shapes[-1][0])], inside

    def evaluate(self, params: dict, points):
        """(Re σ, Im σ) Float at ``points`` Array3f (metres); differentiable in the
        parameters and the points."""
        import drjit as dr
        out, inside = self.outputs(params, points)
        re = dr.select(inside, out[0], 0.0)
        im = dr.zeros(self.m.Float, dr.width(re)) if self.incoherent else dr.select(inside, out[1], 0.0)
        return re, im

    def bind(self, params: dict) -> "BoundNetwork":
        return BoundNetwork(self, params)

    def warm_values(self, params: dict, points):
        """The complex values the warm start fits to the backprojection: σ."""
        return self.evaluate(params, points)

    def volume(self, params: dict, grid: Grid | None = None, chunk: int = 1 << 17) -> np.ndarray:
        """The complex field on ``grid`` (default: the scene's grid) [nx, ny, nz] complex64,
        in chunks of ``chunk`` points (any resolution, §4.6)."""
        def field(detached, points):
            re, im = self.evaluate(detached, points)
            return np.asarray(re) + 1j * np.asarray(im)
        return self.on_grid(field, params, grid, np.complex64, chunk)

    def on_grid(self, value, params: dict, grid: Grid | None, dtype, chunk: int = 1 << 17
                ) -> np.ndarray:
        """``value(detached params, points Array3f)`` → NumPy [n] evaluated at the voxel centres
        of ``grid`` (default: the scene's grid), ``chunk`` points at a time, without gradients;
        returned as [nx, ny, nz] ``dtype``."""
        import drjit as dr
        m = self.m
        grid = self.grid if grid is None else grid
        detached = {k: dr.detach(v) for k, v in params.items()}
        out = np.empty(grid.size, dtype=dtype)
        with dr.suspend_grad():
            for s in range(0, grid.size, chunk):
                pts = grid.points_range(s, s + chunk).T.astype(np.float32)
                out[s:s + pts.shape[1]] = value(detached, m.Array3f(*(m.Float(a) for a in pts)))
        return out.reshape(grid.shape)

    def warm_start(self, params: dict, x0: np.ndarray, iterations: int,
                   rng: np.random.Generator, lr: float, batch: int = 1 << 14) -> dict:
        """Fit the field to the volume ``x0`` [nx, ny, nz] (e.g. the scaled backprojection) at
        the voxel centres: half the batch uniform, half ∝ |x0|; Adam (learning rate ``lr``, the
        setting ``warm_start_lr``) on mean|σ − x0|²/max|x0|²."""
        import drjit as dr
        from .adam import Adam
        m = self.m
        flat = x0.ravel()
        mag = np.abs(flat).astype(np.float64)
        norm = float(mag.max() ** 2) or 1.0
        p_imp = (mag / mag.sum()) if mag.sum() > 0 else None
        opt = Adam(params, lr)
        for _ in range(int(iterations)):
            idx = rng.integers(0, flat.size, batch)
            if p_imp is not None:
                idx[batch // 2:] = rng.choice(flat.size, batch - batch // 2, p=p_imp)
            pts = (self.grid.bounds[:, 0] + np.stack(np.unravel_index(idx, self.grid.shape), 1)
                   * self.grid.spacing).T.astype(np.float32)
            re, im = self.warm_values(opt.params, m.Array3f(*(m.Float(a) for a in pts)))
            t = flat[idx]
            loss = (dr.mean(dr.square(re - m.Float(t.real.astype(np.float32))))
                    + dr.mean(dr.square(im - m.Float(t.imag.astype(np.float32))))) / norm
            dr.backward(loss)
            opt.step()
        return {k: np.asarray(dr.detach(v)) for k, v in opt.params.items()}


class BoundNetwork:
    """The field with fixed parameters: ``self(points)`` → (re, im) and
    ``gradient_of_magnitude(points)`` → (re, im, ∇|σ|) for the Lambertian normals."""

    def __init__(self, scene: NetworkScene, params: dict):
        self.scene, self.params = scene, params

    def __call__(self, points):
        return self.scene.evaluate(self.params, points)

    def gradient_of_magnitude(self, points):
        """(re, im, ∇ₓ|σ|) from *one* evaluation of the network: the points are a
        grad-enabled leaf, ∇ₓ|σ| comes from a reverse pass to the points alone
        (``dr.backward_to``: the weights' gradients are left untouched, the graph kept for
        the loss), and it is returned detached: a constant in the weight gradient (the
        normal has no second-order term, docs/reconstruction.md)."""
        (re, im), grad = self.with_magnitude_gradient(
            points, lambda p: self.scene.evaluate(self.params, p))
        return re, im, grad

    def with_magnitude_gradient(self, points, evaluate):
        """(``evaluate(p)``, ∇ₓ Σ|re + i·im|) where ``evaluate(p)`` → (re, im, ...) is called
        once at the points ``p`` made a grad-enabled leaf: the reverse pass reaches the points
        alone and the gradient is returned detached (see :meth:`gradient_of_magnitude`)."""
        import drjit as dr
        m = self.scene.m
        p = m.Array3f(dr.detach(points))
        dr.enable_grad(p)
        out = evaluate(p)
        re, im = out[0], out[1]
        total = dr.sum(dr.sqrt(re * re + im * im + 1e-20))
        dr.set_grad(total, 1.0)
        g = dr.backward_to(p, flags=dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput)
        grad = m.Array3f(dr.detach(g))
        dr.disable_grad(p)
        dr.eval(grad)
        return out, grad


class OccupancyScene(NetworkScene):
    """Hash grid + MLP with three outputs: an occupancy o(x) = sigmoid(ℓ(x) + offset) in
    [0, 1] and a complex surface amplitude a(x) (the "occupancy" representation, see
    :func:`recon.forward.render_occupancy`). The first occupied point along a ray scatters,
    interiors are hidden by the transmittance Π(1 − o), and the exported volume is o itself:
    a solid whose boundary is the surface.

    ``solid_floor``: below the grid's lowest voxel plane (the rig's ground, z = z₀) o = 1
    whatever the network says, so the ground's echo is the rise of o at z₀ and never needs
    a slab of occupied voxels inside the grid. Outside the rest of the (widened) box o = 0.
    """

    kind = "occupancy"
    LOGIT_OFFSET = -4.0          # o starts at sigmoid(-4) ≈ 0.018: empty space

    def __init__(self, grid: Grid, settings, incoherent: bool = False):
        super().__init__(grid, settings, incoherent=False)
        self.floor = float(grid.bounds[2, 0]) if settings.solid_floor else None

    @staticmethod
    def n_outputs(incoherent: bool) -> int:
        return 3

    def occupancy_and_amplitude(self, params: dict, points):
        """(o, Re a, Im a) Float at ``points``."""
        import drjit as dr
        out, inside = self.outputs(params, points)
        o = dr.select(inside, 1.0 / (1.0 + dr.exp(-(out[0] + self.LOGIT_OFFSET))), 0.0)
        if self.floor is not None:
            o = dr.select(points[2] < self.floor, 1.0, o)
        return o, dr.select(inside, out[1], 0.0), dr.select(inside, out[2], 0.0)

    def evaluate(self, params: dict, points):
        """(o, 0): the occupancy as the scene's exported value."""
        import drjit as dr
        o, _, _ = self.occupancy_and_amplitude(params, points)
        return o, dr.zeros(self.m.Float, dr.width(o))

    def warm_values(self, params: dict, points):
        """The warm start fits the amplitude a to the scaled backprojection (o stays empty):
        the first steps then raise o where the echoes agree with the backprojection's
        phase, i.e. on the surfaces (from a = 0 no gradient reaches o)."""
        _, a_re, a_im = self.occupancy_and_amplitude(params, points)
        return a_re, a_im

    def bind(self, params: dict) -> "BoundOccupancy":
        return BoundOccupancy(self, params)


class BoundOccupancy(BoundNetwork):
    """An occupancy scene with fixed parameters: ``occupancy_and_amplitude(points)``; the
    forward model leaves what the priors need in ``cache``."""

    def __init__(self, scene: OccupancyScene, params: dict):
        super().__init__(scene, params)
        self.cache = {}

    def occupancy_and_amplitude(self, points):
        return self.scene.occupancy_and_amplitude(self.params, points)
