"""sonarsim batch: manifest expansion and validation, job identity, Dask execution (a 1-worker
process LocalCluster), byte-identical outputs, failures, killed workers, re-runs, batch.csv."""
from __future__ import annotations

import csv
import filecmp
import logging
import os
import signal
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh

from sonarsim import batch
from sonarsim.batch_engine import Engine, Task, plan_local_cluster
from sonarsim.cli import main as cli_main
from sonarsim.errors import InputError

POSES = "cylindrical:12:2"          # 24 poses: each job well under a second


def fast_settings() -> str:
    """TOML lines that keep a job tiny whatever the simulator's defaults are."""
    lines = ["paths_per_pose = 200", "bounces = 1"]
    if "bounce1" in batch.settings_fields():       # the TX-cone estimator is the cheap one
        lines.append('bounce1 = "cone"')
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("meshes")
    for i, r in enumerate((0.04, 0.06)):
        m = trimesh.creation.icosphere(subdivisions=2, radius=r)
        m.apply_translation([0.0, 0.0, r])
        m.export(d / f"ball{i}.obj")
    return d


def write_manifest(path: Path, body: str, poses: str = POSES, extra: str = "") -> Path:
    path.write_text(f'[defaults]\nposes = "{poses}"\n{fast_settings()}{extra}\n{body}')
    return path


THREE_JOBS = """
[[job]]
scene = "sphere"
seed = 3

[[job]]
mesh = "{mesh}"
snr_db = 15

[[job]]
scene = "cube"
seed = 4
snr_db = 10
"""


@pytest.fixture(scope="module")
def client():
    """A Dask cluster of one worker process: each job runs in another process than the test
    (its own imports, Dr.Jit state and kernels), which is what these tests need; every
    assertion reads the same with one worker as with two, and each worker process costs
    ~3 CPU-s of imports and kernel loading (a killed one, again on its restart)."""
    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=logging.CRITICAL)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def h5_contents(path: Path) -> dict:
    """Every dataset (array) and attribute of an HDF5 file, by path."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            for k, v in obj.attrs.items():
                out[f"{name}@{k}"] = v
        for k, v in f.attrs.items():
            out[f"@{k}"] = v
        f.visititems(visit)
    return out


def assert_same_contents(a: Path, b: Path) -> None:
    ca, cb = h5_contents(a), h5_contents(b)
    assert sorted(ca) == sorted(cb)
    for key in ca:
        np.testing.assert_array_equal(np.asarray(ca[key]), np.asarray(cb[key]), err_msg=key)


def one_by_one(job: batch.Job, out: Path) -> Path:
    """The job run alone through the plain Python API (no batch code on the way)."""
    from sonarsim.geometry import trajectory
    from sonarsim.scene import load_scene
    from sonarsim.signals import pulse_from_spec
    from sonarsim.simulate import SimulationSettings, simulate
    p = job.params
    if "scene" in p:
        spec = load_scene(p["scene"])
    else:   # the batch's mesh scene: the mesh fitted on the default ground
        toml = out.parent / f"{Path(p['mesh']).stem}.toml"
        toml.write_text(f'name = "{Path(p["mesh"]).stem}"\nground = true\n[[object]]\n'
                        f'mesh = "{p["mesh"]}"\nfit = true\n')
        import dataclasses
        spec = dataclasses.replace(load_scene(toml), source=f"mesh {p['mesh']} (fit=true)")
    values = {k: (tuple(v) if isinstance(v, list) else v) for k, v in p.items()
              if k in batch.settings_fields()}
    settings = SimulationSettings(pulse=pulse_from_spec(p["pulse"], p["fs"]), **values,
                                  extra_meta=batch.job_meta(job))
    path = out / Path(job.output).name
    simulate(spec, trajectory(p["poses"], box=spec.box), path, settings, resume=False)
    return path


@pytest.fixture(scope="module")
def three(tmp_path_factory, mesh_dir):
    """The 3-job manifest, its plan and the same three runs made one by one."""
    d = tmp_path_factory.mktemp("three")
    manifest = write_manifest(d / "three.toml", THREE_JOBS.format(mesh=mesh_dir / "ball0.obj"))
    plan = batch.plan_batch(manifest, d / "out", log=lambda s: None)
    ref = d / "ref"
    ref.mkdir()
    refs = {job.name: one_by_one(job, ref) for job in plan.jobs}
    return manifest, plan, refs


# ----------------------------------------------------------------------------- manifests

def test_sweep_expands_to_named_jobs_with_ids(tmp_path, mesh_dir):
    manifest = write_manifest(tmp_path / "m.toml", f"""
[[sweep]]
mesh = "{mesh_dir}/*.obj"
snr_db = [10, 20]
seed = 2
bounce_set = [[1]]
[[job]]
scene = "sphere"
seed = 0
""")
    plan = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    names = [j.name for j in plan.jobs]          # explicit jobs first, then the sweeps
    assert names == ["sphere_seed-0_bounce_set-none_snr_db-none",
                     "ball0_seed-2_bounce_set-1_snr_db-10", "ball0_seed-2_bounce_set-1_snr_db-20",
                     "ball1_seed-2_bounce_set-1_snr_db-10", "ball1_seed-2_bounce_set-1_snr_db-20"]
    by = {j.name: j for j in plan.jobs}
    assert by[names[1]].params["bounce_set"] == [1] and by[names[1]].params["bounces"] == 1
    assert by[names[1]].params["mesh"] == str((mesh_dir / "ball0.obj").resolve())
    assert len({j.job_id for j in plan.jobs}) == 5
    # seed 0 written out or left to its default: the same simulation, refused as a duplicate
    with open(manifest, "a") as fh:
        fh.write('[[job]]\nscene = "sphere"\n')
    with pytest.raises(InputError, match=r"job\[1\].*same simulation as job\[0\]"):
        batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    assert all(Path(j.output).parent == (tmp_path / "out").resolve() for j in plan.jobs)
    assert not (tmp_path / "out").exists()          # planning writes nothing


def test_validation_names_the_bad_job_and_nothing_starts(tmp_path, mesh_dir, capsys):
    body = THREE_JOBS.format(mesh=mesh_dir / "missing.obj")
    manifest = write_manifest(tmp_path / "m.toml", body)
    with pytest.raises(InputError, match=r"job\[1\].*missing\.obj.*not found"):
        batch.plan_batch(manifest, tmp_path / "out")
    assert cli_main(["batch", str(manifest), "--out", str(tmp_path / "out"),
                     "--scheduler", "sequential"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "job[1]" in err[0] and "missing.obj" in err[0]
    assert not (tmp_path / "out").exists()
    for bad, match in ((f'[[job]]\nscene = "sphere"\nsedd = 1\n', r"job\[0\]: unknown key.*sedd"),
                       (f'[[job]]\nscene = "sphere"\npaths_per_pose = 0\n', r"job\[0\].*paths_per_pose"),
                       (f'[[job]]\nscene = "sphere"\nname = "a"\n[[job]]\nscene = "cube"\n'
                        f'name = "a"\n', r"job\[1\].*'a'"),
                       (f'[[sweep]]\nmesh = "{mesh_dir}/*.stl"\n', r"sweep\[0\].*matches no file"),
                       (f'[[job]]\nscene = "sphere"\nposes = "spiral"\n', r"job\[0\].*spiral")):
        write_manifest(tmp_path / "bad.toml", bad)
        with pytest.raises(InputError, match=match):
            batch.plan_batch(tmp_path / "bad.toml", tmp_path / "out")


def test_local_cluster_plan_divides_cores():
    assert plan_local_cluster(20, cores=2, memory=2**35) == plan_local_cluster(20, cores=2)
    p = plan_local_cluster(20, cores=2)
    assert (p.n_workers, p.threads, p.gpus) == (1, 2, ())
    p = plan_local_cluster(20, cores=16)                         # 2 Dr.Jit threads each
    assert (p.n_workers, p.threads) == (8, 2)
    p = plan_local_cluster(3, cores=16)                          # at most one per task
    assert (p.n_workers, p.threads) == (3, 5)
    p = plan_local_cluster(50, cores=16, memory=6 * 2**30)      # 2 GiB per worker
    assert (p.n_workers, p.threads) == (3, 5)
    p = plan_local_cluster(50, cores=16, workers=16)
    assert (p.n_workers, p.threads) == (16, 1)
    p = plan_local_cluster(50, cores=16, gpus=["0", "1"])
    assert (p.n_workers, p.threads, p.gpus, p.variant) == (2, 8, ("0", "1"), "cuda_ad_mono")
    assert plan_local_cluster(50, cores=16, gpus=["0"], variant="llvm_ad_mono").gpus == ()
    from sonarsim.batch_engine import gpu_worker_specs
    specs = gpu_worker_specs(p, 2**30)
    assert [s["options"]["env"]["CUDA_VISIBLE_DEVICES"] for s in specs.values()] == ["0", "1"]
    assert all(s["options"]["env"]["SONARSIM_VARIANT"] == "cuda_ad_mono" for s in specs.values())


# ----------------------------------------------------------------------------- running

def read_csv(path: Path) -> dict[str, dict]:
    with open(path, newline="") as fh:
        return {r["job"]: r for r in csv.DictReader(fh)}


def test_cluster_gives_the_one_by_one_bytes_and_a_rerun_does_nothing(three, client, tmp_path):
    manifest, plan, refs = three
    plan = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    with Engine(client=client, threads=1, log=lambda s: None) as engine:
        result = batch.run_batch(plan, engine, progress=False, log=lambda s: None)
    assert result.status == {j.name: "done" for j in plan.jobs}
    for job in plan.jobs:
        # same settings, same bytes (HDF5 files carry no timestamps here)
        assert filecmp.cmp(job.output, refs[job.name], shallow=False), job.name
        assert_same_contents(Path(job.output), refs[job.name])
    rows = read_csv(result.csv)
    assert set(rows) == {j.name for j in plan.jobs}
    for job in plan.jobs:
        row = rows[job.name]
        assert row["status"] == "done" and row["output"] == job.output
        assert float(row["wall_s"]) > 0 and row["job_id"] == job.job_id
        # every simulation measures its Monte-Carlo SNR; the table carries that measurement
        from sonarsim.dataset import SonarDataset
        measured = SonarDataset.read(job.output).meta["mc_snr_db"]
        assert float(row["mc_snr_db"]) == pytest.approx(measured, rel=1e-6)
    assert rows[plan.jobs[2].name]["snr_db"] == "10"

    stamps = {j.name: os.stat(j.output).st_mtime_ns for j in plan.jobs}
    again = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    with Engine(client=client, threads=1, log=lambda s: None) as engine:
        second = batch.run_batch(again, engine, progress=False, log=lambda s: None)
    assert second.submitted == 0
    assert second.status == {j.name: "skipped" for j in plan.jobs}
    assert stamps == {j.name: os.stat(j.output).st_mtime_ns for j in plan.jobs}
    rows2 = read_csv(second.csv)
    assert [rows2[n]["wall_s"] for n in rows] == [rows[n]["wall_s"] for n in rows]
    # the simulations' CPU time too (benchmarks/table2.py sums it for its cost table)
    assert all(float(rows[n]["cpu_s"]) > 0 for n in rows)
    assert [rows2[n]["cpu_s"] for n in rows] == [rows[n]["cpu_s"] for n in rows]


def test_skip_needs_the_parameters_not_only_the_name(tmp_path):
    manifest = write_manifest(tmp_path / "m.toml", '[[job]]\nname = "fixed"\nscene = "sphere"\n'
                                                   'seed = 1\n')
    run = lambda force=False: batch.run_batch(
        batch.plan_batch(manifest, tmp_path / "out", log=print, force=force),
        Engine("sequential", log=print), progress=False, log=print)
    assert run().status == {"fixed": "done"}
    first = h5_contents(tmp_path / "out" / "fixed.h5")
    assert run().status == {"fixed": "skipped"}
    write_manifest(tmp_path / "m.toml", '[[job]]\nname = "fixed"\nscene = "sphere"\nseed = 2\n')
    with pytest.raises(InputError, match="another batch job .*pass --force"):
        run()                                          # same name, other seed: not replaced ...
    assert h5_contents(tmp_path / "out" / "fixed.h5")["@seed"] == 1
    assert run(force=True).status == {"fixed": "done"}  # ... unless forced
    second = h5_contents(tmp_path / "out" / "fixed.h5")
    assert first["@seed"] == 1 and second["@seed"] == 2
    assert not np.array_equal(first["waveforms"], second["waveforms"])


def test_a_job_failing_at_run_time_fails_alone(tmp_path, mesh_dir, client):
    mesh = tmp_path / "doomed.obj"
    mesh.write_bytes((mesh_dir / "ball1.obj").read_bytes())
    manifest = write_manifest(tmp_path / "m.toml", THREE_JOBS.format(mesh=mesh))
    plan = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    mesh.unlink()                                  # after validation, before running
    with Engine(client=client, threads=1, retries=2, log=lambda s: None) as engine:
        result = batch.run_batch(plan, engine, progress=False, log=lambda s: None)
    bad = plan.jobs[1].name
    assert result.failed == [bad]
    assert "doomed.obj" in result.errors[bad] and "not found" in result.errors[bad]
    assert [result.status[j.name] for j in plan.jobs] == ["done", "failed", "done"]
    rows = read_csv(result.csv)
    assert rows[bad]["status"] == "failed" and "doomed.obj" in rows[bad]["error"]
    assert not Path(plan.jobs[1].output).exists()


def test_killed_worker_loses_only_its_job(client, tmp_path, mesh_dir):
    # bigger jobs in small chunks, so that a worker is surely killed in the middle of one
    big = write_manifest(tmp_path / "big.toml", THREE_JOBS.format(mesh=mesh_dir / "ball0.obj"),
                         poses="cylindrical:90:6", extra="chunk_size = 30\n")
    plan = batch.plan_batch(big, tmp_path / "out", log=lambda s: None)
    pids = client.run(os.getpid)
    killed = []

    def killer():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            busy = [w for w, keys in client.processing().items() if keys]
            partial = list((tmp_path / "out").glob("*.partial"))
            if busy and partial:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.append((busy[0], [p.name for p in partial]))
            time.sleep(0.02)

    thread = threading.Thread(target=killer)
    thread.start()
    try:
        with Engine(client=client, threads=1, log=lambda s: None) as engine:
            result = batch.run_batch(plan, engine, progress=False, log=lambda s: None)
    finally:
        thread.join()
    assert killed, "no worker was killed mid-job"
    assert result.status == {j.name: "done" for j in plan.jobs}, result.errors
    for job in plan.jobs:
        assert batch.dataset_record(job.output, job.job_id) is not None
    assert not list((tmp_path / "out").glob("*.partial"))
    client.wait_for_workers(1, timeout=60)


def test_reconstruction_and_evaluation_step(tmp_path, capsys):
    manifest = write_manifest(tmp_path / "m.toml", """
[[job]]
scene = "sphere"
[job.reconstruct]
method = "backproject"
shape = [9, 9, 7]
evaluate = {threshold = 0.3, samples = 500}
""")
    args = ["batch", str(manifest), "--out", str(tmp_path / "out"), "--scheduler", "sequential",
            "--no-progress"]
    assert cli_main(args) == 0
    rows = read_csv(tmp_path / "out" / "batch.csv")
    (row,) = rows.values()
    assert row["status"] == "done" and row["backproject_status"] == "done"
    volume = tmp_path / "out" / f"{row['job']}.backproject.h5"
    assert row["backproject_output"] == str(volume)
    from sonarsim.dataset import Volume
    vol = Volume.read(volume)
    assert vol.shape == (9, 9, 7) and vol.params["batch_step_id"]
    assert 0.0 <= float(row["backproject_iou"]) <= 1.0
    assert cli_main(args) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out       # the result: stdout
    assert read_csv(tmp_path / "out" / "batch.csv")[row["job"]]["backproject_status"] == "skipped"


def test_engine_runs_dependent_tasks_and_reports_failures():
    tasks = [Task("a", _double, (2,), job="j1"), Task("b", _double, (), needs=("a",), job="j1"),
             Task("c", _fail, ("no such mesh",), job="j2"),
             Task("d", _double, (), needs=("c",), job="j2")]
    seen = []
    with Engine("sequential", log=lambda s: None) as engine:
        out = engine.run(tasks, progress=False, on_job=lambda job, o: seen.append(job))
    assert out["b"].result == 8 and out["b"].ok
    assert not out["c"].ok and "no such mesh" in out["c"].error
    assert not out["d"].ok and out["d"].error.startswith("not run")
    assert sorted(seen) == ["j1", "j2"]


def _double(x):
    return 2 * x


def _fail(message):
    raise InputError(message)


def test_cli_submits_to_an_existing_scheduler(client, tmp_path, capsys):
    manifest = write_manifest(tmp_path / "m.toml", '[[sweep]]\nscene = "sphere"\nseed = [1, 2]\n')
    args = ["batch", str(manifest), "--out", str(tmp_path / "out"), "--scheduler",
            client.scheduler.address, "--threads", "1", "--no-progress"]
    assert cli_main(args) == 0
    out, err = capsys.readouterr()
    assert f"Dask scheduler {client.scheduler.address}" in err and "dashboard" in err
    assert "2 done, 0 skipped" in out
    rows = read_csv(tmp_path / "out" / "batch.csv")
    assert sorted(rows) == ["sphere_seed-1", "sphere_seed-2"]
    assert all(r["status"] == "done" for r in rows.values())


def test_job_id_follows_the_mesh_contents_not_its_name(tmp_path, mesh_dir):
    mesh = tmp_path / "part.obj"
    mesh.write_bytes((mesh_dir / "ball0.obj").read_bytes())
    manifest = write_manifest(tmp_path / "m.toml", f'[[job]]\nmesh = "{mesh}"\nfit = false\n')
    first = batch.plan_batch(manifest, tmp_path / "out").jobs[0]
    assert batch.plan_batch(manifest, tmp_path / "out").jobs[0].job_id == first.job_id
    mesh.write_bytes((mesh_dir / "ball1.obj").read_bytes())       # same path, other sphere
    second = batch.plan_batch(manifest, tmp_path / "out").jobs[0]
    assert second.name == first.name and second.job_id != first.job_id


def test_one_batch_per_directory(tmp_path):
    from sonarsim.outputs import OutputBusyError, output_lock
    manifest = write_manifest(tmp_path / "m.toml", '[[job]]\nscene = "sphere"\n')
    plan = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    (tmp_path / "out").mkdir()
    with output_lock(tmp_path / "out" / batch.CSV_NAME):          # another batch runs there
        with pytest.raises(OutputBusyError):
            batch.run_batch(plan, Engine("sequential", log=lambda s: None), progress=False,
                            log=lambda s: None)
    assert not Path(plan.jobs[0].output).exists()


def test_engine_starts_its_own_local_cluster():
    import operator
    tasks = [Task("mul", operator.mul, (6, 7)),
             Task("trim", os.environ.get, ("MALLOC_TRIM_THRESHOLD_", "unset")),
             Task("omp", os.environ.get, ("OMP_NUM_THREADS", "unset"))]
    logged = []
    with Engine(workers=1, threads=2, log=logged.append) as engine:
        out = engine.run(tasks, progress=False)
        assert engine.plan.n_workers == 1 and engine.task_threads == 2
    assert out["mul"].result == 42
    # Dask's default malloc trimming made workers 1.7x slower: not set; BLAS gets the threads
    assert out["trim"].result == "unset" and out["omp"].result == "2"
    assert any("local cluster: 1 worker" in line for line in logged)
    assert any(line.startswith("batch: dashboard") for line in logged)


def test_steps_share_one_deconvolution_and_evaluate_under_several_protocols(tmp_path,
                                                                          monkeypatch):
    """Table 2's pipeline as a manifest: two steps fit the same Wiener-deconvolved dataset
    (made once, identified by its own id), one evaluated under both protocols."""
    from sonarsim.dataset import SonarDataset, Volume
    manifest = write_manifest(tmp_path / "m.toml", """
[[job]]
name = "a"
scene = "sphere"
[[job.reconstruct]]
method = "backproject"
label = "bp"
shape = [9, 9, 7]
deconvolve = "wiener"
evaluate = [{samples = 500},
            {name = "ref", protocol = "reference", volume_samples = 2000, samples = 500}]
[[job.reconstruct]]
method = "backproject"
label = "bp2"
shape = [9, 9, 7]
deconvolve = "wiener"
""")
    plan = batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    (job,) = plan.jobs
    bp, bp2 = job.recon
    assert bp.files == bp2.files and bp.files[0][0].endswith("a.pd-wiener.h5")
    assert [e.output.rsplit("/", 1)[1] for e in bp.evaluations] == ["a.bp.exact.json",
                                                                    "a.bp.ref.json"]
    from recon import deconvolution
    calls = []
    real = deconvolution.deconvolve
    monkeypatch.setattr(deconvolution, "deconvolve",
                        lambda *a, **k: calls.append(a[1]) or real(*a, **k))
    result = batch.run_batch(plan, Engine("sequential", log=lambda s: None), progress=False,
                             log=lambda s: None)
    assert result.status == {"a": "done"} and calls == ["wiener"]     # once for both steps
    pd = SonarDataset.read(tmp_path / "out" / "a.pd-wiener.h5")
    assert pd.waveform_kind != "real" and pd.meta["batch_job_id"] == bp.files[0][2]
    vol = Volume.read(tmp_path / "out" / "a.bp.h5")
    assert vol.params["dataset"] == job.output
    import json
    ref = json.loads((tmp_path / "out" / "a.bp.ref.json").read_text())
    assert ref["metrics"]["protocol"] == "reference" and ref["wall_s"]["solve"] > 0
    rows = read_csv(result.csv)
    assert {"bp_exact_iou", "bp_ref_iou"} <= set(rows["a"])
    stamp = os.stat(tmp_path / "out" / "a.pd-wiener.h5").st_mtime_ns
    again = batch.run_batch(batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None),
                            Engine("sequential", log=lambda s: None), progress=False,
                            log=lambda s: None)
    assert again.submitted == 0 and os.stat(tmp_path / "out" / "a.pd-wiener.h5").st_mtime_ns \
        == stamp


@pytest.mark.parametrize("step, message", [
    ('deconvolve = "magic"', "deconvolve method must be one of wiener, inr"),
    ('deconvolve = {method = "wiener", iterations = 5}', "apply to method 'inr' only"),
    ('deconvolve = {method = "inr", iterations = -1}', "deconvolve inr iterations: must be"),
    ('deconvolve = {method = "inr", width = 8}', "'width' is now 'mlp_width'"),
    ('evaluate = [{protocol = "exact"}, {protocol = "exact"}]', "two evaluations are named"),
    ('evaluate = {threshold = 1.5}', "threshold must lie in [0, 1)"),
    ('evaluate = {colour = "red"}', "evaluate takes"),
])
def test_step_deconvolution_and_evaluation_options_are_checked(tmp_path, step, message):
    manifest = write_manifest(tmp_path / "m.toml", f'[[job]]\nscene = "sphere"\n'
                                                   f'[job.reconstruct]\nmethod = "bp"\n'
                                                   f'shape = [5, 5, 5]\n{step}\n')
    with pytest.raises(InputError) as info:
        batch.plan_batch(manifest, tmp_path / "out", log=lambda s: None)
    assert message in str(info.value)
