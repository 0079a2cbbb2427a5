"""Runtime: libLLVM discovery, variant selection, CLI skeleton."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sonarsim import runtime


@pytest.mark.parametrize("name,version", [
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15),
    ("/usr/lib/llvm-17/lib/libLLVM-17.so", 17),
    ("/opt/homebrew/opt/llvm/lib/libLLVM.dylib", None),
    ("/usr/lib/llvm-18/lib/libLLVM.so", 18),
    ("/usr/local/lib/libLLVM.20.dylib", 20),
])
def test_llvm_version_from_name(name, version):
    assert runtime.llvm_version(name) == version


def _run(code: str, **env):
    full = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    full.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=full, timeout=120)


def test_configured_llvm_is_never_15():
    r = _run("import os, sonarsim; print(os.environ.get('DRJIT_LIBLLVM_PATH'))")
    assert r.returncode == 0, r.stderr
    path = r.stdout.strip()
    assert path != "None", "no libLLVM >= 16 found; make install should have installed one"
    assert runtime.llvm_version(path) is None or runtime.llvm_version(path) >= 16


def test_invalid_user_llvm_path_is_replaced():
    bad = "/lib/x86_64-linux-gnu/libLLVM-15.so.1"
    r = _run("import os, sonarsim; print(os.environ.get('DRJIT_LIBLLVM_PATH'))",
             DRJIT_LIBLLVM_PATH=bad)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() != bad


def test_valid_user_llvm_path_is_honoured():
    good = runtime.configure_llvm()
    r = _run("import os, sonarsim; print(os.environ.get('DRJIT_LIBLLVM_PATH'))",
             DRJIT_LIBLLVM_PATH=good)
    assert r.stdout.strip() == good


def test_kernel_runs_in_fresh_interpreter():
    """Importing sonarsim, then running a Dr.Jit kernel with min/max, must not abort."""
    r = _run("from sonarsim import runtime; mi = runtime.mitsuba(); import drjit as dr; "
             "x = dr.arange(mi.Float, 8); print(dr.sum(dr.minimum(x, 3.0) + dr.maximum(x, 5.0)))")
    assert r.returncode == 0, r.stderr
    assert float(r.stdout.strip().strip("[]")) == pytest.approx(sum(min(i, 3) + max(i, 5) for i in range(8)))


def test_default_variant(mi):
    assert runtime.current_variant() == "llvm_ad_mono"
    assert mi.variant() == "llvm_ad_mono"


def test_unknown_variant_is_a_clear_error():
    with pytest.raises(runtime.RuntimeSetupError, match="unknown variant"):
        runtime.set_variant("scalar_rgb")


def test_cuda_variant_without_gpu_is_a_clear_error():
    r = _run("import sonarsim.runtime as r\n"
             "try:\n    r.set_variant('cuda_ad_mono'); print('ok')\n"
             "except r.RuntimeSetupError as e:\n    print('ERR', e)")
    assert r.returncode == 0, r.stderr
    out = r.stdout.strip()
    assert out == "ok" or (out.startswith("ERR") and "cuda_ad_mono" in out)


@pytest.mark.parametrize("prog", ["sonarsim", "recon"])
def test_cli_help(prog):
    r = subprocess.run([sys.executable, "-m", f"{prog}.cli", "--help"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage" in r.stdout.lower()
