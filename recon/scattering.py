"""Direction-dependent scattering for neural backprojection: a hash grid + MLP whose outputs
are complex spherical-harmonic (SH) coefficients per point, so that a surface may return a
different echo toward different look directions (SH-SAS: Vengurlekar, Pediredla, Jayasuriya,
"SH-SAS: An Implicit Neural Representation for Complex Spherical-Harmonic Scattering Fields
for 3D Synthetic Aperture Sonar", 3DV 2026, arXiv 2509.11087; reference code
OmkarV23/SH-SAS, ``inr_reconstruction/network_sh_mlp.py``).

``--scattering sh:L`` (``recon nbp``; the setting ``scattering``) uses degree L: the MLP
has 2·(L+1)² real outputs, the complex coefficients c_lm(x) (Re, Im of each, index
i = l(l+1)+m, l = 0…L, m = −l…l). The field seen from the unit look direction ω is

    σ(x, ω) = Σ_lm c_lm(x) · Ỹ_lm(ω),      Ỹ_lm = √(4π) · Y_lm

with Y_lm Dr.Jit's real, orthonormal SH (:func:`drjit.sh_eval`, the convention of SciPy's
``sph_harm_y`` with the Condon–Shortley phase; checked in tests/test_scattering.py). The
factor √(4π) makes Ỹ_00 = 1, so that

- c_00(x) is the direction average of σ(x, ω) over the sphere (∫Ỹ_lm dω = 0 for l ≥ 1),
- with L = 0 the network, its initialisation and its loss are those of isotropic NBP
  exactly (factor 1; tests/test_scattering.py), and
- for every L, the mean over uniform directions of |σ(x, ω)|² is Σ_lm |c_lm|² (Parseval).

SH-SAS writes the same model with Y_lm, i.e. coefficients √(4π) times ours.

Which value plays which role (as SH-SAS): the scattered amplitude summed over the rays is
σ(x, ω); the transmittance and the Lambertian normals (−∇|σ|) use the *density* c_00; the
exported volume is c_00 (complex: the direction-averaged scattering; its magnitude is what
``recon evaluate`` thresholds); :meth:`ShNetworkScene.rms_volume` gives the alternative
√(Σ|c_lm|²), the RMS of σ over directions (docs/scattering.md compares both). The priors that re-evaluate the field at shifted points
(smoothness, phase) see c_00; sparsity and TV act on the scattered σ(x, ω) of each sample.

Look direction ω: the unit vector from the sample point toward the midpoint of its ping's
TX and RX (the array: co-located TX/RX make this the monostatic back-scatter direction;
:meth:`recon.forward.EllipsoidSamples.look_directions`). SH-SAS uses the direction from the
receiver to the point, −ω for a monostatic array; the odd-l coefficients change sign and
nothing else.

The warm start fits σ(x, ω) at uniformly random directions to the scaled backprojection:
its optimum is c_00 = the backprojection and c_lm = 0 for l ≥ 1 (Parseval), so the
optimisation starts isotropic. Two options of SH-SAS keep the field near isotropic (both off
by default; measured in docs/scattering.md): ``sh_start`` (the l ≥ 1 coefficients enter the
model from that iteration on; before it σ = c_00, the warm start included: SH-SAS raises the
active degree during training) and ``sh_sparsity`` (an L1 prior, weight × the mean over the
samples of Σ_{l≥1}|c_lm|, from ``reg_start`` as the other priors: SH-SAS's optional prior on
the higher-order coefficients).
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from sonarsim.errors import InputError

from .field import BoundNetwork, NetworkScene, OccupancyScene
from .grid import Grid

ISOTROPIC = "isotropic"
MAX_DEGREE = 4          # (L+1)² = 25 complex coefficients: 50 MLP outputs per point
SQRT_4PI = math.sqrt(4.0 * math.pi)


def parse_scattering(text: str) -> int | None:
    """The SH degree of a ``scattering`` setting: None for 'isotropic', L for 'sh:L'
    (0 ≤ L ≤ :data:`MAX_DEGREE`); anything else: one-line :class:`InputError`."""
    if text == ISOTROPIC:
        return None
    head, _, tail = str(text).partition(":")
    if head == "sh" and tail.isdigit() and 0 <= int(tail) <= MAX_DEGREE:
        return int(tail)
    raise InputError(f"scattering: 'isotropic' or 'sh:L' with L in 0..{MAX_DEGREE}, "
                     f"got {text!r}")


def check_settings(settings) -> None:
    """Refuse the combinations the SH field does not support (one line): the occupancy
    representation and the incoherent ablation."""
    degree = parse_scattering(settings.scattering)
    if not degree and (getattr(settings, "sh_start", 0) > 0
                       or getattr(settings, "sh_sparsity", 0.0) > 0):
        raise InputError("sh_start / sh_sparsity act on the l >= 1 coefficients: "
                         "use --scattering sh:L with L >= 1")
    if degree is None:
        return
    if getattr(settings, "occupancy", False):
        raise InputError("scattering: sh:L is not available with --occupancy")
    if getattr(settings, "incoherent", False):
        raise InputError("scattering: sh:L needs a coherent field, not --incoherent")


def n_coefficients(degree: int) -> int:
    """Complex SH coefficients per point up to ``degree``: (L+1)²."""
    return (int(degree) + 1) ** 2


def sh_basis(m, directions, degree: int) -> list:
    """[Ỹ_lm(ω)] (Float per lane, or the Python float 1.0 for Ỹ_00), index l(l+1)+m, of unit
    ``directions`` Array3f: √(4π) × :func:`drjit.sh_eval`."""
    import drjit as dr
    if degree == 0:
        return [1.0]
    basis = dr.sh_eval(directions, int(degree))
    return [1.0] + [b * SQRT_4PI for b in basis[1:]]


def sh_basis_numpy(directions: np.ndarray, degree: int) -> np.ndarray:
    """Ỹ_lm of unit directions [N, 3] → [(L+1)², N] float64 (NumPy; for tests and tools)."""
    from ._jit import jit
    m = jit()
    d = np.asarray(directions, dtype=np.float32)
    out = sh_basis(m, m.Array3f(*(m.Float(d[:, a].copy()) for a in range(3))), degree)
    return np.stack([np.broadcast_to(np.asarray(b, dtype=np.float64), (len(d),)) for b in out])


class ShNetworkScene(NetworkScene):
    """Hash grid + MLP whose 2·(L+1)² outputs are the complex SH coefficients c_lm(x)
    (module docstring). ``evaluate`` (exported volume, warm start base) gives c_00; the
    forward model gets σ(x, ω) through :meth:`BoundShNetwork.scatter_toward`."""

    kind = "network"

    def __init__(self, grid: Grid, settings, degree: int):
        self.degree = int(degree)
        super().__init__(grid, settings, incoherent=False)
        self._warm_calls = itertools.count()
        self.sh_start = int(getattr(settings, "sh_start", 0))
        self.directions_on = self.sh_start == 0

    def at_iteration(self, iteration: int) -> None:
        """Called by the solver before each iteration: the l ≥ 1 terms enter the model from
        iteration ``sh_start`` on."""
        self.directions_on = iteration >= self.sh_start

    def n_outputs(self, incoherent: bool = False) -> int:
        return 2 * n_coefficients(self.degree)

    def coefficients(self, params: dict, points):
        """([(Re c_lm, Im c_lm)] per lm, zero outside the box) at ``points`` Array3f."""
        import drjit as dr
        out, inside = self.outputs(params, points)
        return [(dr.select(inside, out[2 * i], 0.0), dr.select(inside, out[2 * i + 1], 0.0))
                for i in range(n_coefficients(self.degree))]

    def combine(self, coeffs, directions):
        """σ(x, ω) = Σ c_lm Ỹ_lm(ω): (re, im) Float from :meth:`coefficients`' list and unit
        look ``directions`` Array3f (one per lane)."""
        re, im = coeffs[0]
        if not self.directions_on:
            return re, im
        basis = sh_basis(self.m, directions, self.degree)
        for (c_re, c_im), b in zip(coeffs[1:], basis[1:]):
            re = re + b * c_re
            im = im + b * c_im
        return re, im

    def scatter(self, params: dict, points, directions):
        """σ(x, ω) (re, im) at ``points`` seen from ``directions``; differentiable."""
        return self.combine(self.coefficients(params, points), directions)

    def warm_values(self, params: dict, points):
        """σ(x, ω) at directions uniform on the sphere (a new PCG32 stream per call): the
        warm start's fit then has c_00 = the backprojection, c_lm = 0 (l ≥ 1) as optimum. For
        L = 0 exactly c_00 (isotropic NBP's warm start)."""
        import drjit as dr
        if self.degree == 0 or not self.directions_on:
            return self.evaluate(params, points)
        from .solver.priors import random_directions
        dirs = random_directions(self.m, dr.width(points[0]), 0x5EED0000 + next(self._warm_calls))
        return self.scatter(params, points, dirs)

    def bind(self, params: dict) -> "BoundShNetwork":
        return BoundShNetwork(self, params)

    def rms_volume(self, params: dict, grid: Grid | None = None, chunk: int = 1 << 17) -> np.ndarray:
        """The RMS of σ(x, ω) over uniform directions, √(Σ_lm |c_lm|²) (Parseval), on ``grid``
        (default: the scene's) [nx, ny, nz] float32: an alternative export that also sees points
        scattering toward a few directions only (the exported volume is c_00, :meth:`volume`)."""
        def rms(detached, points):
            energy = sum(np.asarray(re, np.float64) ** 2 + np.asarray(im, np.float64) ** 2
                         for re, im in self.coefficients(detached, points))
            return np.sqrt(energy)
        return self.on_grid(rms, params, grid, np.float32, chunk)


class BoundShNetwork(BoundNetwork):
    """An SH scene with fixed parameters. ``self(points)`` and
    ``gradient_of_magnitude(points)`` are those of the density c_00 (inherited: the scene's
    ``evaluate`` is c_00); :func:`recon.forward.render` calls :meth:`scatter_toward`."""

    directional = True

    def __init__(self, scene: ShNetworkScene, params: dict):
        super().__init__(scene, params)
        self.cache = {}

    def scatter_toward(self, points, directions, with_gradient: bool):
        """(σ_re, σ_im, c00_re, c00_im, ∇|c_00| or None) at ``points`` seen from unit look
        ``directions``, from one network evaluation. The gradient (for the Lambertian normals)
        is taken as in :meth:`recon.field.BoundNetwork.gradient_of_magnitude`: a reverse pass
        to the points alone, detached (a constant in the weight gradient)."""
        scene = self.scene

        def density_and_coefficients(p):
            coeffs = scene.coefficients(self.params, p)
            return coeffs[0][0], coeffs[0][1], coeffs

        if with_gradient:
            (_, _, coeffs), grad = self.with_magnitude_gradient(points, density_and_coefficients)
        else:
            coeffs, grad = scene.coefficients(self.params, points), None
        re, im = scene.combine(coeffs, directions)
        if scene.directions_on:
            self.cache["sh"] = coeffs[1:]       # the l >= 1 coefficients, for sh_sparsity
        return re, im, coeffs[0][0], coeffs[0][1], grad


def make_scene(grid: Grid, settings):
    """The network scene of ``settings.scattering``: :class:`ShNetworkScene` for 'sh:L', or
    None for 'isotropic' (the caller's :class:`recon.field.NetworkScene`)."""
    check_settings(settings)
    degree = parse_scattering(settings.scattering)
    return None if degree is None else ShNetworkScene(grid, settings, degree)


def n_outputs(settings) -> int:
    """MLP outputs of the network scene ``settings`` asks for: 3 for the occupancy scene,
    2·(L+1)² for 'sh:L', else 2 (the memory estimate's parameter count)."""
    if getattr(settings, "occupancy", False):
        return OccupancyScene.n_outputs(False)
    degree = parse_scattering(getattr(settings, "scattering", ISOTROPIC))
    return NetworkScene.n_outputs(False) if degree is None else 2 * n_coefficients(degree)
