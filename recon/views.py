"""Depth and shaded renders of meshes around a turntable, and image metrics (PSNR, SSIM).

The reference renders with pyrender (OpenGL; reference code ``evaluate/visualize_render_utils.py``
and ``evaluate/main_image_space_loss.py``); here the same pinhole cameras are ray cast with
Mitsuba's ``scene.ray_intersect`` on the CPU variant, so no OpenGL or RGB variant is needed.

* Cameras (:class:`Turntable`, the reference's placement): view i at azimuth a = 360°·i/n sits at
  (r·cos(90° − a), r·sin(90° − a), elevation), r = √(distance² − elevation²) (distance from the
  origin 0.3 m, elevation 0.1 m), looking at (0, 0, 0.1) with z up; near plane 5 cm (pyrender's
  default). ``yfov`` is the value pyrender's ``PerspectiveCamera`` receives, in radians: the
  exact protocol uses π/3 (60°). ``--protocol reference`` uses the reference's camera table
  (:data:`REFERENCE_CAMERAS`, its ``evaluate/predefined_configs.py``: π/3 at 0.3 m, the cube
  and cylinder from 0.45 m with π/4), with which its evaluation code of 2023-04
  (``evaluate/main_render.py`` at commit 4cd4190) rendered every mesh; the released command line
  of 2023-06 (``evaluate/main_render.sh``) passes ``--fov 60`` instead, which pyrender reads
  as 60 *radians*: tan(30) = −6.4, a 162° field of view with the image turned by 180°
  (:data:`RELEASED_VIEWS`, ``--reference-views released``). The camera table gives depth PSNRs
  in the published range (docs/evaluation.md), the released one 10–20 dB above it.
* ``depth``: distance along the camera axis (m), 0 where no surface is hit (pyrender's
  convention); ``shaded``: ``|n · v|`` headlight Lambert shading in [0, 1] (v = view ray).
* PSNR over the whole stack of views (one MSE), SSIM averaged over views (scikit-image;
  optionally with torchmetrics' Gaussian window, as the reference). The exact protocol uses
  data range 1 on depth clipped to [0, 1] m; the reference's ``PeakSignalNoiseRatio()`` has no
  data range and takes it from its second argument (the reconstruction's depth images:
  max − min, the running minimum starting at 0): ``psnr(..., data_range=None)``.
* LPIPS (the reference's VGG LPIPS) is not computed: it needs PyTorch and VGG weights
  downloaded at run time (docs/evaluation.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

ZNEAR = 0.05      # pyrender's PerspectiveCamera default near plane (m)


@dataclass(frozen=True)
class Turntable:
    """Camera ring (module docstring): ``n_views`` azimuths, ``distance`` (m) from the origin,
    camera height ``elevation`` (m), look-at height ``look_height`` (m), vertical field of view
    ``yfov`` (radians, as pyrender reads it; tan(yfov/2) < 0 turns the image by 180°), square
    images of ``resolution`` pixels."""
    n_views: int = 10
    distance: float = 0.3
    elevation: float = 0.1
    look_height: float = 0.1
    yfov: float = float(np.pi / 3)
    resolution: int = 256

    def rays(self, views=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Origins [V*H*W, 3] (on the near plane), unit directions [V*H*W, 3], camera forward
        axes [V, 3] of the views ``views`` (indices into the ring; None: all, V = n_views)."""
        n, res = self.n_views, self.resolution
        idx = np.arange(n) if views is None else np.atleast_1d(np.asarray(views, dtype=np.int64))
        az = np.deg2rad(90.0 - idx * 360.0 / n)
        r = np.sqrt(max(self.distance ** 2 - self.elevation ** 2, 0.0))
        eye = np.stack([r * np.cos(az), r * np.sin(az), np.full(len(idx), self.elevation)], axis=1)
        target = np.array([0.0, 0.0, self.look_height])
        forward = target - eye
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
        right /= np.linalg.norm(right, axis=1, keepdims=True)
        true_up = np.cross(right, forward)
        half = np.tan(self.yfov / 2)
        s = (2 * (np.arange(res) + 0.5) / res - 1) * half
        u, v = np.meshgrid(s, -s, indexing="xy")  # row 0 = top of the picture
        d = (forward[:, None, None, :] + u[None, :, :, None] * right[:, None, None, :]
             + v[None, :, :, None] * true_up[:, None, None, :])
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        along = np.einsum("vhwk,vk->vhw", d, forward)
        o = eye[:, None, None, :] + d * (ZNEAR / along)[..., None]
        return o.reshape(-1, 3), d.reshape(-1, 3), forward


def render_views(mesh: trimesh.Trimesh, cams: Turntable = Turntable(),
                 views=None) -> dict[str, np.ndarray]:
    """Ray-cast depth and headlight-shaded images of ``mesh`` from the cameras ``views`` of
    ``cams`` (indices; None: every one): ``{'depth': [V, H, W] float32 (m), 'shaded':
    [V, H, W] float32 in [0, 1]}``."""
    n_views = cams.n_views if views is None else len(np.atleast_1d(views))
    shape = (n_views, cams.resolution, cams.resolution)
    if len(mesh.faces) == 0:
        return {"depth": np.zeros(shape, np.float32), "shaded": np.zeros(shape, np.float32)}
    from sonarsim import runtime
    mi = runtime.mitsuba()
    import drjit as dr

    verts = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    shape_mi = mi.Mesh("evaluated", int(len(verts)), int(len(faces)),
                       has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(shape_mi)
    params["vertex_positions"] = mi.Float(verts.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "mesh": shape_mi})

    o, d, forward = cams.rays(views)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    t = dr.select(valid, si.t, 0.0)
    cos = dr.select(valid, dr.abs(dr.dot(si.n, ray.d)), 0.0)
    fwd_cos = np.einsum("vhwk,vk->vhw", d.reshape(*shape, 3), forward)
    t_np = np.asarray(t, dtype=np.float64).reshape(shape)
    hit = np.asarray(valid, dtype=bool).reshape(shape)
    depth = np.where(hit, t_np * fwd_cos + ZNEAR, 0.0)
    return {"depth": depth.astype(np.float32),
            "shaded": np.asarray(cos, dtype=np.float32).reshape(shape)}


def psnr(reference: np.ndarray, test: np.ndarray, data_range: float | None = 1.0) -> float:
    """PSNR (dB) over a whole image stack; ``inf`` for identical stacks.

    ``data_range=None``: torchmetrics' ``PeakSignalNoiseRatio()`` without a range, as the
    reference calls it: max(test, 0) − min(test, 0) over the stack."""
    ref, tst = np.asarray(reference, np.float64), np.asarray(test, np.float64)
    if data_range is None:
        data_range = max(float(tst.max(initial=0.0)), 0.0) - min(float(tst.min(initial=0.0)), 0.0)
    mse = float(np.mean((ref - tst) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(data_range ** 2 / mse))


def ssim(reference: np.ndarray, test: np.ndarray, data_range: float = 1.0,
         gaussian: bool = False) -> float:
    """Mean SSIM over the views of [V, H, W] stacks (scikit-image).

    ``gaussian=False``: 7x7 uniform window (scikit-image's default); ``True``: 11x11
    Gaussian window of sigma 1.5 with population statistics, torchmetrics' default (the
    reference's image metrics, ``main_image_space_loss.py``).
    """
    from skimage.metrics import structural_similarity
    opts = ({"gaussian_weights": True, "sigma": 1.5, "use_sample_covariance": False}
            if gaussian else {})
    return float(np.mean([structural_similarity(r, t, data_range=data_range, **opts)
                          for r, t in zip(np.asarray(reference, np.float64),
                                          np.asarray(test, np.float64))]))


# The reference's cameras (evaluate/predefined_configs.py, get_camera_pose_dict; yfov in radians
# as pyrender takes it): distance from the origin (m), camera height, look-at height, yfov.
REFERENCE_CAMERAS = {
    "default": {"distance": 0.3, "elevation": 0.1, "look_height": 0.1, "yfov": float(np.pi / 3)},
    "xyz_dragon": {"distance": 0.35, "elevation": 0.1, "look_height": 0.1,
                   "yfov": float(np.pi / 3)},
    "lucy": {"distance": 0.25, "elevation": 0.1, "look_height": 0.1, "yfov": float(np.pi / 3)},
    "cube": {"distance": 0.45, "elevation": 0.21, "look_height": 0.07, "yfov": float(np.pi / 4)},
    "cylinder": {"distance": 0.45, "elevation": 0.1, "look_height": 0.1, "yfov": float(np.pi / 4)},
}
# The reference's ten views at 512² with its camera table's default (the paper-era renders)...
REFERENCE_VIEWS = Turntable(n_views=10, resolution=512, **REFERENCE_CAMERAS["default"])
# ... and with its released command line's "--fov 60", which pyrender reads as 60 radians.
RELEASED_VIEWS = Turntable(n_views=10, distance=0.3, elevation=0.1, look_height=0.1,
                           yfov=60.0, resolution=512)
from .evaluation_options import REFERENCE_VIEW_SETS  # noqa: E402 (re-exported)


def reference_views(shape: str | None, which: str = "paper") -> Turntable:
    """The reference protocol's cameras for the GT shape named ``shape`` (e.g. 'cube'; None
    or an unknown name: the table's default): ``which='paper'`` the camera table
    (:data:`REFERENCE_CAMERAS`), ``'released'`` the released command line's 60-rad views
    (the same for every shape)."""
    from sonarsim.errors import InputError
    if which not in REFERENCE_VIEW_SETS:
        raise InputError(f"reference views: choose one of {', '.join(REFERENCE_VIEW_SETS)}, "
                         f"got {which!r}")
    if which == "released":
        return RELEASED_VIEWS
    from dataclasses import replace
    return replace(REFERENCE_VIEWS, **REFERENCE_CAMERAS.get(str(shape), REFERENCE_CAMERAS["default"]))


def image_metrics(gt_mesh: trimesh.Trimesh, mesh: trimesh.Trimesh,
                  cams: Turntable = Turntable(), reference: bool = False) -> dict:
    """PSNR and SSIM of depth and shaded renders of ``mesh`` against ``gt_mesh``.

    ``reference=False`` (exact protocol): depth clipped to [0, 1] m, data range 1, SSIM with
    scikit-image's 7 × 7 window. ``reference=True`` (use ``cams=reference_views(shape)``): the
    reference's ``main_image_space_loss.py`` on depth images in metres, unclipped: PSNR with
    the data range of the reconstruction's images, SSIM with torchmetrics' Gaussian window and
    data range 1; the shaded images get the same treatment.
    """
    from dataclasses import astuple

    from .metrics import cached_gt
    ref = cached_gt("renders", gt_mesh, astuple(cams),            # once per GT and cameras
                    lambda: render_views(gt_mesh, cams))
    test = render_views(mesh, cams)
    out = {}
    for kind in ("depth", "shaded"):
        if reference:
            r, t = ref[kind], test[kind]
            out[f"psnr_{kind}"] = psnr(r, t, data_range=None)
            out[f"ssim_{kind}"] = ssim(r, t, gaussian=True)
        else:
            r, t = np.clip(ref[kind], 0, 1), np.clip(test[kind], 0, 1)
            out[f"psnr_{kind}"] = psnr(r, t)
            out[f"ssim_{kind}"] = ssim(r, t)
    return out
