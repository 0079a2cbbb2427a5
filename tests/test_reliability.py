"""Reliability (issue 13): refuse before allocating, one-line errors, safe outputs.

Each test reproduces one failure of the hostile-user run (a traceback, an allocation
without refusal, a silent all-zero result, a silently replaced or interleaved output) and
checks the one-line refusal or the right result.
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from recon import synthetic
from recon.cli import main as recon_main
from sonarsim import outputs
from sonarsim.cli import main as sonarsim_main
from sonarsim.dataset import SonarDataset, Volume
from sonarsim.errors import FormatError, InputError

POINT = [0.01, -0.02, 0.09]
BOUNDS = ["-0.04", "0.04", "-0.05", "0.03", "0.06", "0.14"]


def one_line_error(capsys) -> str:
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if not line.startswith("warning")]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.fixture(scope="module")
def point_ds():
    return synthetic.point_dataset([POINT], n_pings=12, heights=(0.05, 0.15))


@pytest.fixture()
def ds_file(point_ds, tmp_path):
    path = tmp_path / "d.h5"
    point_ds.write(path)
    return path


def _variant(ds: SonarDataset, **changes) -> SonarDataset:
    fields = {k: getattr(ds, k) for k in ("waveforms", "tx", "rx", "boresight", "pulse", "fs",
                                          "sound_speed", "source", "start_sample", "meta")}
    fields.update(changes)
    return SonarDataset(**fields)


# ----------------------------------------------------------------------------- recon refusals

@pytest.mark.parametrize("extra, message", [
    (["--pings", "0:10:0"], "STEP must be a positive integer"),
    (["--pings", "0:10:-1"], "STEP must be a positive integer"),
    (["--pings", "99"], "ping 99 does not exist (the dataset has 24: 0 .. 23)"),
    (["--pings=-99"], "ping -99 does not exist"),
    (["--upsample", "100000"], "--upsample must be an integer in 1..1024"),
    (["--shape", "10000", "10000", "10000"], "the volume needs 52154.1 GiB"),
    (["--shape", "2000", "2000", "2000"], "GiB (2000 x 2000 x 2000 voxels"),
    (["--voxel-size", "1e-6"], "GiB ("),
    (["--voxel-size", "1e-300"], "more than 10^12 voxels"),
    (["--max-memory", "1M", "--shape", "64", "64", "64"], "needs 14.0 MiB (64 x 64 x 64 voxels x 56 bytes) but --max-memory is 1.0 MiB"),
    (["--max-memory", "lots"], "--max-memory: expected a size"),
    (["--bounds", "50", "51", "50", "51", "50", "51"], "no voxel of the grid lies within"),
    (["--threads", "0"], "--threads must be an integer >= 1"),
    (["--threads", "100000"], "--threads must be at most 1024"),
])
def test_backproject_refuses_before_allocating(ds_file, tmp_path, capsys, extra, message):
    out = tmp_path / "v.h5"
    argv = ["backproject", str(ds_file), "--out", str(out), "--no-progress"]
    if "--bounds" not in extra:
        argv += ["--bounds", *BOUNDS]
    if "--shape" not in extra and "--voxel-size" not in extra:
        argv += ["--shape", "9", "9", "9"]
    start = time.perf_counter()
    assert recon_main(argv + extra) == 2
    assert time.perf_counter() - start < 20      # refused, not computed
    assert message in one_line_error(capsys)
    assert not out.exists()


@pytest.mark.parametrize("change, message", [
    ({"pulse": "zeros"}, "pulse is all zero"),
    ({"start_sample": -1000}, "no voxel of the grid lies within"),
])
def test_backproject_refuses_silent_all_zero_volume(point_ds, tmp_path, capsys, change, message):
    if change.get("pulse") == "zeros":
        change = {"pulse": np.zeros_like(point_ds.pulse)}
    src = tmp_path / "bad.h5"
    _variant(point_ds, **change).write(src)
    out = tmp_path / "v.h5"
    assert recon_main(["backproject", str(src), "--out", str(out), "--bounds", *BOUNDS,
                       "--shape", "9", "9", "9", "--no-progress"]) == 2
    assert message in one_line_error(capsys)
    assert not out.exists()


def test_backproject_threads_option_gives_the_same_volume(ds_file, tmp_path):
    vols = []
    for threads in ("1", "2"):
        out = tmp_path / f"v{threads}.h5"
        assert recon_main(["backproject", str(ds_file), "--out", str(out), "--bounds", *BOUNDS,
                           "--shape", "9", "9", "9", "--no-progress", "--threads", threads]) == 0
        vols.append(Volume.read(out).volume)
    assert np.array_equal(vols[0], vols[1])
    assert np.abs(vols[0]).max() > 0


# ----------------------------------------------------------------------------- outputs

def _bp(ds_file, out, *extra):
    return recon_main(["backproject", str(ds_file), "--out", str(out), "--bounds", *BOUNDS,
                       "--shape", "5", "5", "5", "--no-progress", *extra])


def test_existing_output_is_not_replaced_without_force(ds_file, tmp_path, capsys):
    out = tmp_path / "notes.txt"
    out.write_text("an unrelated file\n")
    assert _bp(ds_file, out) == 2
    assert "file exists; pass --force to replace it" in one_line_error(capsys)
    assert out.read_text() == "an unrelated file\n"
    assert _bp(ds_file, out, "--force") == 0
    assert Volume.read(out).shape == (5, 5, 5)
    assert not outputs.lock_path(out).exists()       # the lock is removed after the run


def test_out_naming_a_directory_is_refused_up_front(ds_file, tmp_path, capsys):
    target = tmp_path / "adir"
    target.mkdir()
    assert _bp(ds_file, target, "--force") == 2
    assert "is a directory" in one_line_error(capsys)
    start = time.perf_counter()           # simulate: refused before rendering anything
    assert sonarsim_main(["simulate", "sphere", "--poses", "cylindrical:2:1", "--out",
                          str(target), "--no-progress"]) == 2
    assert "is a directory" in one_line_error(capsys)
    assert time.perf_counter() - start < 10


def test_second_writer_fails_at_once(ds_file, tmp_path, capsys):
    out = tmp_path / "v.h5"
    with outputs.output_lock(out):       # a first writer holds the output
        start = time.perf_counter()
        assert _bp(ds_file, out) == 2
        assert time.perf_counter() - start < 20
        assert "another process is writing this output" in one_line_error(capsys)
        assert not out.exists()
    assert _bp(ds_file, out) == 0        # free again once the first writer is done


def test_lock_is_exclusive_across_processes(tmp_path):
    out = tmp_path / "x.h5"
    code = ("import sys, time; from sonarsim import outputs\n"
            "with outputs.output_lock(sys.argv[1]):\n"
            "    print('locked', flush=True); time.sleep(30)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(outputs.OutputBusyError, match="another process"):
            with outputs.output_lock(out):
                pass
    finally:
        proc.kill()
        proc.wait()
    with outputs.output_lock(out):       # the kernel released the killed holder's lock
        pass


# ----------------------------------------------------------------------------- sonarsim info

def _transients_file(path, **changes):
    from sonarsim.dataset import Transients
    t = Transients(transients=np.ones((2, 1, 40), np.float32), path_start=1.0,
                   path_bin_width=343.0 / (100e3 * 20), sound_speed=343.0, fs=100e3,
                   oversample=20, tx=np.zeros((2, 3)), rx=np.zeros((2, 3)))
    t.write(path)
    with h5py.File(path, "r+") as f:
        for key, value in changes.items():
            f.attrs[key] = value
    return path


def _edit_dataset(src, dst, edit):
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst


def _set_nan(f):
    f["waveforms"][1, 3] = np.nan


@pytest.mark.parametrize("edit, problem, refusal", [
    (lambda f: f.attrs.__setitem__("fs", 0.0), "fs must be positive and finite, got 0.0",
     "fs must be positive"),
    (lambda f: f.attrs.__setitem__("sound_speed", 0.0), "sound_speed must be positive",
     "sound_speed must be positive"),
    (_set_nan, "dataset 'waveforms' contains 1 NaN or inf values (first in ping 1)",
     "'waveforms' contains NaN or inf"),
    (lambda f: f["pulse"].__setitem__(slice(None), 0.0), "dataset 'pulse' is all zero",
     "pulse is all zero"),
    (lambda f: f["pings/boresight"].__setitem__(0, [0.0, 0.0, 0.0]), "zero-length direction",
     "zero-length direction"),
    (lambda f: f.__delitem__("pulse"), "missing dataset 'pulse'", "missing dataset 'pulse'"),
])
def test_info_validates_like_the_readers(ds_file, tmp_path, capsys, edit, problem, refusal):
    """`sonarsim info` reports the problem for which the reader (or, for an all-zero pulse,
    recon's check before any work) refuses the file."""
    bad = _edit_dataset(ds_file, tmp_path / "bad.h5", edit)
    if "pulse' is all zero" not in problem:           # every reader refuses these files
        with pytest.raises((FormatError, InputError), match=refusal):
            SonarDataset.read(bad)
    else:                                             # the reader loads it; recon refuses it
        from recon.checks import check_signal
        with pytest.raises(InputError, match=refusal):
            check_signal(SonarDataset.read(bad), "bad.h5")
    assert sonarsim_main(["info", str(bad)]) == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert problem in captured.out
    assert f"{'PROBLEMS':<22} 1: a reader refuses this file" in captured.out


def test_info_summary_still_printed_for_invalid_dataset(ds_file, tmp_path, capsys):
    bad = _edit_dataset(ds_file, tmp_path / "bad.h5", lambda f: f.attrs.__setitem__("fs", 0.0))
    assert sonarsim_main(["info", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "N = 24 pings" in out and "tx positions" in out


def test_info_transients_with_zero_bin_width(tmp_path, capsys):
    bad = _transients_file(tmp_path / "t.h5", path_bin_width=0.0)
    assert sonarsim_main(["info", str(bad)]) == 1
    assert "path_bin_width must be positive" in capsys.readouterr().out
    good = _transients_file(tmp_path / "good.h5")
    assert sonarsim_main(["info", str(good)]) == 0
    assert "PROBLEMS" not in capsys.readouterr().out


def test_info_valid_dataset_exits_zero(ds_file, capsys):
    assert sonarsim_main(["info", str(ds_file)]) == 0
    out = capsys.readouterr().out
    assert "PROBLEMS" not in out and "N = 24 pings" in out


# ----------------------------------------------------------------------------- importers

def _shared_tuple_bomb(depth: int, as_key: bool) -> bytes:
    """t0 = (); t(i+1) = (t(i), t(i)) through the memo: a few bytes per level, 2^depth
    leaves. As a dictionary key (hashed while loading) or as the top-level 'wfm_data'."""
    out = bytearray(b"\x80\x02)q\x000")             # PROTO 2, EMPTY_TUPLE, BINPUT 0, POP
    for i in range(depth):       # BINGET i, BINGET i, TUPLE2, BINPUT i+1, POP
        out += b"h" + bytes([i]) + b"h" + bytes([i]) + b"\x86q" + bytes([i + 1]) + b"0"
    top = b"h" + bytes([depth])
    if as_key:
        out = b"\x80\x02}q\xfe" + bytes(out[2:]) + top + b"N" + b"s."   # {t: None}
    else:
        out = (b"\x80\x02}q\xfeX\x08\x00\x00\x00wfm_data" + bytes(out[2:]) + top
               + b"s.")                                 # {'wfm_data': t}
    return bytes(out)


@pytest.mark.parametrize("depth, as_key, message", [
    (34, True, "nested deeper than"),
    (34, False, "nested deeper than"),
    (20, True, "dictionary key or set member of type tuple"),
    (20, False, "field 'wfm_data' is a tuple, expected a NumPy array"),
])
def test_pickle_bombs_are_refused_fast(tmp_path, capsys, depth, as_key, message):
    from sonarsim.importers.pik import import_pik
    path = tmp_path / "system_data.pik"
    path.write_bytes(_shared_tuple_bomb(depth, as_key))
    assert len(path.read_bytes()) < 320
    start = time.perf_counter()
    with pytest.raises(FormatError, match=message):
        import_pik(path)
    assert time.perf_counter() - start < 5
    out = tmp_path / "d.h5"
    assert sonarsim_main(["import-pik", str(path), "--out", str(out)]) == 2
    assert message in one_line_error(capsys)
    assert not out.exists()


def test_pickle_length_field_beyond_the_file_is_refused(tmp_path):
    from sonarsim.importers.pik import load_system_pickle
    path = tmp_path / "system_data.pik"
    path.write_bytes(b"\x80\x04\x8e" + (2**40).to_bytes(8, "little") + b"abc")  # BINBYTES8
    with pytest.raises(FormatError, match="only 3 remain"):
        load_system_pickle(path)


AIRSAS_SCAN = "airsas_real/small_features_cutout_5k"


@pytest.fixture()
def small_scan(shared_data, tmp_path):
    import shutil
    src, dst = shared_data / AIRSAS_SCAN, tmp_path / "scan"
    dst.mkdir()
    for name in ("SysParams.csv", "WaveformParams.csv", "Waveforms.csv"):
        shutil.copy(src / name, dst / name)
    lines = (src / "Coordinates.csv").read_text().splitlines()[:3]
    (dst / "Coordinates.csv").write_text("\n".join(lines) + "\n")
    for i in (1, 2):
        shutil.copy(src / f"Flight-{i:06d}.csv", dst / f"Flight-{i:06d}.csv")
    return dst


def _set_group_delay(scan: Path, value: str) -> None:
    path = scan / "SysParams.csv"
    lines = [f"Group Delay,{value}" if ln.startswith("Group Delay") else ln
             for ln in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("damage, message", [
    ("header-only", "Coordinates.csv: line 2: no data rows (only a header)"),
    ("delay 1e9", "field 'Group Delay' = 1e+09 samples is not shorter than"),
    ("delay -1e9", "field 'Group Delay' = -1e+09 samples is not shorter than"),
])
def test_import_airsas_refuses_damaged_scans(small_scan, tmp_path, capsys, damage, message):
    if damage == "header-only":
        coords = small_scan / "Coordinates.csv"
        coords.write_text(coords.read_text().splitlines()[0] + "\n")
    else:
        _set_group_delay(small_scan, damage.split()[1])
    out = tmp_path / "d.h5"
    assert sonarsim_main(["import-airsas", str(small_scan), "--out", str(out),
                          "--no-progress"]) == 2
    assert message in one_line_error(capsys)
    assert not out.exists()


# ----------------------------------------------------------------------------- .partial files

def _writer(path, ds, **kw):
    from sonarsim.dataset import DatasetStreamWriter
    return DatasetStreamWriter(path, n_samples=ds.n_samples, tx=ds.tx, rx=ds.rx,
                               boresight=ds.boresight, pulse=ds.pulse, fs=ds.fs,
                               sound_speed=ds.sound_speed, source=ds.source,
                               start_sample=ds.start_sample, meta=ds.meta, **kw)


def test_corrupted_partial_file_is_verified_before_resuming(point_ds, tmp_path, capsys):
    out = tmp_path / "D.h5"
    w = _writer(out, point_ds)
    w.write(0, point_ds.waveforms[:20])           # an interrupted run: 20 of 24 pings
    w.close()
    partial = Path(str(out) + ".partial")
    with h5py.File(partial, "r") as f:
        offset = f["waveforms"].id.get_offset()
    rng = np.random.default_rng(1)
    with open(partial, "r+b") as f:               # 4 KiB of random bytes over the data
        f.seek(offset + 4 * point_ds.n_samples * 3)
        f.write(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    w = _writer(out, point_ds)
    assert w.resumed
    assert "fail their checksum" in capsys.readouterr().err
    missing = w.missing_ranges(100)
    rows = -(-4096 // (4 * point_ds.n_samples))    # rows the random bytes overwrote
    assert missing == [(3, 3 + rows), (20, 24)]
    for a, b in missing:
        w.write(a, point_ds.waveforms[a:b])
    w.finish()
    result = SonarDataset.read(out)                # no NaN rows, the same data
    assert np.array_equal(result.waveforms, point_ds.waveforms)


# ----------------------------------------------------------------------------- simulate / render

SIM = ["simulate", "sphere", "--poses", "cylindrical:2:1", "--paths-per-pose", "600",
       "--no-progress"]


@pytest.mark.parametrize("extra, message", [
    (["--fs", "1e12"], "--fs must be in (0, 1e+08] Hz, got 1e+12"),
    (["--pulse", "lfm:30000:10000:10"], "lasts 10 s (1000000 samples at 100000 Hz)"),
    (["--fs", "2e7", "--max-memory", "64M"], "the simulation needs"),
    (["--pulse", "ZEROS"], "is all zero: every waveform would be zero"),
])
def test_simulate_refuses_before_rendering(tmp_path, capsys, extra, message):
    if "ZEROS" in extra:
        np.save(tmp_path / "zeros.npy", np.zeros(100))
        extra = ["--pulse", str(tmp_path / "zeros.npy")]
    out = tmp_path / "d.h5"
    start = time.perf_counter()
    assert sonarsim_main(SIM + ["--out", str(out)] + extra) == 2
    assert time.perf_counter() - start < 30
    assert message in one_line_error(capsys)
    assert not out.exists() and not Path(str(out) + ".partial").exists()


def test_finished_simulate_is_not_rendered_again(tmp_path, capsys):
    out = tmp_path / "d.h5"
    assert sonarsim_main(SIM + ["--out", str(out)]) == 0
    before = out.stat().st_mtime_ns, out.read_bytes()
    capsys.readouterr()
    assert sonarsim_main(SIM + ["--out", str(out)]) == 0          # same settings
    assert "already complete" in capsys.readouterr().out          # a result: stdout
    assert (out.stat().st_mtime_ns, out.read_bytes()) == before
    assert sonarsim_main(SIM + ["--out", str(out), "--seed", "7"]) == 2   # other settings
    assert "file exists (not this run's result); pass --force" in one_line_error(capsys)
    assert out.read_bytes() == before[1]
    assert sonarsim_main(SIM + ["--out", str(out), "--seed", "7", "--force"]) == 0
    assert SonarDataset.read(out).seed == 7


def test_render_refuses_huge_fs_and_existing_output(tmp_path, capsys):
    out = tmp_path / "t.h5"
    render = ["render", "sphere", "--poses", "cylindrical:2:1", "--paths-per-pose", "200",
              "--no-progress", "--out", str(out)]
    assert sonarsim_main(render + ["--fs", "1e12"]) == 2
    assert "--fs must be in" in one_line_error(capsys)
    out.write_text("keep me")
    assert sonarsim_main(render) == 2
    assert "file exists; pass --force" in one_line_error(capsys)
    assert out.read_text() == "keep me"


def test_export_keeps_existing_outputs_without_force(ds_file, tmp_path, capsys):
    vol = tmp_path / "v.h5"
    assert _bp(ds_file, vol) == 0
    mip = tmp_path / "mip.png"
    mip.write_text("old picture")
    assert recon_main(["export", str(vol), "--mip", str(mip)]) == 2
    assert "--mip" in one_line_error(capsys) and mip.read_text() == "old picture"
    slices = tmp_path / "slices"
    slices.mkdir()
    (slices / "mine.txt").write_text("x")
    assert recon_main(["export", str(vol), "--slices", str(slices)]) == 2
    assert "directory is not empty" in one_line_error(capsys)
    assert recon_main(["export", str(vol), "--mip", str(mip), "--force"]) == 0
    assert mip.read_bytes()[:4] == b"\x89PNG"


def test_gd_refuses_a_huge_grid_before_allocating(ds_file, tmp_path, capsys):
    out = tmp_path / "v.h5"
    start = time.perf_counter()
    assert recon_main(["gd", str(ds_file), "--out", str(out), "--bounds", *BOUNDS,
                       "--shape", "2000", "2000", "2000", "--no-progress"]) == 2
    assert time.perf_counter() - start < 30
    assert "GiB (2000 x 2000 x 2000 voxels" in one_line_error(capsys)


def test_output_in_a_new_directory_is_still_created(ds_file, tmp_path):
    out = tmp_path / "new" / "sub" / "v.h5"
    assert _bp(ds_file, out) == 0
    assert Volume.read(out).shape == (5, 5, 5)
    assert sorted(p.name for p in out.parent.iterdir()) == ["v.h5"]


def test_simulate_while_another_simulate_writes_the_same_output(tmp_path, capsys):
    """The issue's race: a second run on the same --out fails at once, the first is unharmed."""
    out = tmp_path / "d.h5"
    first = subprocess.Popen(
        [sys.executable, "-m", "sonarsim.cli", "simulate", "sphere", "--poses", "cylindrical:30:2",
         "--paths-per-pose", "4000", "--snr-db", "20", "--no-progress", "--out", str(out)],
        stderr=subprocess.PIPE, text=True)
    try:
        lock = outputs.lock_path(out)
        deadline = time.time() + 60
        while not lock.exists() and first.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert lock.exists(), "the first run never took the lock"
        assert sonarsim_main(SIM + ["--out", str(out), "--snr-db", "20"]) == 2
        assert "another process is writing this output" in one_line_error(capsys)
        assert first.wait(timeout=240) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert SonarDataset.read(out).n_pings == 60
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5"]     # no scratch left behind


@pytest.mark.parametrize("text, expected", [
    ("8G", 8 * 2**30), ("512M", 512 * 2**20), ("1.5GiB", int(1.5 * 2**30)), ("2e9", 2 * 10**9),
    ("100k", 102400)])
def test_max_memory_sizes(text, expected):
    from sonarsim import limits
    assert limits.parse_size(text) == expected


def test_max_memory_from_the_environment(ds_file, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SONARSIM_MAX_MEMORY", "100k")
    assert _bp(ds_file, tmp_path / "v.h5") == 2
    assert "but SONARSIM_MAX_MEMORY is 0.1 MiB" in one_line_error(capsys)


def test_negative_seed_is_one_line_for_every_command(ds_file, tmp_path, capsys):
    vol = tmp_path / "v.h5"
    assert _bp(ds_file, vol) == 0
    assert recon_main(["evaluate", str(vol), "--gt", "sphere", "--no-images", "--no-sweep",
                       "--seed", "-1"]) == 2
    assert "--seed must be in [0, 2^32), got -1" in one_line_error(capsys)


# ----------------------------------------------------- rails: issue 23 (data lost, disk full,
# ----------------------------------------------------- manifests, readers); issue 22 item 1

BATCH_FAST = ('[defaults]\nposes = "cylindrical:4:1"\npaths_per_pose = 200\nbounces = 1\n'
              'bounce1 = "cone"\n')


def _manifest(tmp_path, body: str, defaults: str = BATCH_FAST) -> Path:
    path = tmp_path / "m.toml"
    path.write_text(defaults + body)
    return path


def _batch(manifest, out, *extra):
    return sonarsim_main(["batch", str(manifest), "--out", str(out), "--scheduler",
                          "sequential", "--no-progress", *extra])


def test_batch_outputs_that_would_overwrite_each_other_are_refused(tmp_path, capsys):
    """Job 'a' with a 'bp' reconstruction writes a.bp.h5, which is also job 'a.bp''s dataset."""
    m = _manifest(tmp_path, '[[job]]\nname = "a"\nscene = "sphere"\n[job.reconstruct]\n'
                            'method = "backproject"\nlabel = "bp"\nshape = [5, 5, 5]\n'
                            '[[job]]\nname = "a.bp"\nscene = "sphere"\nseed = 1\n')
    assert _batch(m, tmp_path / "out", "--dry-run") == 2
    line = one_line_error(capsys)
    assert "a.bp.h5 would be both" in line and "'a.bp'" in line
    assert not (tmp_path / "out").exists()


def test_batch_never_replaces_a_dataset_it_did_not_make_for_that_job(point_ds, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    point_ds.write(out / "mine.h5")                  # the user's dataset
    before = (out / "mine.h5").read_bytes()
    m = _manifest(tmp_path, '[[job]]\nname = "mine"\nscene = "sphere"\n')
    assert _batch(m, out) == 2
    assert "mine.h5 exists and is a sonar dataset not made by this batch" in \
        one_line_error(capsys)
    assert (out / "mine.h5").read_bytes() == before and not (out / "batch.csv").exists()


@pytest.mark.parametrize("setting, message", [
    ('paths_per_pose = 1e30', "paths_per_pose must be an integer"),
    ('snr_db = "abc"', "snr_db must be a number"),
    ('beams = {tx_beam = "laser"}', "laser"),
    ('threads = 100000', "threads must be at most 1024"),
    ('fs = 1e12', "must be in (0, 1e+08] Hz, got 1e+12"),
    ('[job.reconstruct]\nmethod = "gd"\niterations = -3', "iterations: must be >= 1, got -3"),
    ('[job.reconstruct]\nmethod = "gd"\nlr = "fast"', "lr must be a number, got 'fast'"),
    ('[job.reconstruct]\nmethod = "backproject"\nvoxel_size = 1e-6', "the volume needs"),
    ('[job.reconstruct]\nmethod = "backproject"\nvoxel_size = 1e-300',
     "gives more than 10^12 voxels"),
])
def test_batch_refuses_bad_settings_before_anything_runs(tmp_path, capsys, setting, message):
    m = _manifest(tmp_path, f'[[job]]\nscene = "sphere"\n{setting}\n')
    start = time.perf_counter()
    assert _batch(m, tmp_path / "out") == 2
    assert time.perf_counter() - start < 30
    line = one_line_error(capsys)
    assert message in line and line.startswith("sonarsim: error: job[0]"), line
    assert not (tmp_path / "out").exists()


def test_batch_absurd_sample_rate_and_grid_say_what_the_cli_says(ds_file, tmp_path, capsys):
    """The same rule, so the same sentence (the CLI names --fs, the manifest fs)."""
    assert sonarsim_main(["simulate", "sphere", "--poses", "cylindrical:4:1", "--fs", "1e12",
                          "--out", str(tmp_path / "s.h5")]) == 2
    cli = one_line_error(capsys).split("--fs ", 1)[1]
    assert _batch(_manifest(tmp_path, '[[job]]\nscene = "sphere"\nfs = 1e12\n'),
                  tmp_path / "out") == 2
    assert one_line_error(capsys).endswith("fs " + cli)
    assert recon_main(["backproject", str(ds_file), "--out", str(tmp_path / "v.h5"),
                       "--bounds", *BOUNDS, "--voxel-size", "1e-300"]) == 2
    cli = one_line_error(capsys).split("error: ", 1)[1]
    bounds = "[" + ", ".join(BOUNDS) + "]"
    assert _batch(_manifest(tmp_path, f'[[job]]\nscene = "sphere"\n[job.reconstruct]\n'
                                      f'method = "backproject"\nbounds = {bounds}\n'
                                      f'voxel_size = 1e-300\n'), tmp_path / "out") == 2
    # ... in the manifest's words: its keys, not the command line's options
    for option in ("voxel-size", "shape", "bounds"):
        cli = cli.replace(f"--{option}", option.replace("-", "_"))
    assert one_line_error(capsys).endswith(": " + cli)


@pytest.mark.parametrize("step, message", [
    ("voxel_size = -1", "reconstruct[0]: voxel_size: must be a positive finite number"),
    ('method = "gd"\npings_per_iteration = 0', "reconstruct[0]: pings_per_iteration"),
    ('method = "nbp"\nn_rays = 100000000', "lower n_rays, bins_per_ping or pings_per_chunk"),
    ('evaluate = {protocol = "nonsense"}', "evaluate protocol: choose one of exact, reference"),
    ('evaluate = [{mapping = "x"}]', "evaluate mapping: choose one of reference, centre"),
])
def test_batch_step_messages_name_the_manifests_keys(tmp_path, capsys, step, message):
    method = "" if "method" in step else 'method = "bp"\n'
    m = _manifest(tmp_path, f'[[job]]\nscene = "sphere"\n[job.reconstruct]\n{method}{step}\n')
    assert _batch(m, tmp_path / "out", "--dry-run") == 2
    line = one_line_error(capsys)
    assert message in line and "--" not in line.split("reconstruct[0]")[1], line


def test_batch_job_count_is_capped_and_planning_is_quick(tmp_path, capsys):
    seeds = ", ".join(str(i) for i in range(200))
    m = _manifest(tmp_path, f'[[sweep]]\nscene = "sphere"\nseed = [{seeds}]\n'
                            f'snr_db = [{", ".join(str(i) for i in range(60))}]\n')
    start = time.perf_counter()
    assert _batch(m, tmp_path / "out", "--dry-run") == 2
    assert time.perf_counter() - start < 10
    assert "12000 jobs, more than the 10000 allowed without --max-jobs" in one_line_error(capsys)


@pytest.mark.parametrize("argv, message", [
    (["--scheduler", "garbage"], "--scheduler 'garbage': expected 'sequential' or a Dask"),
    (["--threads", "100000"], "--threads must be at most 1024"),
    (["--max-jobs", "0"], "--max-jobs must be >= 1"),
])
def test_batch_command_line_refusals_are_one_line(tmp_path, capsys, argv, message):
    m = _manifest(tmp_path, '[[job]]\nscene = "sphere"\n')
    assert sonarsim_main(["batch", str(m), "--out", str(tmp_path / "out"), *argv]) == 2
    assert message in one_line_error(capsys)


def test_batch_workers_are_capped_to_the_machine():
    from sonarsim.batch_engine import plan_local_cluster
    with pytest.warns(UserWarning, match="--workers 50 is more than this machine"):
        plan = plan_local_cluster(100, cores=2, workers=50, memory=64 * 2**30)
    assert plan.n_workers == 2 and plan.threads == 1


def test_batch_corrupt_table_does_not_block_a_rerun(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "batch.csv").write_bytes(b"job,status\n\xff\xfe\x00garbage\x9c\n")
    m = _manifest(tmp_path, '[[job]]\nname = "s"\nscene = "sphere"\n')
    assert _batch(m, out) == 0
    assert "s,done," in (out / "batch.csv").read_text()


def _unexpected(counter: list):
    counter.append(1)
    raise TypeError("unsupported operand type(s) for +: 'int' and 'str'")


def test_batch_unexpected_errors_are_not_retried_as_if_transient():
    from sonarsim.batch_engine import Engine, Task
    calls: list = []
    with Engine("sequential", retries=2, log=lambda s: None) as engine:
        (outcome,) = engine.run([Task("t", _unexpected, (calls,))], progress=False).values()
    assert len(calls) == 1
    assert not outcome.ok and outcome.error.startswith("unexpected TypeError: unsupported")


class _LostEngine:
    """An engine whose cluster is lost mid-run (after it started)."""

    def __init__(self):
        self.started = False

    def start(self, n):
        self.started = True

    def run(self, tasks, progress, on_job):
        raise ConnectionError("the scheduler went away")


def test_batch_unfinished_jobs_are_not_left_pending(tmp_path):
    import csv
    from sonarsim import batch
    m = _manifest(tmp_path, '[[job]]\nname = "s"\nscene = "sphere"\n')
    plan = batch.plan_batch(m, tmp_path / "out", log=lambda s: None)
    with pytest.raises(ConnectionError):
        batch.run_batch(plan, _LostEngine(), progress=False, log=lambda s: None)
    with open(tmp_path / "out" / "batch.csv") as fh:
        (row,) = csv.DictReader(fh)
    assert row["status"] == "not run" and "stopped" in row["error"]


def test_concurrent_batch_finds_the_lock_before_starting_a_cluster(tmp_path):
    from sonarsim import batch
    m = _manifest(tmp_path, '[[job]]\nname = "s"\nscene = "sphere"\n')
    plan = batch.plan_batch(m, tmp_path / "out", log=lambda s: None)
    engine = _LostEngine()
    (tmp_path / "out").mkdir()
    with outputs.output_lock(tmp_path / "out" / "batch.csv"):
        with pytest.raises(outputs.OutputBusyError):
            batch.run_batch(plan, engine, progress=False, log=lambda s: None)
    assert not engine.started


def test_info_exits_1_for_a_killed_runs_partial_file(point_ds, tmp_path, capsys):
    out = tmp_path / "D.h5"
    w = _writer(out, point_ds)
    w.write(0, point_ds.waveforms[:5])
    w.close()                                        # as a killed run leaves it
    renamed = tmp_path / "renamed.h5"
    renamed.write_bytes(Path(str(out) + ".partial").read_bytes())
    for path in (Path(str(out) + ".partial"), renamed):
        assert sonarsim_main(["info", str(path)]) == 1
        text = capsys.readouterr().out
        assert "INCOMPLETE" in text and "incomplete file" in text


def test_zero_ping_datasets_are_refused_by_the_writer_and_the_readers(point_ds, ds_file,
                                                                       tmp_path, capsys):
    with pytest.raises(InputError, match="at least one ping"):
        _variant(point_ds, waveforms=point_ds.waveforms[:0], tx=point_ds.tx[:0],
                 rx=point_ds.rx[:0], boresight=point_ds.boresight[:0])
    empty = tmp_path / "empty.h5"
    with h5py.File(ds_file, "r") as src, h5py.File(empty, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        def copy(name, obj):
            if isinstance(obj, h5py.Dataset):
                data = obj[()]
                dst.create_dataset(name, data=data[:0] if name.startswith(("pings", "wave"))
                                   else data)
        src.visititems(copy)
    with pytest.raises(FormatError, match="at least one ping"):
        SonarDataset.read(empty)
    assert sonarsim_main(["info", str(empty)]) == 1
    assert "at least one ping" in capsys.readouterr().out
    assert recon_main(["backproject", str(empty), "--out", str(tmp_path / "v.h5")]) == 2
    assert "at least one ping" in one_line_error(capsys)


@pytest.mark.parametrize("command", ["backproject", "pfa", "gd", "nbp"])
def test_a_volume_given_as_dataset_says_what_it_is(ds_file, tmp_path, capsys, command):
    vol = tmp_path / "v.h5"
    assert _bp(ds_file, vol) == 0
    capsys.readouterr()
    assert recon_main([command, str(vol), "--out", str(tmp_path / "w.h5"), "--shape", "5", "5",
                       "5", "--no-progress"]) == 2
    line = one_line_error(capsys)
    assert "this is a volume file, not a sonar dataset" in line and "corrupt" not in line


@pytest.mark.parametrize("command", ["backproject", "pfa", "gd", "nbp", "deconvolve"])
def test_a_transients_file_given_as_dataset_says_what_it_is(tmp_path, capsys, command):
    from sonarsim.dataset import Transients
    rng = np.random.default_rng(0)
    tr = tmp_path / "t.h5"
    Transients(rng.random((2, 1, 50), dtype=np.float32), 1.0, 343.0 / (1e5 * 20), 343.0, 1e5, 20,
               rng.random((2, 3)), rng.random((2, 3))).write(tr)
    grid = [] if command == "deconvolve" else ["--shape", "5", "5", "5", "--no-progress"]
    assert recon_main([command, str(tr), "--out", str(tmp_path / "w.h5"), *grid]) == 2
    line = one_line_error(capsys)
    assert "this is a transients file, not a sonar dataset" in line and "corrupt" not in line


def test_a_full_disk_is_one_line_before_writing(ds_file, tmp_path, capsys, monkeypatch):
    from sonarsim import atomic
    monkeypatch.setattr(atomic, "free_bytes", lambda path: 1000)
    out = tmp_path / "v.h5"
    assert _bp(ds_file, out) == 2
    line = one_line_error(capsys)
    assert f"cannot write {out}: the volume needs about" in line and "are free" in line
    assert list(tmp_path.iterdir()) == [ds_file]


def test_a_fit_whose_volume_will_not_fit_on_the_disk_is_refused_before_any_work(
        ds_file, tmp_path, capsys, monkeypatch):
    """The volume's size is known from the grid: a gradient-descent fit is refused before its
    first iteration instead of failing at the end (a 4 MB tmpfs as --out)."""
    from recon import solver
    from sonarsim import atomic
    monkeypatch.setattr(atomic, "free_bytes", lambda path: 1000)
    monkeypatch.setattr(solver, "solve", lambda *a, **k: pytest.fail("the fit ran"))
    out = tmp_path / "v.h5"
    assert recon_main(["gd", str(ds_file), "--out", str(out), "--shape", "5", "5", "5",
                       "--iterations", "2", "--no-progress"]) == 2
    assert f"cannot write {out}: the volume needs about" in one_line_error(capsys)
    assert list(tmp_path.iterdir()) == [ds_file]


def test_a_write_failing_midway_is_one_line_and_leaves_nothing(tmp_path):
    """A file-size limit makes a write fail halfway (EFBIG; a full disk fails the same way
    with ENOSPC, reproduced on a 20 MB tmpfs): one WriteError line naming the final path, no
    file there, no temporary file left. (HDF5 2.0 itself crashes after a failed write, which
    is why HDF5 writers check the free space first: test above.)"""
    out = tmp_path / "poses.npy"
    code = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            "resource.setrlimit(resource.RLIMIT_FSIZE, (30000, 30000)); "
            "import numpy as np; from sonarsim.atomic import atomic_path; "
            "from sonarsim.errors import WriteError\n"
            "try:\n"
            "    with atomic_path(sys.argv[1]) as tmp:\n"
            "        np.save(tmp, np.zeros(100000))\n"
            "except WriteError as exc:\n"
            "    print(exc); sys.exit(2)")
    r = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True,
                       timeout=300)
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and not r.stderr, r
    assert lines[0].startswith(f"cannot write {out}: ")
    assert list(tmp_path.iterdir()) == []


def test_a_killed_writers_temporary_file_is_removed_by_the_next_run(ds_file, tmp_path):
    out = tmp_path / "v.h5"
    leftover = tmp_path / ".v.h5.k1ll3d_x.tmp"        # what kill -9 mid-write leaves
    leftover.write_bytes(b"\0" * 4096)
    other = tmp_path / ".w.h5.k1ll3d_x.tmp"           # another output's: not ours to judge
    other.write_bytes(b"\0")
    assert _bp(ds_file, out) == 0
    assert not leftover.exists() and other.exists()
    assert Volume.read(out).shape == (5, 5, 5)


def test_a_librarys_disk_full_error_is_one_line_and_leaves_nothing(tmp_path):
    """OpenEXR says a disk is full as RuntimeError('... No space left on device.') and pyevtk
    writes to the name it is given + '.vti' (reproduced on a 4 MB tmpfs: `recon export --exr`
    was a traceback, `--vti` left .v.vti.XXXXXXXX.vti.vti behind)."""
    from sonarsim.atomic import atomic_path
    from sonarsim.errors import WriteError
    out = tmp_path / "v.vti"
    with pytest.raises(WriteError) as info:
        with atomic_path(out) as tmp:
            Path(f"{tmp}.vti").write_bytes(b"\0" * 4096)
            raise RuntimeError(f'Failed to write pixel data to image file "{tmp}". '
                               "No space left on device.")
    assert str(info.value) == (f"cannot write {out}: no space left on the device (disk full); "
                               "free some space or write elsewhere")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="a bug"):     # not a write failure: unchanged
        with atomic_path(out):
            raise RuntimeError("a bug")


def test_a_killed_writers_derived_temporary_file_is_removed_by_the_next_run(tmp_path):
    from sonarsim.atomic import atomic_path
    out = tmp_path / "v.vti"
    leftover = tmp_path / ".v.vti.k1ll3d_x.vti.vti"    # pyevtk's name for atomic_path's temp
    leftover.write_bytes(b"\0" * 4096)
    with atomic_path(out) as tmp:
        tmp.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.vti"]


# ------------------------------------------- firstday-b: broken pipes and Ctrl-C (issue 23.6)

def _into_a_closed_pipe(args):
    """Run ``python -m ARGS`` with stdout a pipe whose reader has gone (``... | head -1``
    after head exited)."""
    import os
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run([sys.executable, "-m", *args], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(write)


def test_output_into_a_closed_pipe_stops_silently_with_sigpipe_status(ds_file, tmp_path):
    # was: a BrokenPipeError traceback and exit status 1
    info = _into_a_closed_pipe(["sonarsim.cli", "info", str(ds_file)])
    assert (info.returncode, info.stderr) == (141, "")
    vol = tmp_path / "v.h5"
    assert _bp(ds_file, vol) == 0
    evaluate = _into_a_closed_pipe(["recon.cli", "evaluate", str(vol), "--gt", "sphere",
                                    "--no-images", "--no-sweep", "--json"])
    assert evaluate.returncode == 141          # stderr: at most the evaluation's own warnings
    assert all(line.startswith(("warning", "recon evaluate: warning"))
               for line in evaluate.stderr.splitlines()), evaluate.stderr


def test_ctrl_c_while_the_commands_load_is_one_line(monkeypatch, capsys):
    # was: a KeyboardInterrupt traceback (an interrupt before the command ran, e.g. while
    # the command modules were being imported)
    from sonarsim import cli_common

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli_common, "build_parser", interrupted)
    assert sonarsim_main(["info", "x.h5"]) == 130
    assert one_line_error(capsys) == "sonarsim: interrupted"


def test_ctrl_c_during_a_run_is_one_line_and_leaves_no_output(tmp_path):
    import os
    import signal
    ds = synthetic.point_dataset([POINT], n_pings=4000, heights=(0.05, 0.15))
    ds.write(tmp_path / "d.h5")
    out = tmp_path / "v.h5"
    env = dict(os.environ, SONARSIM_PROGRESS_INTERVAL="0.05")
    proc = subprocess.Popen([sys.executable, "-m", "recon.cli", "backproject",
                             str(tmp_path / "d.h5"), "--out", str(out), "--shape", "120", "120",
                             "120", "--threads", "1"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stderr.readline()           # the first progress line: the run is under way
        assert "backprojection" in line, line
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [x for x in err.splitlines() if not x.startswith("recon backproject: backprojection")]
    assert proc.returncode == 130 and lines == ["recon: interrupted"], err
    assert not out.exists()


def test_an_os_error_no_writer_caught_is_one_line(tmp_path, capsys, monkeypatch):
    # firstday-b, issue 23.6 at the CLI level: was an OSError traceback (e.g. ENOSPC from a
    # writer that does not go through sonarsim.atomic)
    import errno
    import os
    from sonarsim.importers import openstb

    def disk_full(dataset, path, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    monkeypatch.setattr(openstb, "write_openstb", disk_full)
    d = tmp_path / "d.h5"
    synthetic.point_dataset([POINT], n_pings=4).write(d)
    assert sonarsim_main(["export-openstb", str(d), "--out", str(tmp_path / "r.zarr")]) == 1
    assert one_line_error(capsys) == f"sonarsim: error: {tmp_path / 'r.zarr'}: No space left on device"


# ------------------------------------------------ evaltable: issue 23 (items 4, 5), my commands

def test_backproject_with_a_beam_mask_no_voxel_sees_is_refused(ds_file, tmp_path, capsys):
    # was: an all-zero volume written with exit 0 (`--beam-mask 0.0001`)
    out = tmp_path / "v.h5"
    assert recon_main(["backproject", str(ds_file), "--out", str(out), "--bounds", *BOUNDS,
                       "--shape", "8", "8", "8", "--beam-mask", "0.0001"]) == 2
    line = one_line_error(capsys)
    assert "--beam-mask" in line and "all zero" in line
    assert not out.exists()
    assert recon_main(["backproject", str(ds_file), "--out", str(out), "--bounds", *BOUNDS,
                       "--shape", "8", "8", "8", "--beam-mask", "60"]) == 0
    assert np.any(Volume.read(out).volume)


# ----------------------------------------------------- solver: issue 23 (checkpoints, warm
# ----------------------------------------------------- start chunking, solver option ranges)

GD_SMALL = ["--bounds", *BOUNDS, "--shape", "6", "6", "6", "--iterations", "2", "--n-rays", "50",
            "--bins-per-ping", "8", "--no-progress"]


@pytest.mark.parametrize("method", ["gd", "nbp"])
def test_checkpoint_never_replaces_the_dataset(ds_file, tmp_path, capsys, method):
    """``--checkpoint`` naming the input dataset turned it into a zip (exit 0); now refused
    in one line without --force, and with --force too (it is not a checkpoint); unchanged."""
    before = ds_file.read_bytes()
    for force in ([], ["--force"]):
        rc = recon_main([method, str(ds_file), *GD_SMALL, "--out", str(tmp_path / "v.h5"),
                         "--checkpoint", str(ds_file), *force])
        assert rc == 2
        line = one_line_error(capsys)
        assert "--checkpoint" in line and ("exists" in line or "not a solver checkpoint" in line)
    assert ds_file.read_bytes() == before
    assert not (tmp_path / "v.h5").exists()


def test_checkpoint_directory_refused_before_the_run(ds_file, tmp_path, capsys, monkeypatch):
    from recon import solver
    ran = []
    monkeypatch.setattr(solver, "fit", lambda *a, **k: ran.append(1))
    rc = recon_main(["gd", str(ds_file), *GD_SMALL, "--out", str(tmp_path / "v.h5"),
                     "--checkpoint", str(tmp_path)])
    assert rc == 2 and "is a directory" in one_line_error(capsys) and not ran


def test_existing_checkpoint_replaced_only_with_force_or_resumed(ds_file, tmp_path, capsys):
    ck = tmp_path / "ck.npz"
    args = ["gd", str(ds_file), *GD_SMALL, "--checkpoint", str(ck)]
    assert recon_main([*args, "--out", str(tmp_path / "a.h5")]) == 0
    stamp = ck.read_bytes()
    assert recon_main([*args, "--out", str(tmp_path / "b.h5")]) == 2
    assert "exists" in one_line_error(capsys) and ck.read_bytes() == stamp
    assert recon_main([*args, "--out", str(tmp_path / "c.h5"), "--resume"]) == 0
    # (e.h5: d.h5 is the dataset, which this line once overwrote with --force)
    assert recon_main([*args, "--out", str(tmp_path / "e.h5"), "--force"]) == 0


def test_checkpoint_with_a_negative_iteration_is_refused(ds_file, tmp_path, capsys):
    ck = tmp_path / "ck.npz"
    args = ["gd", str(ds_file), *GD_SMALL, "--checkpoint", str(ck)]
    assert recon_main([*args, "--out", str(tmp_path / "a.h5")]) == 0
    with np.load(ck) as z:
        data = {k: z[k] for k in z.files}
    data["iteration"] = np.array(-3, dtype=np.int64)
    with open(ck, "wb") as fh:
        np.savez(fh, **data)
    rc = recon_main([*args, "--out", str(tmp_path / "b.h5"), "--resume"])
    assert rc == 2 and "iteration -3" in one_line_error(capsys)
    assert not (tmp_path / "b.h5").exists()


def test_warm_start_renders_pings_per_chunk_at_a_time(point_ds, monkeypatch):
    """The scaled-backprojection start built one operator for 4 × pings_per_iteration pings
    whatever --pings-per-chunk said (300 pings per iteration: a segfault); it now renders
    chunks like the iterations do."""
    from recon import forward, gradient_descent
    from recon.grid import Grid
    sizes = []
    real = forward.EllipsoidOperator

    class Recording(real):
        def __init__(self, grid, geometry, *args, **kwargs):
            sizes.append(geometry.n_pings)
            super().__init__(grid, geometry, *args, **kwargs)

    monkeypatch.setattr(forward, "EllipsoidOperator", Recording)
    grid = Grid([[-0.04, 0.04], [-0.05, 0.03], [0.06, 0.14]], (6, 6, 6))
    gradient_descent.solve(point_ds, grid, iterations=1, pings_per_iteration=6,
                           pings_per_chunk=2, n_rays=50, bins_per_ping=8, progress=False,
                           ensemble=1)          # one fit, in this process (the patch is here)
    assert sizes and max(sizes) <= 2 and sum(sizes) == 24


@pytest.mark.parametrize("method, option, value, message", [
    ("nbp", "--mlp-width", "100000", "mlp_width"),
    ("nbp", "--hash-levels", "100", "hash_levels"),
    ("nbp", "--n-rays", "10000000", "sample points per pass"),
    ("gd", "--n-rays", "100000000", "sample points per pass"),
    ("gd", "--pings-per-iteration", "1000000", "recon gd needs"),
])
def test_solver_options_have_ranges_and_a_memory_estimate(ds_file, tmp_path, capsys, method,
                                                          option, value, message):
    """Each of these crashed, ran out of memory or ran for minutes into NaN; now one line
    before any work."""
    t0 = time.perf_counter()
    rc = recon_main([method, str(ds_file), *GD_SMALL, "--out", str(tmp_path / "v.h5"),
                     option, value, "--max-memory", "4G"])
    assert rc == 2 and message in one_line_error(capsys)
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "v.h5").exists()


def test_batch_and_library_share_the_solver_checks():
    from recon import gradient_descent, nbp
    from recon.grid import Grid
    from sonarsim import limits
    grid = Grid([[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.2]], (20, 20, 20))
    nbp.check_options(grid, iterations=5)                  # a sane run passes
    with pytest.raises(InputError, match="hash_levels"):
        nbp.check_options(grid, hash_levels=100)
    limits.set_max_memory("1G")
    try:
        with pytest.raises(InputError, match="recon gd needs"):
            gradient_descent.check_options(grid, pings_per_iteration=2000)
    finally:
        limits.set_max_memory(None)


# --- coordinator: export --slices on a full disk (#23 item 2) ---------------------------------

def test_slices_interrupted_by_a_full_disk_leave_no_file_at_a_final_path(tmp_path, monkeypatch):
    """The third slice's write fails (ENOSPC): the two written before are removed, no index."""
    import errno
    from PIL import Image
    from recon import export

    real_save, calls = Image.Image.save, []

    def save(self, fp, *args, **kwargs):
        calls.append(fp)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(self, fp, *args, **kwargs)

    monkeypatch.setattr(Image.Image, "save", save)
    magnitude = np.random.default_rng(0).random((4, 5, 6))
    from sonarsim.errors import WriteError
    with pytest.raises(WriteError, match="slice_z_0002.png: no space left"):
        export.write_slices(tmp_path / "s", magnitude, [[0, 1], [0, 1], [0, 1]])
    assert len(calls) == 3 and sorted(p.name for p in (tmp_path / "s").iterdir()) == []


# --- house: the INR's network settings are recon.field.NetworkSettings' (#22, one settings
# object); the same refusals under the new names, and the old names refused naming the new one

@pytest.mark.parametrize("option, value, word", [
    ("--hash-levels", "1000", "hash_levels"), ("--mlp-width", "100000", "mlp_width"),
    ("--mlp-hidden", "99", "mlp_hidden"), ("--lr", "50", "lr"),
    ("--hash-level-scale", "8", "hash_level_scale"), ("--pings-per-inr", "0", "pings_per_inr")])
def test_deconvolve_inr_network_options_are_checked_before_any_work(ds_file, tmp_path, capsys,
                                                                    option, value, word):
    out = tmp_path / "pd.h5"
    t0 = time.perf_counter()
    assert recon_main(["deconvolve", str(ds_file), "--out", str(out), option, value]) == 2
    line = one_line_error(capsys)
    assert word in line and "lower --lr" not in line
    assert time.perf_counter() - t0 < 5 and not out.exists()


def test_deconvolve_inr_memory_is_estimated_before_any_work_new_names(ds_file, tmp_path, capsys):
    out = tmp_path / "pd.h5"
    assert recon_main(["deconvolve", str(ds_file), "--out", str(out), "--max-memory", "64M",
                       "--mlp-width", "1024", "--mlp-hidden", "8"]) == 2
    assert "INR deconvolution" in one_line_error(capsys) and not out.exists()


@pytest.mark.parametrize("old, new", [("--n-levels", "--hash-levels"), ("--width", "--mlp-width"),
                                      ("--hidden-layers", "--mlp-hidden")])
def test_deconvolve_old_inr_option_names_are_refused_naming_the_new(ds_file, tmp_path, capsys,
                                                                    old, new):
    out = tmp_path / "pd.h5"
    with pytest.raises(SystemExit) as stop:          # a usage error (argparse), exit 2
        recon_main(["deconvolve", str(ds_file), "--out", str(out), old, "4"])
    assert stop.value.code == 2
    assert f"{old} is now {new}" in one_line_error(capsys) and not out.exists()
