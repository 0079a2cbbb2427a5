"""Every example in examples/ runs at a small size (``--quick``; the notebook with small
parameters injected after its ``parameters`` cell) and gives physically sensible results;
the API reference builds (``make docs``' command on two modules)."""
from __future__ import annotations

import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run_example(name: str, out: Path) -> dict:
    return runpy.run_path(str(EXAMPLES / name), run_name="example")["main"](
        ["--quick", "--out", str(out)])


def _distance_to_box(p: np.ndarray, lo, hi) -> np.ndarray:
    return np.linalg.norm(p - np.clip(p, lo, hi), axis=-1)


TESTED_HERE = {"custom_scene.py", "reconstruct.py", "real_airsas.py", "workflow.ipynb"}


def test_every_example_is_tested_and_listed():
    """Each example is run here or by another test file (which names it), and
    examples/README.md lists it."""
    examples = {p.name for p in EXAMPLES.iterdir() if p.suffix in (".py", ".ipynb")}
    others = examples - TESTED_HERE
    tests_text = "".join(t.read_text() for t in (ROOT / "tests").glob("test_*.py")
                         if t.name != "test_examples.py")
    assert {n for n in others if f"examples/{n}" not in tests_text
            and f'"{n}"' not in tests_text} == set()
    listing = (EXAMPLES / "README.md").read_text()
    assert {n for n in examples if n not in listing} == set()


def test_custom_scene(tmp_path):
    r = run_example("custom_scene.py", tmp_path)
    tr, shares = r["transients"], r["shares"]
    assert tr.transients.shape[:2] == (12, 3)
    assert shares.sum() == pytest.approx(100.0)
    assert shares[0] > 50 and shares[1] > 0 and shares[2] > 0      # single scattering dominates
    # No energy arrives before the shortest possible path: TX -> scene box -> RX.
    from sonarsim.render import scene_box
    box = scene_box(r["spec"].to_mitsuba())
    shortest = (_distance_to_box(tr.tx, box.lo, box.hi) + _distance_to_box(tr.rx, box.lo, box.hi))
    first = np.array([tr.path_lengths()[np.flatnonzero(row)[0]] for row in tr.transients[:, 0]])
    assert np.all(first >= shortest - tr.path_bin_width)
    assert {p.name for p in r["pictures"]} >= {"transients.png", "transients_energy.png"}


def test_reconstruct(tmp_path):
    r = run_example("reconstruct.py", tmp_path)
    ds, grid = r["dataset"], r["grid"]
    assert abs(ds.meta["effective_snr_db"] - 20.0) < 0.5
    lo, hi = ds.gt_vertices.min(axis=0) - 0.01, ds.gt_vertices.max(axis=0) + 0.01
    X, Y, Z = np.meshgrid(*grid.axes(), indexing="ij")
    inside = _distance_to_box(np.stack([X, Y, Z], -1), lo, hi) == 0
    for name, volume in r["volumes"].items():
        energy = np.abs(volume) ** 2
        # the image is concentrated on the object: its box holds 12.7 % of the voxels and, at
        # this tiny size, 26 % (BP) and 50 % (NBP) of the energy (the ground takes the rest)
        assert energy[inside].sum() / energy.sum() > 1.5 * inside.mean(), name
        assert 0 <= r["scores"][name]["iou"] <= 1
    assert r["figure"].stat().st_size > 10_000
    assert (tmp_path / "scores.json").is_file() and (tmp_path / "nbp.h5").is_file()


def test_real_airsas(tmp_path):
    r = run_example("real_airsas.py", tmp_path)
    np.testing.assert_allclose(r["raw"].waveforms, r["scan"].waveforms[:6], atol=1e-8)
    for name, vol in r["images"].items():
        mag = np.abs(vol.volume[:, :, 0])
        x = np.linspace(-0.3, 0.3, mag.shape[0])
        radius = np.hypot(*np.meshgrid(x, x, indexing="ij"))
        # the target sits on the turntable: its echo energy is within 0.15 m of the axis
        assert (mag ** 2)[radius < 0.15].sum() > 0.9 * (mag ** 2).sum(), name
        assert radius.flat[np.argmax(mag)] < 0.15, name
    assert r["figure"].stat().st_size > 10_000


QUICK_NOTEBOOK = """\
ANGLES, HEIGHTS = 8, 2
SHAPE = (16, 16, 12)
NBP_STEPS = 5
NBP_OPTIONS = dict(hash_levels=4, n_rays=100, bins_per_ping=32, warm_start_iterations=5)
"""


def test_notebook_runs(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(EXAMPLES / "workflow.ipynb", as_version=4)
    (index,) = [i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", [])]
    nb.cells.insert(index + 1, nbformat.v4.new_code_cell(QUICK_NOTEBOOK))
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.outputs)
    snr = float(text.split("effective SNR ")[1].split(" dB")[0])
    assert abs(snr - 20.0) < 0.5
    images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code"
                 for o in c.outputs)
    assert images == 3                   # transients, reconstructions, real scan


def test_api_reference_builds(tmp_path):
    """``make docs`` runs pdoc with reST docstrings; here on two modules (the whole run is slow)."""
    r = subprocess.run([sys.executable, "-m", "pdoc", "--docformat", "restructuredtext",
                        "--output-directory", str(tmp_path), "sonarsim.data", "recon.grid"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    page = (tmp_path / "sonarsim" / "data.html").read_text()
    assert "real_scan" in page and "<code>meshes/bunny.obj</code>" in page
    makefile = (ROOT / "Makefile").read_text()
    assert "pdoc --docformat restructuredtext" in makefile


def test_demo_verdict_names_the_measured_winner():
    """scripts/demo.py's verdict is computed from the scores it is given: the best IoU is the
    highest, the best Chamfer the lowest, and 'NBP wins' is said only when it wins both.
    (The whole demo, `python scripts/demo.py --quick`, costs about a CPU-minute: not run here.)"""
    demo = runpy.run_path(str(ROOT / "scripts" / "demo.py"), run_name="demo")
    seconds = {"bp": 1.0, "gd": 2.0, "nbp": 3.0}

    def scores(iou, chamfer_mm):
        return {k: {"iou": i, "chamfer_m": c / 1e3} for k, i, c in
                zip(("bp", "gd", "nbp"), iou, chamfer_mm)}

    text = demo["verdict"](scores((0.30, 0.20, 0.60), (30.0, 40.0, 20.0)), seconds)
    assert "Best IoU: NBP (deconvolved); best Chamfer: NBP (deconvolved)." in text
    assert "NBP wins on both: IoU 0.600 vs 0.300" in text and "GD scores below BP" in text
    text = demo["verdict"](scores((0.30, 0.40, 0.35), (25.0, 40.0, 20.0)), seconds)
    assert "Best IoU: GD (deconvolved); best Chamfer: NBP (deconvolved)." in text
    assert "NBP wins" not in text and "NBP does not win" in text
    assert "GD scores below BP" not in text
    rows = [line.split() for line in text.splitlines()
            if line.startswith(("BP ", "GD ", "NBP ")) and line.endswith(" s")]
    assert [r[0] for r in rows] == ["BP", "GD", "NBP"]
    assert [float(r[-5]) for r in rows] == [0.30, 0.40, 0.35]          # IoU column
