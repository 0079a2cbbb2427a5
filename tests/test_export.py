"""Tests of recon.export and `recon export`: normalisation, iso-surface in world
coordinates, MIPs (PNG/EXR), slices, degenerate volumes."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from recon import export
from sonarsim.errors import InputError

# Anisotropic, off-centre grid: catches swapped axes, /n instead of /(n-1), and a
# padding offset left in the vertex mapping (reference code evaluate/ quirks).
BOUNDS = np.array([[-0.1, 0.1], [-0.05, 0.15], [0.0, 0.3]])
SHAPE = (41, 31, 51)
CENTRE = np.array([0.01, 0.04, 0.12])
RADIUS = 0.05


def radial(shape=SHAPE, bounds=BOUNDS, centre=CENTRE):
    x, y, z = np.meshgrid(*export.voxel_axes(bounds, shape), indexing="ij")
    return np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2)


def cone(radius=RADIUS, **kw):
    """Magnitude 1 - r/(2R), clipped at 0: equals 0.5 exactly on the sphere r = R."""
    return np.clip(1.0 - radial(**kw) / (2 * radius), 0.0, 1.0).astype(np.float32)


def test_normalisation_minmax_max_and_constant():
    v = np.array([1 + 1j, 3, -5j, 2j], dtype=np.complex64).reshape(1, 2, 2) * 1.0
    mm = export.normalized_magnitude(v, "minmax")
    assert mm.min() == 0 and mm.max() == pytest.approx(1.0)
    assert mm.ravel()[3] == pytest.approx((2 - np.sqrt(2)) / (5 - np.sqrt(2)), rel=1e-6)
    mx = export.normalized_magnitude(v, "max")
    assert mx.ravel()[1] == pytest.approx(3 / 5, rel=1e-6)
    assert not export.normalized_magnitude(np.full((3, 3, 3), 2.0 + 0j)).any()
    assert not export.normalized_magnitude(np.zeros((3, 3, 3), np.complex64)).any()
    with pytest.raises(InputError):
        export.normalized_magnitude(np.full((2, 2, 2), np.nan))
    with pytest.raises(InputError):
        export.normalized_magnitude(v, "l2")
    with pytest.raises(InputError):
        export.check_threshold(1.0)


def test_voxel_spacing_conventions():
    assert np.allclose(export.voxel_spacing(BOUNDS, SHAPE), [0.2 / 40, 0.2 / 30, 0.3 / 50])
    one_z = np.array([[0, 0.1], [0, 0.2], [0.05, 0.05]])
    assert np.allclose(export.voxel_spacing(one_z, (11, 11, 1)), [0.01, 0.02, 0.01])
    with pytest.raises(InputError):
        export.voxel_spacing(one_z, (1, 1, 1))
    with pytest.raises(InputError):  # several voxels but an empty range
        export.voxel_spacing(np.array([[0, 0], [0, 1], [0, 1]]), (3, 3, 3))


def test_occupied_points_are_the_centres_strictly_above_the_threshold():
    """The Chamfer's point set: voxel centres with magnitude > τ (a voxel at τ is out, as in
    the evaluation's cached sweep, ``mag > t``), in world metres."""
    mag = np.zeros((3, 2, 2))
    mag[0, 1, 0], mag[2, 0, 1], mag[1, 1, 1] = 0.2, 0.7, 0.2 + 1e-6
    pts = export.occupied_points(mag, [[-1.0, 1.0], [0.0, 0.5], [2.0, 3.0]], 0.2)
    assert sorted(map(tuple, pts.tolist())) == [(0.0, 0.5, 3.0), (1.0, 0.0, 3.0)]


def test_sphere_mesh_vertices_lie_on_world_sphere():
    mesh = export.extract_surface(cone(), BOUNDS, 0.5)
    r = np.linalg.norm(mesh.vertices - CENTRE, axis=1)
    h = export.voxel_spacing(BOUNDS, SHAPE)
    assert np.abs(r - RADIUS).max() < 0.25 * h.min()   # "within a voxel", with margin
    assert abs(np.mean(r) - RADIUS) < 0.05 * h.min()   # no systematic offset
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.02)  # outward


def test_surface_touching_the_box_is_closed_and_inside_it():
    # sphere centred on the box's lower z face: padding closes it along z = lo
    centre = np.array([0.0, 0.05, 0.0])
    mag = np.clip(1.0 - radial(centre=centre) / (2 * RADIUS), 0, 1)
    mesh = export.extract_surface(mag, BOUNDS, 0.5)
    assert mesh.is_watertight
    h = export.voxel_spacing(BOUNDS, SHAPE)
    assert mesh.vertices[:, 2].min() >= BOUNDS[2, 0] - h[2] - 1e-12
    assert mesh.vertices[:, 2].min() <= BOUNDS[2, 0] - 0.5 * h[2] + 1e-9  # cap below lo


def test_degenerate_volumes_give_defined_results(tmp_path):
    empty = export.extract_surface(np.zeros((5, 6, 7), np.float32), BOUNDS, 0.2)
    assert len(empty.vertices) == 0 and len(empty.faces) == 0
    # one voxel along z: a slab one voxel thick around z = lo
    b = np.array([[-0.1, 0.1], [-0.1, 0.1], [0.07, 0.07]])
    x, y = np.meshgrid(*export.voxel_axes(b, (21, 21, 1))[:2], indexing="ij")
    mag = (np.hypot(x, y) < 0.05).astype(np.float32)[:, :, None]
    slab = export.extract_surface(mag, b, 0.5)
    assert len(slab.faces) > 0
    assert slab.vertices[:, 2].min() >= 0.07 - 0.01 - 1e-9
    assert slab.vertices[:, 2].max() <= 0.07 + 0.01 + 1e-9
    export.write_mip_png(tmp_path / "slab.png", mag, b)
    export.write_mip_exr(tmp_path / "slab.exr", mag, b)
    assert export.read_mip_exr(tmp_path / "slab.exr")["mip_x"].shape == (1, 21)
    export.write_vti(tmp_path / "slab.vti", mag.astype(np.complex64), b)     # one z voxel
    assert _read_vti(tmp_path / "slab.vti")[2] == pytest.approx((0.01, 0.01, 0.01))


def test_mip_orientation_png_and_exr_roundtrip(tmp_path):
    import matplotlib.image as mpimg

    mag = np.zeros(SHAPE, np.float32)
    mag[3, 7, 11] = 1.0
    mag[30, 20, 40] = 0.25
    assert export.mip(mag, 2).shape == (SHAPE[1], SHAPE[0])
    assert export.mip(mag, 2)[7, 3] == 1.0 and export.mip(mag, 1)[11, 3] == 1.0
    assert export.mip(mag, 0)[40, 20] == 0.25
    png = export.write_mip_png(tmp_path / "m.png", mag, BOUNDS, title="t")
    img = mpimg.imread(png)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 300
    files = export.write_mip_exr(tmp_path / "m.exr", mag, BOUNDS)
    assert [f.name for f in files] == ["m_z.exr", "m_y.exr", "m_x.exr"]
    back = export.read_mip_exr(tmp_path / "m.exr")
    assert set(back) == {"mip_x", "mip_y", "mip_z"}
    for axis, name in enumerate("xyz"):
        assert np.array_equal(back[f"mip_{name}"], export.mip(mag, axis))
    import OpenEXR
    # each file is a plain single-part image with one channel Y, as generic readers expect
    # (was one multi-part file, which OpenEXR.File(...).channels() and imageio cannot read whole)
    for axis, name in enumerate("xyz"):
        with OpenEXR.File(str(tmp_path / f"m_{name}.exr")) as f:
            assert len(f.parts) == 1 and list(f.channels()) == ["Y"]
            pixels = np.array(f.channels()["Y"].pixels)
            assert pixels.dtype == np.float32
            assert np.array_equal(pixels, export.mip(mag, axis)[::-1])    # top row = highest
            if name == "z":
                lo, hi = map(float, f.header()["sonarsim_u_range_m"].split())
                assert (lo, hi) == pytest.approx((-0.1 - 0.0025, 0.1 + 0.0025))
            if name == "y":
                assert f.header()["sonarsim_v_axis"] == "z"


def test_slices_and_mesh_files(tmp_path):
    from PIL import Image

    mag = cone()
    files = export.write_slices(tmp_path / "s", mag, BOUNDS, axis=2)
    assert len(files) == SHAPE[2]
    meta = json.loads((tmp_path / "s" / "slices.json").read_text())
    assert meta["coordinates_m"][-1] == pytest.approx(0.3)
    k = int(np.argmin(np.abs(np.array(meta["coordinates_m"]) - CENTRE[2])))
    grey = np.asarray(Image.open(files[k]))
    assert grey.shape == (SHAPE[1], SHAPE[0])
    assert np.abs(grey[::-1].T / 255.0 - mag[:, :, k]).max() <= 0.5 / 255 + 1e-6
    mesh = export.extract_surface(mag, BOUNDS, 0.5)
    for suffix in ("ply", "obj"):
        path = export.write_mesh(tmp_path / f"m.{suffix}", mesh)
        back = trimesh.load(path, force="mesh", process=False)
        assert np.allclose(back.bounds, mesh.bounds, atol=1e-6)
    with pytest.raises(InputError):
        export.write_mesh(tmp_path / "m.xyz", mesh)


def test_cli_export(tmp_path, capsys):
    from recon.cli import main
    from sonarsim.dataset import Volume

    mag = cone()
    mag.flat[np.argmax(mag)] = 1.0  # so min-max normalisation leaves the 0.5 level at R
    Volume(mag.astype(np.complex64), BOUNDS, "test").write(tmp_path / "v.h5")
    Volume(np.zeros((4, 4, 4), np.complex64), BOUNDS, "zero").write(tmp_path / "z.h5")
    rc = main(["export", str(tmp_path / "v.h5"), "--mesh", str(tmp_path / "m.ply"),
               "--mip", str(tmp_path / "m.png"), "--exr", str(tmp_path / "m.exr"),
               "--slices", str(tmp_path / "sl"), "--threshold", "0.5"])
    assert rc == 0
    for name in ("m.ply", "m.png", "m_z.exr", "m_y.exr", "m_x.exr", "sl/slices.json"):
        assert (tmp_path / name).is_file()
    mesh = trimesh.load(tmp_path / "m.ply", force="mesh")
    assert np.abs(np.linalg.norm(mesh.vertices - CENTRE, axis=1) - RADIUS).max() < 1e-3
    # all-zero volume: pictures work, a mesh is a clear one-line error (exit 2)
    assert main(["export", str(tmp_path / "z.h5"), "--mip", str(tmp_path / "z.png")]) == 0
    assert main(["export", str(tmp_path / "z.h5"), "--mesh", str(tmp_path / "z.ply")]) == 2
    assert "no voxel above threshold" in capsys.readouterr().err
    assert not (tmp_path / "z.ply").exists()


# ------------------------------------------------- files other tools open (issue 24, item 3)

def _test_volume():
    """A complex volume on the anisotropic grid: magnitude and phase both vary per voxel."""
    x, y, z = np.meshgrid(*export.voxel_axes(BOUNDS, SHAPE), indexing="ij")
    mag = 0.1 + cone()
    return (mag * np.exp(1j * (40 * x - 25 * y + 10 * z))).astype(np.complex64)


def _read_vti(path):
    """(magnitude [nx, ny, nz], phase, spacing, origin) through VTK's XML reader, the reader
    ParaView uses."""
    io_xml = pytest.importorskip("vtkmodules.vtkIOXML")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    reader = io_xml.vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    nx, ny, nz = image.GetDimensions()
    arrays = [vtk_to_numpy(image.GetPointData().GetArray(name)).reshape(nz, ny, nx)
              .transpose(2, 1, 0) for name in ("magnitude", "phase")]   # VTK: x fastest
    return arrays[0], arrays[1], image.GetSpacing(), image.GetOrigin(), image


def test_vti_opens_in_vtk_with_world_coordinates(tmp_path):
    v = _test_volume()
    export.write_vti(tmp_path / "v.vti", v, BOUNDS)
    mag, phase, spacing, origin, image = _read_vti(tmp_path / "v.vti")
    assert mag.shape == SHAPE
    np.testing.assert_array_equal(mag, np.abs(v).astype(np.float32))
    np.testing.assert_allclose(phase, np.angle(v), atol=1e-6)
    assert spacing == pytest.approx((0.2 / 40, 0.2 / 30, 0.3 / 50))
    assert origin == pytest.approx((-0.1, -0.05, 0.0))
    # VTK's own world position of a voxel is its centre as docs/frames.md defines it
    centres = export.voxel_axes(BOUNDS, SHAPE)
    i, j, k = 30, 7, 44
    assert image.GetPoint(image.ComputePointId([i, j, k])) == pytest.approx(
        (centres[0][i], centres[1][j], centres[2][k]))
    assert image.GetBounds() == pytest.approx(BOUNDS.ravel())


def test_ome_tiff_has_channels_pitch_and_position(tmp_path):
    import xml.etree.ElementTree as ET

    import tifffile
    v = _test_volume()
    export.write_ome_tiff(tmp_path / "v.ome.tif", v, BOUNDS)
    with tifffile.TiffFile(tmp_path / "v.ome.tif") as tif:
        series = tif.series[0]
        assert series.axes == "CZYX"
        data = series.asarray()
        ome = ET.fromstring(tif.ome_metadata)
    np.testing.assert_array_equal(data[0], np.abs(v).astype(np.float32).transpose(2, 1, 0))
    np.testing.assert_allclose(data[1], np.angle(v).transpose(2, 1, 0), atol=1e-6)
    ns = {"o": "http://www.openmicroscopy.org/Schemas/OME/2016-06"}
    pixels = ome.find(".//o:Pixels", ns)
    for axis, pitch in zip("XYZ", (0.2 / 40, 0.2 / 30, 0.3 / 50)):
        assert float(pixels.get(f"PhysicalSize{axis}")) == pytest.approx(pitch)
        assert pixels.get(f"PhysicalSize{axis}Unit") == "m"
    assert [c.get("Name") for c in pixels.findall("o:Channel", ns)] == ["magnitude", "phase"]
    planes = pixels.findall("o:Plane", ns)
    z = export.voxel_axes(BOUNDS, SHAPE)[2]
    for p in planes:
        assert float(p.get("PositionZ")) == pytest.approx(z[int(p.get("TheZ"))])
        assert (float(p.get("PositionX")), float(p.get("PositionY"))) == (-0.1, -0.05)


def test_cli_export_vti_and_tiff(tmp_path, capsys):
    from recon.cli import main
    from sonarsim.dataset import Volume

    v = _test_volume()
    Volume(v, BOUNDS, "test").write(tmp_path / "v.h5")
    assert main(["export", str(tmp_path / "v.h5"), "--vti", str(tmp_path / "v.vti"),
                 "--tiff", str(tmp_path / "v.ome.tif")]) == 0
    out = capsys.readouterr().out
    assert "vti: " in out and "first centre (-0.1, -0.05, 0) m" in out
    mag = _read_vti(tmp_path / "v.vti")[0]
    np.testing.assert_array_equal(mag, np.abs(v))
    # existing outputs are kept without --force, the derived EXR names included
    (tmp_path / "e_y.exr").write_text("keep")
    assert main(["export", str(tmp_path / "v.h5"), "--exr", str(tmp_path / "e.exr")]) == 2
    assert "--exr " in capsys.readouterr().err and (tmp_path / "e_y.exr").read_text() == "keep"
    assert not (tmp_path / "e_z.exr").exists()


def test_mip_png_of_a_single_slice_is_one_image_and_of_a_line_a_plot(tmp_path, monkeypatch):
    import matplotlib.figure
    saved = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda self, *a, **k: saved.append(self))
    rng = np.random.default_rng(0)
    b = np.array([[-0.3, 0.3], [-0.3, 0.3], [0.0, 0.0]])
    export.write_mip_png(tmp_path / "s.png", rng.random((20, 20, 1)), b)
    images = [ax for ax in saved[-1].axes if ax.images]
    assert len(images) == 1 and images[0].get_title() == "z = 0.000 m (single slice)"
    assert images[0].images[0].get_array().shape == (20, 20)
    export.write_mip_png(tmp_path / "m.png", rng.random((5, 6, 7)), BOUNDS)
    assert [ax.get_title() for ax in saved[-1].axes if ax.images] == \
        ["max over z", "max over y", "max over x"]
    line = np.linspace(0, 1, 9).reshape(1, 1, 9)
    export.write_mip_png(tmp_path / "l.png", line, BOUNDS)
    (ax,) = saved[-1].axes
    assert not ax.images and np.allclose(ax.lines[0].get_xdata(), np.linspace(0.0, 0.3, 9))
