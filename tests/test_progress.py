"""Progress in logs, --quiet/--verbose, one-line usage errors and warnings (issue 24, item 2).

The progress lines are measurements: the rate and ETA in a line are checked against the
steps done and the time elapsed, and a command run with stderr to a file (not a terminal)
is checked to write them.
"""
from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import time
import types
import warnings

import pytest

from recon import synthetic
from recon.cli import main as recon_main
from sonarsim import progress
from sonarsim.errors import InputError

LINE = re.compile(r"^stage (\d+)/(\d+) step \((\d+)%\), ([0-9.e+]+) step/s, "
                  r"elapsed (\d+):(\d\d):(\d\d), ETA (\d+):(\d\d):(\d\d), loss=0\.5$")


def _seconds(h, m, s) -> int:
    return 3600 * int(h) + 60 * int(m) + int(s)


def test_log_lines_report_done_total_rate_and_eta(caplog, monkeypatch):
    """On a clock the test drives (1/64 s a step, a line every 1/16 s; binary fractions, so
    no rounding), every line's rate is the steps done over the time elapsed: 64 step/s,
    or 64·n/(n + 1) if the background ticker wrote the line between the clock's step and
    the bar's update. (On the real clock a loaded machine stretched the first steps: 15
    step/s with 10 ms sleeps.)"""
    clock = [1000.0]
    monkeypatch.setattr(progress, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    caplog.set_level(logging.INFO, logger=progress.LOGGER_NAME)
    bar = progress.LogProgress(40, unit="step", desc="stage", interval=1 / 16)
    bar.set_postfix(loss="0.5", refresh=False)
    for _ in range(40):
        clock[0] += 1 / 64
        bar.update(1)
    bar.close()
    lines = [r.getMessage() for r in caplog.records]
    ticks = [LINE.match(line) for line in lines[:-1]]
    assert len(ticks) >= 3 and all(ticks), lines
    for m in ticks:
        n, total, pct, rate = int(m[1]), int(m[2]), int(m[3]), float(m[4])
        assert total == 40 and pct == round(100 * n / 40)
        assert 64 * n / (n + 1) * 0.999 <= rate <= 64 * 1.001, lines
        assert _seconds(*m.groups()[7:10]) == pytest.approx((40 - n) / rate, abs=1.0)
    done = re.match(r"^stage done: 40/40 step in (\d+):(\d\d):(\d\d) \(([0-9.]+) step/s\), "
                    r"loss=0\.5$", lines[-1])
    assert done, lines[-1]
    assert float(done[4]) == pytest.approx(64, rel=1e-3)


def test_a_short_stage_prints_nothing(caplog):
    caplog.set_level(logging.INFO, logger=progress.LOGGER_NAME)
    with progress.LogProgress(5, unit="step", desc="stage", interval=30) as bar:
        bar.update(5)
    assert caplog.records == []


def test_a_stage_that_makes_no_step_still_reports_it_is_alive(caplog):
    caplog.set_level(logging.INFO, logger=progress.LOGGER_NAME)
    bar = progress.LogProgress(3, unit="it", desc="warm start", interval=0.03)
    time.sleep(0.2)
    bar.close()
    lines = [r.getMessage() for r in caplog.records]
    assert sum(line.startswith("warm start 0/3 it (0%), ? it/s") for line in lines) >= 2, lines
    assert lines[-1].startswith("warm start stopped: 0/3 it in")


def test_bar_kind_follows_the_terminal_and_quiet(monkeypatch):
    undo = progress.setup_logging("t", progress.NORMAL)
    try:
        monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
        bar = progress.progress_bar(3, True, unit="x", desc="d")
        assert isinstance(bar, progress.LogProgress)
        bar.close()
        assert progress.progress_bar(3, False, unit="x", desc="d").disable
        monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
        bar = progress.progress_bar(3, True, unit="x", desc="d")
        assert not isinstance(bar, progress.LogProgress) and not bar.disable
        bar.close()
    finally:
        undo()
    undo = progress.setup_logging("t", progress.QUIET)
    try:
        assert progress.progress_bar(3, True, unit="x", desc="d").disable
    finally:
        undo()


def test_warnings_and_notes_are_one_line_each(capsys):
    undo = progress.setup_logging("sonarsim render", progress.NORMAL)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.warn("mesh.obj: 3 non-manifold edges\n(shared by more than two)")
        logging.getLogger("sonarsim.simulate").info("automatic sampling: 12 rays")
        logging.getLogger("recon.solver").debug("not shown at the normal level")
    finally:
        undo()
    assert capsys.readouterr().err.splitlines() == [
        "warning: mesh.obj: 3 non-manifold edges; (shared by more than two)",
        "sonarsim render: automatic sampling: 12 rays"]
    assert logging.getLogger("sonarsim").handlers == []      # undone


def test_bad_progress_interval_is_one_line(monkeypatch):
    monkeypatch.setenv(progress.INTERVAL_ENV, "soon")
    with pytest.raises(InputError, match="SONARSIM_PROGRESS_INTERVAL must be a positive"):
        progress.progress_interval()
    monkeypatch.setenv(progress.INTERVAL_ENV, "2.5")
    assert progress.progress_interval() == 2.5


def test_usage_error_is_one_line_with_a_pointer_to_help(capsys):
    with pytest.raises(SystemExit) as exc:
        recon_main(["backproject", "d.h5", "--out", "v.h5", "--shape", "4", "x", "4"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["recon backproject: error: argument --shape: invalid int value: 'x' "
                   "(see 'recon backproject --help')"]


@pytest.fixture(scope="module")
def dataset_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("progress") / "d.h5"
    synthetic.point_dataset([[0.01, -0.02, 0.09]], n_pings=200, heights=(0.05, 0.15)).write(path)
    return path


def test_command_with_output_to_a_file_prints_progress(tmp_path, dataset_file):
    env = dict(os.environ, **{progress.INTERVAL_ENV: "0.05"})
    with open(tmp_path / "out.txt", "w") as so, open(tmp_path / "err.txt", "w") as se:
        rc = subprocess.run([sys.executable, "-m", "recon.cli", "backproject", str(dataset_file),
                             "--out", str(tmp_path / "v.h5"), "--shape", "24", "24", "24",
                             "--verbose"], stdout=so, stderr=se, env=env, timeout=300).returncode
    out, err = (tmp_path / "out.txt").read_text(), (tmp_path / "err.txt").read_text()
    assert rc == 0, err
    assert out.startswith("wrote ") and "Traceback" not in err          # result on stdout
    assert re.search(r"^recon backproject: backprojection \d+/400 ping \(\d+%\), .* ETA ",
                     err, re.M), err
    assert re.search(r"^recon backproject: backprojection done: 400/400 ping in ", err, re.M)
    assert re.search(r"^recon backproject: finished in [0-9.]+ s \(CPU [0-9.]+ s\), peak memory",
                     err, re.M)                                       # --verbose


def test_quiet_keeps_the_result_and_drops_progress(tmp_path, dataset_file, capsys, monkeypatch):
    monkeypatch.setenv(progress.INTERVAL_ENV, "0.01")
    args = ["backproject", str(dataset_file), "--shape", "24", "24", "24", "--out"]
    assert recon_main(args + [str(tmp_path / "a.h5")]) == 0
    first = capsys.readouterr()
    assert first.out.startswith("wrote ") and "backprojection done: 400/400" in first.err
    assert recon_main(args + [str(tmp_path / "b.h5"), "--quiet"]) == 0
    second = capsys.readouterr()
    assert second.out.startswith("wrote ") and second.err == ""
    assert recon_main(["-q"] + args + [str(tmp_path / "c.h5")]) == 0   # before the command
    third = capsys.readouterr()
    assert third.out.startswith("wrote ") and third.err == ""
