"""Scene files: TOML descriptions of what the sonar looks at, turned into Mitsuba scenes.

A scene is a set of triangle-mesh objects (procedural shapes or mesh files) on an
optional ground plane, plus the rig's *scene box* (the region the crop window and the
reconstruction grid cover). All lengths are metres, z is up, the ground is z = 0.

File format (every key is optional unless marked)::

    name = "two spheres"            # free text
    description = "..."             # free text
    ground = true                   # default true; or a table:
    [ground]
    albedo = 1.0                    # Lambertian albedo in [0, 1] (reference: 1.0)
    size = [0.4, 0.4]               # x, y extent in m; centred on the box centre, at z = 0
    [box]                           # default SIM_BOX: x, y in [-0.2, 0.2], z in [0, 0.3]
    lo = [-0.2, -0.2, 0.0]
    hi = [0.2, 0.2, 0.3]

    [[object]]                      # any number of these
    shape = "sphere"                # "sphere" | "cube" | "cylinder"  (or `mesh`, not both)
    radius = 0.05                   # sphere, cylinder (m)
    size = 0.1                      # cube edge (m), or [sx, sy, sz]
    height = 0.2                    # cylinder, along z (m)
    center = [0, 0, 0.05]           # default: on the ground at the box centre
    subdivisions = 4                # sphere: icosphere level (5120 faces at 4)
    sections = 64                   # cylinder: facets around the axis
    mesh = "part.obj"               # .obj/.ply/.stl/.off/.glb/.gltf, relative to the TOML
    fit = false                     # mesh only: scale and place into the box (below)
    fit_fill = 0.6                  # mesh only: fraction of the box the fit may fill
    scale = 1.0                     # number or [sx, sy, sz], about the origin
    translate = [0, 0, 0]           # applied last
    albedo = 1.0                    # Lambertian albedo in [0, 1]
    normals = "auto"                # shading normals: "auto" | "file" | "smooth" | "flat"
    smooth = true                   # older spelling: true = "smooth", false = "flat"

Transform order per object: build (shape at `center`, or mesh as loaded) -> `fit` ->
`scale` -> `translate`.

**Fit rule** (``fit = true``): the mesh is scaled uniformly by
``fit_fill * min(box_extent / mesh_extent)`` over the three axes, then moved so its
axis-aligned bounding box is centred on the box centre in x and y and its lowest point is
at z = 0 (standing on the ground). With the default fill 0.6 the shared Stanford bunny gets
0.18 m tall in the simulation box, within 3 % of the reference's bunny (0.184 m).

**Mesh checks.** Missing, unreadable or empty files, point clouds / polylines (no
triangles) and non-finite vertices are errors (:class:`FormatError`). Polygons with more
than three corners are triangulated by the loader. Degenerate (zero-area) triangles are
dropped with a :class:`SceneWarning`; if nothing is left that is an error. Non-manifold
edges (shared by more than two triangles) and objects reaching outside the box or below
the ground give a :class:`SceneWarning`; open (non-watertight) meshes are accepted
silently, since the rendering only needs surfaces (the reference's own bunny is open).

Rendering: every object becomes a Mitsuba ``mesh`` with a two-sided ``diffuse`` BSDF with
reflectance = albedo; the ground is a ``rectangle`` with the same BSDF, as in the reference
renderer (twosided diffuse, reflectance 1). Shading normals (``normals``, docs/scenes.md):

* ``"file"``: the normals stored in the mesh file (OBJ ``vn``, PLY ``nx ny nz``), per
  triangle corner and normalised, as Mitsuba's own loaders (and so mitransient and the
  reference renderer) use them; an error for a file without normals or a procedural shape;
* ``"smooth"``: sonarsim's smoothed normals: area-weighted vertex normals that keep edges
  sharper than 30° (:func:`corner_normals`): a cube stays flat, a faceted sphere shades
  like a true sphere;
* ``"flat"``: the triangles' own (geometric) normals;
* ``"auto"`` (default): ``"file"`` when the mesh file has normals, else ``"smooth"``.

The geometry itself (and :meth:`SceneSpec.gt_mesh`) is always the triangle mesh as given.
"""
from __future__ import annotations

import importlib.resources
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from .errors import FormatError
from .geometry import SIM_BOX, SceneBox

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
SHAPES = ("sphere", "cube", "cylinder")
DEFAULT_FIT_FILL = 0.6
DEFAULT_GROUND_SIZE = (0.4, 0.4)
CREASE_ANGLE_DEG = 30.0
FILE_NORMALS_KEY = "sonarsim_file_normals"   # trimesh metadata: the file's corner normals

_TOP_KEYS = {"name", "description", "ground", "box", "object"}
_GROUND_KEYS = {"albedo", "size"}
_BOX_KEYS = {"lo", "hi"}
_COMMON_KEYS = {"name", "albedo", "scale", "translate", "smooth", "normals"}
NORMALS = ("auto", "file", "smooth", "flat")
_OBJECT_KEYS = {
    "sphere": _COMMON_KEYS | {"shape", "radius", "center", "subdivisions"},
    "cube": _COMMON_KEYS | {"shape", "size", "center"},
    "cylinder": _COMMON_KEYS | {"shape", "radius", "height", "center", "sections"},
    "mesh": _COMMON_KEYS | {"mesh", "fit", "fit_fill"},
}


class SceneWarning(UserWarning):
    """A scene is usable but probably not what was meant (bad mesh parts, object off the box)."""


@dataclass(frozen=True)
class Ground:
    """The ground plane: a Lambertian rectangle at z = 0, `size` = (x, y) extent in metres."""
    albedo: float = 1.0
    size: tuple[float, float] = DEFAULT_GROUND_SIZE


@dataclass(frozen=True)
class SceneObject:
    """One object: a triangle mesh in world coordinates (metres), its Lambertian albedo and
    its shading normals: ``normals`` is 'file', 'smooth' or 'flat' (resolved from 'auto');
    ``file_normals`` [F, 3, 3] the mesh file's unit normals per triangle corner (or None)."""
    label: str
    mesh: trimesh.Trimesh
    albedo: float = 1.0
    normals: str = "smooth"
    file_normals: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def smooth(self) -> bool:
        """Whether the shading normals are interpolated (not the flat triangle normals)."""
        return self.normals != "flat"


@dataclass(frozen=True)
class SceneSpec:
    """A parsed scene: objects, optional ground, scene box and where it came from."""
    objects: tuple[SceneObject, ...]
    ground: Ground | None = field(default_factory=Ground)
    box: SceneBox = SIM_BOX
    name: str = ""
    source: str = ""

    def gt_mesh(self) -> trimesh.Trimesh:
        """All objects merged into one mesh (no ground), world coordinates in metres."""
        if not self.objects:
            return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), int),
                                   process=False)
        return trimesh.util.concatenate([o.mesh for o in self.objects])

    def to_mitsuba(self):
        """Build the ``mi.Scene`` (needs :func:`sonarsim.runtime.mitsuba`)."""
        from . import runtime
        mi = runtime.mitsuba()
        items: dict[str, Any] = {"type": "scene"}
        for i, obj in enumerate(self.objects):
            items[f"object_{i}"] = _mitsuba_mesh(mi, f"object_{i}", obj)
        if self.ground is not None:
            cx, cy = (float(v) for v in self.box.center[:2])
            sx, sy = (float(v) / 2 for v in self.ground.size)
            items["ground"] = {
                "type": "rectangle",
                # The rectangle spans [-1, 1]^2 at z = 0 with normal +z.
                "to_world": mi.ScalarTransform4f().translate([cx, cy, 0.0]).scale([sx, sy, 1.0]),
                "bsdf": {"type": "twosided", "material": _diffuse(self.ground.albedo)},
            }
        return mi.load_dict(items)


def _diffuse(albedo: float) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "uniform", "value": float(albedo)}}


def _mitsuba_mesh(mi, name: str, obj: SceneObject):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "twosided", "material": _diffuse(obj.albedo)})
    if obj.normals == "file":
        faces = np.asarray(obj.mesh.faces)
        vertices = np.asarray(obj.mesh.vertices)[faces.ravel()]
        faces = np.arange(3 * len(faces)).reshape(-1, 3)
        normals = np.asarray(obj.file_normals).reshape(-1, 3)
    elif obj.normals == "smooth":
        vertices, faces, normals = corner_normals(obj.mesh)
    else:
        vertices, faces, normals = obj.mesh.vertices, obj.mesh.faces, None
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props,
                   has_vertex_normals=normals is not None, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(normals, np.float32).ravel())
    params.update()
    return mesh


def corner_normals(mesh: trimesh.Trimesh, crease_deg: float = CREASE_ANGLE_DEG
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth shading normals that keep creases: (vertices [3F, 3], faces [F, 3], normals [3F, 3]).

    Each triangle corner gets its own vertex; its normal is the area-weighted mean of the
    normals of the triangles around that vertex that deviate less than ``crease_deg`` from
    the corner's own triangle (so a cube stays flat and a cylinder keeps its rim).
    """
    faces = np.asarray(mesh.faces)
    face_normals = np.asarray(mesh.face_normals)
    weighted = face_normals * np.asarray(mesh.area_faces)[:, None]
    corner_vertex = faces.ravel()
    corner_face = np.repeat(np.arange(len(faces)), 3)
    vertex_faces = np.asarray(mesh.vertex_faces)                  # [V, D], -1 padded
    cos_crease = np.cos(np.radians(crease_deg)) - 1e-9
    normals = np.empty((len(corner_vertex), 3))
    for a in range(0, len(corner_vertex), 100_000):                 # bounded temporaries
        cf = corner_face[a:a + 100_000]
        around = vertex_faces[corner_vertex[a:a + 100_000]]
        valid = around >= 0
        around = np.where(valid, around, 0)
        same_side = np.einsum("cdk,ck->cd", face_normals[around], face_normals[cf])
        keep = valid & (same_side >= cos_crease)
        sums = np.einsum("cd,cdk->ck", keep.astype(float), weighted[around])
        length = np.linalg.norm(sums, axis=1, keepdims=True)
        normals[a:a + 100_000] = np.where(length > 0, sums / np.where(length > 0, length, 1.0),
                                          face_normals[cf])
    vertices = np.asarray(mesh.vertices)[corner_vertex]
    return vertices, np.arange(3 * len(faces)).reshape(-1, 3), normals


# ----------------------------------------------------------------------------- loading

def _shipped_dir():
    """The installed ``sonarsim.scenes`` package (a wheel install or the repository's scenes/)."""
    return importlib.resources.files("sonarsim.scenes")


def shipped_scenes() -> list[str]:
    """Names of the scenes shipped with sonarsim (usable wherever a scene file is)."""
    return sorted(p.name[:-5] for p in _shipped_dir().iterdir() if p.name.endswith(".toml"))


def resolve_scene_path(spec: str | Path) -> Path:
    """A TOML path as given, or the shipped scene of that name."""
    path = Path(spec)
    if path.suffix.lower() == ".toml" or path.exists() or len(path.parts) > 1:
        if not path.is_file():
            raise FormatError(f"{path}: scene file not found")
        return path
    shipped = _shipped_dir() / f"{spec}.toml"
    if shipped.is_file():
        return Path(str(shipped))
    raise FormatError(f"{spec}: no such scene file or shipped scene "
                      f"(shipped: {', '.join(shipped_scenes())})")


def load_scene(spec: str | Path) -> SceneSpec:
    """Parse a scene TOML file (path) or a shipped scene (name) into a :class:`SceneSpec`.

    Raises :class:`FormatError` naming the file and key for any problem in the file or
    in a mesh it references; warns with :class:`SceneWarning` (see module docstring).
    """
    path = resolve_scene_path(spec)
    _refuse_other_formats(path)
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        if _looks_like_xml(path):
            _refuse_other_formats(path, xml=True)
        raise FormatError(f"{path}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read: {exc.strerror}") from None
    return _parse(doc, _Ctx(path))


def _refuse_other_formats(path: Path, xml: bool = False) -> None:
    """A Mitsuba XML scene or a bare mesh given where a scene is expected: say what a
    scene is here instead of reporting a TOML syntax error."""
    suffix = path.suffix.lower()
    if xml or suffix == ".xml":
        raise FormatError(
            f"{path}: Mitsuba XML scenes are not a scene format here; a scene is a TOML file "
            f"(docs/scenes.md) or a shipped name ({', '.join(shipped_scenes())}): list the "
            "XML scene's meshes as [[object]] mesh = \"part.ply\" in a TOML scene")
    if suffix in MESH_SUFFIXES:
        raise FormatError(
            f"{path}: this is a mesh, not a scene; write a TOML scene with [[object]] "
            f"mesh = \"{path.name}\" (fit = true places it in the scene box), see docs/scenes.md")


def _looks_like_xml(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(256).lstrip().startswith(b"<")
    except OSError:
        return False


class _Ctx:
    """Error reporting context: the file being parsed."""

    def __init__(self, path: Path):
        self.path = path

    def error(self, key: str, msg: str) -> FormatError:
        return FormatError(f"{self.path}: {key}: {msg}")


def _parse(doc: dict, ctx: _Ctx) -> SceneSpec:
    _check_keys(doc, _TOP_KEYS, "", ctx)
    name = _string(doc, "name", "", ctx, "name") or ctx.path.stem
    _string(doc, "description", "", ctx, "description")
    box = _parse_box(doc.get("box"), ctx)
    ground = _parse_ground(doc.get("ground", True), ctx)
    raw_objects = doc.get("object", [])
    if not isinstance(raw_objects, list) or not all(isinstance(o, dict) for o in raw_objects):
        raise ctx.error("object", "must be an array of tables ([[object]])")
    objects = tuple(_parse_object(o, i, box, ctx) for i, o in enumerate(raw_objects))
    for obj in objects:
        _warn_outside_box(obj, box, ctx)
    return SceneSpec(objects=objects, ground=ground, box=box, name=name, source=str(ctx.path))


def _parse_box(raw: Any, ctx: _Ctx) -> SceneBox:
    if raw is None:
        return SIM_BOX
    if not isinstance(raw, dict):
        raise ctx.error("box", "must be a table with lo = [x, y, z] and hi = [x, y, z]")
    _check_keys(raw, _BOX_KEYS, "box.", ctx)
    for key in ("lo", "hi"):
        if key not in raw:
            raise ctx.error(f"box.{key}", "missing")
    lo = _vector(raw, "lo", 3, ctx, "box.lo")
    hi = _vector(raw, "hi", 3, ctx, "box.hi")
    if np.any(hi <= lo):
        raise ctx.error("box", f"hi must exceed lo on every axis (lo={lo.tolist()}, hi={hi.tolist()})")
    return SceneBox(lo, hi)


def _parse_ground(raw: Any, ctx: _Ctx) -> Ground | None:
    if isinstance(raw, bool):
        return Ground() if raw else None
    if not isinstance(raw, dict):
        raise ctx.error("ground", "must be true, false or a table")
    _check_keys(raw, _GROUND_KEYS, "ground.", ctx)
    albedo = _albedo(raw, ctx, "ground.albedo")
    size = _vector(raw, "size", 2, ctx, "ground.size", default=DEFAULT_GROUND_SIZE)
    if np.any(size <= 0):
        raise ctx.error("ground.size", f"must be positive (got {size.tolist()})")
    return Ground(albedo=albedo, size=(float(size[0]), float(size[1])))


def _parse_object(raw: dict, index: int, box: SceneBox, ctx: _Ctx) -> SceneObject:
    where = f"object[{index}]"
    has_shape, has_mesh = "shape" in raw, "mesh" in raw
    if has_shape == has_mesh:
        raise ctx.error(where, "needs exactly one of `shape` or `mesh`")
    if has_shape:
        kind = raw["shape"]
        if kind not in SHAPES:
            raise ctx.error(f"{where}.shape", f"must be one of {', '.join(SHAPES)} (got {kind!r})")
    else:
        kind = "mesh"
    _check_keys(raw, _OBJECT_KEYS[kind], f"{where}.", ctx)
    label = _string(raw, "name", "", ctx, f"{where}.name") or \
        (f"{where} ({kind})" if has_shape else f"{where} ({raw['mesh']})")
    albedo = _albedo(raw, ctx, f"{where}.albedo")
    smooth = raw.get("smooth")
    if smooth is not None and not isinstance(smooth, bool):
        raise ctx.error(f"{where}.smooth", "must be true or false")
    mode = raw.get("normals", "auto" if smooth is None else ("smooth" if smooth else "flat"))
    if "normals" in raw and smooth is not None:
        raise ctx.error(f"{where}.smooth", "give `normals` or the older `smooth`, not both")
    if mode not in NORMALS:
        raise ctx.error(f"{where}.normals", f"must be one of {', '.join(NORMALS)} (got {mode!r})")
    file_normals = None

    if kind == "mesh":
        mesh = _load_mesh_file(raw, where, ctx)
        file_normals = mesh.metadata.get(FILE_NORMALS_KEY)
        fit = raw.get("fit", False)
        if not isinstance(fit, bool):
            raise ctx.error(f"{where}.fit", "must be true or false")
        fill = _number(raw, "fit_fill", DEFAULT_FIT_FILL, ctx, f"{where}.fit_fill")
        if not 0 < fill <= 1:
            raise ctx.error(f"{where}.fit_fill", f"must be in (0, 1] (got {fill})")
        if fit:
            mesh = fit_to_box(mesh, box, fill)
    else:
        mesh = _build_shape(kind, raw, where, box, ctx)

    scale = raw.get("scale", 1.0)
    if isinstance(scale, (int, float)) and not isinstance(scale, bool):
        scale_vec = np.full(3, float(scale))
    else:
        scale_vec = _vector(raw, "scale", 3, ctx, f"{where}.scale")
    if not np.all(np.isfinite(scale_vec)) or np.any(scale_vec <= 0):
        raise ctx.error(f"{where}.scale", f"must be positive (got {np.asarray(scale).tolist()})")
    translate = _vector(raw, "translate", 3, ctx, f"{where}.translate", default=(0.0, 0.0, 0.0))
    vertices = mesh.vertices * scale_vec + translate
    mesh = trimesh.Trimesh(vertices=vertices, faces=mesh.faces, process=False)
    if mode == "file" and file_normals is None:
        raise ctx.error(f"{where}.normals", "'file' needs a mesh file with vertex normals "
                                            "(this object has none; use 'smooth' or 'flat')")
    if mode == "auto":
        mode = "file" if file_normals is not None else "smooth"
    if mode == "file":   # normals transform with the inverse transpose of the scale
        n = file_normals / scale_vec
        file_normals = n / np.linalg.norm(n, axis=-1, keepdims=True)
    else:
        file_normals = None
    return SceneObject(label=label, mesh=mesh, albedo=albedo, normals=mode,
                       file_normals=file_normals)


def fit_to_box(mesh: trimesh.Trimesh, box: SceneBox, fill: float = DEFAULT_FIT_FILL) -> trimesh.Trimesh:
    """Scale `mesh` uniformly to `fill` of the box (limiting axis) and stand it on z = 0.

    The result's bounding box is centred on the box centre in x, y; its minimum z is 0.
    """
    lo, hi = mesh.bounds
    extent = hi - lo
    box_extent = np.asarray(box.hi, float) - np.asarray(box.lo, float)
    with np.errstate(divide="ignore"):
        ratios = np.where(extent > 0, box_extent / np.where(extent > 0, extent, 1.0), np.inf)
    scale = fill * float(np.min(ratios))
    center_xy = (lo[:2] + hi[:2]) / 2
    target = np.asarray(box.center, float)
    offset = np.array([target[0] - scale * center_xy[0], target[1] - scale * center_xy[1],
                       -scale * lo[2]])
    return trimesh.Trimesh(vertices=mesh.vertices * scale + offset, faces=mesh.faces,
                           process=False)


def _build_shape(kind: str, raw: dict, where: str, box: SceneBox, ctx: _Ctx) -> trimesh.Trimesh:
    cx, cy = (float(v) for v in np.asarray(box.center)[:2])
    if kind == "sphere":
        radius = _positive(raw, "radius", ctx, f"{where}.radius")
        level = _integer(raw, "subdivisions", 4, 0, 7, ctx, f"{where}.subdivisions")
        center = _vector(raw, "center", 3, ctx, f"{where}.center", default=(cx, cy, radius))
        mesh = trimesh.creation.icosphere(subdivisions=level, radius=radius)
    elif kind == "cube":
        size = raw.get("size")
        if isinstance(size, (int, float)) and not isinstance(size, bool):
            size_vec = np.full(3, float(_positive(raw, "size", ctx, f"{where}.size")))
        elif size is None:
            raise ctx.error(f"{where}.size", "missing (edge length in m, or [sx, sy, sz])")
        else:
            size_vec = _vector(raw, "size", 3, ctx, f"{where}.size")
            if np.any(size_vec <= 0):
                raise ctx.error(f"{where}.size", f"must be positive (got {size_vec.tolist()})")
        center = _vector(raw, "center", 3, ctx, f"{where}.center", default=(cx, cy, size_vec[2] / 2))
        mesh = trimesh.creation.box(extents=size_vec)
    else:
        radius = _positive(raw, "radius", ctx, f"{where}.radius")
        height = _positive(raw, "height", ctx, f"{where}.height")
        sections = _integer(raw, "sections", 64, 3, 4096, ctx, f"{where}.sections")
        center = _vector(raw, "center", 3, ctx, f"{where}.center", default=(cx, cy, height / 2))
        mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    return trimesh.Trimesh(vertices=mesh.vertices + center, faces=mesh.faces, process=False)


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Load a triangle mesh file (metres) with the checks of the module docstring.

    Raises :class:`FormatError` ("<path>: <problem>"); warns with :class:`SceneWarning`.
    """
    path = Path(path)

    def fail(msg: str) -> FormatError:
        return FormatError(f"{path}: {msg}")

    if path.suffix.lower() not in MESH_SUFFIXES:
        raise fail(f"unsupported mesh format {path.suffix!r} (use {', '.join(MESH_SUFFIXES)})")
    if not path.is_file():
        raise fail("mesh file not found")
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # the loaders raise anything from IndexError to KeyError
        raise fail(f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        parts = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        if not parts:
            raise fail("contains no triangles (empty, or no faces)")
        loaded = trimesh.util.concatenate(parts)
    if not isinstance(loaded, trimesh.Trimesh):
        raise fail(f"contains no triangles (read as a {type(loaded).__name__})")
    if len(loaded.faces) == 0:
        raise fail("contains no triangles")
    vertices = np.asarray(loaded.vertices, float)
    faces = np.asarray(loaded.faces, np.int64)
    if not np.all(np.isfinite(vertices)):
        raise fail("has non-finite (NaN/inf) vertex coordinates")
    corners = vertices[faces]
    area2 = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                           axis=1)
    diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    good = area2 > 1e-12 * diag ** 2
    if not np.any(good):
        raise fail("all triangles are degenerate (zero area)")
    if not np.all(good):
        warnings.warn(f"{path}: dropped {int(np.sum(~good))} degenerate (zero-area) triangles "
                      f"of {len(faces)}", SceneWarning, stacklevel=2)
        faces = faces[good]
    normals = _file_vertex_normals(loaded)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    if normals is not None and len(mesh.faces) == len(faces):
        mesh.metadata[FILE_NORMALS_KEY] = normals[faces]          # [F, 3 corners, 3]
    _, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    n_nonmanifold = int(np.sum(counts > 2))
    if n_nonmanifold:
        warnings.warn(f"{path}: {n_nonmanifold} non-manifold edges (shared by more than two "
                      f"triangles)", SceneWarning, stacklevel=2)
    return mesh


def _file_vertex_normals(loaded: trimesh.Trimesh) -> np.ndarray | None:
    """The unit vertex normals [V, 3] stored in the mesh file, or None if it has none.

    trimesh keeps normals read from a file in its cache (it computes them only when asked),
    and its loaders split vertices whose corners carry different normals.
    """
    cache = getattr(getattr(loaded, "_cache", None), "cache", {})
    normals = cache.get("vertex_normals") if hasattr(cache, "get") else None
    if normals is None:
        return None
    normals = np.asarray(normals, float)
    if normals.shape != np.asarray(loaded.vertices).shape:
        return None
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if not np.all(np.isfinite(normals)) or np.any(length == 0):
        return None
    return normals / length


def _load_mesh_file(raw: dict, where: str, ctx: _Ctx) -> trimesh.Trimesh:
    name = raw["mesh"]
    if not isinstance(name, str) or not name:
        raise ctx.error(f"{where}.mesh", "must be a file name")
    path = Path(name).expanduser()
    if not path.is_absolute():
        path = ctx.path.parent / path
        if not path.exists():          # e.g. mesh = "bunny.obj": the mesh shipped with sonarsim
            from . import data
            shipped = data.find(name)
            if shipped is not None and shipped.suffix.lower() in MESH_SUFFIXES:
                path = shipped
    try:
        return load_mesh(path)
    except FormatError as exc:
        extra = ""
        if not path.exists():
            from . import data
            extra = f" (shipped meshes: {', '.join(data.mesh_names())})"
        raise ctx.error(f"{where}.mesh", f"{exc}{extra}") from None


def _warn_outside_box(obj: SceneObject, box: SceneBox, ctx: _Ctx) -> None:
    lo, hi = obj.mesh.bounds
    size = float(np.linalg.norm(hi - lo))
    tol = 1e-3 * size
    if lo[2] < -tol:
        warnings.warn(f"{ctx.path}: {obj.label} reaches below the ground (min z = {lo[2]:.4g} m)",
                      SceneWarning, stacklevel=4)
    if np.any(lo < np.asarray(box.lo) - tol) or np.any(hi > np.asarray(box.hi) + tol):
        warnings.warn(f"{ctx.path}: {obj.label} extends outside the scene box "
                      f"(object {np.round(lo, 4).tolist()}..{np.round(hi, 4).tolist()}, "
                      f"box {np.asarray(box.lo).tolist()}..{np.asarray(box.hi).tolist()}); "
                      f"echoes from outside the box may fall outside the crop window",
                      SceneWarning, stacklevel=4)


# ----------------------------------------------------------------------------- value checks

def _check_keys(table: dict, allowed: set[str], prefix: str, ctx: _Ctx) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ctx.error(prefix + unknown[0], f"unknown key (allowed here: {', '.join(sorted(allowed))})")


def _string(table: dict, key: str, default: str, ctx: _Ctx, where: str) -> str:
    value = table.get(key, default)
    if not isinstance(value, str):
        raise ctx.error(where, f"must be a string (got {value!r})")
    return value


def _number(table: dict, key: str, default: float | None, ctx: _Ctx, where: str) -> float:
    value = table.get(key, default)
    if value is None:
        raise ctx.error(where, "missing")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ctx.error(where, f"must be a finite number (got {value!r})")
    return float(value)


def _positive(table: dict, key: str, ctx: _Ctx, where: str) -> float:
    value = _number(table, key, None, ctx, where)
    if value <= 0:
        raise ctx.error(where, f"must be positive (got {value})")
    return value


def _integer(table: dict, key: str, default: int, lo: int, hi: int, ctx: _Ctx, where: str) -> int:
    value = table.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ctx.error(where, f"must be an integer in [{lo}, {hi}] (got {value!r})")
    return value


def _albedo(table: dict, ctx: _Ctx, where: str) -> float:
    value = _number(table, "albedo", 1.0, ctx, where)
    if not 0 <= value <= 1:
        raise ctx.error(where, f"must be in [0, 1] (got {value})")
    return value


def _vector(table: dict, key: str, n: int, ctx: _Ctx, where: str, default=None) -> np.ndarray:
    value = table.get(key, default)
    if value is None:
        raise ctx.error(where, "missing")
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not all(np.isfinite(v) for v in value)):
        raise ctx.error(where, f"must be a list of {n} finite numbers (got {value!r})")
    return np.asarray(value, dtype=float)
