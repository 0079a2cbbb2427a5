"""Mitsuba-native rendering (sensor ``sonar``, film ``sonar_film``) and its gradients.

``mi.render(scene)`` must give the chunked driver's histograms for the same pose and seed;
``mi.render(scene, params)`` + ``dr.backward`` must match central finite differences of the
primal rendered with the gradient pass's seed (the same random numbers, so the difference
is the derivative itself, not Monte-Carlo noise). Scenes without moving visibility
boundaries (docs/differentiable.md): a convex mesh or sphere seen from outside (single
scattering) and a closed sphere mesh seen from inside (double scattering, every point sees
every other). The loss is ⟨W, T⟩ with a smooth weight W over the bins, in float64.
"""
from __future__ import annotations

import numpy as np
import pytest

NB = 160                      # bins of 2 mm: short kernels, a smooth weight over them
WIDTH = 0.002
SEED, SEED_GRAD = 3, 11


def diffuse(rho):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": float(rho)}}


def sonar(tx, look, rx=None, start=1.0, bins=NB, **beams):
    sensor = {"type": "sonar", "tx_origin": list(tx), "tx_boresight": list(look),
              "film": {"type": "sonar_film", "temporal_bins": bins, "start_opl": start,
                       "bin_width_opl": WIDTH}, **beams}
    if rx is not None:
        sensor["rx_origin"] = list(rx)
    return sensor


def scene_of(mi, target, sensor, bounces=1, **props):
    return mi.load_dict({"type": "scene", "integrator": {
        "type": "sonar_transient", "max_bounces": bounces, "tx_beam": "isotropic",
        "rx_beam": "isotropic", **props}, "sensor": sensor, "target": target})


@pytest.fixture(scope="module")
def icosphere(tmp_path_factory):
    """A closed sphere mesh (radius 0.1 m, 642 vertices) as a PLY file with smooth normals."""
    import trimesh
    path = tmp_path_factory.mktemp("mesh") / "icosphere.ply"
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(path)
    return str(path)


def smooth_weight(bounces, bins=NB):
    j = np.arange(bins)
    w = np.sin(j / 7.0) + 0.5 * np.cos(j / 3.1)
    return np.broadcast_to(w, (bounces, bins)).astype(np.float32).copy()


class Derivative:
    """AD (through mi.render) and central finite differences of ⟨W, T⟩ for one parameter."""

    def __init__(self, mi, scene):
        import drjit as dr
        self.mi, self.dr, self.scene = mi, dr, scene
        self.params = mi.traverse(scene)
        self.weight = smooth_weight(scene.integrator().max_bounces)

    def primal(self, seed=SEED_GRAD) -> float:
        t = self.mi.render(self.scene, seed=seed).numpy().astype(np.float64)
        return float((t * self.weight).sum())

    def ad(self, *keys):
        """Reverse-mode gradients of the loss for ``keys`` (one backward pass): float64
        arrays, one per key (a single key: its array)."""
        dr, mi = self.dr, self.mi
        for key in keys:
            dr.enable_grad(self.params[key])
        self.params.update()
        image = mi.render(self.scene, self.params, seed=SEED, seed_grad=SEED_GRAD)
        dr.backward(dr.sum(image * mi.TensorXf(self.weight), axis=None))
        grads = [np.array(dr.grad(self.params[key]), np.float64).ravel() for key in keys]
        for key in keys:
            dr.disable_grad(self.params[key])
        self.params.update()
        return grads[0] if len(keys) == 1 else grads

    def fd(self, key, direction, h, make) -> float:
        base = np.array(self.params[key], np.float64).ravel()
        values = []
        for sign in (1.0, -1.0):
            self.params[key] = make(base + sign * h * np.asarray(direction, np.float64))
            self.params.update()
            values.append(self.primal())
        self.params[key] = make(base)
        self.params.update()
        return (values[0] - values[1]) / (2.0 * h)


def floats(mi):
    return lambda v: mi.Float(np.asarray(v, np.float32))


def point(mi):
    return lambda v: mi.Point3f(*(float(x) for x in v))


# ----------------------------------------------------------------------------- mi.render
def test_mi_render_is_the_driver_for_that_pose(mi, shared_data):
    """The issue's snippet: TensorXf (max_bounces, temporal_bins), equal to render_transients."""
    tx, rx, look = [0.6, 0.1, 0.3], [0.6, 0.15, 0.3], [-1.0, 0.0, -0.3]
    scene = mi.load_dict({"type": "scene",
        "integrator": {"type": "sonar_transient", "max_bounces": 2},
        "sensor": {"type": "sonar", "tx_origin": tx, "rx_origin": rx, "tx_boresight": look,
                   "rx_boresight": look, "film": {"type": "sonar_film", "temporal_bins": 400,
                                                  "start_opl": 1.0, "bin_width_opl": 0.002}},
        "target": {"type": "obj", "filename": str(shared_data / "meshes" / "cube.obj"),
                   "bsdf": diffuse(0.8)}})
    image = mi.render(scene, seed=1)
    assert type(image).__name__ == "TensorXf" and image.shape == (2, 400)
    ref = scene.integrator().render_transients(scene, tx, rx, look, look, 1.0, 0.002, 400, 4, 1)
    assert np.count_nonzero(ref) > 100
    np.testing.assert_array_equal(image.numpy(), ref[0])
    assert np.array_equal(scene.sensors()[0].film().develop().numpy(), ref[0])


def test_batch_sensor_and_several_sensors(mi, icosphere):
    """A sensor holding N poses returns (N, B, T), pose i as the driver's pose i; a second
    sensor of the scene renders its own pose."""
    import drjit as dr
    tx = np.array([[0.5, 0.0, 0.1], [0.0, 0.45, 0.0], [-0.4, -0.2, 0.05]])
    look = -tx
    target = {"type": "ply", "filename": icosphere, "bsdf": diffuse(0.6)}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "sonar_transient",
                                                          "max_bounces": 1},
                          "sensor": sonar(tx[0], look[0], start=0.6, bins=200),
                          "other": sonar(tx[2], look[2], start=0.6, bins=200),
                          "target": target})
    from sonarsim.plugins import sonar as sonar_plugin
    params = mi.traverse(scene)
    sonar_plugin.set_poses(params, tx, look)             # monostatic: rx = tx, same boresight
    params.update()
    batch = mi.render(scene, seed=5).numpy()
    assert batch.shape == (3, 1, 200)
    ref = scene.integrator().render_transients(scene, tx, tx, look, look, 0.6, WIDTH, 200, 4, 5)
    assert np.count_nonzero(ref) > 100
    np.testing.assert_array_equal(batch, ref)
    rx, rx_look = tx + [0.0, 0.04, 0.0], look + [0.0, 0.0, 0.1]     # bistatic: every vector its own
    sonar_plugin.set_poses(params, tx, look, rx, rx_look)
    params.update()
    bistatic = scene.integrator().render_transients(scene, tx, rx, look, rx_look, 0.6, WIDTH,
                                                    200, 4, 5)
    assert not np.array_equal(bistatic, ref)
    np.testing.assert_array_equal(mi.render(scene, seed=5).numpy(), bistatic)
    sonar_plugin.set_poses(params, tx, look)
    params.update()
    other = mi.render(scene, sensor=1, seed=5).numpy()
    single = scene.integrator().render_transients(scene, tx[2], tx[2], look[2], look[2], 0.6,
                                                   WIDTH, 200, 4, 5)
    np.testing.assert_array_equal(other, single[0])
    assert not np.array_equal(other, batch[2])           # pose offset 0 vs 2: other numbers
    np.testing.assert_allclose(other.sum(), batch[2].sum(), rtol=0.02)
    with pytest.raises(ValueError, match="width N or 1"):
        params["sensor.rx_origin"] = mi.Point3f(*(mi.Float(tx[:2, i]) for i in range(3)))
        params.update()
    dr.eval()


def test_bad_sensor_and_film_settings_are_refused(mi):
    for sensor, match in (
            ({"tx_origin": [1, 0, 0]}, "tx_boresight"),
            ({"tx_origin": [1, 0, 0], "tx_boresight": [0, 0, 0]}, "zero-length"),
            ({"tx_origin": [1, 0, 0], "tx_boresight": [1, 0, 0], "tx_beam": "laser"}, "tx_beam"),
            ({"tx_origin": [1, 0, 0], "tx_boresight": [1, 0, 0],
              "film": {"type": "sonar_film", "bin_width_opl": 0.0}}, "bin_width_opl"),
            ({"tx_origin": [1, 0, 0], "tx_boresight": [1, 0, 0],
              "film": {"type": "sonar_film", "temporal_bins": 0}}, "temporal_bins")):
        with pytest.raises(RuntimeError, match=match):
            mi.load_dict({"type": "sonar", "film": {"type": "sonar_film"}, **sensor})


# ----------------------------------------------------------------------------- gradients
def test_reflectance_gradient_is_exact(mi, icosphere):
    """Bounce 1 is linear in the albedo: AD equals the finite difference to 1e-4."""
    scene = scene_of(mi, {"type": "ply", "filename": icosphere, "bsdf": diffuse(0.6)},
                     sonar([0.55, 0.1, 0.2], [-1, 0, -0.3]))
    d = Derivative(mi, scene)
    key = "target.bsdf.reflectance.value"
    ad = d.ad(key)[0]
    fd = d.fd(key, [1.0], 0.05, floats(mi))
    assert abs(ad) > 1e-4
    assert ad == pytest.approx(fd, rel=1e-4)
    assert ad == pytest.approx(d.primal() / 0.6, rel=1e-4)      # linear: T / ρ
    # Forward mode (render_forward): ⟨W, ∂T/∂ρ⟩ is the reverse-mode gradient.
    import drjit as dr
    dr.enable_grad(d.params[key])
    d.params.update()
    image = mi.render(scene, d.params, seed=SEED, seed_grad=SEED_GRAD)
    dr.forward(d.params[key])
    forward = float((np.array(dr.grad(image), np.float64) * d.weight).sum())
    assert forward == pytest.approx(ad, rel=1e-5)


@pytest.mark.parametrize("bounces", [1, 2])
def test_mesh_translation_vertex_and_tx_gradients(mi, icosphere, bounces):
    """Single scattering: the sphere mesh seen from outside (convex). Double scattering:
    TX and RX inside the closed mesh (every point sees every other). Rigid translation of
    the mesh (3 axes), one vertex (normal and tangential), the TX origin, and the window
    start (where the sound speed enters), against central differences."""
    target = {"type": "ply", "filename": icosphere, "bsdf": diffuse(0.7)}
    if bounces == 1:
        scene = scene_of(mi, target, sonar([0.55, 0.1, 0.2], [-1, 0, -0.3],
                                           rx=[0.52, 0.16, 0.2]))
    else:
        scene = scene_of(mi, target, sonar([0.03, 0.01, -0.02], [1, 0, 0],
                                           rx=[-0.02, 0.03, 0.0], start=0.05),
                         bounces=2, surface_spacing=0.012)
    d = Derivative(mi, scene)
    key = "target.vertex_positions"
    positions = np.array(d.params[key], np.float64).reshape(-1, 3)
    grad, tx_grad, rx_grad, start_grad = d.ad(key, "sensor.tx_origin", "sensor.rx_origin",
                                              "sensor.film.start_opl")
    grad = grad.reshape(-1, 3)
    assert np.all(np.isfinite(grad))
    checks = []
    for axis in range(3):                 # rigid translation
        direction = np.zeros_like(positions)
        direction[:, axis] = 1.0
        checks.append((grad.ravel() @ direction.ravel(),
                       d.fd(key, direction.ravel(), 3e-4, floats(mi))))
    # one vertex facing the TX (outside) / any vertex (inside), along its normal and a tangent
    tx = np.array(d.params["sensor.tx_origin"], np.float64).ravel()
    to_tx = tx - positions
    vertex = int(np.argmax(np.einsum("ij,ij->i", positions, to_tx)))
    normal = positions[vertex] / np.linalg.norm(positions[vertex])
    tangent = np.cross(normal, [0.0, 0.0, 1.0])
    for vector in (normal, tangent / np.linalg.norm(tangent)):
        direction = np.zeros_like(positions)
        direction[vertex] = vector
        checks.append((grad.ravel() @ direction.ravel(),
                       d.fd(key, direction.ravel(), 3e-4, floats(mi))))
    for axis in (0, 2):
        checks.append((tx_grad[axis], d.fd("sensor.tx_origin", np.eye(3)[axis], 3e-4, point(mi))))
    checks.append((start_grad[0], d.fd("sensor.film.start_opl", [1.0], 3e-4, floats(mi))))
    scale = max(abs(fd) for _, fd in checks)
    for ad, fd in checks:
        assert ad == pytest.approx(fd, rel=0.01, abs=0.01 * scale), checks
    # Translating scene, TX and RX together changes nothing: the three gradients cancel.
    moved = grad.sum(axis=0) + tx_grad + rx_grad
    assert np.all(np.abs(moved) < 1e-3 * np.abs(grad.sum(axis=0)).max()), (moved, tx_grad)


def test_example_renders_and_recovers_an_offset(mi, capsys):
    """examples/mitsuba_render.py: the issue's snippet, then gradient descent through
    mi.render finds a 5.4 mm offset of the bunny again (to well under its size)."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "examples" / "mitsuba_render.py"
    spec = importlib.util.spec_from_file_location("mitsuba_render_example", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    image = example.part1(mi)
    assert image.shape == (2, 400) and float(image.numpy()[0].sum()) > 0
    true = np.array([0.004, -0.003, 0.002])
    found, error = example.part2(mi, 15, tuple(true))
    assert error < 0.25 * np.linalg.norm(true), (found, error)
    assert "mi.render: TensorXf (2, 400)" in capsys.readouterr().out
