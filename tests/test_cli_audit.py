"""Bad input to the newer commands (refine, export, evaluate of a mesh): each test is one
failure of a hostile-input audit (2026-11-28: a traceback, an output destroyed or replaced
without --force, a partial output, exit 0 on nonsense) and checks the one-line refusal and
that nothing was written."""
from __future__ import annotations

import pytest
import trimesh

from recon import synthetic
from recon.cli import main as recon_main
from sonarsim.limits import MAX_BOUNCES

REFINE_QUICK = ["--envelope-steps", "1", "--waveform-steps", "0", "--no-progress"]


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0] and err[0].startswith("recon: error")
    return err[0]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("audit")
    synthetic.point_dataset([[0.0, 0.0, 0.1]], n_pings=16, heights=(0.05, 0.1)).write(d / "ds.h5")
    synthetic.point_dataset([[0.0, 0.0, 0.1]], 0.0, n_pings=16,
                            heights=(0.05, 0.1)).write(d / "zero.h5")
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.03)
    sphere.apply_translation([0.0, 0.0, 0.1]).export(d / "s.ply")
    for name in ("ds", "zero"):
        assert recon_main(["backproject", str(d / f"{name}.h5"), "--shape", "8", "8", "8",
                           "--out", str(d / f"{name}_vol.h5"), "-q"]) == 0
    return d


def test_the_bounce_limit_is_the_integrators():
    """One home for the limit: sonarsim.limits mirrors the plugin's (plugins import no sonarsim)."""
    from sonarsim import runtime
    runtime.mitsuba()
    from sonarsim.plugins.sonar_transient import MAX_BOUNCES_LIMIT
    assert MAX_BOUNCES == MAX_BOUNCES_LIMIT


@pytest.mark.parametrize("option, message", [
    (["--bounces", str(MAX_BOUNCES + 1)], "bounces must be at most"),
    (["--oversample", "0"], "oversample must be a positive integer"),
])
def test_refine_refuses_out_of_range_settings(files, tmp_path, capsys, option, message):
    out = tmp_path / "r.ply"
    assert recon_main(["refine", str(files / "ds.h5"), "--init", str(files / "s.ply"),
                       "--out", str(out), *option, *REFINE_QUICK]) == 2
    assert message in one_line_error(capsys) and not out.exists()


def test_refine_refuses_a_nan_ground_height(files, tmp_path, capsys):
    out = tmp_path / "r.ply"
    assert recon_main(["refine", str(files / "ds.h5"), "--init", str(files / "ds_vol.h5"),
                       "--z-min", "nan", "--out", str(out), *REFINE_QUICK]) == 2
    assert "--z-min" in one_line_error(capsys) and not out.exists()


def test_refine_refuses_silent_waveforms_before_building_the_model(files, tmp_path, capsys):
    """Once: a warning that 'the volume will be all zero', the error, then eight lines of
    leaked solver objects."""
    out = tmp_path / "r.ply"
    assert recon_main(["refine", str(files / "zero.h5"), "--init", str(files / "s.ply"),
                       "--out", str(out), *REFINE_QUICK]) == 2
    assert "nothing to fit" in one_line_error(capsys) and not out.exists()


def test_two_outputs_naming_one_file_are_refused(files, tmp_path, capsys):
    """Once: refine --history r.ply --out r.ply left the JSON history under the mesh's name,
    and export --vti x --tiff x only the TIFF, both with exit 0 (names with the wrong suffix
    are refused since, test below; the check holds for any pair of outputs)."""
    out = tmp_path / "r.json"
    assert recon_main(["refine", str(files / "ds.h5"), "--init", str(files / "s.ply"),
                       "--out", str(out), "--history", str(out), *REFINE_QUICK]) == 2
    assert "--out and --history both name" in one_line_error(capsys) and not out.exists()


def test_kept_candidates_are_not_overwritten_without_force(files, tmp_path, capsys):
    out = tmp_path / "r.ply"
    start, refined = tmp_path / "r.wrap0.start.ply", tmp_path / "r.wrap0.ply"
    start.write_text("mine"), refined.write_text("mine too")
    args = ["refine", str(files / "ds.h5"), "--init", str(files / "s.ply"), "--out", str(out),
            "--keep-candidates", *REFINE_QUICK]
    assert recon_main(args) == 2
    assert "--keep-candidates" in one_line_error(capsys)
    assert start.read_text() == "mine" and refined.read_text() == "mine too" and not out.exists()
    assert recon_main(args + ["--force"]) == 0
    assert trimesh.load(start).faces.shape[0] > 0 and trimesh.load(refined).faces.shape[0] > 0


def test_export_writes_nothing_when_the_surface_fails(files, tmp_path, capsys):
    """Once: the VTI and TIFF were written before the mesh step refused an all-zero volume."""
    outs = {"--vti": tmp_path / "v.vti", "--tiff": tmp_path / "t.ome.tif",
            "--mesh": tmp_path / "m.ply"}
    args = [a for k, v in outs.items() for a in (k, str(v))]
    assert recon_main(["export", str(files / "zero_vol.h5"), *args]) == 2
    assert "the volume is all zero" in one_line_error(capsys)
    assert not any(p.exists() for p in outs.values())
    assert recon_main(["export", str(files / "ds_vol.h5"), *args, "--threshold", "0.1"]) == 0
    assert all(p.stat().st_size > 0 for p in outs.values())


@pytest.mark.parametrize("crop", [["nan", "1", "0", "1", "0", "1"], ["1", "0", "0", "1", "0", "1"]])
def test_evaluate_of_a_mesh_checks_the_crop(files, capsys, crop):
    """Once: a NaN crop on the mesh path ended in a traceback (the volume path refused it)."""
    s = str(files / "s.ply")
    assert recon_main(["evaluate", s, "--gt", s, "--crop", *crop, "--no-images"]) == 2
    assert "--crop" in one_line_error(capsys)


def test_compare_shows_the_ground_truth_warnings_once(files, tmp_path, capsys):
    """Once: compare dropped the warnings evaluate prints (here: a GT mesh outside the
    evaluated box, i.e. in another frame), and scored as if nothing were wrong."""
    far = trimesh.load(files / "s.ply")
    far.apply_translation([1.0, 1.0, 1.0])
    gt = tmp_path / "far.ply"
    far.export(gt)
    vol = str(files / "ds_vol.h5")
    assert recon_main(["compare", vol, vol, "--gt", str(gt), "--out", str(tmp_path / "c.png")]) == 0
    err = capsys.readouterr().err
    assert err.count("of the ground-truth mesh's bounding box lies inside") == 1, err


def test_an_output_that_is_the_input_is_refused_even_with_force(files, tmp_path, capsys):
    """Once: deconvolve ds.h5 --out ds.h5 --force replaced the raw data by its deconvolution."""
    import shutil
    ds = tmp_path / "ds.h5"
    shutil.copy(files / "ds.h5", ds)
    before = ds.read_bytes()
    assert recon_main(["deconvolve", str(ds), "--method", "wiener", "--out", str(ds),
                       "--force"]) == 2
    assert "is also the input" in one_line_error(capsys) and ds.read_bytes() == before


@pytest.mark.parametrize("command, option, name", [
    ("export", "--mip", "m.jpg"), ("export", "--vti", "v.txt"), ("export", "--tiff", "t.png"),
    ("refine", "--history", "h.ply"), ("deconvolve", "--out", "d.ply"),
])
def test_an_output_named_for_another_format_is_refused(files, tmp_path, capsys, command, option,
                                                       name):
    """Once: export --mip m.jpg wrote a PNG, --vti v.txt VTK, refine --history h.ply JSON,
    deconvolve --out d.ply HDF5, all with exit 0."""
    out = tmp_path / name
    args = {"export": ["export", str(files / "ds_vol.h5")],
            "refine": ["refine", str(files / "ds.h5"), "--init", str(files / "s.ply"), "--out",
                       str(tmp_path / "r.ply"), *REFINE_QUICK],
            "deconvolve": ["deconvolve", str(files / "ds.h5"), "--method", "wiener"]}[command]
    assert recon_main([*args, option, str(out)]) == 2
    assert f"{option} {out}: the file is written as" in one_line_error(capsys)
    assert not out.exists() and not (tmp_path / "r.ply").exists()


def test_refine_refuses_a_start_mesh_the_scan_never_recorded(files, tmp_path, capsys):
    """Once: a start mesh in millimetres (x1000) ran to exit 0 with misfit 1.000."""
    big = trimesh.load(files / "s.ply")
    big.apply_scale(1000.0)
    start, out = tmp_path / "mm.ply", tmp_path / "r.ply"
    big.export(start)
    assert recon_main(["refine", str(files / "ds.h5"), "--init", str(start), "--out", str(out),
                       *REFINE_QUICK]) == 2
    assert "no part of the start mesh" in one_line_error(capsys) and not out.exists()


def test_grow_options_without_grow_are_refused(files, tmp_path, capsys):
    """Once: --grow-threshold without --grow was silently ignored."""
    out = tmp_path / "r.ply"
    assert recon_main(["refine", str(files / "ds.h5"), "--init", str(files / "ds_vol.h5"),
                       "--grow-threshold", "0.5", "--out", str(out), *REFINE_QUICK]) == 2
    assert "apply with --grow" in one_line_error(capsys) and not out.exists()
