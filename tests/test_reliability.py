"""Reliability (issue 13): refuse before allocating, one-line errors, safe outputs.

Each test reproduces one failure of the hostile-user run (a traceback, an allocation
without refusal, a silent all-zero result, a silently replaced or interleaved output) and
checks the one-line refusal or the right result.
"""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from recon import synthetic
from recon.cli import main as recon_main
from sonarsim import limits, outputs
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
    (["--upsample", "100000"], "--upsample must be an integer in 1..1024"),
    (["--shape", "10000", "10000", "10000"], "the volume needs 48428.8 GiB"),
    (["--shape", "2000", "2000", "2000"], "GiB (2000 x 2000 x 2000 voxels"),
    (["--voxel-size", "1e-6"], "GiB ("),
    (["--voxel-size", "1e-300"], "more than 10^12 voxels"),
    (["--max-memory", "1M", "--shape", "64", "64", "64"], "but --max-memory is 0.0 GiB"),
    (["--max-memory", "lots"], "--max-memory: expected a size"),
    (["--bounds", "50", "51", "50", "51", "50", "51"], "no voxel of the grid lies within"),
    (["--threads", "0"], "--threads must be >= 1"),
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
