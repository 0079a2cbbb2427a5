"""Depth and shaded renders of meshes around a turntable, and image metrics (PSNR, SSIM).

The reference renders with pyrender (OpenGL; reference code ``evaluate/``); here a pinhole
camera grid is ray cast with Mitsuba's ``scene.ray_intersect`` on the CPU variant, so no
OpenGL or RGB variant is needed.

* Cameras: ``n_views`` azimuths 0°, 360°/n, ... at distance 0.3 m from the z axis and
  height 0.1 m, looking horizontally at (0, 0, 0.1); vertical field of view 60°. (The
  reference's CLI passes "60" to pyrender as *radians*; its intended value is π/3 = 60°,
  which is used here.)
* ``depth``: distance along the camera axis (m), 0 where no surface is hit (pyrender's
  convention); the reference compares depth images with data_range 1, i.e. metres.
* ``shaded``: ``|n · v|`` headlight Lambert shading in [0, 1] (v = view ray), 0 for the
  background.
* PSNR over the whole stack of views (one MSE), SSIM averaged over views, both with
  data range 1 (scikit-image; optionally with torchmetrics' Gaussian window, as the reference).
* LPIPS (the reference's VGG LPIPS) is not computed: it needs PyTorch and VGG weights
  downloaded at run time (docs/evaluation.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True)
class Turntable:
    """Camera ring: ``n_views`` azimuths, ``distance`` (m) from the z axis, ``height`` (m),
    vertical ``fov_deg``, square images of ``resolution`` pixels."""
    n_views: int = 10
    distance: float = 0.3
    height: float = 0.1
    fov_deg: float = 60.0
    resolution: int = 256

    def rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Origins [V*H*W, 3], unit directions [V*H*W, 3], camera forward axes [V, 3]."""
        n, res = self.n_views, self.resolution
        az = np.deg2rad(np.arange(n) * 360.0 / n)
        eye = np.stack([self.distance * np.cos(az), self.distance * np.sin(az),
                        np.full(n, self.height)], axis=1)
        forward = -eye * np.array([1.0, 1.0, 0.0])
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        up = np.array([0.0, 0.0, 1.0])
        right = np.cross(forward, up)
        right /= np.linalg.norm(right, axis=1, keepdims=True)
        true_up = np.cross(right, forward)
        half = np.tan(np.deg2rad(self.fov_deg) / 2)
        s = (2 * (np.arange(res) + 0.5) / res - 1) * half
        u, v = np.meshgrid(s, -s, indexing="xy")  # row 0 = top of the picture
        d = (forward[:, None, None, :] + u[None, :, :, None] * right[:, None, None, :]
             + v[None, :, :, None] * true_up[:, None, None, :])
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(eye[:, None, None, :], d.shape)
        return o.reshape(-1, 3), d.reshape(-1, 3), forward


def render_views(mesh: trimesh.Trimesh, cams: Turntable = Turntable()) -> dict[str, np.ndarray]:
    """Ray-cast depth and headlight-shaded images of ``mesh`` from every camera of ``cams``:
    ``{'depth': [V, H, W] float32 (m), 'shaded': [V, H, W] float32 in [0, 1]}``."""
    shape = (cams.n_views, cams.resolution, cams.resolution)
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

    o, d, forward = cams.rays()
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    t = dr.select(valid, si.t, 0.0)
    cos = dr.select(valid, dr.abs(dr.dot(si.n, ray.d)), 0.0)
    t_np = np.asarray(t, dtype=np.float64).reshape(shape)
    fwd_cos = np.einsum("vhwk,vk->vhw", d.reshape(*shape, 3), forward)
    return {"depth": (t_np * fwd_cos).astype(np.float32),
            "shaded": np.asarray(cos, dtype=np.float32).reshape(shape)}


def psnr(reference: np.ndarray, test: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR (dB) over a whole image stack; ``inf`` for identical stacks."""
    mse = float(np.mean((np.asarray(reference, np.float64) - np.asarray(test, np.float64)) ** 2))
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


REFERENCE_VIEWS = Turntable(n_views=10, distance=0.3, height=0.1, fov_deg=60.0, resolution=512)


def image_metrics(gt_mesh: trimesh.Trimesh, mesh: trimesh.Trimesh,
                  cams: Turntable = Turntable(), gaussian_ssim: bool = False) -> dict:
    """PSNR and SSIM of depth and shaded renders of ``mesh`` against ``gt_mesh``.

    The reference's protocol uses ``cams=REFERENCE_VIEWS`` (its 10 views at 512²) and
    ``gaussian_ssim=True`` (torchmetrics' SSIM window).
    """
    ref, test = render_views(gt_mesh, cams), render_views(mesh, cams)
    out = {}
    for kind in ("depth", "shaded"):
        r, t = np.clip(ref[kind], 0, 1), np.clip(test[kind], 0, 1)
        out[f"psnr_{kind}"] = psnr(r, t)
        out[f"ssim_{kind}"] = ssim(r, t, gaussian=gaussian_ssim)
    return out
