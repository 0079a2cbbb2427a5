"""Bounce 2 against an independent computation: a wall standing on the ground plane (an
L-shaped concave corner), seen from one pose. A direct NumPy double integral over pairs of
surface elements (midpoint rule, explicit visibility by ray–triangle tests against the
scene's triangles) gives the two-bounce transient

    b_T · cosθ_A / r_TA² · ρ/π · cosθ_A' cosθ_B / r_AB² · ρ/π · cosθ_B' · b_R / r_BR² dA dB

at path length r_TA + r_AB + r_BR; the integrator's bounce-2 histogram must match it in
energy within 3 % and in shape within its Monte-Carlo noise (four independent estimates)
plus the quadrature error of the NumPy integral."""
from __future__ import annotations

import numpy as np
import pytest

from sonarsim.scene import load_scene

TX = np.array([-0.40, 0.0, 0.25])
RX = np.array([-0.40, 0.03, 0.25])
AIM = np.array([-0.05, 0.0, 0.05])
BEAMWIDTH = 80.0          # deg: both cones cover the whole corner (gains are 1 on it)
WALL_X = 0.05             # the wall: x = 0.05, y in [-0.08, 0.08], z in [0, 0.12]
WALL_Y, WALL_H = 0.08, 0.12
GROUND = ((-0.15, 0.05), (-0.10, 0.10))    # the ground rectangle at z = 0 (x and y ranges)
ALBEDO = 0.8
STEP = 5e-3               # m: quadrature cell (energy within 0.7 % of STEP/2)
BLOCK = 96                # first-surface cells per vectorised block


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    d = tmp_path_factory.mktemp("corner")
    (d / "wall.obj").write_text(
        f"v {WALL_X} {-WALL_Y} 0\nv {WALL_X} {WALL_Y} 0\nv {WALL_X} {WALL_Y} {WALL_H}\n"
        f"v {WALL_X} {-WALL_Y} {WALL_H}\nf 1 2 3\nf 1 3 4\n")
    (d / "corner.toml").write_text(
        f"[box]\nlo = [{GROUND[0][0]}, {GROUND[1][0]}, 0.0]\nhi = [{GROUND[0][1]}, "
        f"{GROUND[1][1]}, 0.2]\n[ground]\nalbedo = {ALBEDO}\nsize = [0.2, 0.2]\n"
        f'[[object]]\nmesh = "wall.obj"\nalbedo = {ALBEDO}\nnormals = "flat"\n')
    return load_scene(d / "corner.toml")


def cells(x_range, y_range, step, plane):
    """Midpoints [n, 3] and normal of a rectangle split into cells of about ``step``."""
    nx = int(round((x_range[1] - x_range[0]) / step))
    ny = int(round((y_range[1] - y_range[0]) / step))
    u = x_range[0] + (np.arange(nx) + 0.5) * (x_range[1] - x_range[0]) / nx
    v = y_range[0] + (np.arange(ny) + 0.5) * (y_range[1] - y_range[0]) / ny
    uu, vv = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
    area = (x_range[1] - x_range[0]) * (y_range[1] - y_range[0]) / (nx * ny)
    if plane == "ground":
        return np.c_[uu, vv, np.zeros_like(uu)], np.array([0.0, 0, 1]), area
    return np.c_[np.full_like(uu, WALL_X), uu, vv], np.array([-1.0, 0, 0]), area


def segment_blocked(p, q, triangles) -> np.ndarray:
    """Whether the open segments p→q [n, 3] hit any triangle [m, 3, 3] (Möller–Trumbore)."""
    d = q - p
    blocked = np.zeros(len(p), bool)
    for a, b, c in triangles:
        e1, e2 = b - a, c - a
        h = np.cross(d, e2)
        det = h @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = p - a
        u = np.einsum("ij,ij->i", s, h) * inv
        qv = np.cross(s, e1)
        v = np.einsum("ij,ij->i", d, qv) * inv
        t = (qv @ e2) * inv
        blocked |= ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-6)
    return blocked


def numpy_bounce2(edges: np.ndarray, step: float) -> np.ndarray:
    """Two-bounce energy per path-length bin (``edges``) by the direct double integral."""
    ground, n_g, a_g = cells(*GROUND, step, "ground")
    wall, n_w, a_w = cells((-WALL_Y, WALL_Y), (0.0, WALL_H), step, "wall")
    g0 = np.array([[GROUND[0][0], GROUND[1][0], 0], [GROUND[0][1], GROUND[1][0], 0],
                   [GROUND[0][1], GROUND[1][1], 0], [GROUND[0][0], GROUND[1][1], 0]], float)
    w0 = np.array([[WALL_X, -WALL_Y, 0], [WALL_X, WALL_Y, 0], [WALL_X, WALL_Y, WALL_H],
                   [WALL_X, -WALL_Y, WALL_H]], float)
    triangles = [q[[0, 1, 2]] for q in (g0, w0)] + [q[[0, 2, 3]] for q in (g0, w0)]
    axis = (AIM - TX) / np.linalg.norm(AIM - TX)
    cos_cut = np.cos(np.radians(BEAMWIDTH / 2))
    hist = np.zeros(len(edges) - 1)
    for first, n1, a1, second, n2, a2 in ((ground, n_g, a_g, wall, n_w, a_w),
                                          (wall, n_w, a_w, ground, n_g, a_g)):
        to_a = first - TX
        r_ta = np.linalg.norm(to_a, axis=1)
        cos_in = np.clip(-(to_a @ n1) / r_ta, 0, None)
        lit = (cos_in > 0) & ((to_a @ axis) / r_ta >= cos_cut)
        lit &= ~segment_blocked(np.repeat(TX[None], len(first), 0), first, triangles)
        e_a = ALBEDO / np.pi * cos_in / r_ta ** 2 * a1          # radiance factor at A
        to_rx = RX - second
        r_br = np.linalg.norm(to_rx, axis=1)
        cos_out = np.clip((to_rx @ n2) / r_br, 0, None)
        seen = (cos_out > 0) & ((-to_rx @ ((AIM - RX) / np.linalg.norm(AIM - RX))) / r_br
                                >= cos_cut)
        seen &= ~segment_blocked(second, np.repeat(RX[None], len(second), 0), triangles)
        w_b = ALBEDO / np.pi * cos_out / r_br ** 2 * a2
        idx = np.flatnonzero(lit)
        for a in range(0, len(idx), BLOCK):        # pairs (A in a block of cells) x (all B)
            i = idx[a:a + BLOCK]
            d = second[None] - first[i][:, None]                       # [m, n2, 3]
            r = np.linalg.norm(d, axis=2)
            c1 = np.clip((d @ n1) / r, 0, None)
            c2 = np.clip(-(d @ n2) / r, 0, None)
            ok = seen[None] & (c1 > 0) & (c2 > 0)
            rows, cols = np.nonzero(ok)
            visible = ~segment_blocked(first[i][rows], second[cols], triangles)
            rows, cols = rows[visible], cols[visible]
            value = e_a[i][rows] * c1[rows, cols] * c2[rows, cols] / r[rows, cols] ** 2 * w_b[cols]
            length = r_ta[i][rows] + r[rows, cols] + r_br[cols]
            hist += np.histogram(length, edges, weights=value)[0]
    return hist


def test_bounce2_matches_direct_double_integral(mi, corner):
    from sonarsim.render import make_integrator
    beams = {"tx_beamwidth": BEAMWIDTH, "rx_beamwidth": BEAMWIDTH}
    integ = make_integrator(2, beams, bounce1="cone")
    scene = corner.to_mitsuba()
    width, start, n_bins, coarse = 2e-3, 0.74, 400, 10          # compared on 2 cm bins
    runs = np.concatenate([integ.render_transients(
        scene, TX[None], RX[None], (AIM - TX)[None], (AIM - RX)[None], start, width, n_bins,
        1_000_000, seed, halves=True)[:, 0, 1] for seed in (7, 8)]).astype(float)
    est = runs.reshape(4, -1, coarse).sum(axis=2)               # 4 independent estimates
    ours = est.mean(axis=0)
    sigma = est.std(axis=0, ddof=1) / 2                         # MC error of their mean
    edges = start + width * coarse * np.arange(n_bins // coarse + 1)
    ref = numpy_bounce2(edges, STEP)
    coarser = numpy_bounce2(edges, 2 * STEP)                    # quadrature error estimate
    assert ref[0] == 0 and ref[-1] == 0 and ref.sum() > 0       # the window holds it all
    e_sigma = est.sum(axis=1).std(ddof=1) / 2
    assert ours.sum() == pytest.approx(ref.sum(), rel=0.03), (ours.sum(), ref.sum(), e_sigma)
    assert e_sigma < 0.005 * ours.sum()
    # Shape: every bin within its Monte-Carlo noise plus the midpoint rule's error
    # (|ref(STEP) - ref(2 STEP)|, which bounds the error of ref(STEP)), 3 sigma.
    shape = ours - ref * ours.sum() / ref.sum()
    tolerance = 3 * np.sqrt(sigma ** 2 + (ref - coarser) ** 2) + 1e-4 * ref.max()
    assert np.all(np.abs(shape) <= tolerance), (shape / ref.max(), tolerance / ref.max())
    assert np.sum(np.abs(shape)) < 0.05 * ours.sum()
