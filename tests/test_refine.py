"""recon refine: the mesh echo model, the pulse chain's adjoint, the losses, the solver, the CLI."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import integrate

from recon import refine
from recon.mesh_echo import MeshEcho, Pings, Window, ground_mesh, subdivision_barycentrics
from recon.pulse_chain import Envelope, PulseChain, envelope_misfit, scaled_misfit
from sonarsim.signals import named_pulse

FS = 100e3
C = 343.0


# ------------------------------------------------------------------ helpers: an independent model

def _segment_blocked(origins, targets, tri) -> np.ndarray:
    """Möller–Trumbore: does the open segment origin→target cross any triangle? [n] bool."""
    d = targets - origins
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pvec = np.cross(d[:, None], e2[None])
    det = np.einsum("tk,ntk->nt", e1, pvec)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins[:, None] - v0[None]
    u = np.einsum("ntk,ntk->nt", s, pvec) * inv
    q = np.cross(s, e1[None])
    v = np.einsum("nk,ntk->nt", d, q) * inv
    t = np.einsum("tk,ntk->nt", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-6)
    return hit.any(axis=1)


def numpy_histograms(vertices, faces, pings: Pings, window: Window, order: int,
                     ground=None) -> np.ndarray:
    """The same physics written plainly: loops over pings, brute-force visibility."""
    meshes = [(np.asarray(vertices, float), np.asarray(faces), 1.0, order)]
    occluders = [np.asarray(vertices, float)[faces]]
    if ground is not None:
        gv, gf = ground_mesh(ground[:2], ground[3])
        meshes.append((gv, gf, ground[2], 1))
        occluders.append(gv[gf])
    occ = np.concatenate(occluders)
    out = np.zeros((len(pings), window.n_bins))
    for verts, fcs, rho, o in meshes:
        tri = verts[fcs]
        b = subdivision_barycentrics(o)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        cr = np.cross(e1, e2)
        area = np.linalg.norm(cr, axis=1)
        pts = (tri[:, None, 0] + b[None, :, :1] * e1[:, None] + b[None, :, 1:] * e2[:, None]).reshape(-1, 3)
        nrm = np.repeat(cr / area[:, None], len(b), axis=0)
        dA = np.repeat(area / 2 / len(b), len(b))
        for i in range(len(pings)):
            tx, rx = pings.tx[i], pings.rx[i]
            rt, rr = np.linalg.norm(tx - pts, axis=1), np.linalg.norm(rx - pts, axis=1)
            wt, wr = (tx - pts) / rt[:, None], (rx - pts) / rr[:, None]
            n = nrm * np.where(np.einsum("ij,ij->i", nrm, wt) < 0, -1.0, 1.0)[:, None]
            ci, co = np.einsum("ij,ij->i", n, wt), np.einsum("ij,ij->i", n, wr)
            ok = co > 0
            for bore, w, width in ((pings.tx_boresight[i], wt, pings.tx_beamwidth),
                                   (pings.rx_boresight[i], wr, pings.rx_beamwidth)):
                if width < 360:
                    ok &= -(w @ bore) >= np.cos(np.radians(width) / 2)
            origin = pts + n * 1e-7
            ok &= ~_segment_blocked(origin, np.broadcast_to(tx, pts.shape), occ)
            ok &= ~_segment_blocked(origin, np.broadcast_to(rx, pts.shape), occ)
            val = rho / np.pi * ci * co * dA / (rt ** 2 * rr ** 2)
            pos = (rt + rr - window.start) / window.width - 0.5
            j = np.floor(pos).astype(int)
            f = pos - j
            for jj, ww in ((j, 1 - f), (j + 1, f)):
                m = ok & (jj >= 0) & (jj < window.n_bins)
                np.add.at(out[i], jj[m], (val * ww)[m])
    return out


def looking_at(tx, rx, target, width=30.0) -> Pings:
    tx, rx = np.atleast_2d(tx).astype(float), np.atleast_2d(rx).astype(float)
    unit = lambda d: d / np.linalg.norm(d, axis=1, keepdims=True)
    return Pings(tx, rx, unit(target - tx), unit(target - rx), width, width)


@pytest.fixture(scope="module")
def small_scene():
    """A lumpy closed mesh on a small ground, three pings from different heights and sides."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    v = mesh.vertices * np.array([1.0, 0.7, 1.2]) + np.array([0.0, 0.0, 0.05])
    tx = np.array([[0.5, 0.0, 0.1], [0.0, -0.45, 0.3], [-0.35, 0.35, 0.05]])
    rx = tx + np.array([0.0, 0.0, -0.03])
    pings = looking_at(tx, rx, np.array([0.0, 0.0, 0.05]))
    window = Window(0.6, 0.5e-3, 1200)
    return v, np.asarray(mesh.faces), pings, window


# ------------------------------------------------------------------ the pulse chain and losses

def test_pulse_chain_adjoint_identity():
    rng = np.random.default_rng(1)
    chain = PulseChain(named_pulse("lfm-20k", FS), 8, 60, 60 * 8 + 5)
    h, r = rng.normal(size=(4, chain.n_bins)), rng.normal(size=(4, 60))
    lhs = np.vdot(chain.forward(h).astype(np.float64), r)
    rhs = np.vdot(h, chain.adjoint(r))
    assert abs(lhs - rhs) < 1e-5 * abs(lhs)


def test_pulse_chain_places_an_impulse_at_its_sample():
    pulse = named_pulse("lfm-20k", FS)[:30]
    chain = PulseChain(pulse, 10, 80, 800)
    h = np.zeros((1, 800))
    h[0, 200] = 1.0                       # bin 20·K: the path of sample 20
    w = chain.forward(h)[0]
    np.testing.assert_allclose(w[20:50], pulse, atol=2e-3 * np.abs(pulse).max())
    assert np.abs(w[:20]).max() < 1e-3 * np.abs(pulse).max()


def test_envelope_vjp_matches_finite_differences():
    rng = np.random.default_rng(2)
    env = Envelope(named_pulse("lfm-20k", FS), 70)
    w, d = rng.normal(size=(2, 70)), rng.normal(size=(2, 70))
    data = env(rng.normal(size=(2, 70)))[0]
    loss, _, grad = envelope_misfit(w, data, env)
    eps = 1e-6
    fd = (envelope_misfit(w + eps * d, data, env)[0] - envelope_misfit(w - eps * d, data, env)[0]) / (2 * eps)
    assert loss > 0.1
    assert abs(np.vdot(grad, d) - fd) < 1e-5 * abs(fd)


def test_scaled_misfit_fits_the_scale_in_closed_form():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(3, 40))
    loss, alpha, _ = scaled_misfit(m, 2.5 * m)
    assert loss < 1e-12 and alpha == pytest.approx(2.5)
    y = rng.normal(size=(3, 40))
    loss, alpha, grad = scaled_misfit(m, y)
    best = min(np.sum((a * m - y) ** 2) for a in np.linspace(alpha - 0.05, alpha + 0.05, 11))
    assert loss * np.sum(y ** 2) == pytest.approx(best)
    d, eps = rng.normal(size=m.shape), 1e-6
    fd = (scaled_misfit(m + eps * d, y)[0] - scaled_misfit(m - eps * d, y)[0]) / (2 * eps)
    assert np.vdot(grad, d) == pytest.approx(fd, rel=1e-5)


# ------------------------------------------------------------------ the mesh echo

def test_subdivision_points_are_the_subtriangle_centroids():
    b = subdivision_barycentrics(3)
    assert b.shape == (9, 2)
    assert np.all(b > 0) and np.all(b.sum(axis=1) < 1)
    np.testing.assert_allclose(b.mean(axis=0), [1 / 3, 1 / 3])    # the triangle's centroid


def test_mesh_echo_equals_a_plain_numpy_model(mi, small_scene):
    v, f, pings, window = small_scene
    ground = (0.3, 0.3, 0.7, 0.03)
    echo = MeshEcho(f, pings, window, order=2, ground=ground)
    got = echo.histograms(mi.Float(v.astype(np.float32).ravel()), mi.Float(1.0),
                          np.arange(len(pings))).numpy().reshape(len(pings), -1)
    want = numpy_histograms(v, f, pings, window, 2, ground)
    assert want.sum() > 0
    # every ping sees the object, part of it shadowed, and the ground
    assert np.all(want.sum(axis=1) > 0)
    np.testing.assert_allclose(got.sum(axis=1), want.sum(axis=1), rtol=2e-4)
    np.testing.assert_allclose(got, want, atol=2e-4 * want.max())


def test_mesh_echo_total_is_the_closed_form_sphere_integral(mi):
    """Co-located TX/RX at distance D from a sphere of radius R, isotropic: the bounce-1
    total is ∫_cap ρ cos²θ/(π r⁴) dA (DESIGN §4)."""
    R, D = 0.05, 0.6
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=R)
    tx = np.array([[D, 0.0, 0.0]])
    pings = Pings(tx, tx.copy(), np.array([[-1.0, 0, 0]]), np.array([[-1.0, 0, 0]]), 360.0, 360.0)
    window = Window(2 * (D - R) - 0.01, 1e-4, 1200)   # up to 2·sqrt(D² − R²) = 1.196 m
    echo = MeshEcho(np.asarray(sphere.faces), pings, window, order=2, ground=None)
    total = echo.histograms(mi.Float(sphere.vertices.astype(np.float32).ravel()), mi.Float(1.0),
                            np.arange(1)).numpy().sum()

    def integrand(phi):   # phi: polar angle on the sphere from the direction to the TX
        x = np.array([R * np.cos(phi), R * np.sin(phi)])
        r_vec = np.array([D, 0.0]) - x
        r = np.linalg.norm(r_vec)
        cos_t = (x @ r_vec) / (R * r)
        return (cos_t ** 2 / (np.pi * r ** 4)) * 2 * np.pi * R ** 2 * np.sin(phi) if cos_t > 0 else 0.0
    exact = integrate.quad(integrand, 0, np.arccos(R / D), limit=200)[0]
    assert total == pytest.approx(exact, rel=5e-3)


def test_mesh_echo_gradients_match_finite_differences(mi, small_scene):
    import drjit as dr
    v, f, pings, window = small_scene
    echo = MeshEcho(f, pings, window, order=2, ground=None)
    idx = np.arange(len(pings))
    V = mi.Float(v.astype(np.float32).ravel())
    vis = echo.visibility(V, idx)
    weights = np.random.default_rng(4).normal(size=(len(pings), window.n_bins))
    smooth = np.cumsum(weights, axis=1)              # a smooth test functional of the bins
    W = mi.Float(smooth.ravel().astype(np.float32))

    def objective(vert: np.ndarray, rho: float = 1.0) -> float:
        h = echo.histograms(mi.Float(vert.astype(np.float32).ravel()), mi.Float(rho), idx, vis)
        return float(np.vdot(h.numpy().astype(np.float64), smooth.ravel()))

    dr.enable_grad(V)
    rho = mi.Float(0.8)
    dr.enable_grad(rho)
    dr.backward(dr.sum(echo.histograms(V, rho, idx, vis) * W))
    grad = dr.grad(V).numpy().reshape(-1, 3)
    vi = int(np.argmax(np.linalg.norm(grad, axis=1)))
    for axis in range(3):
        eps = 1e-5
        vp, vm = v.copy(), v.copy()
        vp[vi, axis] += eps
        vm[vi, axis] -= eps
        fd = (objective(vp, 0.8) - objective(vm, 0.8)) / (2 * eps)
        assert grad[vi, axis] == pytest.approx(fd, rel=2e-2, abs=2e-2 * float(np.abs(grad[vi]).max()))
    # linear in the albedo
    assert dr.grad(rho)[0] == pytest.approx(objective(v, 1.0), rel=1e-4)


# ------------------------------------------------------------------ the solver and the command

@pytest.fixture(scope="module")
def ball_scan(tmp_path_factory):
    """A noiseless scan of a 3 cm sphere (no ground): 24 poses around it at two heights."""
    from sonarsim import simulate as sim
    from sonarsim.geometry import SceneBox, rig_poses
    from sonarsim.scene import load_scene
    from sonarsim.signals import pulse_from_spec
    d = tmp_path_factory.mktemp("ball")
    (d / "ball.toml").write_text('ground = false\nbox = {lo = [-0.1, -0.1, 0.0], hi = [0.1, 0.1, 0.15]}\n'
                                 '[[object]]\nshape = "sphere"\nradius = 0.03\n'
                                 'center = [0.0, 0.0, 0.06]\n')
    spec = load_scene(d / "ball.toml")
    angles = np.tile(np.arange(0, 360, 30.0), 2)
    heights = np.repeat([0.05, 0.25], 12)
    poses = rig_poses(angles, heights, box=SceneBox(np.array([-0.1, -0.1, 0.0]),
                                                    np.array([0.1, 0.1, 0.15])))
    out = d / "ball.h5"
    sim.simulate(spec, poses, out, sim.SimulationSettings(
        pulse=pulse_from_spec("lfm-20k", FS), surface_spacing=2e-3, seed=1))
    return out


def _radius_error(vertices) -> float:
    """Mean radius error (m) of the upper half, the part the poses (all above it) see."""
    upper = vertices[vertices[:, 2] > 0.065]
    return float(np.mean(np.linalg.norm(upper - [0.0, 0.0, 0.06], axis=1)) - 0.03)


def test_refine_shrinks_an_inflated_sphere_onto_the_scanned_one(mi, ball_scan):
    """A real (short) refinement: start 5 mm too large; the surface must move most of the way."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    start = trimesh.creation.icosphere(subdivisions=3, radius=0.035)
    start.vertices += [0.0, 0.0, 0.06]
    settings = refine.RefineSettings(envelope_steps=15, waveform_steps=15, lr=4e-3,
                                     edge_length=8e-3, remesh_every=0, order=2,
                                     pings_per_batch=12, visibility_every=2)
    result = refine.solve(ds, start, settings, ground=None)
    assert _radius_error(start.vertices) == pytest.approx(0.005, abs=1e-4)
    assert abs(_radius_error(result.vertices)) < 0.0015
    first = [h["loss"] for h in result.history if h["stage"] == "waveform"][:2]
    last = [h["loss"] for h in result.history if h["stage"] == "waveform"][-2:]
    assert np.mean(last) < 0.5 * np.mean(first)


def test_refine_command_writes_a_mesh_and_refuses_bad_input(ball_scan, tmp_path, capsys):
    from recon.cli import main
    start = trimesh.creation.icosphere(subdivisions=2, radius=0.033)
    start.vertices += [0.0, 0.0, 0.06]
    init = tmp_path / "start.ply"
    start.export(init)
    out = tmp_path / "refined.ply"
    args = [str(ball_scan), "--init", str(init), "--out", str(out), "--no-ground",
            "--envelope-steps", "1", "--waveform-steps", "1", "--pings", "::2",
            "--edge-length", "0.01", "--history", str(tmp_path / "h.json"), "--no-progress"]
    assert main(["refine", *args]) == 0
    mesh = trimesh.load(out)
    assert len(mesh.faces) > 100 and np.all(np.isfinite(mesh.vertices))
    import json
    record = json.loads((tmp_path / "h.json").read_text())
    assert [h["stage"] for h in record["history"]] == ["envelope", "waveform"]
    assert record["settings"]["pings"] == 12
    capsys.readouterr()
    # an existing output is refused without --force; bad values are one line, exit 2
    for bad, words in ((args, "file exists"),
                       ([*args, "--force", "--order", "0"], "order must be a positive integer"),
                       ([str(ball_scan), "--init", str(tmp_path / "none.ply"), "--out",
                         str(tmp_path / "x.ply")], "not found")):
        assert main(["refine", *bad]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
