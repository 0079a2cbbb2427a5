"""The data shipped with sonarsim (sonarsim.data, docs/data.md): intact, found by name, in
the package data, and the shipped scan datasets are what the importer makes of the raw flights."""
from __future__ import annotations

import fnmatch
import hashlib
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sonarsim import data
from sonarsim.dataset import SonarDataset
from sonarsim.errors import FormatError
from sonarsim.importers.airsas import import_airsas

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_file_matches_its_recorded_digest():
    """SHA256SUMS lists exactly the shipped data files, each byte-exact (a line-ending
    conversion or an edited mesh fails here)."""
    recorded = {}
    for line in (data.root() / "SHA256SUMS").read_text().splitlines():
        digest, name = line.split(maxsplit=1)
        recorded[name] = digest
    assert sorted(recorded) == data.names()
    actual = {n: hashlib.sha256((data.root() / n).read_bytes()).hexdigest() for n in recorded}
    assert actual == recorded


def test_names_resolve_to_files():
    assert data.path("bunny.obj") == data.root() / "meshes" / "bunny.obj"
    assert data.path("meshes/bunny.obj") == data.path("bunny.obj")
    assert data.path("small_features_cutout_5k.h5") == data.root() / data.REAL_SCAN
    assert data.mesh_names() == ["bunny.obj", "cube.obj", "cylinder.obj"]
    # a bare name shared by the two raw folders is ambiguous; its relative path is not
    assert data.find("Flight-000001.csv") is None
    assert data.find("airsas_real/bg_5k/Flight-000001.csv").is_file()
    for bad in ("nope.obj", "../pyproject.toml", "/etc/passwd", "__init__.py", ""):
        assert data.find(bad) is None, bad
    with pytest.raises(FormatError, match=r"nope\.obj: not a shipped data file .*bunny\.obj"):
        data.path("nope.obj")


def test_every_shipped_file_is_package_data():
    """Each data file is matched by the package-data globs of the package owning its folder
    (what the wheel ships; the wheel itself is built in test_layout)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages, globs = set(config["packages"]), config["package-data"]
    for name in data.names() + ["SHA256SUMS"]:
        folder, file = name.rsplit("/", 1) if "/" in name else ("", name)
        package = "sonarsim.data" + ("." + folder.replace("/", ".") if folder else "")
        assert package in packages, name
        assert any(fnmatch.fnmatch(file, g) for g in globs.get(package, [])), name


def test_meshes_are_in_metres_standing_on_the_ground():
    """The reference's GT meshes in the rig frame: decimetre objects whose lowest point is
    within 5 mm of the turntable plane z = 0 (bunny -1.2 mm, cube -4.5 mm, cylinder +1.7 mm)."""
    sizes = {}
    for name in data.mesh_names():
        mesh = trimesh.load(data.path(name), force="mesh", process=False)
        lo, hi = mesh.bounds
        assert abs(lo[2]) < 5e-3, name
        sizes[name] = hi - lo
    assert len(trimesh.load(data.path("bunny.obj"), force="mesh", process=False).faces) == 4968
    for name, size in sizes.items():
        assert 0.05 < size.max() < 0.3, (name, size)


def test_pulses_are_the_measured_airsas_pulses():
    for name, band in (("airsas_20khz_measured.npy", (10e3, 30e3)),
                       ("airsas_5khz_measured.npy", (17.5e3, 22.5e3))):
        p = np.load(data.path(name))
        assert p.shape == (603,) and p.dtype == np.float64
        spectrum = np.abs(np.fft.rfft(p[:100], 4096))
        peak_hz = np.argmax(spectrum) * 100e3 / 4096
        assert band[0] < peak_hz < band[1], (name, peak_hz)


@pytest.mark.parametrize("h5, raw, background", [
    (data.REAL_SCAN, "airsas_real/small_features_cutout_5k", "airsas_real/bg_5k"),
    (data.EMPTY_SCAN, "airsas_real/bg_5k", None),
])
def test_shipped_scan_is_the_import_of_its_raw_flights(h5, raw, background):
    """The first flights of a shipped scan dataset equal a fresh import of the shipped raw
    excerpt (same importer, same options); the dataset holds the whole 360-ping scan."""
    ds = SonarDataset.read(data.path(h5))
    assert ds.waveforms.shape == (360, 1000) and ds.meta["n_flights"] == 360
    bg = None if background is None else data.root() / background
    fresh = import_airsas(data.root() / raw, bg, progress=False)
    n = fresh.n_pings
    assert n == 6
    np.testing.assert_allclose(ds.waveforms[:n], fresh.waveforms, rtol=0,
                               atol=1e-6 * np.abs(fresh.waveforms).max())
    np.testing.assert_array_equal(ds.tx[:n], fresh.tx)
    np.testing.assert_array_equal(ds.rx[:n], fresh.rx)
    np.testing.assert_array_equal(ds.temperatures[:n], fresh.temperatures)
    np.testing.assert_array_equal(ds.pulse, fresh.pulse)
    # the sound speed is the importer's rule over all 360 temperatures
    assert ds.sound_speed == pytest.approx(331.4 + 0.6 * ds.temperatures.mean(), rel=1e-12)


def test_shipped_scan_minus_empty_scan_is_background_subtraction():
    """cut-out scan (background subtracted) + empty scan = the scan as recorded, checked on
    the raw excerpt: so both shipped datasets are consistent with each other."""
    scan, empty = data.real_scan(), data.empty_scan()
    recorded = import_airsas(data.root() / "airsas_real/small_features_cutout_5k", None,
                             progress=False)
    n = recorded.n_pings
    total = scan.waveforms[:n].astype(np.float64) + empty.waveforms[:n]
    np.testing.assert_allclose(total, recorded.waveforms, rtol=0,
                               atol=1e-6 * np.abs(recorded.waveforms).max())
    # the target's echo is what subtraction leaves: far above the float32 rounding
    assert np.abs(scan.waveforms[:n]).max() > 1e-2 * np.abs(recorded.waveforms).max()


def test_data_command_lists_and_prints_paths(capsys):
    from sonarsim.cli import main
    assert main(["data"]) == 0
    out = capsys.readouterr().out
    assert "meshes/bunny.obj" in out and "airsas_real/small_features_cutout_5k.h5" in out
    assert main(["data", "bunny.obj"]) == 0
    assert Path(capsys.readouterr().out.strip()) == data.path("bunny.obj")
    assert main(["data", "nope.obj"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope.obj: not a shipped data file" in err
