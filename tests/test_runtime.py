"""Runtime: libLLVM discovery, variant selection, CLI skeleton."""
from __future__ import annotations

import os
import shutil
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
    """The libLLVM Dr.Jit loads (its own report) is >= 16 and is the one configured."""
    r = _run("import os; from sonarsim import runtime; runtime.mitsuba(); import drjit as dr; "
             "print(os.environ.get('DRJIT_LIBLLVM_PATH')); print(dr.detail.llvm_version()[0])")
    assert r.returncode == 0, r.stderr
    path, loaded = r.stdout.split()
    assert path != "None", "no libLLVM >= 16 found; make install should have installed one"
    assert int(loaded) >= 16
    assert runtime.llvm_version(path) == int(loaded)


def test_invalid_user_llvm_path_is_replaced(tmp_path):
    """A user's libLLVM 15 (an existing file: 15 aborts) and a missing file are both replaced
    by the newest discovered libLLVM >= 16."""
    found = [path for version, path in runtime.find_llvm_candidates() if version >= 16][0]
    existing_15 = tmp_path / "libLLVM-15.so.1"
    existing_15.write_bytes(b"")
    for bad in (str(existing_15), str(tmp_path / "libLLVM-19.so.1")):
        r = _run("import os; from sonarsim import runtime; runtime.mitsuba(); "
                 "print(os.environ.get('DRJIT_LIBLLVM_PATH'))", DRJIT_LIBLLVM_PATH=bad)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == found


def test_valid_user_llvm_path_is_honoured():
    good = runtime.configure_llvm()
    r = _run("import os; from sonarsim import runtime; runtime.mitsuba(); "
             "print(os.environ.get('DRJIT_LIBLLVM_PATH'))", DRJIT_LIBLLVM_PATH=good)
    assert r.stdout.strip() == good


def test_kernel_runs_in_fresh_interpreter():
    """Importing sonarsim, then running a Dr.Jit kernel with min/max, must not abort."""
    r = _run("from sonarsim import runtime; mi = runtime.mitsuba(); import drjit as dr; "
             "x = dr.arange(mi.Float, 8); print(dr.sum(dr.minimum(x, 3.0) + dr.maximum(x, 5.0)))")
    assert r.returncode == 0, r.stderr
    assert float(r.stdout.strip().strip("[]")) == pytest.approx(sum(min(i, 3) + max(i, 5) for i in range(8)))


def test_default_variant(mi, monkeypatch):
    """llvm_ad_mono unless SONARSIM_VARIANT asks for another (the suite runs on a GPU so)."""
    assert runtime.current_variant() == mi.variant() == runtime.requested_variant()
    monkeypatch.delenv(runtime.VARIANT_ENV, raising=False)
    assert runtime.requested_variant() == "llvm_ad_mono"


def test_unknown_variant_is_a_clear_error():
    with pytest.raises(runtime.RuntimeSetupError, match="unknown variant"):
        runtime.set_variant("scalar_rgb")


def test_cuda_variant_without_gpu_is_a_clear_error():
    r = _run("import sonarsim.runtime as r\n"
             "try:\n    r.set_variant('cuda_ad_mono'); print('ok')\n"
             "except r.RuntimeSetupError as e:\n    print('ERR', e)")
    assert r.returncode == 0, r.stderr
    out = r.stdout.strip()
    if shutil.which("nvidia-smi") is None:       # no driver: the variant must be refused clearly
        assert out.startswith("ERR") and "cuda_ad_mono" in out and "CUDA" in out
    else:
        assert out == "ok"


def test_import_has_no_side_effects():
    """Importing the packages runs no subprocess (ldconfig) and leaves the environment alone."""
    r = _run("import subprocess, os\n"
             "def boom(*a, **k): raise SystemExit('subprocess at import')\n"
             "subprocess.run = subprocess.Popen = boom\n"
             "before = dict(os.environ)\n"
             "import sonarsim, sonarsim.cli, recon, recon.cli, sonarsim.scene, recon.backprojection\n"
             "print(dict(os.environ) == before)", DRJIT_LIBLLVM_PATH="")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "True"


def test_plugins_are_discovered_and_load_by_name(mi):
    from sonarsim import plugins
    assert "sonar_transient" in plugins.plugin_modules()
    from sonarsim.plugins.sonar_transient import SonarTransientIntegrator
    integrator = mi.load_dict({"type": "sonar_transient", "max_bounces": 2})
    assert isinstance(integrator, SonarTransientIntegrator)
    assert integrator.max_bounces == 2


def test_broken_plugin_is_an_error_with_its_name(mi, tmp_path, monkeypatch):
    from sonarsim import plugins
    (tmp_path / "broken_plugin.py").write_text("import mitsuba as mi\nraise ValueError('typo')\n")
    monkeypatch.setattr(plugins, "__path__", [*plugins.__path__, str(tmp_path)])
    with pytest.raises(plugins.PluginImportError, match="broken_plugin.*ValueError: typo"):
        plugins.register_all(mi)


@pytest.mark.parametrize("prog", ["sonarsim", "recon"])
def test_cli_help(prog):
    r = subprocess.run([sys.executable, "-m", f"{prog}.cli", "--help"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage" in r.stdout.lower()


def test_export_and_deconvolution_import_no_heavy_libraries():
    """recon.export and recon.deconvolution import trimesh (networkx, scipy.spatial) and
    scipy.fft where a mesh or an FFT is made, not at import: every ``recon`` command imports
    them to build its parser, and these imports were most of its start-up CPU."""
    heavy = ("trimesh", "networkx", "scipy.spatial", "scipy.fft")
    r = _run("import sys, recon.export, recon.deconvolution\n"
             f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
    r = _run("import sys, numpy as np\n"
             "from recon import deconvolution, export\n"
             "mesh = export.extract_surface(np.pad(np.ones((2, 2, 2)), 1), [[0, 1]] * 3, 0.5)\n"
             "deconvolution.analytic(np.ones(8))\n"
             f"print(sorted(m for m in {heavy!r} if m in sys.modules), len(mesh.faces) > 0)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"{sorted(heavy)!r} True"


# The libraries only some commands need: importing them was most of a command's start-up
# (measured 2026-11-25, shared machine, CPU-s: recon --help 1.05-1.3 -> 0.26-0.28, sonarsim
# --help 0.52-0.61 -> 0.24-0.29).
HEAVY_LIBRARIES = ("trimesh", "networkx", "scipy.spatial", "scipy.fft", "scipy.ndimage",
                   "scipy.signal")


@pytest.mark.parametrize("prog", ["sonarsim", "recon"])
def test_help_imports_no_heavy_library(prog):
    """Every command module is imported to build the parser: none may import these at the
    top (import them where they are used)."""
    r = _run(f"import sys\nfrom {prog}.cli import main\n"
             "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             f"print('HEAVY', sorted(m for m in {HEAVY_LIBRARIES!r} if m in sys.modules))")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "HEAVY []"
