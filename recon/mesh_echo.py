"""Differentiable single-scattering echo of a triangle mesh over a fixed ground (Dr.Jit).

The model of :mod:`recon.refine`: for every ping it gives the bounce-1 energy histogram over
round-trip path length that the ``sonar_transient`` integrator renders (DESIGN §4, intensity
mode), as a Dr.Jit array that is differentiable with respect to the mesh's vertex positions
and the object's albedo. A surface element dA at x seen by both ends contributes

    b_T · b_R · ρ/π · cosθ_i · cosθ_o / (r_T² r_R²) dA     at path length L = r_T + r_R,

two-sided (the normal is oriented towards the TX; both ends must be on that side), with the
beam gains b_T, b_R of the dataset's cone beams (1 inside the cone, 0 outside). The
contribution is split linearly (tent) between the two bins whose centres enclose L, as the
integrator does, so after convolution with the oversampled pulse and decimation
(:mod:`recon.pulse_chain`) the waveform is the pulse evaluated at the continuous delay.

Quadrature: every triangle carries ``order²`` points, the centroids of its regular
subdivision into ``order²`` sub-triangles, each standing for area/order². The ground (fixed,
no gradient) is a regular triangulated rectangle at z = 0 treated the same way.

Visibility: shadow rays from each point (offset along its oriented normal) to the TX and the
RX through a Mitsuba scene of the current mesh and the ground (Embree). Visibility is
evaluated on detached positions, so its discontinuities contribute no gradient (the interior
terms are exact; the silhouette terms are left out: a documented bias, docs/refine.md).

Lanes are (ping, point) pairs of one batch of pings, one wavefront kernel; no Python loop
over pings or points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonarsim.errors import InputError

CONE_BEAMS = ("cone", "isotropic")


def subdivision_barycentrics(order: int) -> np.ndarray:
    """Barycentric coordinates (b1, b2) [order², 2] of the centroids of the regular
    subdivision of a triangle into order² sub-triangles (weights b1, b2 of corners 1, 2)."""
    if int(order) != order or order < 1:
        raise InputError(f"quadrature order must be a positive integer, got {order}")
    n = int(order)
    pts = []
    for i in range(n):
        for j in range(n - i):       # 'up' sub-triangle with lower corner (i, j)
            pts.append(((i + 1 / 3) / n, (j + 1 / 3) / n))
            if i + j < n - 1:        # its 'down' neighbour
                pts.append(((i + 2 / 3) / n, (j + 2 / 3) / n))
    return np.asarray(pts, np.float64)


def ground_mesh(size: tuple[float, float], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle [−sx/2, sx/2] × [−sy/2, sy/2] at z = 0 as a regular triangle grid
    (vertices [V, 3] m, faces [F, 3]) of cells about ``spacing`` metres wide."""
    sx, sy = (float(v) for v in size)
    if not (sx > 0 and sy > 0 and spacing > 0):
        raise InputError(f"ground size and spacing must be positive, got {size}, {spacing}")
    nx, ny = max(1, round(sx / spacing)), max(1, round(sy / spacing))
    x, y = np.linspace(-sx / 2, sx / 2, nx + 1), np.linspace(-sy / 2, sy / 2, ny + 1)
    gx, gy = np.meshgrid(x, y, indexing="ij")
    verts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange(gx.size).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


@dataclass(frozen=True)
class Pings:
    """The geometry of the pings the model renders: positions [N, 3] (m), unit boresights
    [N, 3], full cone beamwidths (degrees; 'isotropic' = 360)."""

    tx: np.ndarray
    rx: np.ndarray
    tx_boresight: np.ndarray
    rx_boresight: np.ndarray
    tx_beamwidth: float = 30.0
    rx_beamwidth: float = 30.0

    def __len__(self) -> int:
        return len(self.tx)

    @classmethod
    def of_dataset(cls, dataset) -> "Pings":
        """The pings of a :class:`sonarsim.dataset.SonarDataset` with the beams of its meta
        (cone or isotropic; default cone 30° as the simulator's)."""
        beams = dict(dataset.meta.get("beams") or {})
        widths = []
        for end in ("tx", "rx"):
            kind = beams.get(f"{end}_beam", "cone")
            if kind not in CONE_BEAMS:
                raise InputError(f"the {end} beam of the dataset is {kind!r}; the mesh model "
                                 f"handles {', '.join(CONE_BEAMS)}")
            widths.append(360.0 if kind == "isotropic" else float(beams.get(f"{end}_beamwidth", 30.0)))
        return cls(np.asarray(dataset.tx, float), np.asarray(dataset.rx, float),
                   np.asarray(dataset.boresight, float), np.asarray(dataset.receiver_boresight, float),
                   widths[0], widths[1])


@dataclass(frozen=True)
class Window:
    """Histogram bins: bin j covers round-trip path [start + j·width, start + (j+1)·width) m
    and stands for its centre."""

    start: float
    width: float
    n_bins: int


@dataclass
class Visibility:
    """What :meth:`MeshEcho.visibility` traced for a batch of pings: the object's visible
    lanes (Dr.Jit UInt32) and the ground's histograms with the object's shadows (Float)."""

    object_lanes: object
    ground: object


class MeshEcho:
    """Bounce-1 histograms of a mesh (vertices differentiable) over a fixed ground.

    faces: int [F, 3]; order: quadrature points per triangle = order²; ground: None or
    (size_x, size_y, albedo, spacing) in metres; window: the bins; pings: their geometry.
    Call :meth:`set_mesh` when the topology changes, :meth:`histograms` per step.
    """

    def __init__(self, faces: np.ndarray, pings: Pings, window: Window, *, order: int = 2,
                 ground: tuple[float, float, float, float] | None = (0.4, 0.4, 1.0, 4e-3)):
        from sonarsim import runtime
        self.mi = runtime.mitsuba()
        import drjit as dr
        self.dr = dr
        self.pings, self.window, self.order = pings, window, int(order)
        self.bary = subdivision_barycentrics(self.order)
        self.ground = ground
        self._ground_points = None
        if ground is not None:
            gv, gf = ground_mesh(ground[:2], ground[3])
            self._ground_points = self._static_points(gv, gf, float(ground[2]), order=1)
        self._scene = None
        self.set_mesh(faces)

    # ------------------------------------------------------------------ geometry
    def set_mesh(self, faces: np.ndarray) -> None:
        """Use a new triangle list (int [F, 3]); the next call rebuilds the visibility scene."""
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise InputError(f"faces must be a non-empty [F, 3] array, got shape {faces.shape}")
        mi = self.mi
        self.faces_np = faces.astype(np.uint32)
        m = len(self.bary)
        self.n_points = len(faces) * m
        self._point_face = mi.UInt32(np.repeat(np.arange(len(faces), dtype=np.uint32), m))
        self._point_b = [mi.Float(np.tile(self.bary[:, a], len(faces)).astype(np.float32))
                         for a in (0, 1)]
        self._faces = mi.UInt32(self.faces_np.ravel())
        self._scene = None

    def _static_points(self, verts: np.ndarray, faces: np.ndarray, albedo: float,
                       order: int = 1) -> dict:
        """Quadrature points (``order``² per triangle) of a fixed mesh, as Dr.Jit constants."""
        mi = self.mi
        tri = verts[faces]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        cross = np.cross(e1, e2)
        area = np.linalg.norm(cross, axis=1)
        b = subdivision_barycentrics(order)
        p = tri[:, None, 0] + b[None, :, :1] * e1[:, None] + b[None, :, 1:] * e2[:, None]
        n = np.repeat(cross / area[:, None], len(b), axis=0)
        dA = np.repeat(area / 2 / len(b), len(b))
        vec = lambda a: mi.Vector3f(*(mi.Float(a[:, i].astype(np.float32)) for i in range(3)))
        return {"p": vec(p.reshape(-1, 3)), "n": vec(n), "dA": mi.Float(dA.astype(np.float32)),
                "rho": float(albedo), "count": len(dA)}

    def _visibility_scene(self, vertices: np.ndarray):
        mi = self.mi
        if self._scene is None or self._scene_nv != len(vertices):
            mesh = mi.Mesh("object", vertex_count=len(vertices), face_count=len(self.faces_np))
            params = mi.traverse(mesh)
            params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
            params["faces"] = mi.UInt32(self.faces_np.ravel())
            params.update()
            items = {"type": "scene", "object": mesh}
            if self.ground is not None:
                sx, sy = self.ground[0] / 2, self.ground[1] / 2
                items["ground"] = {"type": "rectangle",
                                   "to_world": mi.ScalarTransform4f().scale([sx, sy, 1.0])}
            self._scene = mi.load_dict(items)
            self._scene_params = mi.traverse(self._scene)
            self._scene_nv = len(vertices)
        else:
            self._scene_params["object.vertex_positions"] = mi.Float(
                vertices.astype(np.float32).ravel())
            self._scene_params.update()
        return self._scene

    # ------------------------------------------------------------------ rendering
    def object_points(self, vertices):
        """Quadrature points of the mesh: positions p, unit normals n, areas dA [P] (Dr.Jit,
        differentiable in ``vertices``, Float [V·3] m)."""
        dr, mi = self.dr, self.mi
        V = dr.unravel(mi.Point3f, vertices)
        corner = [dr.gather(mi.Point3f, V, dr.gather(mi.UInt32, self._faces, self._point_face * 3 + j))
                  for j in range(3)]
        e1, e2 = mi.Vector3f(corner[1] - corner[0]), mi.Vector3f(corner[2] - corner[0])
        p = mi.Point3f(corner[0] + self._point_b[0] * e1 + self._point_b[1] * e2)
        cross = dr.cross(e1, e2)
        area2 = dr.norm(cross)
        return p, mi.Vector3f(cross / dr.maximum(area2, 1e-20)), area2 * (0.5 / len(self.bary))

    def visibility(self, vertices, ping_index: np.ndarray) -> "Visibility":
        """The visibility of the pings ``ping_index`` for the current mesh (detached).

        The object's lanes (ping · P + point) that face both ends, lie in both beams and in
        the window and see both ends (shadow rays), and the ground's histograms with the
        shadows of the current mesh (a constant: the ground does not move). Pass it to
        :meth:`histograms` to reuse it for a few steps while the mesh moves a little.
        """
        dr, mi = self.dr, self.mi
        v = dr.detach(vertices)
        scene = self._visibility_scene(np.asarray(v.numpy(), np.float64).reshape(-1, 3))
        with dr.suspend_grad():
            p, n, dA = self.object_points(v)
            lanes = dr.arange(mi.UInt32, len(ping_index) * dr.width(p))
            geo = self._lane_geometry(lanes, ping_index, p, n, dA)
            object_lanes = dr.compress(geo["active"] & self._unoccluded(scene, geo))
            ground = dr.zeros(mi.Float, len(ping_index) * self.window.n_bins)
            if self._ground_points is not None:
                g = self._ground_points
                lanes = dr.arange(mi.UInt32, len(ping_index) * g["count"])
                geo = self._lane_geometry(lanes, ping_index, g["p"], g["n"], g["dA"])
                geo["active"] &= self._unoccluded(scene, geo)
                self._splat(ground, geo, mi.Float(g["rho"]))
            dr.eval(object_lanes, ground)
        return Visibility(object_lanes, ground)

    def histograms(self, vertices, albedo, ping_index: np.ndarray,
                   visibility: "Visibility | None" = None):
        """Histograms [n · n_bins] (Dr.Jit Float, row-major over the pings ``ping_index``).

        vertices: Dr.Jit Float [V·3] (m; may carry gradients); albedo: Dr.Jit Float [1]
        (the object's ρ, may carry gradients); ping_index: int [n] into :attr:`pings`;
        visibility: :meth:`visibility` of these pings (default: traced now).
        """
        dr = self.dr
        if visibility is None:
            visibility = self.visibility(vertices, ping_index)
        hist = dr.copy(visibility.ground)       # the splat adds in place
        p, n, dA = self.object_points(vertices)
        geo = self._lane_geometry(visibility.object_lanes, ping_index, p, n, dA)
        self._splat(hist, geo, albedo)
        return hist

    def _lane_geometry(self, lanes, ping_index, p, n, dA) -> dict:
        """Per lane (ping · P + point): distances, cosines, window position and the mask of
        facing, in-beam, in-window lanes (no visibility)."""
        dr, mi = self.dr, self.mi
        pings = self.pings
        n_pts = dr.opaque(mi.UInt32, dr.width(p))
        idx = np.asarray(ping_index, np.int64)
        vec = lambda a: mi.Vector3f(*(mi.Float(a[idx, i].astype(np.float32)) for i in range(3)))
        ping = lanes // n_pts
        k = lanes - ping * n_pts
        x = mi.Point3f(dr.gather(type(p), p, k))
        nx = mi.Vector3f(dr.gather(type(n), n, k))
        p_tx = mi.Point3f(dr.gather(mi.Vector3f, vec(pings.tx), ping))
        p_rx = mi.Point3f(dr.gather(mi.Vector3f, vec(pings.rx), ping))
        to_tx, to_rx = p_tx - x, p_rx - x
        r_t, r_r = dr.norm(to_tx), dr.norm(to_rx)
        w_t, w_r = to_tx / r_t, to_rx / r_r
        cos_i, cos_o = dr.dot(nx, w_t), dr.dot(nx, w_r)
        flip = dr.select(dr.detach(cos_i) < 0.0, -1.0, 1.0)   # two-sided: face the TX
        cos_i, cos_o = cos_i * flip, cos_o * flip
        active = dr.detach(cos_o) > 0.0
        for bore, w, width in ((pings.tx_boresight, w_t, pings.tx_beamwidth),
                               (pings.rx_boresight, w_r, pings.rx_beamwidth)):
            if width < 360.0:
                cut = dr.opaque(mi.Float, float(np.cos(np.radians(width) / 2)))
                b = dr.gather(mi.Vector3f, vec(bore), ping)
                active &= -dr.dot(dr.detach(w), b) >= cut
        win = self.window
        pos = ((r_t + r_r - dr.opaque(mi.Float, win.start)) * dr.opaque(mi.Float, 1.0 / win.width)
               - 0.5)
        bin0 = dr.floor(dr.detach(pos))
        active &= (bin0 >= -1.0) & (bin0 < float(win.n_bins))
        return {"ping": ping, "x": x, "normal": nx * flip, "p_tx": p_tx, "p_rx": p_rx,
                "r_t": r_t, "r_r": r_r, "cos_i": cos_i, "cos_o": cos_o,
                "dA": dr.gather(mi.Float, dA, k), "pos": pos, "bin0": bin0, "active": active}

    def _unoccluded(self, scene, geo):
        """Lanes that see both the TX and the RX (shadow rays from the point, detached)."""
        dr, mi = self.dr, self.mi
        xd, nd = dr.detach(geo["x"]), dr.detach(geo["normal"])
        scale = dr.maximum(dr.maximum(dr.abs(xd.x), dr.abs(xd.y)), dr.abs(xd.z))
        origin = xd + nd * ((1.0 + scale) * mi.math.RayEpsilon)
        seen = mi.Bool(geo["active"])
        for target in (dr.detach(geo["p_tx"]), dr.detach(geo["p_rx"])):
            ray = mi.Ray3f(origin, target - origin)
            ray.maxt = mi.Float(1.0 - mi.math.ShadowEpsilon)
            seen &= ~scene.ray_test(ray, seen)
        return seen

    def _splat(self, hist, geo, rho) -> None:
        """Tent-splat the lanes' contributions into ``hist``."""
        dr, mi = self.dr, self.mi
        r_t, r_r = geo["r_t"], geo["r_r"]
        value = (rho * dr.inv_pi * geo["cos_i"] * geo["cos_o"] * geo["dA"]) / (r_t * r_t * r_r * r_r)
        frac = geo["pos"] - geo["bin0"]
        n_bins = self.window.n_bins
        base = mi.Int32(geo["ping"]) * n_bins + mi.Int32(geo["bin0"])
        active = geo["active"]
        dr.scatter_add(hist, value * (1.0 - frac), mi.UInt32(dr.maximum(base, 0)),
                       active & (geo["bin0"] >= 0.0))
        dr.scatter_add(hist, value * frac, mi.UInt32(base + 1),
                       active & (geo["bin0"] + 1.0 < float(n_bins)))
