"""recon refine: the rendered scene against a plain NumPy model, the pulse chain's adjoint, the losses, the solver, the CLI."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
import trimesh
from scipy import integrate

from recon import refine
from recon.pulse_chain import Envelope, PulseChain, envelope_misfit, scaled_misfit
from sonarsim.signals import named_pulse

FS = 100e3
C = 343.0


# ------------------------------------------------------------------ helpers: an independent model

def subdivision_barycentrics(order: int) -> np.ndarray:
    """(b1, b2) of the centroids of the regular subdivision of a triangle into order² parts."""
    pts = []
    for i in range(order):
        for j in range(order - i):
            pts.append(((i + 1 / 3) / order, (j + 1 / 3) / order))
            if i + j < order - 1:
                pts.append(((i + 2 / 3) / order, (j + 2 / 3) / order))
    return np.asarray(pts)


def ground_mesh(size, spacing):
    """The rectangle [−sx/2, sx/2] × [−sy/2, sy/2] at z = 0 as a triangle grid."""
    nx, ny = round(size[0] / spacing), round(size[1] / spacing)
    x, y = np.linspace(-size[0] / 2, size[0] / 2, nx + 1), np.linspace(-size[1] / 2, size[1] / 2, ny + 1)
    gx, gy = np.meshgrid(x, y, indexing="ij")
    verts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange(gx.size).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


class Pings:
    def __init__(self, tx, rx, tx_boresight, rx_boresight, tx_beamwidth, rx_beamwidth):
        self.tx, self.rx = tx, rx
        self.tx_boresight, self.rx_boresight = tx_boresight, rx_boresight
        self.tx_beamwidth, self.rx_beamwidth = tx_beamwidth, rx_beamwidth

    def __len__(self):
        return len(self.tx)


def _segment_blocked(origins, targets, tri) -> np.ndarray:
    """Möller–Trumbore: does the open segment origin→target cross any triangle? [n] bool."""
    if len(origins) > 2000:
        return np.concatenate([_segment_blocked(origins[i:i + 2000], targets[i:i + 2000], tri)
                               for i in range(0, len(origins), 2000)])
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


def numpy_histograms(vertices, faces, pings: Pings, window, order: int,
                     ground=None) -> np.ndarray:
    """The same physics written plainly: loops over pings, brute-force visibility."""
    meshes = [(np.asarray(vertices, float), np.asarray(faces), 1.0, order)]
    occ = np.asarray(vertices, float)[faces]     # the ground (z = 0, below all) never occludes
    if ground is not None:
        gv, gf = ground_mesh(ground[:2], ground[3])
        meshes.append((gv, gf, ground[2], 1))
    start, width, n_bins = window
    out = np.zeros((len(pings), n_bins))
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
            for bore, w, beam_width in ((pings.tx_boresight[i], wt, pings.tx_beamwidth),
                                        (pings.rx_boresight[i], wr, pings.rx_beamwidth)):
                if beam_width < 360:
                    ok &= -(w @ bore) >= np.cos(np.radians(beam_width) / 2)
            origin = pts + n * 1e-7
            ok &= ~_segment_blocked(origin, np.broadcast_to(tx, pts.shape), occ)
            ok &= ~_segment_blocked(origin, np.broadcast_to(rx, pts.shape), occ)
            val = rho / np.pi * ci * co * dA / (rt ** 2 * rr ** 2)
            pos = (rt + rr - start) / width - 0.5
            j = np.floor(pos).astype(int)
            f = pos - j
            for jj, ww in ((j, 1 - f), (j + 1, f)):
                m = ok & (jj >= 0) & (jj < n_bins)
                np.add.at(out[i], jj[m], (val * ww)[m])
    return out


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


@pytest.mark.parametrize("sigma", [0.0, 3.0])
def test_envelope_vjp_matches_finite_differences(sigma):
    rng = np.random.default_rng(2)
    env = Envelope(named_pulse("lfm-20k", FS), 70)
    w, d = rng.normal(size=(2, 70)), rng.normal(size=(2, 70))
    data = env(rng.normal(size=(2, 70)))[0]
    loss, _, grad = envelope_misfit(w, data, env, sigma)
    eps = 1e-6
    fd = (envelope_misfit(w + eps * d, data, env, sigma)[0]
          - envelope_misfit(w - eps * d, data, env, sigma)[0]) / (2 * eps)
    assert loss > 0.1
    assert abs(np.vdot(grad, d) - fd) < 1e-5 * abs(fd)


def test_blurred_envelope_loss_sees_an_echo_several_resolution_cells_away():
    """Coarse to fine: with the echo 16 samples (2.8 cm of range, ~3 range resolutions of the
    20 kHz pulse) late, a step of 2 samples toward the data's echo does not lower the sharp
    envelope loss (its sidelobes even raise it) but lowers the blurred one (σ 8 samples)."""
    pulse = named_pulse("lfm-20k", FS)
    n = 200
    env = Envelope(pulse, n)

    def echo(delay):
        w = np.zeros((1, n))
        w[0, delay:delay + pulse.size] = pulse
        return w

    data = env(echo(60))[0]
    sharp = [envelope_misfit(echo(76 + k), data, env)[0] for k in (0, -2)]
    smooth = [envelope_misfit(echo(76 + k), data, env, 8.0)[0] for k in (0, -2)]
    assert sharp[1] >= sharp[0]
    assert smooth[1] < smooth[0] - 0.05


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


# ------------------------------------------------------------------ the rendered scene

@pytest.fixture(scope="module")
def small_scene():
    """A lumpy closed mesh on a 0.3 m ground (albedo 0.7), three pings from different sides."""
    from types import SimpleNamespace
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    v = mesh.vertices * np.array([1.0, 0.7, 1.2]) + np.array([0.0, 0.0, 0.05])
    tx = np.array([[0.5, 0.0, 0.1], [0.0, -0.45, 0.3], [-0.35, 0.35, 0.05]])
    rx = tx + np.array([0.0, 0.0, -0.03])
    unit = lambda d: d / np.linalg.norm(d, axis=1, keepdims=True)
    look = np.array([0.0, 0.0, 0.05])
    pings = SimpleNamespace(tx=tx, rx=rx, boresight=unit(look - tx), receiver_boresight=unit(look - rx),
                            meta={"beams": {"tx_beam": "cone", "tx_beamwidth": 30.0,
                                            "rx_beam": "cone", "rx_beamwidth": 30.0}})
    return trimesh.Trimesh(v, mesh.faces, process=False), pings, (0.6, 0.5e-3, 1200)


def test_rendered_scene_equals_a_plain_numpy_model(mi, small_scene, tmp_path):
    """The scene refine renders (mesh, ground, beams, window) against the physics written
    plainly (brute-force visibility): per-ping energy and the waveform after the pulse."""
    mesh, pings, window = small_scene
    ground = (0.3, 0.3, 0.7)
    settings = refine.RefineSettings(surface_spacing=2e-3, path_samples=16)
    scene = refine.RenderedScene(mesh, pings, window, ground, settings, tmp_path)
    v, _ = scene.vertices
    got = scene.render(v, mi.Float(1.0), np.arange(3), seed=1).numpy()[:, 0]
    ref = numpy_histograms(mesh.vertices, mesh.faces,
                           Pings(pings.tx, pings.rx, pings.boresight, pings.receiver_boresight, 30.0, 30.0),
                           window, 3, ground + (0.0025,))
    assert np.all(ref.sum(axis=1) > 0)
    np.testing.assert_allclose(got.sum(axis=1), ref.sum(axis=1), rtol=0.02)
    fs = C / (window[1] * 10)                 # 10 bins of 0.5 mm per sample: 68.6 kHz
    chain = PulseChain(named_pulse("lfm-20k", fs), 10, 120, 1200)
    a, b = chain.forward(got), chain.forward(ref)
    for i in range(3):
        # different quadratures (strata + path quantiles vs 9 points per facet): 0.979 seen;
        # a one-sample shift of the window gives < 0.5
        assert np.vdot(a[i], b[i]) / (np.linalg.norm(a[i]) * np.linalg.norm(b[i])) > 0.97


def test_rendered_scene_albedo_gradient_is_linear(mi, small_scene, tmp_path):
    import drjit as dr
    mesh, pings, window = small_scene
    scene = refine.RenderedScene(mesh, pings, window, None, refine.RefineSettings(), tmp_path)
    v, _ = scene.vertices
    weight = mi.TensorXf(np.sin(np.arange(window[2]) / 9.0)[None, None].repeat(3, 0).astype(np.float32))
    rho = mi.Float(0.6)
    dr.enable_grad(rho)
    value = dr.sum(scene.render(v, rho, np.arange(3), seed=2) * weight, axis=None)
    dr.backward(value)
    total = float(value.numpy())
    assert abs(total) > 0
    # the adjoint pass draws its own random numbers (seed_grad): equal to 1 % (0.3 % seen)
    assert dr.grad(rho)[0] == pytest.approx(total / 0.6, rel=1e-2)


def test_patches_render_as_the_whole_mesh_with_one_albedo_each(mi, small_scene, tmp_path):
    """The support stage's scene: the mesh cut into patches (own shapes, one vertex buffer)
    renders what the whole mesh renders, and each patch's albedo gradient is its own echo:
    value_k / rho_k, summing to the whole (patch 1 at albedo 0 leaves patch 0's echo)."""
    import drjit as dr
    mesh, pings, window = small_scene
    settings = refine.RefineSettings(surface_spacing=2e-3, path_samples=16)
    labels = (mesh.vertices[mesh.faces].mean(axis=1)[:, 0] > 0).astype(np.int64)
    whole = refine.RenderedScene(mesh, pings, window, None, settings, tmp_path)
    cut = refine.RenderedScene(mesh, pings, window, None, settings, tmp_path, labels)
    assert cut.n_patches == 2
    v, _ = whole.vertices
    ref = whole.render(v, mi.Float(1.0), np.arange(3), seed=3).numpy().sum(axis=(1, 2))
    rho = mi.Float([0.5, 0.8])
    dr.enable_grad(rho)
    value = dr.sum(cut.render(v, rho, np.arange(3), seed=3), axis=None)
    dr.backward(value)
    grad = dr.grad(rho).numpy()
    assert np.all(grad > 0)
    # the histograms are energies, linear in each patch's albedo: d value / d rho_k = value_k at rho_k = 1
    one = cut.render(v, mi.Float([1.0, 0.0]), np.arange(3), seed=3).numpy().sum()
    two = cut.render(v, mi.Float([0.0, 1.0]), np.arange(3), seed=3).numpy().sum()
    np.testing.assert_allclose(one + two, ref.sum(), rtol=0.02)
    np.testing.assert_allclose(grad, [one, two], rtol=0.02)
    assert float(value.numpy()) == pytest.approx(0.5 * one + 0.8 * two, rel=0.02)


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


@pytest.mark.parametrize("schedule", [{"uniform_adam": True},
                                      {"uniform_adam": False, "envelope_blur": 0.01, "lr": 2e-3}],
                         ids=["uniform-adam", "adam-blurred-envelopes"])
def test_refine_shrinks_an_inflated_sphere_onto_the_scanned_one(mi, ball_scan, schedule):
    """A real (short) refinement: start 5 mm too large; the surface must move most of the way
    (with UniformAdam, and with per-coordinate Adam on blurred envelopes)."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    start = trimesh.creation.icosphere(subdivisions=3, radius=0.035)
    start.vertices += [0.0, 0.0, 0.06]
    settings = refine.RefineSettings(**{**dict(affine_steps=0, envelope_steps=15, waveform_steps=15,
                                               lr=4e-3, edge_length=8e-3, remesh_every=0,
                                               pings_per_batch=12, surface_spacing=3e-3),
                                        **schedule})
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
            "--affine-steps", "1", "--envelope-steps", "1", "--waveform-steps", "1", "--pings", "::2",
            "--edge-length", "0.01", "--history", str(tmp_path / "h.json"), "--no-progress"]
    assert main(["refine", *args]) == 0
    mesh = trimesh.load(out)
    assert len(mesh.faces) > 100 and np.all(np.isfinite(mesh.vertices))
    import json
    record = json.loads((tmp_path / "h.json").read_text())
    assert [h["stage"] for h in record["history"]] == ["affine", "envelope", "waveform"]
    assert record["settings"]["pings"] == 12
    fitted = record["candidates"][0]["affine"]
    assert len(fitted["scale"]) == 3 and len(fitted["shift"]) == 2 and fitted["scale"] != [1.0] * 3
    capsys.readouterr()
    # an existing output is refused without --force; bad values are one line, exit 2
    for bad, words in ((args, "file exists"),
                       ([*args, "--force", "--bounces", "0"], "bounces must be a positive integer"),
                       ([*args, "--force", "--affine-steps", "-1"],
                        "affine_steps must be a non-negative integer"),
                       ([*args, "--force", "--support-keep", "1.5"], "support_keep must be in [0, 1)"),
                       ([*args, "--force", "--envelope-blur", "-0.01"], "envelope_blur must be a non-negative"),
                       ([*args, "--force", "--wrap", "-1"], "--wrap: must be >= 0"),
                       ([*args, "--force", "--wrap", "1,x"], "--wrap: expected K[,K...]"),
                       ([*args, "--force", "--wrap", "2"], "--wrap and --grow apply to a volume"),
                       ([*args, "--force", "--grow", str(init)], "--wrap and --grow apply to a volume"),
                       ([str(ball_scan), "--init", str(tmp_path / "none.ply"), "--out",
                         str(tmp_path / "x.ply")], "not found")):
        assert main(["refine", *bad]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_support_stage_removes_a_floater_the_data_does_not_see(mi, ball_scan):
    """The support stage (per-patch albedo fit, then unsupported patches removed): a start
    made of the scanned sphere plus a floating blob where the scene is empty loses the blob
    and keeps most of the sphere."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    ball.vertices += [0.0, 0.0, 0.06]
    blob = trimesh.creation.icosphere(subdivisions=2, radius=0.015)
    blob.vertices += [0.09, 0.0, 0.06]
    start = trimesh.util.concatenate([ball, blob])
    settings = refine.RefineSettings(support_steps=12, affine_steps=0, envelope_steps=0,
                                     waveform_steps=0,
                                     patch_size=0.03, edge_length=8e-3, pings_per_batch=12,
                                     surface_spacing=3e-3)
    result = refine.solve(ds, start, settings, ground=None)
    centres = result.vertices[result.faces].mean(axis=1)
    near_blob = np.linalg.norm(centres - [0.09, 0.0, 0.06], axis=1) < 0.03
    assert not near_blob.any()
    support = result.settings["support"]
    assert support["patches_kept"] < support["patches"]
    assert result.mesh.area > 0.7 * ball.area


# ------------------------------------------------------------------ wrapped starts

def _porous_box_shell(n=40, lo=10, hi=30):
    """bool [n, n, n]: the 2-voxel-thick walls of a box [lo, hi)³ with the top face missing
    and tunnels (1-voxel holes every 4 voxels) through the side walls: the porous, open shell
    of an NBP solid of the Table-2 cube (docs/refine.md "Wrapped starts")."""
    occ = np.zeros((n, n, n), bool)
    occ[lo:hi, lo:hi, lo:hi] = True
    occ[lo + 2:hi - 2, lo + 2:hi - 2, lo + 2:] = False          # hollow, open at the top
    for k in range(lo + 3, hi - 3, 4):
        occ[k, :, k] = False                                     # tunnels along y through two walls
    return occ


def test_wrap_seals_a_porous_open_shell_into_the_solid_box():
    shell = _porous_box_shell()
    box = np.zeros_like(shell)
    box[10:30, 10:30, 10:30] = True
    wrapped = refine.wrap_occupancy(shell, np.full(3, 0.003), radius=0.003 * 9)
    # the open top is 16 voxels wide: a ball of radius 9 voxels bridges it with a lid that
    # sags into the opening (a dish), so the interior fills; nothing is added outside the box
    assert not (wrapped & ~box).any()
    assert wrapped[20, 20, 20] and wrapped[20, 20, 24] and wrapped.sum() > 0.9 * box.sum()
    # too small a radius leaves the top open, so nothing inside is filled
    small = refine.wrap_occupancy(shell, np.full(3, 0.003), radius=0.003 * 2)
    assert small[20, 20, 20] == 0 and small.sum() < 0.6 * box.sum()


def test_wrap_keeps_a_concavity_wider_than_the_ball_open():
    """A cup (solid walls, a 16-voxel-wide well open upward): a ball of radius 3 voxels must
    not lid it, and a second, separate object of comparable size is kept."""
    occ = np.zeros((48, 40, 40), bool)
    occ[4:28, 8:32, 4:28] = True
    occ[8:24, 12:28, 8:] = False                                   # the well
    occ[34:46, 12:28, 4:16] = True                                 # a second object
    wrapped = refine.wrap_occupancy(occ, np.full(3, 0.003), radius=0.009)
    assert not wrapped[16, 20, 10:26].any()                        # the well stays empty
    assert wrapped[40, 20, 8]                                      # the second object stays
    assert wrapped.sum() <= occ.sum() * 1.05


def test_range_resolution_is_c_over_twice_the_half_amplitude_band():
    # a band-limited pulse with a flat 20 kHz band around 20 kHz (sinc envelope, 20 ms long)
    t = (np.arange(2000) - 1000) / FS
    pulse = np.sinc(20e3 * t) * np.cos(2 * np.pi * 20e3 * t)
    assert refine.range_resolution(pulse, FS, C) == pytest.approx(C / (2 * 20e3), rel=0.02)
    # the Table-2 chirp (30 -> 10 kHz, 1 ms, Tukey 0.1): its half-amplitude band is narrower
    # than the sweep (the chirp's spectrum falls to half at the sweep's ends)
    res = refine.range_resolution(named_pulse("lfm-20k", FS), FS, C)
    assert C / (2 * 20e3) < res < C / (2 * 16e3)
    with pytest.raises(Exception, match="pulse is zero"):
        refine.range_resolution(np.zeros(8), FS, C)


def test_start_mesh_with_wrap_is_one_closed_genus_zero_surface():
    shell = _porous_box_shell().astype(np.complex64)
    bounds = np.array([[0.0, 0.117], [0.0, 0.117], [0.0, 0.117]])        # 3 mm voxels
    plain = refine.start_mesh(shell, bounds, threshold=0.5, z_min=0.0)
    wrapped = refine.start_mesh(shell, bounds, threshold=0.5, z_min=0.0, wrap_radius=0.027)
    assert plain.euler_number != 2
    assert wrapped.is_watertight and wrapped.euler_number == 2
    assert wrapped.volume == pytest.approx(0.06 ** 3, rel=0.1)


def test_final_misfit_is_the_last_stage_over_its_last_pass():
    hist = [{"stage": "envelope", "loss": 9.0}] * 3 + [{"stage": "waveform", "loss": v}
                                                      for v in (5.0, 4.0, 0.2, 0.4)]
    result = refine.RefineResult(np.zeros((3, 3)), np.zeros((1, 3), int), None, hist, {"batches": 2})
    assert result.final_misfit == pytest.approx(0.3)
    assert result.stage_misfit("envelope") == pytest.approx(9.0)
    assert result.stage_misfit("support") is None
    result.settings["batches"] = 10                     # a stage shorter than a pass: all of it
    assert result.final_misfit == pytest.approx(2.4)
    assert result.stage_misfit("waveform") == pytest.approx(2.4)


def test_final_misfit_ranks_the_scanned_sphere_before_a_displaced_one(mi, ball_scan):
    """The criterion that picks among --wrap starts: with the geometry barely moving, the
    true sphere's final misfit is far below that of the same sphere 2 cm off."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    settings = refine.RefineSettings(affine_steps=0, envelope_steps=0, waveform_steps=4, lr=1e-7,
                                     edge_length=8e-3, remesh_every=0, pings_per_batch=12,
                                     surface_spacing=3e-3)
    misfits = []
    for centre in ([0.0, 0.0, 0.06], [0.02, 0.0, 0.06]):
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
        ball.vertices += centre
        misfits.append(refine.solve(ds, ball, settings, ground=None).final_misfit)
    assert misfits[0] < 0.3 and misfits[1] > 2 * misfits[0]


def test_wrap_candidates_are_ranked_by_the_envelope_misfit():
    """The envelope stage's misfit ranks the candidates, not the waveform (final) misfit; the
    final misfit only where no envelope stage ran (the Table-2 cube: waveform misfits
    0.92 / 0.49 / 0.63, envelope 0.54 / 0.31 / 0.23, refined Chamfer² 5.3 / 2.6 / 1.3e-4)."""
    from recon.commands.refine import choose_candidate
    cands = [{"wrap": w, "envelope_misfit": e, "final_misfit": f}
             for w, e, f in ((0, 0.54, 0.92), (3, 0.31, 0.49), (6, 0.23, 0.63))]
    assert choose_candidate(cands) == 2
    no_envelope = [{**c, "envelope_misfit": None} for c in cands]
    assert choose_candidate(no_envelope) == 1
    assert choose_candidate([{**cands[1], "wrap": 1}, cands[1]]) == 0      # a tie: the first


def test_refine_command_keeps_the_wrap_start_with_the_lowest_misfit(ball_scan, tmp_path, capsys):
    """A porous spherical shell volume (tunnels through it) refined from --wrap 0 and 1: both
    candidates are recorded and the written mesh is the one with the lower envelope misfit."""
    import json
    from recon.cli import main
    from sonarsim.dataset import Volume
    axes = [np.linspace(-0.1, 0.1, 51), np.linspace(-0.1, 0.1, 51), np.linspace(0.0, 0.15, 38)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    r = np.sqrt(x ** 2 + y ** 2 + (z - 0.06) ** 2)
    shell = (np.abs(r - 0.028) < 0.005) & ~(np.abs(x) < 0.003)       # a slot through the shell
    Volume(shell.astype(np.complex64), np.array([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.15]]),
           "test").write(tmp_path / "shell.h5")
    out, hist = tmp_path / "refined.ply", tmp_path / "h.json"
    assert main(["refine", str(ball_scan), "--init", str(tmp_path / "shell.h5"), "--out", str(out),
                 "--wrap", "0,1", "--smooth", "0", "--shrink", "0", "--seal", "0", "--grow-unexplained", "0",
                 "--no-ground",
                 "--envelope-steps", "1",
                 "--waveform-steps", "2",
                 "--pings", "::2", "--edge-length", "0.01", "--history", str(hist),
                 "--keep-candidates", "--no-progress"]) == 0
    record = json.loads(hist.read_text())
    cands = record["candidates"]
    assert [c["wrap"] for c in cands] == [0.0, 1.0]
    assert all(c["final_misfit"] == c["waveform_misfit"] and 0 <= c["envelope_misfit"] <= 1
               for c in cands)
    best = min(cands, key=lambda c: c["envelope_misfit"])
    assert record["wrap"] == best["wrap"] and len(trimesh.load(out).faces) == best["faces"]
    # --keep-candidates: each start and its refinement, the chosen one identical to --out
    for c in cands:
        start = trimesh.load(tmp_path / f"refined.wrap{c['wrap']:g}.start.ply")
        mesh = trimesh.load(tmp_path / f"refined.wrap{c['wrap']:g}.ply")
        assert len(mesh.faces) == c["faces"] and len(start.faces) > 0
    chosen = trimesh.load(tmp_path / f"refined.wrap{record['wrap']:g}.ply")
    np.testing.assert_array_equal(chosen.vertices, trimesh.load(out).vertices)
    starts = [trimesh.load(tmp_path / f"refined.wrap{k}.start.ply") for k in (0, 1)]
    assert starts[1].euler_number == 2 and starts[0].euler_number != 2   # the wrap sealed the slot
    assert "final misfit" in capsys.readouterr().out


def test_default_wrap_is_three_starts_for_a_volume_and_none_for_a_mesh(ball_scan, tmp_path):
    import argparse
    from recon.commands import refine as command
    from sonarsim.dataset import SonarDataset, Volume
    ds = SonarDataset.read(ball_scan)
    b = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.0, 0.1]])
    ball = np.zeros((21, 21, 21), np.complex64)
    ball[6:15, 6:15, 4:13] = 1
    Volume(volume=ball, bounds=b, method="test").write(tmp_path / "start.h5")
    trimesh.creation.icosphere(2, radius=0.03).export(tmp_path / "start.ply")
    args = dict(threshold=0.5, z_min=0.005, wrap=None, grow=None, grow_threshold=0.2, grow_beyond=0.0)
    starts = command.initial_meshes(argparse.Namespace(init=tmp_path / "start.h5", **args), ds)
    assert [k for k, _ in starts] == [0.0, 3.0, 6.0] == command.wrap_factors(command.DEFAULT_WRAP)
    starts = command.initial_meshes(argparse.Namespace(init=tmp_path / "start.ply", **args), ds)
    assert [k for k, _ in starts] == [0.0]


def test_a_solid_keeps_its_small_separate_part_a_field_does_not(ball_scan, tmp_path):
    """A volume of a large block and a small separate cube (under 5 % of the block's faces): as
    an exported solid (params output = 'solid', whose floaters the solid already dropped) the
    start keeps both parts, unwrapped and wrapped; as a field the small one is dropped as a
    blob (fails when the solid's parts are filtered like a field's, by the start's component
    rule or by the wrap's)."""
    from recon.commands import refine as command
    from sonarsim.dataset import SonarDataset, Volume
    ds = SonarDataset.read(ball_scan)
    b = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.0, 0.1]])
    vol = np.zeros((41, 41, 41), np.complex64)
    vol[5:25, 5:25, 3:30] = 1
    vol[34:37, 34:37, 20:23] = 1                                   # 27 voxels, 2 cm apart
    args = dict(threshold=0.5, z_min=0.005, wrap="0,1", grow=None, grow_threshold=0.2,
                grow_beyond=0.0)
    count = {}
    for output in ("solid", "field"):
        Volume(volume=vol, bounds=b, method="nbp", params={"output": output}).write(
            tmp_path / f"{output}.h5")
        starts = command.initial_meshes(argparse.Namespace(init=tmp_path / f"{output}.h5",
                                                           **args), ds)
        count[output] = [len(mesh.split(only_watertight=False)) for _, mesh in starts]
    assert count == {"solid": [2, 2], "field": [1, 1]}      # unwrapped and wrapped alike


@pytest.mark.parametrize("radius", [0.003, 0.0065, 0.009, 0.0125])
def test_ball_closing_equals_scipy_binary_closing_with_the_ball(radius):
    """The distance-transform closing is the binary closing by the same Euclidean ball (the
    structure x² + y² + z² < r² on anisotropic voxels, offsets at exactly r left out), voxel
    for voxel."""
    from scipy import ndimage
    rng = np.random.default_rng(3)
    occ = ndimage.binary_dilation(rng.random((30, 26, 22)) > 0.985, iterations=2)
    occ[0, :, :] |= rng.random((26, 22)) > 0.7                     # touching the box's face
    spacing = np.array([0.003, 0.0025, 0.004])
    half = np.ceil(radius / spacing).astype(int)
    x, y, z = np.meshgrid(*[np.arange(-h, h + 1) * d for h, d in zip(half, spacing)], indexing="ij")
    ball = x * x + y * y + z * z <= (radius * (1 - 1e-9)) ** 2      # 3 × 3 mm = 9 mm: left out
    pad = [(h + 1, h + 1) for h in half]
    want = ndimage.binary_closing(np.pad(occ, pad), structure=ball)
    want = want[tuple(slice(p[0], -p[1]) for p in pad)]
    got = refine.ball_closing(occ, spacing, radius)
    assert want.sum() > occ.sum()                                    # the closing adds voxels
    np.testing.assert_array_equal(got, want)
    assert not refine.wrap_occupancy(np.zeros((5, 5, 5), bool), spacing, radius).any()


def _bow_tie():
    """Two fans of two triangles that meet at vertex 0 only (a pinched vertex)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.3], [-1, 0, 0], [0, -1, 0],
                  [-1, -1, 0.3]], float)
    return v, np.array([[0, 1, 3], [0, 3, 2], [0, 4, 6], [0, 6, 5]])


def test_split_pinched_vertices_gives_each_fan_its_own_vertex():
    v, f = _bow_tie()
    v2, f2 = refine.split_pinched_vertices(v, f)
    assert len(v2) == len(v) + 1
    np.testing.assert_array_equal(v2[f2], v[f])                  # the same triangles
    assert not set(f2[:2].ravel()) & set(f2[2:].ravel())         # the fans share no vertex
    sphere = trimesh.creation.icosphere(2)                       # nothing pinched: unchanged
    v3, f3 = refine.split_pinched_vertices(sphere.vertices, sphere.faces)
    assert len(v3) == len(sphere.vertices)
    np.testing.assert_array_equal(v3[f3], sphere.vertices[sphere.faces])


def test_drop_faces_leaves_no_pinched_vertex():
    """Removing two faces of one vertex's fan that share no edge leaves that vertex a bow-tie
    on a still connected surface; the support stage's :func:`refine.drop_faces` splits it."""
    sphere = trimesh.creation.icosphere(2)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    fan = np.flatnonzero((f == 0).any(axis=1))
    a = fan[0]
    b = next(c for c in fan[1:] if len(set(f[a]) & set(f[c])) == 1)   # only vertex 0 shared
    keep = np.ones(len(f), bool)
    keep[[a, b]] = False
    v2, f2 = refine.drop_faces(v, f, keep)
    assert len(f2) == len(f) - 2 and len(v2) == len(v) + 1        # vertex 0 split in two
    np.testing.assert_allclose(np.sort(v2[f2].reshape(-1, 9), axis=0),
                               np.sort(v[f[keep]].reshape(-1, 9), axis=0))   # the same triangles
    assert len(refine.split_pinched_vertices(v2, f2)[0]) == len(v2)   # nothing pinched is left


def test_remesh_takes_a_surface_with_a_fin():
    """An edge of three faces (a fin on a sphere, as remesh_botsch's own output can have):
    gpytoolbox refuses it; :func:`refine.remesh` drops the faces of that edge and remeshes."""
    from gpytoolbox import non_manifold_edges, remesh_botsch
    sphere = trimesh.creation.icosphere(3)
    v = np.vstack([sphere.vertices, sphere.vertices[sphere.faces[0, :2]].mean(0) * 1.3])
    f = np.vstack([sphere.faces, [[*sphere.faces[0, :2], len(v) - 1]]])
    assert len(non_manifold_edges(f.astype(np.int32))) == 1
    with pytest.raises(ValueError, match="non-manifold"):
        remesh_botsch(v, f.astype(np.int32), i=1, h=0.2, project=True)
    v2, f2 = refine.manifold(v, f)
    assert len(f2) == len(f) - 3 and len(non_manifold_edges(f2.astype(np.int32))) == 0
    vr, fr = refine.remesh(v, f, 0.2)
    assert len(fr) > 100 and len(non_manifold_edges(fr.astype(np.int32))) == 0


def test_remesh_keeps_a_box_sharp_when_asked():
    """A box remeshed to 8 mm edges: by default its edges are cut (bevels, volume lost);
    with ``keep_creases`` every corner is still a vertex, every face flat and the volume
    exact. The bevels matter: on a simulated scan of a 17 cm box the envelope misfit of the
    GT box goes from 0.014 to 0.15 when bevelled (docs/refine.md "Creases")."""
    box = trimesh.creation.box(extents=(0.17, 0.156, 0.12))
    v0, f0 = refine.remesh(box.vertices, box.faces, 8e-3)
    v1, f1 = refine.remesh(box.vertices, box.faces, 8e-3, keep_creases=True)
    cut, kept = trimesh.Trimesh(v0, f0), trimesh.Trimesh(v1, f1)
    assert cut.volume < 0.99 * box.volume                        # what it fixes
    assert kept.is_watertight and abs(kept.volume / box.volume - 1) < 1e-3
    corner_gap = np.linalg.norm(box.vertices[:, None] - v1[None], axis=2).min(axis=1)
    assert corner_gap.max() < 1e-6
    normals = np.round(kept.face_normals, 6)                     # only the six face normals
    assert len(np.unique(normals, axis=0)) == 6
    edges = np.linalg.norm(v1[kept.edges_unique[:, 0]] - v1[kept.edges_unique[:, 1]], axis=1)
    assert 5e-3 < np.median(edges) < 11e-3                       # still remeshed to ~8 mm
    ball = trimesh.creation.icosphere(3, radius=0.05)            # nothing to keep: unchanged
    vb, fb = refine.remesh(ball.vertices, ball.faces, 8e-3, keep_creases=True)
    vc, fc = refine.remesh(ball.vertices, ball.faces, 8e-3)
    np.testing.assert_allclose(vb, vc)


def _box_with_a_sliver(kind: str):
    """A closed 10 cm box with one zero-area face: a 'cap' (a vertex inserted at the middle
    of an edge, the cap closing the crack) or a 'needle' (a vertex doubled, two needles
    closing the crack)."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    v, f = np.array(box.vertices), np.array(box.faces)
    front = int(np.flatnonzero(box.face_normals[:, 0] > 0.5)[0])     # a face toward +x
    f = np.roll(f, -front, axis=0)
    if kind == "cap":
        a, c, x1 = f[0]                                     # face 0 holds the edge a → c
        j = int(np.flatnonzero(((f == c) & (np.roll(f, -1, axis=1) == a)).any(axis=1))[0])
        k = int(np.flatnonzero(f[j] == c)[0])
        x2 = f[j, (k + 2) % 3]                              # face j: c → a → x2
        b = len(v)
        v = np.vstack([v, (v[a] + v[c]) / 2])
        f = np.vstack([np.delete(f, j, axis=0), [[c, b, x2], [b, a, x2], [c, a, b]]])
    else:
        a, p, q = f[0]
        a2 = len(v)
        v = np.vstack([v, v[a]])
        f = np.vstack([[[a2, p, q]], f[1:], [[a, p, a2], [a2, q, a]]])
    return v, f


@pytest.mark.parametrize("kind", ["cap", "needle"])
def test_repair_slivers_leaves_the_box_closed_and_whole(kind):
    """A zero-area face (``remesh_botsch`` leaves some along a straight crease, and the
    renderer's vertex gradient at a needle's corners is NaN) is flipped away (a cap) or collapsed
    (a needle): no sliver left, still closed, the same volume; a sound mesh is unchanged."""
    v, f = _box_with_a_sliver(kind)
    before = trimesh.Trimesh(v, f, process=False)
    assert before.is_watertight and np.sum(before.area_faces < 1e-12) == (1 if kind == "cap" else 2)
    v2, f2 = refine.repair_slivers(v, f)
    after = trimesh.Trimesh(v2, f2, process=False)
    assert after.area_faces.min() > 1e-4 * 0.01
    assert after.is_watertight and after.is_winding_consistent
    assert after.volume == pytest.approx(1e-3, rel=1e-9)
    assert len(f2) == (len(f) if kind == "cap" else 12)
    ball = trimesh.creation.icosphere(2)
    vb, fb = refine.repair_slivers(ball.vertices, ball.faces)
    np.testing.assert_array_equal(fb, ball.faces)
    np.testing.assert_array_equal(vb, ball.vertices)


def test_remesh_repairs_the_slivers_remesh_botsch_returns(monkeypatch):
    """``remesh_botsch`` with feature edges left 59 zero-area faces on a smoothed NBP start
    of the Table-2 cube, and the renderer's gradient was NaN at 14 of their corners, which
    LargeSteps spread over the mesh until the next render failed (docs/refine.md "Slivers");
    whatever it returns, :func:`refine.remesh` hands on no sliver."""
    import gpytoolbox
    v, f = _box_with_a_sliver("needle")
    monkeypatch.setattr(gpytoolbox, "remesh_botsch", lambda *a, **k: (v, f.astype(np.int32)))
    v2, f2 = refine.remesh(v, f, 8e-3, keep_creases=True)
    mesh = trimesh.Trimesh(v2, f2, process=False)
    assert len(f2) == 12 and mesh.is_watertight and mesh.area_faces.min() > 1e-4


def test_an_iso_surface_keeps_no_creases():
    """A volume's marching-cubes surface (a voxelised box's steps) is no model with sharp
    edges: its crease density is far above :data:`refine.CREASE_DENSITY_MAX` and
    ``keep_creases`` remeshes it as without; a box's is below."""
    from skimage.measure import marching_cubes
    occ = np.zeros((40, 40, 40))
    x, y, z = np.meshgrid(*(np.arange(40),) * 3, indexing="ij")
    occ[(x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 < 14 ** 2] = 1.0     # a voxelised ball
    v, f, _, _ = marching_cubes(occ, 0.5, spacing=(3.2e-3,) * 3)
    steps = refine.crease_density(v, f, 8e-3)
    box = trimesh.creation.box(extents=(0.17, 0.156, 0.12))
    edges = refine.crease_density(box.vertices, box.faces, 8e-3)
    assert edges < refine.CREASE_DENSITY_MAX < steps
    assert edges == pytest.approx(4 * (0.17 + 0.156 + 0.12) * 8e-3 / box.area, rel=1e-9)
    np.testing.assert_allclose(refine.remesh(v, f, 8e-3, keep_creases=True)[0],
                               refine.remesh(v, f, 8e-3)[0])


def test_a_box_remeshed_with_its_creases_renders_the_scanned_echoes(mi, tmp_path):
    """The reason for ``keep_creases``, through the renderer: a noiseless scan of a 10 cm box
    on the ground, and the envelope misfit of the box's remeshed surface against it. Kept
    creases: the misfit of the box itself (its surface split exactly); bevelled: several
    times larger (docs/refine.md "Creases": 0.014 against 0.148 on a full scan)."""
    import tempfile
    from sonarsim import simulate as sim
    from sonarsim.dataset import SonarDataset
    from sonarsim.geometry import SceneBox, rig_poses
    from sonarsim.scene import load_scene
    from sonarsim.signals import pulse_from_spec
    (tmp_path / "box.toml").write_text('ground = true\nbox = {lo = [-0.1, -0.1, 0.0], hi = [0.1, 0.1, 0.15]}\n'
                                       '[[object]]\nshape = "cube"\nsize = [0.1, 0.08, 0.06]\n'
                                       'center = [0.0, 0.0, 0.03]\n')
    box_lo, box_hi = np.array([-0.1, -0.1, 0.0]), np.array([0.1, 0.1, 0.15])
    poses = rig_poses(np.tile(np.arange(0, 360, 30.0), 2), np.repeat([0.1, 0.3], 12),
                      box=SceneBox(box_lo, box_hi))
    sim.simulate(load_scene(tmp_path / "box.toml"), poses, tmp_path / "box.h5",
                 sim.SimulationSettings(pulse=pulse_from_spec("lfm-20k", FS),
                                        surface_spacing=2e-3, seed=1))
    ds = SonarDataset.read(tmp_path / "box.h5")
    settings = refine.RefineSettings(surface_spacing=2e-3, path_samples=8)
    _, window, chain = refine.dataset_chain(ds, settings)
    objective = refine._Objective(ds, chain)
    box = trimesh.creation.box(extents=(0.1, 0.08, 0.06))
    box.apply_translation([0.0, 0.0, 0.03])
    exact = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 8e-3))
    meshes = {"exact": (exact.vertices, exact.faces),
              "kept": refine.remesh(box.vertices, box.faces, 8e-3, keep_creases=True),
              "bevelled": refine.remesh(box.vertices, box.faces, 8e-3)}
    index = np.arange(ds.n_pings)
    misfit = {}
    with tempfile.TemporaryDirectory() as workdir:
        for name, (v, f) in meshes.items():
            model = refine.RenderedScene(trimesh.Trimesh(v, f, process=False), ds, window,
                                         refine.dataset_ground(ds), settings, workdir)
            hist = model.render(model.vertices[0], mi.Float([1.0]), index, seed=3)
            misfit[name] = objective("envelope", hist.numpy().astype(np.float64).sum(axis=1),
                                     0, index)[0]
    assert misfit["exact"] < 0.01, misfit                # the model fits its own scan
    assert misfit["kept"] < 1.5 * misfit["exact"] + 0.005, misfit
    assert misfit["bevelled"] > 10 * misfit["kept"], misfit


def test_refine_keeps_creases_only_of_a_given_mesh():
    from pathlib import Path
    from recon.commands.refine import keeps_creases
    mesh, volume = (argparse.Namespace(init=Path(p)) for p in ("m.PLY", "nbp.h5"))
    assert keeps_creases(mesh, {"wrap": 0.0, "smooth": 0.0})
    assert not keeps_creases(mesh, {"wrap": 0.0, "smooth": 1.0})
    assert not keeps_creases(mesh, {"wrap": 0.0, "smooth": 0.0, "grown": 0.1})
    assert not keeps_creases(volume, {"wrap": 0.0, "smooth": 0.0})


def _box_volume(first_kept: float = 1.0):
    """A 10 × 10 cm box standing on the ground up to 6 cm, on a grid of 3.2 mm voxels
    (z planes 0, 3.2, 6.4 ... mm): 1 in its voxels, ``first_kept`` in its plane at 6.4 mm."""
    bounds = np.array([[-0.08, 0.08], [-0.08, 0.08], [0.0, 0.0992]])      # 51 × 51 × 32 voxels
    vol = np.zeros((51, 51, 32), np.complex64)
    vol[10:41, 10:41, :19] = 1.0                                          # z ≤ 5.76 cm
    vol[10:41, 10:41, 2] = first_kept
    return vol, bounds


@pytest.mark.parametrize("value, cap", [(1.0, 0.00384), (0.22, 0.0061)],
                         ids=["binary", "just-above-threshold"])
def test_seating_continues_a_cut_start_straight_down_to_the_ground(value, cap):
    """The start is cut at z_min = 5 mm: its closing face lies between the last cleared plane
    (3.2 mm) and the first kept one (6.4 mm), nearer the kept one the closer that plane's
    voxels are to the threshold (0.22 against 0.2: 6.1 mm, above z_min). Seated below z_min +
    one voxel, the mesh reaches the ground with its top and sides where they were and stays
    closed; its volume is the box's from the ground up."""
    vol, bounds = _box_volume(value)
    start = refine.start_mesh(vol, bounds, threshold=0.2, z_min=0.005)
    dz = 0.0992 / 31
    assert start.vertices[:, 2].min() == pytest.approx(cap, abs=1e-4) and start.is_watertight
    seated, moved = refine.seat_on_ground(start, 0.005 + dz)
    assert moved > 0 and seated.is_watertight
    assert seated.vertices[:, 2].min() == 0.0
    np.testing.assert_allclose(seated.bounds[1], start.bounds[1])
    np.testing.assert_allclose(seated.bounds[0][:2], start.bounds[0][:2])
    top = start.bounds[1][2]
    assert seated.volume == pytest.approx(np.prod(np.ptp(start.bounds[:, :2], axis=0)) * top,
                                          rel=0.02)
    # every vertex below the cut went straight down: x, y unchanged
    np.testing.assert_array_equal(seated.vertices[:, :2], start.vertices[:, :2])


def test_seating_leaves_an_object_above_the_cut_and_lifts_what_sank():
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.04])
    box.vertices += [0.0, 0.0, 0.03]                                      # floats 1 cm up
    same, moved = refine.seat_on_ground(box, 0.008)
    assert moved == 0
    np.testing.assert_array_equal(same.vertices, box.vertices)
    sunk = box.copy()
    sunk.vertices[sunk.vertices[:, 2] < 0.02, 2] = -0.004                # base 4 mm under the ground
    lifted, moved = refine.seat_on_ground(sunk, 0.008)
    assert moved == 4 and lifted.vertices[:, 2].min() == 0.0


def test_seating_follows_a_closing_face_the_fit_lifted():
    """The fit can lift the closing face with the walls it joins (the Table-2 bunny's by 3.5
    mm, above z_min + one voxel): the seating height rises by the lift, so the face still
    reaches the ground; a start that was not cut there is not seated."""
    vol, bounds = _box_volume()
    start = refine.start_mesh(vol, bounds, threshold=0.2, z_min=0.005)
    base = 0.005 + 0.0992 / 31
    lifted = start.copy()
    lifted.vertices[lifted.vertices[:, 2] < 0.03, 2] += 0.0045             # base 3.84 -> 8.34 mm
    cut = refine.seat_cut(start, lifted, base)
    assert cut == pytest.approx(base + 0.0045)
    seated, _ = refine.seat_on_ground(lifted, cut)
    assert seated.vertices[:, 2].min() == 0.0 and seated.is_watertight
    assert not refine.seat_on_ground(lifted, base)[0].vertices[:, 2].min() < 0.008   # a fixed cut misses it
    sunk = start.copy()
    sunk.vertices[sunk.vertices[:, 2] < 0.03, 2] -= 0.002
    assert refine.seat_cut(start, sunk, base) == base
    floating = start.copy()
    floating.vertices[:, 2] += 0.02
    assert refine.seat_cut(floating, floating, base) is None


def test_refine_command_writes_the_mesh_seated(ball_scan, tmp_path):
    """A ball's volume cut at 4.5 cm (--z-min), refined a few steps with --seat: the written
    mesh reaches the ground, its top stays, and the history says where and how much."""
    import json
    from recon.cli import main
    from sonarsim.dataset import Volume
    axes = [np.linspace(-0.1, 0.1, 51), np.linspace(-0.1, 0.1, 51), np.linspace(0.0, 0.15, 38)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    ball = np.sqrt(x ** 2 + y ** 2 + (z - 0.06) ** 2) < 0.03
    Volume(ball.astype(np.complex64), np.array([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.15]]),
           "test").write(tmp_path / "ball.h5")
    out, hist = tmp_path / "seated.ply", tmp_path / "h.json"
    assert main(["refine", str(ball_scan), "--init", str(tmp_path / "ball.h5"), "--out", str(out),
                 "--wrap", "0", "--smooth", "0", "--shrink", "0", "--seal", "0",
                 "--grow-unexplained", "0", "--no-ground", "--seat",
                 "--z-min", "0.045", "--envelope-steps", "1", "--waveform-steps", "1",
                 "--pings", "::2", "--edge-length", "0.01", "--history", str(hist),
                 "--no-progress"]) == 0
    mesh, seat = trimesh.load(out), json.loads(hist.read_text())["seat"]
    assert seat["vertices_moved"] > 0 and seat["below_m"] >= 0.045 + 0.15 / 37
    assert mesh.vertices[:, 2].min() == 0.0 and mesh.vertices[:, 2].max() > 0.085


def test_seating_is_on_for_a_volume_with_a_ground_and_off_otherwise(tmp_path):
    from pathlib import Path
    from types import SimpleNamespace
    from recon.commands.refine import seat_height
    from sonarsim.dataset import Volume
    vol, bounds = _box_volume()
    Volume(vol, bounds, "test").write(tmp_path / "v.h5")
    grounded = SimpleNamespace(meta={})                  # no scene file: the default ground
    def args(init, seat=None, no_ground=False):
        return argparse.Namespace(init=Path(init), seat=seat, no_ground=no_ground, z_min=0.005)
    volume = tmp_path / "v.h5"
    assert seat_height(args(volume), grounded) == pytest.approx(0.005 + 0.0992 / 31)
    assert seat_height(args(volume, no_ground=True), grounded) is None
    assert seat_height(args(volume, seat=False), grounded) is None
    assert seat_height(args(volume, seat=True, no_ground=True), grounded) is not None
    assert seat_height(args("m.ply"), grounded) is None
    with pytest.raises(Exception, match="--seat applies to a volume"):
        seat_height(args("m.ply", seat=True), grounded)


def test_grow_adds_the_parts_of_the_other_volume_that_touch_the_start():
    occ = np.zeros((30, 30, 30), bool)
    occ[10:20, 10:20, 5:15] = True                      # the start: a box
    other = np.zeros((30, 30, 30))
    other[12:18, 12:18, 15:25] = 0.5                    # an "ear" on its top: touches it
    other[2:5, 2:5, 10:12] = 0.9                        # a separate blob: does not
    other[20:24, 12:14, 1:4] = 0.6                      # touches the box's side, below z_min
    other[12:14, 20:22, 8:10] = 0.1                     # touches, but below the threshold
    allowed = np.arange(30) >= 5
    grown = refine.grow_occupancy(occ, other, 0.2, allowed)
    np.testing.assert_array_equal(grown[occ], True)
    added = grown & ~occ
    assert added[12:18, 12:18, 15:25].all()
    assert added.sum() == 6 * 6 * 10
    # through the start mesh: the ear raises the surface's top from 15 to 25 voxels
    bounds = np.array([[0.0, 0.087], [0.0, 0.087], [0.0, 0.087]])     # 3 mm voxels
    top = refine.start_mesh(occ.astype(np.float32), bounds, 0.5, 0.0).vertices[:, 2].max()
    grown_top = refine.start_mesh(occ.astype(np.float32), bounds, 0.5, 0.0, grow=other,
                                  grow_threshold=0.2).vertices[:, 2].max()
    assert top == pytest.approx(14.5 * 0.003, abs=1e-3) and grown_top == pytest.approx(24.5 * 0.003, abs=1e-3)


def test_refine_command_refuses_a_grow_volume_on_another_grid(ball_scan, tmp_path, capsys):
    from recon.cli import main
    from sonarsim.dataset import Volume
    b = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.0, 0.1]])
    ball = np.zeros((11, 11, 11), np.complex64)
    ball[3:8, 3:8, 3:8] = 1
    Volume(volume=ball, bounds=b, method="test").write(tmp_path / "start.h5")
    Volume(volume=ball[:, :, :10], bounds=b, method="test").write(tmp_path / "other.h5")
    capsys.readouterr()
    base = [str(ball_scan), "--init", str(tmp_path / "start.h5"), "--out", str(tmp_path / "x.ply"),
            "--threshold", "0.5", "--no-progress"]
    for extra, words in ((["--grow", str(tmp_path / "other.h5")], "differs from --init's"),
                         (["--grow", str(tmp_path / "none.h5")], "not found"),
                         (["--grow", str(tmp_path / "start.h5"), "--grow-threshold", "1.5"],
                          "--grow-threshold: must be in [0, 1)")):
        assert main(["refine", *base, *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.ply").exists()


def test_grow_beyond_adds_the_far_structure_and_its_bridge_not_the_hugging_layer():
    occ = np.zeros((40, 40, 40), bool)
    occ[10:20, 10:20, 5:15] = True                      # the start: a box
    other = np.zeros((40, 40, 40))
    other[8:22, 8:22, 5:17] = 0.5                       # a 2-voxel layer hugging it (BP's blur)
    other[13:16, 13:16, 15:30] = 0.5                    # an "ear" 15 voxels tall on its top
    spacing = np.full(3, 0.003)
    every = refine.grow_occupancy(occ, other, 0.2, None)
    far = refine.grow_occupancy(occ, other, 0.2, None, spacing, beyond=4 * 0.003)
    assert (every & ~occ).sum() == (other >= 0.2).sum() - occ.sum()      # all of it
    added = far & ~occ
    assert added[13:16, 13:16, 15:30].all()             # the whole ear, its base included
    assert not added[8:10, 8:22, 5:15].any() and not added[20:22, 8:22, 5:15].any()   # no layer
    assert added.sum() < 1.3 * 3 * 3 * 15


# ------------------------------------------------------------------ smoothed starts

def _grid_mesh(n: int, h: float):
    """A flat square grid of n × n vertices (spacing h) split along one diagonal: every interior
    vertex has the six neighbours (i±1, j), (i, j±1), (i+1, j+1), (i−1, j−1)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v = np.stack([i.ravel() * h, j.ravel() * h, np.zeros(n * n)], axis=1)
    idx = (i * n + j)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([idx, idx + n, idx + n + 1], 1),
                            np.stack([idx, idx + n + 1, idx + 1], 1)])
    return v, faces, i, j


def test_smoothing_damps_the_checkerboard_by_its_closed_form_and_keeps_the_centroid():
    """On the six-neighbour grid the checkerboard z = ε(−1)^(i+j) is an eigenvector of the graph
    Laplacian with eigenvalue 8 (6 z minus 4 opposite and 2 equal neighbours), so (I + λL)⁻¹
    scales it by 1 / (1 + 8λ) away from the border; a plane stays where it is and the vertex
    centroid is kept exactly."""
    v, f, i, j = _grid_mesh(71, 0.008)
    eps = 1e-3
    v[:, 2] = 0.05 + eps * (-1.0) ** (i + j).ravel()
    for lam in (0.25, 1.0, 3.0):
        out = refine.smooth_vertices(v, f, lam)
        inner = ((i > 20) & (i < 50) & (j > 20) & (j < 50)).ravel()
        np.testing.assert_allclose((out[inner, 2] - 0.05) / (v[inner, 2] - 0.05), 1 / (1 + 8 * lam),
                                   rtol=1e-3)   # the border's effect has decayed
        np.testing.assert_allclose(out.mean(axis=0), v.mean(axis=0), atol=1e-12)
    flat = v.copy()
    flat[:, 2] = 0.05
    np.testing.assert_allclose(refine.smooth_vertices(flat, f, 2.0)[:, 2], 0.05, atol=1e-12)
    np.testing.assert_array_equal(refine.smooth_vertices(v, f, 0.0), v)
    from sonarsim.errors import InputError
    with pytest.raises(InputError, match="lambda must be >= 0"):
        refine.smooth_vertices(v, f, -1.0)


def test_smoothing_takes_bumps_a_few_edges_wide_off_a_sphere():
    """Bumps of ±1 mm about two edges wide on an icosphere of radius 3 cm (edge 2.4 mm):
    smoothing is linear, so what is left of them is the smoothed bumpy sphere minus the
    smoothed plain one; at λ = 1 less than half of their spread remains, while the plain
    sphere only shrinks (its radius by λ·Lr, about 0.6 mm here) and stays round. The
    remeshed-and-smoothed start is a closed surface with edges near the target."""
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.03)
    u = ball.vertices / np.linalg.norm(ball.vertices, axis=1, keepdims=True)
    rng = np.random.default_rng(1)
    centres = rng.normal(size=(80, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    bumps = (rng.choice([-1.0, 1.0], 80) * np.exp(-((u @ centres.T - 1) / 0.003) ** 2)).sum(axis=1)
    bumps *= 0.001 / np.abs(bumps).max()
    plain = refine.smooth_vertices(ball.vertices, ball.faces, 1.0)
    rough = refine.smooth_vertices(ball.vertices + u * bumps[:, None], ball.faces, 1.0)
    left = np.einsum("ij,ij->i", rough - plain, u)
    assert left.std() < bumps.std() / 2
    r = np.linalg.norm(plain, axis=1)
    assert 0.0290 < r.mean() < 0.0298 and r.std() < 0.1 * (0.03 - r.mean())
    start = refine.smoothed_start(trimesh.Trimesh(ball.vertices + u * bumps[:, None], ball.faces),
                                  1.0, 0.006)
    assert start.is_watertight
    assert 0.004 < np.median(start.edges_unique_length) < 0.008


def test_refine_command_adds_the_smoothed_start_as_a_candidate(ball_scan, tmp_path, capsys):
    """--smooth L adds one candidate per level (the unwrapped start smoothed), ranked with the
    others by the envelope misfit; --keep-candidates writes it as OUT.smoothL(.start).ply; the
    levels 0 and repeats add nothing; a bad level is refused before any work."""
    import json
    from recon.cli import main
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.033)
    ball.vertices += [0.0, 0.0, 0.06]
    ball.export(tmp_path / "start.ply")
    out, hist = tmp_path / "refined.ply", tmp_path / "h.json"
    args = ["refine", str(ball_scan), "--init", str(tmp_path / "start.ply"), "--out", str(out),
            "--no-ground", "--envelope-steps", "1", "--waveform-steps", "1", "--pings", "::2",
            "--edge-length", "0.01", "--history", str(hist), "--no-progress"]
    assert main([*args, "--smooth", "0,2,2", "--keep-candidates"]) == 0
    record = json.loads(hist.read_text())
    cands = record["candidates"]
    assert [(c["wrap"], c["smooth"]) for c in cands] == [(0.0, 0.0), (0.0, 2.0)]
    best = min(cands, key=lambda c: c["envelope_misfit"])
    assert record["smooth"] == best["smooth"] and len(trimesh.load(out).faces) == best["faces"]
    plain = trimesh.load(tmp_path / "refined.wrap0.start.ply")
    smoothed = trimesh.load(tmp_path / "refined.smooth2.start.ply")
    assert (np.linalg.norm(smoothed.vertices - [0, 0, 0.06], axis=1).mean()
            < np.linalg.norm(plain.vertices - [0, 0, 0.06], axis=1).mean())   # λL shrinks a ball
    assert (tmp_path / "refined.smooth2.ply").is_file()
    capsys.readouterr()
    for bad, words in (("x", "--smooth: expected L[,L...]"), ("-1", "--smooth: must be >= 0")):
        assert main([*args, "--force", "--smooth", bad]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("inflate, smoothed_wins", [(0.004, True), (0.0, False)],
                         ids=["rough-and-inflated", "rough-only"])
def test_the_envelope_misfit_keeps_the_smoothed_start_when_it_is_closer(mi, ball_scan, inflate,
                                                                         smoothed_wins):
    """A real refinement from a rough sphere (narrow bumps up to 3 mm) and from its smoothed
    start (λ = 1, which also shrinks it by ~3 mm): when the rough start is 4 mm too large, the
    smoothed one ends closer to the scanned sphere and has the lower envelope misfit; when the
    rough start has the right size, the smoothed one (now too small) ends farther and has the
    higher misfit — the ranking follows the truth both ways."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    ball = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    u = np.asarray(ball.vertices)
    rng = np.random.default_rng(2)
    centres = rng.normal(size=(150, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    bumps = (rng.choice([-1.0, 1.0], 150) * np.exp(-((u @ centres.T - 1) / 0.006) ** 2)).sum(1)
    bumps *= 0.003 / np.abs(bumps).max()
    rough = trimesh.Trimesh(u * (0.03 + inflate + bumps)[:, None] + [0.0, 0.0, 0.06], ball.faces)
    settings = refine.RefineSettings(affine_steps=0, envelope_steps=20, waveform_steps=0, lr=1e-3,
                                     edge_length=6e-3, remesh_every=0, pings_per_batch=12,
                                     surface_spacing=3e-3)
    plain = refine.solve(ds, rough, settings, ground=None)
    smooth = refine.solve(ds, refine.smoothed_start(rough, 1.0, 6e-3), settings, ground=None)
    closer = abs(_radius_error(smooth.vertices)) < abs(_radius_error(plain.vertices))
    lower = smooth.stage_misfit("envelope") < plain.stage_misfit("envelope")
    assert closer == smoothed_wins and lower == smoothed_wins


# ------------------------------------------------------------------------ shrunk starts

def test_shrink_erodes_a_body_from_its_sides_and_top_keeps_its_base_and_a_thin_rod():
    """A 10-voxel cube standing on the grid's lowest plane with a one-voxel rod on top, shrunk
    by 1.5 voxels: the cube loses its outer layer on the four sides and the top, edges and
    corners included (its base stays on the ground: the ground counts as occupied; fails
    without), the rod, thinner than twice the radius and reaching far from the body, is kept
    whole and joined to it (fails without the thin parts added back), with the cube's top
    voxels within the radius of it (its foot)."""
    occ = np.zeros((20, 20, 24), bool)
    occ[5:15, 5:15, 0:10] = True
    occ[10, 10, 10:18] = True                                       # a rod on top
    out = refine.shrink_occupancy(occ, (2e-3, 2e-3, 2e-3), 3e-3)
    body = np.zeros_like(occ)
    body[6:14, 6:14, 0:9] = True
    foot = np.zeros_like(occ)
    foot[9:12, 10, 9] = foot[10, 9:12, 9] = True                    # within 3 mm of the rod
    foot[10, 10, 10:18] = True
    np.testing.assert_array_equal(out, body | foot)
    np.testing.assert_array_equal(refine.shrink_occupancy(occ, (2e-3,) * 3, 0.0), occ)


def test_refine_command_adds_the_shrunk_start_as_a_candidate(ball_scan, tmp_path, capsys):
    """A volume --init gets, by default, the unwrapped start shrunk by --shrink 0.5 range
    resolutions and smoothed as a candidate ranked with the others (named
    shrink0.5-smooth1); its start lies inside the plain one; --shrink 0 adds none, a mesh
    --init refuses --shrink in one line."""
    import json
    from recon.cli import main
    from recon.commands import refine as command
    from sonarsim.dataset import Volume
    b = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.0, 0.1]])
    ball = np.zeros((26, 26, 26), np.complex64)
    x, y, z = np.meshgrid(*(np.linspace(*b[a], 26) for a in range(3)), indexing="ij")
    ball[np.sqrt(x ** 2 + y ** 2 + (z - 0.06) ** 2) < 0.036] = 1.0     # 6 mm too large
    Volume(volume=ball, bounds=b, method="test").write(tmp_path / "start.h5")
    out, hist = tmp_path / "refined.ply", tmp_path / "h.json"
    args = ["refine", str(ball_scan), "--init", str(tmp_path / "start.h5"), "--out", str(out),
            "--no-ground", "--envelope-steps", "1", "--waveform-steps", "1", "--pings", "::2",
            "--edge-length", "0.01", "--history", str(hist), "--no-progress", "--wrap", "0",
            "--grow-unexplained", "0", "--seal", "0"]
    assert main([*args, "--keep-candidates"]) == 0
    cands = json.loads(hist.read_text())["candidates"]
    assert [(c["wrap"], c["smooth"], c["shrink"]) for c in cands] == [
        (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 1.0, float(command.DEFAULT_SHRINK))]
    centre = [0.0, 0.0, 0.06]
    radius = {name: np.linalg.norm(trimesh.load(tmp_path / f"refined.{name}.start.ply").vertices
                                   - centre, axis=1).mean()
              for name in ("smooth1", "shrink0.5-smooth1")}
    assert radius["shrink0.5-smooth1"] < radius["smooth1"] - 0.003
    assert main([*args, "--force", "--shrink", "0", "--smooth", "0"]) == 0
    assert [c["shrink"] for c in json.loads(hist.read_text())["candidates"]] == [0.0]
    trimesh.creation.icosphere(2, radius=0.03).export(tmp_path / "m.ply")
    capsys.readouterr()
    mesh_args = ["refine", str(ball_scan), "--init", str(tmp_path / "m.ply"), "--out", str(out),
                 "--no-ground", "--no-progress"]
    assert main([*mesh_args, "--force", "--shrink", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "--shrink applies to a volume" in err and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------------ the affine stage

def test_affine_map_in_drjit_equals_the_numpy_formula(mi):
    import drjit as dr
    rng = np.random.default_rng(4)
    v = rng.normal(size=(50, 3)) * 0.05 + [0.0, 0.0, 0.1]
    pivot, half = refine.affine_frame(v, 0.008)
    assert pivot[2] == pytest.approx(v[:, 2].min()) and half == pytest.approx(0.5 * np.ptp(v, 0).max())
    q, t = np.array([0.004, -0.006, 0.01]), np.array([0.002, -0.001])
    want = refine.affine_vertices(v, pivot, half, q, t)
    got = refine._affine_ad(mi, dr, mi.Float(v.ravel().astype(np.float32)), pivot, half,
                            mi.Float(q.astype(np.float32)), mi.Float(t.astype(np.float32)))
    np.testing.assert_allclose(np.asarray(got.numpy()).reshape(-1, 3), want, atol=2e-7)
    # the pivot's base stays put under a scale along z alone
    base = refine.affine_vertices(pivot[None], pivot, half, [0.0, 0.0, 0.05], [0.0, 0.0])
    np.testing.assert_allclose(base[0], pivot)
    assert np.all(want[:, 2] - pivot[2] == pytest.approx((v[:, 2] - pivot[2]) * np.exp(0.01 / half)))


def test_affine_stage_undoes_a_stretched_and_shifted_sphere(mi, ball_scan):
    """A real affine-only fit: the scanned sphere stretched by 12 % / −10 % / 10 % along x, y,
    z about its base and moved 3 mm / −2 mm along x / y is brought back: the fitted scales undo the stretch to a
    few per cent and the upper half's radius error falls from several millimetres to one."""
    from sonarsim.dataset import SonarDataset
    ds = SonarDataset.read(ball_scan)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    ball.vertices += [0.0, 0.0, 0.06]
    pivot, half = refine.affine_frame(ball.vertices, 6e-3)
    stretch = np.array([1.12, 0.90, 1.10])
    start = trimesh.Trimesh(refine.affine_vertices(ball.vertices, pivot, half, half * np.log(stretch),
                                                   [0.003, -0.002]), ball.faces)
    settings = refine.RefineSettings(affine_steps=30, envelope_steps=0, waveform_steps=0, lr=3e-3,
                                     edge_length=6e-3, pings_per_batch=12, surface_spacing=3e-3)
    result = refine.solve(ds, start, settings, ground=None)

    def error(v):                      # RMS distance to the sphere over its upper half (seen)
        upper = v[v[:, 2] > 0.065]
        return float(np.sqrt(np.mean((np.linalg.norm(upper - [0.0, 0.0, 0.06], axis=1) - 0.03) ** 2)))
    assert error(start.vertices) > 0.0025
    assert error(result.vertices) < 0.001
    assert [h["stage"] for h in result.history] == ["affine"] * 30
    np.testing.assert_allclose(np.asarray(result.affine["scale"]) * stretch, 1.0, atol=0.04)



def test_an_infinite_gradient_entry_is_cleared_not_spread(mi, ball_scan, monkeypatch):
    """A renderer gradient that is infinite at one vertex coordinate (as at a degenerate
    triangle's corners) is set to 0 there: the fit stays finite, the other vertices still move
    onto the sphere, and the result counts the cleared entries (one per step). Without the
    clearing LargeSteps' solve turns it into NaN vertices and the next render fails."""
    import drjit as dr
    from sonarsim.dataset import SonarDataset
    original = refine.RenderedScene.render

    def poisoned(self, vertices, albedo, index, seed):
        hist = original(self, vertices, albedo, index, seed)
        weight = np.zeros(dr.width(vertices), np.float32)
        weight[0] = np.inf
        # value 0, derivative infinite with respect to the first vertex's x alone
        nan_grad = dr.sum(dr.replace_grad(vertices * 0, vertices * mi.Float(weight)))
        return mi.TensorXf(hist.array + nan_grad, hist.shape)

    monkeypatch.setattr(refine.RenderedScene, "render", poisoned)
    ds = SonarDataset.read(ball_scan)
    start = trimesh.creation.icosphere(subdivisions=3, radius=0.035)
    start.vertices += [0.0, 0.0, 0.06]
    settings = refine.RefineSettings(affine_steps=0, envelope_steps=8, waveform_steps=4, lr=4e-3,
                                     edge_length=8e-3, remesh_every=0, pings_per_batch=12,
                                     surface_spacing=3e-3)
    result = refine.solve(ds, start, settings, ground=None)
    assert np.isfinite(result.vertices).all()
    assert result.settings["nonfinite_gradients"] == {"steps": 12, "entries": 12}
    assert _radius_error(result.vertices) < 0.5 * _radius_error(start.vertices)
    assert np.ptp(result.vertices[:, 0]) < 0.95 * np.ptp(start.vertices[:, 0])   # x moves too


def _box_with_a_tunnel_and_a_pit():
    """A 12 × 12 × 12 cm box (5 mm voxels) on the ground with a 1-voxel tunnel entering one
    side 3 cm above the ground (8 cm long) and a pit 8 cm wide and 1.5 cm deep in its top;
    sensors on a ring of radius 0.5 m around it at heights 0.1–0.5 m."""
    occ = np.zeros((40, 40, 40), bool)
    occ[8:32, 8:32, 0:24] = True
    occ[8:24, 12, 6] = False                    # the tunnel, open at the x = 8 face
    occ[12:28, 12:28, 21:24] = False            # the pit, open upward
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    heights = np.linspace(0.1, 0.5, 5)
    a, h = np.meshgrid(angles, heights)
    sensors = np.stack([0.1 + 0.5 * np.cos(a.ravel()), 0.1 + 0.5 * np.sin(a.ravel()),
                        h.ravel()], axis=1)     # relative to the grid's lower corner (m)
    return occ, np.full(3, 0.005), sensors


def test_seal_fills_a_tunnel_the_sensors_do_not_see_and_keeps_an_open_pit():
    """The sealed occupancy fills the side tunnel (hidden from nearly every sensor) and leaves
    the pit open to the sensors (seen from most of them) open, at quorum 0.6; quorum 1
    still fills the tunnel's deep part (fails when the hidden voxels are not added); a quorum of 0.2 fills
    most of the pit (the reason it is a candidate, ranked by the data)."""
    occ, spacing, sensors = _box_with_a_tunnel_and_a_pit()
    tunnel = np.zeros_like(occ)
    tunnel[8:24, 12, 6] = True
    pit = np.zeros_like(occ)
    pit[12:28, 12:28, 21:24] = True
    sealed = refine.seal_occupancy(occ, spacing, sensors, 0.6)
    assert sealed[occ].all()                              # nothing removed
    assert sealed[tunnel].all()
    assert sealed[pit].mean() < 0.2                       # the pit stays (almost all) open
    assert not sealed[20, 20, 21:24].any()                # its middle wholly
    assert refine.seal_occupancy(occ, spacing, sensors, 1.0)[14:24, 12, 6].all()   # deep part
    assert refine.seal_occupancy(occ, spacing, sensors, 0.2)[pit].mean() > 0.7


def test_refine_command_adds_the_sealed_start_as_a_candidate(ball_scan, tmp_path, capsys):
    """--seal 0.6 adds the unwrapped start sealed at that quorum as a candidate (named seal0.6,
    its start written with --keep-candidates); by default (off) none is added; a quorum above
    1 and a mesh --init are refused in one line."""
    import json
    from recon.cli import main
    from recon.commands import refine as command
    from sonarsim.dataset import Volume
    b = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.0, 0.1]])
    ball = np.zeros((26, 26, 26), np.complex64)
    x, y, z = np.meshgrid(*(np.linspace(*b[a], 26) for a in range(3)), indexing="ij")
    ball[np.sqrt(x ** 2 + y ** 2 + (z - 0.06) ** 2) < 0.033] = 1.0
    Volume(volume=ball, bounds=b, method="test").write(tmp_path / "start.h5")
    out, hist = tmp_path / "refined.ply", tmp_path / "h.json"
    args = ["refine", str(ball_scan), "--init", str(tmp_path / "start.h5"), "--out", str(out),
            "--no-ground", "--envelope-steps", "1", "--waveform-steps", "1", "--pings", "::2",
            "--edge-length", "0.01", "--history", str(hist), "--no-progress", "--wrap", "0",
            "--grow-unexplained", "0", "--smooth", "0", "--shrink", "0"]
    assert main([*args, "--keep-candidates", "--seal", "0.6"]) == 0
    cands = json.loads(hist.read_text())["candidates"]
    assert [(c["wrap"], c["seal"]) for c in cands] == [(0.0, 0.0), (0.0, 0.6)]
    assert (tmp_path / "refined.seal0.6.start.ply").is_file()
    assert command.DEFAULT_SEAL == "0"
    assert main([*args, "--force"]) == 0
    assert [c["seal"] for c in json.loads(hist.read_text())["candidates"]] == [0.0]
    capsys.readouterr()
    assert main([*args, "--force", "--seal", "1.5"]) == 2
    err = capsys.readouterr().err
    assert "--seal: each quorum must be in (0, 1]" in err and len(err.strip().splitlines()) == 1
    trimesh.creation.icosphere(2, radius=0.03).export(tmp_path / "m.ply")
    mesh_args = ["refine", str(ball_scan), "--init", str(tmp_path / "m.ply"), "--out", str(out),
                 "--no-ground", "--no-progress"]
    assert main([*mesh_args, "--force", "--seal", "0.6"]) == 2
    err = capsys.readouterr().err
    assert "--seal applies to a volume" in err and len(err.strip().splitlines()) == 1
