"""Scene files: parsing, shipped scenes, mesh checks, the fit rule, Mitsuba conversion."""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sonarsim.errors import FormatError
from sonarsim.geometry import SIM_BOX, SceneBox
from sonarsim.scene import SceneWarning, fit_to_box, load_mesh, load_scene, shipped_scenes


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_shipped_scenes_load_inside_box():
    names = shipped_scenes()
    assert {"sphere", "cube", "cylinder", "tabletop"} <= set(names)
    for name in names:
        with warnings.catch_warnings():
            warnings.simplefilter("error", SceneWarning)  # shipped scenes must be clean
            spec = load_scene(name)
        assert spec.ground is not None
        if spec.objects:
            lo, hi = spec.gt_mesh().bounds
            assert np.all(lo >= SIM_BOX.lo - 1e-9) and np.all(hi <= SIM_BOX.hi + 1e-9)
    assert len(load_scene("tabletop").objects) >= 3


def test_sphere_geometry_closed_form(tmp_path):
    spec = load_scene(write(tmp_path, """
        ground = false
        [[object]]
        shape = "sphere"
        radius = 0.04
        center = [0.01, -0.02, 0.1]
        albedo = 0.5
    """))
    assert spec.ground is None and spec.box == SIM_BOX
    (obj,) = spec.objects
    assert obj.albedo == 0.5
    r = np.linalg.norm(obj.mesh.vertices - [0.01, -0.02, 0.1], axis=1)
    np.testing.assert_allclose(r, 0.04, rtol=1e-12)
    # icosphere level 4: area within 0.3 % of 4 pi R^2
    assert obj.mesh.area == pytest.approx(4 * np.pi * 0.04 ** 2, rel=3e-3)


def test_shape_defaults_stand_on_ground_and_transforms(tmp_path):
    spec = load_scene(write(tmp_path, """
        [ground]
        albedo = 0.25
        size = [0.6, 0.5]
        [box]
        lo = [-0.3, -0.3, 0.0]
        hi = [0.3, 0.3, 0.4]
        [[object]]
        shape = "cube"
        size = [0.1, 0.2, 0.3]
        [[object]]
        shape = "cylinder"
        radius = 0.02
        height = 0.1
        scale = 2
        translate = [0.1, 0.0, 0.0]
    """))
    assert spec.ground.albedo == 0.25 and spec.ground.size == (0.6, 0.5)
    assert spec.box == SceneBox((-0.3, -0.3, 0.0), (0.3, 0.3, 0.4))
    cube, cyl = (o.mesh for o in spec.objects)
    np.testing.assert_allclose(cube.bounds, [[-0.05, -0.1, 0.0], [0.05, 0.1, 0.3]], atol=1e-12)
    assert cube.volume == pytest.approx(0.1 * 0.2 * 0.3)
    # cylinder built at [0, 0, 0.05], scaled x2 about the origin, then moved +0.1 in x
    np.testing.assert_allclose(cyl.bounds, [[0.06, -0.04, 0.0], [0.14, 0.04, 0.2]], atol=1e-12)
    gt = spec.gt_mesh()
    assert len(gt.faces) == len(cube.faces) + len(cyl.faces)


def test_fit_rule_scales_and_stands_mesh(tmp_path):
    # a 2 x 1 x 4 box mesh, off-centre and floating: the limiting axis is z (0.3 / 4)
    raw = trimesh.creation.box(extents=[2.0, 1.0, 4.0])
    raw.apply_translation([5.0, -3.0, 7.0])
    raw.export(tmp_path / "part.stl")
    spec = load_scene(write(tmp_path, """
        [[object]]
        mesh = "part.stl"
        fit = true
    """))
    s = 0.6 * 0.3 / 4.0
    lo, hi = spec.objects[0].mesh.bounds
    np.testing.assert_allclose(hi - lo, [2 * s, 1 * s, 4 * s], rtol=1e-12)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, [0.0, 0.0], atol=1e-12)
    assert lo[2] == pytest.approx(0.0, abs=1e-12)
    # fit_fill and a box whose x is limiting; shape relations preserved (uniform scale)
    fitted = fit_to_box(raw, SceneBox((1.0, 1.0, 0.0), (1.5, 9.0, 9.0)), fill=0.5)
    lo, hi = fitted.bounds
    np.testing.assert_allclose(hi - lo, np.array([2.0, 1.0, 4.0]) * 0.5 * 0.5 / 2.0, rtol=1e-12)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, [1.25, 5.0], atol=1e-12)


def test_fit_bunny_like_reference(shared_data, tmp_path):
    path = write(tmp_path, f'[[object]]\nmesh = "{shared_data / "meshes" / "bunny.obj"}"\nfit = true\n')
    lo, hi = load_scene(path).gt_mesh().bounds
    assert hi[2] - lo[2] == pytest.approx(0.18, rel=1e-9)      # 0.6 of the 0.3 m box height
    assert hi[2] == pytest.approx(0.1844, rel=0.03)             # the reference bunny's height


def test_mesh_formats_and_relative_paths(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    mesh.apply_translation([0, 0, 0.05])
    (tmp_path / "sub").mkdir()
    for ext in ("obj", "ply", "stl", "glb"):
        mesh.export(tmp_path / "sub" / f"ball.{ext}")
        spec = load_scene(write(tmp_path / "sub", f'[[object]]\nmesh = "ball.{ext}"\n'))
        np.testing.assert_allclose(spec.objects[0].mesh.bounds, mesh.bounds, atol=1e-6)
        assert len(spec.objects[0].mesh.faces) == len(mesh.faces)


def test_quads_are_triangulated(tmp_path):
    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3 4\n")
    mesh = load_mesh(tmp_path / "quad.obj")
    assert len(mesh.faces) == 2 and mesh.area == pytest.approx(0.01)


@pytest.mark.parametrize("content, message", [
    ("", "no triangles"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n", "no triangles"),
    ("v 0 0 0\nv 1 0 0\nf 1 2 7\n", "cannot read mesh"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate"),
    ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "non-finite"),
])
def test_broken_meshes_name_file_and_key(tmp_path, content, message):
    (tmp_path / "m.obj").write_text(content)
    scene = write(tmp_path, '[[object]]\nmesh = "m.obj"\n')
    with pytest.raises(FormatError, match=message) as info:
        load_scene(scene)
    text = str(info.value)
    assert str(scene) in text and "object[0].mesh" in text and "m.obj" in text
    assert "\n" not in text


def test_missing_and_unsupported_mesh(tmp_path):
    with pytest.raises(FormatError, match=r"object\[0\]\.mesh.*not found"):
        load_scene(write(tmp_path, '[[object]]\nmesh = "nowhere.obj"\n'))
    (tmp_path / "m.xyz").write_text("1 2 3\n")
    with pytest.raises(FormatError, match="unsupported mesh format"):
        load_scene(write(tmp_path, '[[object]]\nmesh = "m.xyz"\n'))


def test_degenerate_triangles_dropped_with_warning(tmp_path):
    (tmp_path / "m.obj").write_text(
        "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0.2 0 0\nf 1 2 3\nf 1 2 4\n")
    with pytest.warns(SceneWarning, match="dropped 1 degenerate"):
        mesh = load_mesh(tmp_path / "m.obj")
    assert len(mesh.faces) == 1


def test_non_manifold_warns(tmp_path):
    # three triangles sharing the edge (0,0,0)-(0.1,0,0)
    (tmp_path / "fan.obj").write_text(
        "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 -0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 2 5\n")
    with pytest.warns(SceneWarning, match="non-manifold"):
        load_mesh(tmp_path / "fan.obj")


def test_object_outside_box_warns(tmp_path):
    with pytest.warns(SceneWarning, match="outside the scene box"):
        load_scene(write(tmp_path, '[[object]]\nshape = "sphere"\nradius = 0.05\n'
                                   'center = [0.3, 0, 0.1]\n'))
    with pytest.warns(SceneWarning, match="below the ground"):
        load_scene(write(tmp_path, '[box]\nlo = [-0.2, -0.2, -0.1]\nhi = [0.2, 0.2, 0.2]\n'
                                   '[[object]]\nshape = "sphere"\nradius = 0.05\n'
                                   'center = [0, 0, 0.0]\n'))


@pytest.mark.parametrize("text, key", [
    ("colour = 1\n", "colour"),
    ("ground = 3\n", "ground"),
    ("[ground]\nalbedo = 2.0\n", "ground.albedo"),
    ("[ground]\nsize = [0.4]\n", "ground.size"),
    ("[ground]\nheight = 1\n", "ground.height"),
    ("[box]\nlo = [0, 0, 0]\nhi = [1, 1, 0]\n", "box"),
    ("[box]\nlo = [0, 0, 0]\n", "box.hi"),
    ("[[object]]\nshape = \"cone\"\n", "object[0].shape"),
    ("[[object]]\nradius = 1\n", "object[0]"),
    ("[[object]]\nshape = \"sphere\"\nmesh = \"a.obj\"\n", "object[0]"),
    ("[[object]]\nshape = \"sphere\"\n", "object[0].radius"),
    ("[[object]]\nshape = \"sphere\"\nradius = \"big\"\n", "object[0].radius"),
    ("[[object]]\nshape = \"sphere\"\nradius = -1\n", "object[0].radius"),
    ("[[object]]\nshape = \"sphere\"\nradius = 0.1\ncenter = [0, 0]\n", "object[0].center"),
    ("[[object]]\nshape = \"sphere\"\nradius = 0.1\nsize = 2\n", "object[0].size"),
    ("[[object]]\nshape = \"sphere\"\nradius = 0.1\nfit = true\n", "object[0].fit"),
    ("[[object]]\nshape = \"cube\"\nsize = [1, -1, 1]\n", "object[0].size"),
    ("[[object]]\nshape = \"cube\"\nsize = 0.1\nalbedo = true\n", "object[0].albedo"),
    ("[[object]]\nshape = \"cylinder\"\nradius = 0.1\n", "object[0].height"),
    ("[[object]]\nshape = \"cylinder\"\nradius = 0.1\nheight = 0.1\nsections = 2\n",
     "object[0].sections"),
    ("[[object]]\nshape = \"cube\"\nsize = 0.1\nscale = [1, 0, 1]\n", "object[0].scale"),
    ("[[object]]\nshape = \"cube\"\nsize = 0.1\n[[object]]\nshape = \"cube\"\nsize = 0.1\n"
     "translate = \"up\"\n", "object[1].translate"),
    ("object = 5\n", "object"),
    ("this is = not toml\n", "not valid TOML"),
])
def test_bad_scene_files_raise_one_line_with_key(tmp_path, text, key):
    path = write(tmp_path, text)
    with pytest.raises(FormatError) as info:
        load_scene(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and key in message and "\n" not in message


def test_unknown_scene_name_lists_shipped():
    with pytest.raises(FormatError, match="shipped: .*sphere"):
        load_scene("no_such_scene")
    with pytest.raises(FormatError, match="not found"):
        load_scene("missing/dir/scene.toml")


def test_to_mitsuba_geometry_and_albedo(mi, tmp_path):
    spec = load_scene(write(tmp_path, """
        [ground]
        albedo = 0.5
        size = [0.4, 0.2]
        [[object]]
        shape = "cube"
        size = 0.1
        center = [0.0, 0.0, 0.1]
        albedo = 0.7
    """))
    scene = spec.to_mitsuba()
    assert len(scene.shapes()) == 2
    bbox = scene.bbox()
    np.testing.assert_allclose([bbox.min.x, bbox.min.y, bbox.max.x, bbox.max.y, bbox.max.z],
                               [-0.2, -0.1, 0.2, 0.1, 0.15], atol=1e-6)

    def hit(x, y, z_start, direction):
        ray = mi.Ray3f(mi.Point3f(x, y, z_start), mi.Vector3f(0, 0, direction))
        si = scene.ray_intersect(ray)
        albedo = np.asarray(si.bsdf().eval_diffuse_reflectance(si)).ravel()
        return float(si.t[0]), float(albedo[0])

    t, albedo = hit(0.0, 0.0, 1.0, -1.0)          # top of the cube at z = 0.15
    assert t == pytest.approx(0.85, abs=1e-5) and albedo == pytest.approx(0.7)
    t, albedo = hit(0.15, 0.0, 1.0, -1.0)         # ground
    assert t == pytest.approx(1.0, abs=1e-5) and albedo == pytest.approx(0.5)
    t, albedo = hit(0.0, 0.0, 0.1, 1.0)           # from inside the cube: two-sided surface
    assert t == pytest.approx(0.05, abs=1e-5) and albedo == pytest.approx(0.7)
    t, _ = hit(0.0, 0.15, 1.0, -1.0)              # beyond the 0.2 m ground in y: miss
    assert not np.isfinite(t)


def test_smooth_shading_normals_keep_creases(mi, tmp_path):
    spec = load_scene(write(tmp_path, """
        ground = false
        [[object]]
        shape = "sphere"
        radius = 0.05
        center = [0.0, 0.0, 0.1]
        subdivisions = 2
        [[object]]
        shape = "cube"
        size = 0.04
        center = [0.12, 0.0, 0.1]
        [[object]]
        shape = "sphere"
        radius = 0.02
        center = [-0.12, 0.0, 0.1]
        subdivisions = 2
        smooth = false
    """))
    scene = spec.to_mitsuba()
    rng = np.random.default_rng(1)

    def normals_at(x0, y0, z0, spread):
        n = 200
        origin = np.array([x0, y0, z0]) + np.c_[rng.uniform(-spread, spread, (n, 2)), np.zeros(n)]
        ray = mi.Ray3f(mi.Point3f(*(origin[:, i] for i in range(3))), mi.Vector3f(0, 0, -1))
        si = scene.ray_intersect(ray)
        points = np.array([np.asarray(si.p.x), np.asarray(si.p.y), np.asarray(si.p.z)]).T
        shading = np.array([np.asarray(c) for c in si.sh_frame.n]).T
        geometric = np.array([np.asarray(c) for c in si.n]).T
        return points, shading, geometric

    def angle_deg(a, b):
        return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))

    p, sh, geo = normals_at(0.0, 0.0, 1.0, 0.03)                # smooth sphere
    radial = (p - [0, 0, 0.1]) / np.linalg.norm(p - [0, 0, 0.1], axis=1, keepdims=True)
    smooth_err, flat_err = angle_deg(sh, radial), angle_deg(geo, radial)
    assert smooth_err.max() < 2.0 and smooth_err.mean() < 0.25 * flat_err.mean()
    assert np.all(np.sum(sh * geo, axis=1) > 0.95)    # same side as the geometric normal
    p, sh, geo = normals_at(0.12, 0.0, 1.0, 0.019)              # cube: flat despite smoothing
    np.testing.assert_allclose(sh, [[0, 0, 1]] * len(sh), atol=1e-6)
    p, sh, geo = normals_at(-0.12, 0.0, 1.0, 0.012)             # smooth = false: face normals
    np.testing.assert_allclose(sh, geo, atol=1e-6)


PLATE_OBJ = """v -0.05 -0.05 0.1
v 0.05 -0.05 0.1
v 0.05 0.05 0.1
v -0.05 0.05 0.1
vn -0.6 0.0 0.8
vn 0.6 0.0 0.8
vn 0.6 0.0 0.8
vn -1.2 0.0 1.6
f 1//1 2//2 3//3
f 1//1 3//3 4//4
"""


@pytest.mark.parametrize("mode", ["auto", "file", "smooth", "flat"])
def test_normals_option(mi, tmp_path, mode):
    """A flat plate whose file normals tilt ±37° about y: 'file' (and 'auto') interpolate
    the file's normals (normalised, and transformed by a non-uniform scale), 'smooth' and
    'flat' give the plate's own normal +z."""
    (tmp_path / "plate.obj").write_text(PLATE_OBJ)
    spec = load_scene(write(tmp_path, f"""
        ground = false
        [[object]]
        mesh = "plate.obj"
        scale = [2.0, 1.0, 1.0]
        translate = [0.0, 0.0, -0.1]
        normals = "{mode}"
    """))
    obj = spec.objects[0]
    assert obj.normals == ("file" if mode == "auto" else mode)
    scene = spec.to_mitsuba()
    x = np.array([-0.09, -0.05, 0.0, 0.05, 0.09])
    ray = mi.Ray3f(mi.Point3f(x, np.zeros(5) - 0.02, np.ones(5)), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    shading = np.array([np.asarray(c) for c in si.sh_frame.n]).T
    if obj.normals == "file":
        # Corner normals (±0.6, 0, 0.8) (one given unnormalised) -> scaled by 1/[2, 1, 1]
        # -> (±0.3, 0, 0.8)/|.|, interpolated across the plate from left to right.
        left, right = np.array([-0.3, 0, 0.8]), np.array([0.3, 0, 0.8])
        left, right = left / np.linalg.norm(left), right / np.linalg.norm(right)
        assert shading[0, 0] < -0.3 and shading[-1, 0] > 0.3        # tilted at the edges
        np.testing.assert_allclose(shading[0], left, atol=0.06)
        np.testing.assert_allclose(shading[-1], right, atol=0.06)
        np.testing.assert_allclose(np.linalg.norm(shading, axis=1), 1.0, atol=1e-5)
    else:
        np.testing.assert_allclose(np.abs(shading), [[0, 0, 1]] * 5, atol=1e-6)


def test_normals_option_errors(tmp_path):
    with pytest.raises(FormatError, match="normals"):
        load_scene(write(tmp_path, '[[object]]\nshape = "sphere"\nradius = 0.05\nnormals = "file"\n'))
    with pytest.raises(FormatError, match="normals"):
        load_scene(write(tmp_path, '[[object]]\nshape = "sphere"\nradius = 0.05\nnormals = "round"\n'))
    with pytest.raises(FormatError, match="not both"):
        load_scene(write(tmp_path, '[[object]]\nshape = "sphere"\nradius = 0.05\n'
                                   'normals = "flat"\nsmooth = true\n'))
    assert load_scene(write(tmp_path, '[[object]]\nshape = "sphere"\nradius = 0.05\n'
                                      'smooth = false\n')).objects[0].normals == "flat"


# ------------------------------------------------- issue 24: the docs' keys block, other formats

def test_keys_block_of_the_docs_is_a_scene_that_loads(tmp_path):
    import tomllib
    text = (Path(__file__).resolve().parents[1] / "docs" / "scenes.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert blocks
    for block in blocks:
        tomllib.loads(block)                                 # every TOML block parses as copied
    keys = next(b for b in blocks if 'mesh = "part.obj"' in b)
    trimesh.creation.box(extents=[1.0, 2.0, 0.5]).export(tmp_path / "part.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneWarning)          # and it is a clean scene
        spec = load_scene(write(tmp_path, keys))
    assert spec.name == "my scene" and spec.ground.albedo == 1.0
    cylinder, part = spec.objects
    lo, hi = cylinder.mesh.bounds
    assert np.allclose([lo[2], hi[2]], [0.0, 0.2]) and np.isclose(hi[0] - lo[0], 0.06, rtol=1e-3)
    lo, hi = part.mesh.bounds                                 # fitted: 0.3 * 0.4 m along y
    assert np.isclose(hi[1] - lo[1], 0.12) and np.isclose(lo[2], 0.0) and part.albedo == 0.5
    assert np.isclose((lo[0] + hi[0]) / 2, -0.08)


@pytest.mark.parametrize("name, text, message", [
    ("scene.xml", '<scene version="3.0.0"><shape type="ply"/></scene>',
     "Mitsuba XML scenes are not a scene format here; a scene is a TOML file"),
    ("scene.toml", '<?xml version="1.0"?>\n<scene version="3.0.0"/>',
     "Mitsuba XML scenes are not a scene format here"),
    ("bunny.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
     'this is a mesh, not a scene; write a TOML scene with [[object]] mesh = "bunny.obj"'),
])
def test_other_formats_given_as_a_scene_say_what_a_scene_is(tmp_path, name, text, message):
    with pytest.raises(FormatError, match=re.escape(message)):
        load_scene(write(tmp_path, text, name))


def test_a_mesh_name_finds_the_shipped_mesh_unless_a_file_is_next_to_the_scene(tmp_path):
    scene = write(tmp_path, '[[object]]\nmesh = "bunny.obj"\nfit = true\n')
    assert len(load_scene(scene).objects[0].mesh.faces) == 4968       # the reference's bunny
    trimesh.creation.box(extents=[0.1, 0.1, 0.1]).export(tmp_path / "bunny.obj")
    assert len(load_scene(scene).objects[0].mesh.faces) == 12         # the file next to it
    with pytest.raises(FormatError, match=r"object\[0\]\.mesh: .*\(shipped meshes: bunny\.obj"):
        load_scene(write(tmp_path, '[[object]]\nmesh = "rabbit.obj"\n'))
