"""benchmarks/table2.py --quick end to end (the CI run of Table 2): every cell present, the
stored metrics equal an independent re-evaluation of the stored volumes, labels are
measurements, the Markdown means are the means of the cells, resuming recomputes nothing."""
from __future__ import annotations

import csv
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "table2.py"


def _module():
    spec = importlib.util.spec_from_file_location("table2", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["table2"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def table2():
    return _module()


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("table2")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _result(out: Path) -> dict:
    return json.loads((out / "table2.json").read_text())


@pytest.mark.slow
def test_every_cell_is_there_with_its_outputs(quick_run, table2):
    for name in ("table2.md", "table2.csv", "table2.png", "table2.json"):
        assert (quick_run / name).stat().st_size > 0, name
    assert (quick_run / "table2.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    shapes = ["bunny", "cube", "cylinder"]        # the reference meshes ship with sonarsim
    methods, _ = table2.available_methods(None)
    settings = table2.SIZES["quick"]
    expected = table2.cells_of([m.key for m in methods], shapes, settings)
    cells = _result(quick_run)["cells"]
    assert sorted(c["cell"] for c in cells) == sorted(c.name for c in expected)
    # the SNR sweep and the 5 kHz row are there, for the first shape
    assert {(c["snr_db"], c["bandwidth"]) for c in cells} == {(0.0, "20k"), (10.0, "20k"),
                                                                (20.0, "20k"), (20.0, "5k")}
    for c in cells:
        assert (quick_run / "cells" / f"{c['cell']}_{settings.digest()}.json").is_file()


@pytest.mark.slow
def test_stored_metrics_equal_a_fresh_evaluation_of_the_stored_volume(quick_run, table2):
    """The table's numbers are what recon.metrics gives for the stored volumes (wiring: the
    right volume, GT, threshold, crop and protocol options reach the evaluation)."""
    from recon import export, metrics, protocol_reference
    from sonarsim.dataset import Volume
    settings = table2.SIZES["quick"]
    cells = _result(quick_run)["cells"]
    for c in [c for c in cells if c["method"] in ("bp", "pfa")][:3]:
        vol = Volume.read(c["volume"])
        gt = metrics.load_gt_mesh(c["dataset"])
        ref, _ = protocol_reference.evaluate_reference(
            vol.volume, vol.bounds, gt, threshold=0.2, n_volume=settings.volume_samples,
            n_surface=settings.samples, sweep=None, chamfer_sweep=None)
        assert c["reference"]["iou"] == ref["iou"]
        assert c["reference"]["chamfer_sq"] == pytest.approx(ref["chamfer_sq"], rel=1e-12)
        crop = np.array([[-1e3, 1e3], [-1e3, 1e3], [table2.CROP_Z, 1e3]])
        exact = metrics.evaluate(vol.volume, vol.bounds, gt, threshold=0.2, sweep=None,
                                 n_samples=settings.samples, crop=crop)
        assert c["exact"]["iou"] == exact["iou"]
        assert c["exact"]["chamfer_sq"] == pytest.approx(exact["chamfer_sq"], rel=1e-12)
        assert c["exact"]["evaluated_bounds"][2][0] >= table2.CROP_Z
        assert c["reference"]["evaluated_bounds"][2][0] == pytest.approx(0.0)
        grid_shape = export.check_volume_array(vol.volume).shape
        assert grid_shape == settings.shape


@pytest.mark.slow
def test_metrics_are_consistent_and_labels_are_measured(quick_run):
    for c in _result(quick_run)["cells"]:
        for protocol in ("exact", "reference"):
            e = c[protocol]
            assert e["protocol"] == protocol and abs(e["threshold"] - 0.2) < 1e-12
            assert 0.0 <= e["iou"] <= 1.0
            if e["empty"]:
                assert e["chamfer_sq"] is None
                continue
            # Σ mean d² ≥ 2·(mean of the two mean d)²: the squared and the plain Chamfer are
            # the two definitions of one set of distances, not swapped or rescaled
            assert e["chamfer_sq"] >= 2 * e["chamfer_m"] ** 2 * (1 - 1e-9)
            assert 0.0 < e["chamfer_m"] < 0.5
            assert -1.0 <= e["ssim_depth"] <= 1.0 and 0.0 < e["psnr_depth"] < 100
        assert c["reference"]["iou_bounds"] == [[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]]
        # a dataset labelled X dB measures X dB (the simulator's measured SNR)
        assert c["measured_snr_db"] == pytest.approx(c["snr_db"], abs=0.5)


@pytest.mark.slow
def test_markdown_means_and_published_rows(quick_run, table2):
    cells = _result(quick_run)["cells"]
    main = [c for c in cells if c["snr_db"] == 20.0 and c["bandwidth"] == "20k"]
    text = (quick_run / "table2.md").read_text()
    section = text.split("— the reference's protocol")[1].split("## ")[0]
    for label, ref in table2.REFERENCE.items():
        sel = [c for c in main if c["label"] == label]
        row = next((line for line in section.splitlines() if line.startswith(f"| {label} |")), None)
        assert row is not None, label
        parts = [p.strip() for p in row.split("|")]
        assert parts[8] == f"{ref['iou']:.4f}" and parts[7] == f"{ref['chamfer_sq']:.2e}"
        if sel:   # a method that ran: its mean over shapes, in the table's format
            assert parts[3] == f"{np.mean([c['reference']['iou'] for c in sel]):.4f}"
            assert parts[2] == f"{np.mean([c['reference']['chamfer_sq'] for c in sel]):.2e}"
            assert parts[4] == "n/a"        # LPIPS is not computed
    with open(quick_run / "table2.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len([r for r in rows if r["source"] == "ours"]) == 2 * len(cells)
    published = {r["method"]: r for r in rows if r["source"] == "published"}
    assert float(published["PFA"]["iou"]) == pytest.approx(0.3586)


@pytest.mark.slow
def test_bp_and_pfa_put_energy_on_the_object(quick_run):
    """The fraction of image energy (z ≥ 5 mm) within 2 cm of the GT box, divided by the
    fraction of the volume there: > 1.2 for a focused image (measured 1.3–3.4 at the quick
    size), ≈ 1 for one with a wrong time axis or geometry."""
    from recon import export, metrics
    from sonarsim.dataset import Volume
    for c in _result(quick_run)["cells"]:
        if c["method"] not in ("bp", "pfa") or c["snr_db"] < 20:
            continue
        vol = Volume.read(c["volume"])
        v, b = export.crop_volume(vol.volume, vol.bounds,
                                  np.array([[-1, 1], [-1, 1], [0.005, 1]]))
        e = np.abs(v) ** 2
        x, y, z = np.meshgrid(*export.voxel_axes(b, v.shape), indexing="ij")
        lo, hi = metrics.load_gt_mesh(c["dataset"]).bounds
        near = ((x > lo[0] - 0.02) & (x < hi[0] + 0.02) & (y > lo[1] - 0.02)
                & (y < hi[1] + 0.02) & (z < hi[2] + 0.02))
        assert e[near].sum() / e.sum() / near.mean() > 1.2, c["cell"]


@pytest.mark.slow
def test_resume_recomputes_nothing_and_cells_run_alone(quick_run, table2):
    cells_dir = quick_run / "cells"
    before = {p.name: p.stat().st_mtime_ns for p in cells_dir.iterdir()}
    md = (quick_run / "table2.md").read_text()
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(quick_run)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert {p.name: p.stat().st_mtime_ns for p in cells_dir.iterdir()} == before
    assert (quick_run / "table2.md").read_text() == md
    c = _result(quick_run)["cells"][0]
    again = table2.run_cell(c["method"], c["shape"], c["snr_db"], c["bandwidth"],
                            table2.SIZES["quick"], quick_run)
    assert again == c
    assert math.isfinite(again["reference"]["iou"])


def test_datasets_are_named_by_simulation_settings_only_and_subsampled_by_pose(table2):
    """Changing a solver, grid or evaluation setting never re-simulates (the dataset's digest
    covers the simulation only), changing the poses or the fidelity does; --subsample takes
    every n-th angle and height of the simulated cylindrical scan (angle-fastest order)."""
    from types import SimpleNamespace
    base = table2.SIZES["default"]
    for change in ({"nbp_iterations": 7}, {"shape": (10, 10, 10)}, {"samples": 5},
                   {"subsample_angle": 5}, {"deconvolution": "inr"}):
        other = table2.replace(base, **change)
        assert other.data_digest() == base.data_digest() and other.digest() != base.digest()
    for change in ({"angle_step": 2}, {"paths_per_pose": 100}):
        assert table2.replace(base, **change).data_digest() != base.data_digest()
    sub = table2.replace(base, angle_step=10, height_step=10, subsample_angle=2,
                         subsample_height=3)
    per_height, heights = 36, 15
    angle = np.tile(np.arange(per_height), heights)
    height = np.repeat(np.arange(heights), per_height)
    picked = []
    ds = SimpleNamespace(n_pings=angle.size, select=lambda idx: picked.append(idx) or idx)
    idx = table2.subsampled(ds, sub)
    assert len(idx) == sub.n_pings == 18 * 5
    assert np.all(angle[idx] % 2 == 0) and np.all(height[idx] % 3 == 0)
    assert table2.subsampled(ds, table2.replace(sub, subsample_angle=1, subsample_height=1)) is ds
