"""benchmarks/table2.py --quick end to end (the CI run of the Table-2 protocol)."""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "table2.py"
DISTANCES = ("chamfer_sq", "best_chamfer_sq", "chamfer_m")
ALWAYS_FINITE = ("iou", "best_iou", "psnr_depth", "ssim_depth")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("table2")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.mark.slow
def test_quick_run_writes_every_output(quick_run):
    for name in ("table2.md", "table2.csv", "table2.png", "table2_bars.png", "table2.json"):
        assert (quick_run / name).stat().st_size > 0, name
    # PNG signature: the figures are real images, not empty placeholders.
    for name in ("table2.png", "table2_bars.png"):
        assert (quick_run / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_every_scene_and_method_has_finite_metrics(quick_run):
    result = json.loads((quick_run / "table2.json").read_text())
    scenes = {"bunny", "cube", "cylinder"} if (ROOT.parent / "shared" / "data" / "meshes"
                                                / "bunny.obj").is_file() else {"cube", "cylinder"}
    methods = {r["method"] for r in result["rows"]}
    assert {"bp", "gd"} <= methods
    assert {(r["scene"], r["method"]) for r in result["rows"]} == \
        {(s, m) for s in scenes for m in methods}
    for r in result["rows"]:
        for key in ALWAYS_FINITE:
            assert math.isfinite(r[key]), (r["scene"], r["method"], key)
        for key in DISTANCES:
            if r["empty"]:   # documented null at τ = 0.2 for an empty reconstruction
                assert key == "best_chamfer_sq" or r[key] is None
            else:
                assert r[key] is not None and math.isfinite(r[key]) and r[key] > 0, \
                    (r["scene"], r["method"], key)
        assert 0.0 <= r["iou"] <= r["best_iou"] <= 1.0
        assert abs(r["threshold"] - 0.2) < 1e-12


@pytest.mark.slow
def test_csv_and_markdown_hold_ours_and_reference(quick_run):
    with open(quick_run / "table2.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    result = json.loads((quick_run / "table2.json").read_text())
    ours = [r for r in rows if r["source"] == "ours" and r["scene"] != "mean"]
    assert len(ours) == len(result["rows"])
    reference = {r["method"]: r for r in rows if r["source"] == "reference"}
    assert set(reference) == {"Backprojection", "Gradient Descent", "PFA", "Neural BP (Ours)"}
    assert float(reference["Backprojection"]["iou"]) == pytest.approx(0.2928)
    markdown = (quick_run / "table2.md").read_text()
    for label in reference:
        assert f"| {label} |" in markdown
    for r in ours:
        assert f"| {r['scene']} | {r['method']} |" in markdown


@pytest.mark.slow
def test_backprojection_overlaps_the_object(quick_run):
    """Sanity bound that can fail: BP occupies some GT cells in every scene."""
    result = json.loads((quick_run / "table2.json").read_text())
    bp = [r for r in result["rows"] if r["method"] == "bp"]
    assert bp and all(r["iou"] > 0 for r in bp)
