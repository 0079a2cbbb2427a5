"""benchmarks/table2.py --quick end to end (the CI run of Table 2, a sonarsim batch): every
cell present, the stored metrics equal an independent re-evaluation of the stored volumes,
labels are measurements, the Markdown means are the means of the cells, resuming recomputes
nothing; the manifest's jobs and steps."""
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
    # every cell is a step of a sonarsim batch job: its volume and both protocols' metrics
    # files carry the step's id (the batch's records), the batch table lists every job
    jobs = {c["job"] for c in cells}
    with open(quick_run / "batch" / "batch.csv", newline="") as fh:
        rows = {r["job"]: r for r in csv.DictReader(fh)}
    assert set(rows) == jobs and all(r["status"] == "done" for r in rows.values())
    for c in cells:
        assert c["settings_digest"] == settings.digest()
        assert Path(c["volume"]).parent == quick_run / "batch"
        for protocol in ("reference", "exact"):
            saved = json.loads(Path(c["volume"]).with_suffix(f".{protocol}.json").read_text())
            assert saved["metrics"]["protocol"] == protocol and saved["job"] == c["job"]


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
    cells = _result(quick_run)["cells"]
    # BP and PFA have no free parameter: at the quick size they find every shape under both
    # protocols, so the distance checks below run on at least those cells
    found = [c for c in cells if c["method"] in ("bp", "pfa")]
    assert len(found) >= 2 * len({c["shape"] for c in cells})
    assert all(not c[p]["empty"] for c in found for p in ("exact", "reference"))
    for c in cells:
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
def test_every_stage_records_its_cpu_time(quick_run, table2):
    cells = _result(quick_run)["cells"]
    for c in cells:
        cpu, wall = c["stages_cpu_s"], c["stages_s"]
        assert cpu["dataset_s"] > 0 and cpu["solve_s"] > 0 and cpu["evaluate_s"] > 0
        assert (cpu["deconvolve_s"] is None) == (wall["deconvolve_s"] is None)
    totals, missing = table2.stage_sums(cells, "stages_cpu_s")
    jobs = {c["job"]: c["stages_cpu_s"]["dataset_s"] for c in cells}
    assert totals["dataset_s"] == pytest.approx(sum(jobs.values()))   # once per job
    assert totals["solve_s"] == pytest.approx(sum(c["stages_cpu_s"]["solve_s"] for c in cells))
    assert missing == []


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
    # the cost section: each stage summed over the cells as recorded, a simulation once
    cost = text.split("## Cost")[1].split("\n\n")[1]
    solve = next(line for line in cost.splitlines() if line.startswith("| solve |"))
    assert solve.split("|")[2].strip() == f"{sum(c['stages_s']['solve_s'] for c in cells):.0f}"
    dataset = next(line for line in cost.splitlines() if line.startswith("| dataset |"))
    runs = {c["job"]: c["stages_s"]["dataset_s"] for c in cells}
    assert dataset.split("|")[2].strip() == f"{sum(runs.values()):.0f}"
    with open(quick_run / "table2.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    refined = _result(quick_run)["refined"]
    assert len([r for r in rows if r["source"] == "ours"]) == 2 * (len(cells) + len(refined))
    published = {r["method"]: r for r in rows if r["source"] == "published"}
    assert float(published["PFA"]["iou"]) == pytest.approx(0.3586)


@pytest.mark.slow
def test_nbp_refine_row_is_the_command_on_each_nbp_solid(quick_run, table2):
    """The NBP + recon refine row: one refinement per main NBP cell, made by ``recon refine``
    from that cell's volume with the size's options (its history says so), the stored
    metrics equal a fresh evaluation of the stored mesh, and the table prints the row with no
    published values."""
    from recon.evaluation import evaluate_file
    result = _result(quick_run)
    nbp = {c["shape"]: c for c in result["cells"]
           if c["method"] == "nbp" and c["snr_db"] == 20.0 and c["bandwidth"] == "20k"}
    refined = {r["shape"]: r for r in result["refined"]}
    assert set(refined) == set(nbp) == {"bunny", "cube", "cylinder"}
    settings = table2.SIZES["quick"]
    for shape, r in refined.items():
        assert r["init"] == nbp[shape]["volume"] and r["dataset"] == nbp[shape]["dataset"]
        mesh = Path(r["volume"])
        assert mesh.suffix == ".ply" and mesh.parent == quick_run / "batch"
        assert mesh.name.startswith(Path(nbp[shape]["volume"]).stem + ".refine-")
        history = json.loads(mesh.with_suffix(".json").read_text())
        assert history["settings"]["envelope_steps"] == 2
        assert history["settings"]["waveform_steps"] == 1
        assert "--envelope-steps" in settings.refine_options
        assert r["stages_cpu_s"]["refine_s"] > 0 and r["time_s"] > 0
        fresh = evaluate_file(mesh, r["dataset"], protocol="exact", images=False,
                              samples=settings.samples,
                              crop=[-1e3, 1e3, -1e3, 1e3, table2.CROP_Z, 1e3])
        assert r["exact"]["chamfer_sq"] == pytest.approx(fresh["chamfer_sq"], rel=1e-12)
        assert r["exact"]["iou"] == fresh["iou"]
        assert r["reference"]["protocol"] == "reference"
    section = (quick_run / "table2.md").read_text().split("— the reference's protocol")[1]
    row = next(line for line in section.splitlines()
               if line.startswith(f"| {table2.REFINE.label} |"))
    parts = [p.strip() for p in row.split("|")]
    assert parts[7:11] == ["–"] * 4
    assert parts[3] == f"{np.mean([r['reference']['iou'] for r in refined.values()]):.4f}"


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
def test_resume_recomputes_nothing(quick_run):
    """A second run finds every dataset, volume and metrics file of the batch complete and
    its own: nothing is rewritten, the table is the same."""
    batch = quick_run / "batch"
    before = {p.name: p.stat().st_mtime_ns for p in batch.iterdir()
              if p.suffix in (".h5", ".json")}
    md = (quick_run / "table2.md").read_text()
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(quick_run)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert {p.name: p.stat().st_mtime_ns for p in batch.iterdir()
            if p.suffix in (".h5", ".json")} == before
    assert (quick_run / "table2.md").read_text() == md
    assert "to run" in proc.stdout and " 0 to run" in proc.stdout


def test_manifest_jobs_are_datasets_and_steps_are_cells(table2, tmp_path):
    """The manifest table2 writes plans as a sonarsim batch: one job per dataset whose pose
    file holds exactly the table's cylindrical poses (every n-th angle and height, angle
    fastest), one reconstruct step per cell. A solver, grid or evaluation setting changes
    the steps' labels (new volumes), never a job (no re-simulation); the poses or the
    fidelity change the jobs."""
    from sonarsim.batch import plan_batch
    from sonarsim.batch.identity import poses_digest
    from sonarsim.geometry import CYLINDRICAL_ANGLES
    base = table2.replace(table2.SIZES["quick"], angle_step=90, height_step=75)
    cells = table2.cells_of(["bp", "gd", "pfa"], ["cube", "cylinder"], base)
    doc, where = table2.manifest(cells, base, tmp_path)
    assert len(doc["job"]) == 2 + 3        # 2 shapes + the SNR and 5 kHz rows (pfa: quick)
    assert sorted(where) == sorted(c.name for c in cells)
    path = tmp_path / "batch" / "table2.toml"
    table2.write_manifest(doc, path)
    plan = plan_batch(path, tmp_path / "batch", log=lambda m: None)
    jobs = {j.name: j for j in plan.jobs}
    assert set(jobs) == {j for j, _ in where.values()}
    for cell in cells:
        name, label = where[cell.name]
        step = next(s for s in jobs[name].recon if s.label == label)
        assert step.settings["module"] == table2.METHOD_BY_KEY[cell.method].module
        assert (step.settings["deconvolve"] is not None) == (cell.method == "gd")
        assert [e.name for e in step.evaluations] == ["reference", "exact"]
    job = jobs[where[cells[0].name][0]]
    idx = table2.cylindrical_indices(base)
    assert len(idx) == base.n_poses == 4 * 2
    assert np.all((idx % CYLINDRICAL_ANGLES) % 90 == 0) and np.all((idx // CYLINDRICAL_ANGLES) % 75 == 0)
    import warnings

    from sonarsim.scene import load_scene
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # the cube reaches below the ground
        box = load_scene(job.params["scene"]).box
    assert job.digests["poses"] == poses_digest(table2.cylindrical_poses(base, box))
    for change in ({"nbp_iterations": 7}, {"gd_iterations": 7}, {"shape": (10, 10, 10)},
                   {"samples": 5}, {"deconvolution": "inr"}):
        other = table2.replace(base, **change)
        assert other.data_digest() == base.data_digest()
        doc2, where2 = table2.manifest(cells, other, tmp_path)
        assert {j for j, _ in where2.values()} == {j for j, _ in where.values()}
        if "nbp_iterations" not in change:
            assert where2[cells[1].name][1] != where[cells[1].name][1], change   # gd step
    for change in ({"angle_step": 45}, {"paths_per_pose": 100}):
        other = table2.replace(base, **change)
        assert other.data_digest() != base.data_digest()
        assert table2.job_name(cells[0], other) != table2.job_name(cells[0], base)


def test_a_relative_out_plans_from_any_working_directory(table2, tmp_path, monkeypatch):
    """`--out red` once wrote the scene and pose files' paths relative to the working directory
    into a manifest that resolves paths against its own folder (red/batch/red/data/bunny.toml:
    scene file not found); every path in it is now absolute."""
    from sonarsim.batch import plan_batch
    monkeypatch.chdir(tmp_path)
    out = Path("red")
    base = table2.replace(table2.SIZES["quick"], angle_step=90, height_step=75)
    cells = table2.cells_of(["bp"], ["bunny"], base)
    doc, _ = table2.manifest(cells, base, out)
    path = out / "batch" / "table2.toml"
    table2.write_manifest(doc, path)
    plan = plan_batch(path, out / "batch", log=lambda m: None)
    scene = Path(plan.jobs[0].params["scene"])
    assert scene.is_absolute() and scene.is_file()


def test_subsample_is_refused_in_one_line():
    proc = subprocess.run([sys.executable, str(SCRIPT), "--subsample", "5", "5", "--out",
                           "/nonexistent/t2"], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]      # one line
    assert "--angle-step" in proc.stderr


def test_data_dir_adopts_the_same_simulation_only(table2, tmp_path):
    """``--data DIR``: a scan made outside the batch (no batch metadata) that is the job's
    simulation is adopted (copied with the job's id, so the batch skips the simulation); a
    scan that differs in one recorded setting (the seed) or one pose is refused, naming it,
    and DIR is only read."""
    from sonarsim.batch import plan_batch
    from sonarsim.batch.records import dataset_record
    from sonarsim.batch.tasks import run_simulation
    from sonarsim.dataset import SonarDataset
    base = table2.replace(table2.SIZES["quick"], angle_step=90, height_step=75)
    cells = table2.cells_of(["bp"], ["cube"], base)[:1]

    def plan_in(where: Path):
        doc, _ = table2.manifest(cells, base, where)
        table2.write_manifest(doc, where / "batch" / "table2.toml")
        return plan_batch(where / "batch" / "table2.toml", where / "batch", log=lambda m: None)

    made = plan_in(tmp_path / "a").jobs[0]
    run_simulation(made)
    scan = SonarDataset.read(made.output)
    scan.meta = {k: v for k, v in scan.meta.items() if not k.startswith("batch_")}
    data = tmp_path / "data"
    data.mkdir()
    scan.write(data / "cube_scan.h5")
    other_seed = SonarDataset.read(data / "cube_scan.h5")
    other_seed.seed = 2
    other_seed.write(data / "cube_seed2.h5")
    moved = SonarDataset.read(data / "cube_scan.h5")
    moved.tx = moved.tx.copy()
    moved.tx[3, 0] += 1e-4
    moved.write(data / "cube_moved.h5")
    before = {p.name: p.stat().st_mtime_ns for p in data.iterdir()}

    job = plan_in(tmp_path / "b").jobs[0]
    assert dataset_record(job.output, job.job_id) is None
    assert table2.simulation_mismatches(data / "cube_scan.h5", job) == []
    assert table2.simulation_mismatches(data / "cube_seed2.h5", job) == ["seed"]
    assert table2.simulation_mismatches(data / "cube_moved.h5", job) == ["tx"]
    (data / "cube_scan.h5").rename(data / "zz_cube_scan.h5")     # the mismatches come first
    before["zz_cube_scan.h5"] = before.pop("cube_scan.h5")
    logged: list[str] = []
    adopted = table2.adopt_datasets(plan_in(tmp_path / "b"), data, log=logged.append)
    assert adopted == {job.name: str(data / "zz_cube_scan.h5")}
    assert dataset_record(job.output, job.job_id) is not None
    assert SonarDataset.read(job.output).meta["adopted_from"] == str(data / "zz_cube_scan.h5")
    assert np.array_equal(SonarDataset.read(job.output).waveforms, scan.waveforms)
    assert any("cube_seed2.h5" in m and "seed" in m for m in logged)
    assert {p.name: p.stat().st_mtime_ns for p in data.iterdir()} == before

    # the batch on the adopted scan: no simulation; then a deleted metrics file is evaluated
    # again on the step's own volume, which is not solved again
    first = table2.run_batch(cells, base, tmp_path / "b")[0]
    assert first["stages_s"]["dataset_s"] is None          # adopted: not simulated
    volume = Path(first["volume"])
    stamp = volume.stat().st_mtime_ns
    ref_json = volume.with_name(volume.name[:-3] + ".reference.json")
    saved = json.loads(ref_json.read_text())
    ref_json.unlink()
    again = table2.run_batch(cells, base, tmp_path / "b")[0]
    assert volume.stat().st_mtime_ns == stamp               # not solved again
    redone = json.loads(ref_json.read_text())
    assert redone["wall_s"]["reused_volume"] is True
    assert redone["wall_s"]["solve"] == saved["wall_s"]["solve"]
    assert redone["cpu_s"]["solve"] == saved["cpu_s"]["solve"] > 0    # taken over, not re-timed
    assert first["stages_cpu_s"]["dataset_s"] is None and first["stages_cpu_s"]["solve_s"] > 0
    assert again["reference"]["iou"] == first["reference"]["iou"]
    assert again["reference"]["chamfer_sq"] == first["reference"]["chamfer_sq"]
