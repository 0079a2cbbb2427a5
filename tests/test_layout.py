"""The architecture as the design states it: one-way dependencies, no import cycles between
module pairs, plugins that depend on mitsuba/drjit only, and the promised repository layout."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Where each installed package's modules live in the repository.
PACKAGE_DIRS = {"sonarsim": ROOT / "sonarsim", "sonarsim.plugins": ROOT / "plugins",
                "sonarsim.scenes": ROOT / "scenes", "recon": ROOT / "recon"}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg, d in PACKAGE_DIRS.items():
        for f in d.rglob("*.py"):
            rel = f.relative_to(d).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            mods[".".join([pkg, *parts])] = f
    return mods


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def imports_of(name: str) -> set[str]:
    """Every module (project or not) that ``name`` imports, at any level of its code."""
    tree = ast.parse(MODULES[name].read_text())
    base = name if _is_package(name) else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = base.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                mod = ".".join(anchor + ([node.module] if node.module else []))
            else:
                mod = node.module
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)   # `from pkg import module`
    return found


def project_imports(name: str) -> set[str]:
    return {m for m in imports_of(name) if m in MODULES and m != name}


def test_repository_has_the_design_layout():
    for d in ("plugins", "scenes", "sonarsim", "recon", "tests", "benchmarks", "docs"):
        assert (ROOT / d).is_dir(), d
    assert (ROOT / "plugins" / "sonar_transient.py").is_file()
    assert list((ROOT / "scenes").glob("*.toml"))
    assert not (ROOT / "sonarsim" / "plugins").exists() and not (ROOT / "sonarsim" / "scenes").exists()


def test_no_module_pair_imports_each_other():
    cycles = sorted((a, b) for a in MODULES for b in project_imports(a)
                    if a < b and a in project_imports(b)
                    and not (a.startswith(b + ".") or b.startswith(a + ".")))
    assert cycles == []


def test_sonarsim_never_imports_recon():
    offenders = {m: sorted(i for i in imports_of(m) if i.split(".")[0] == "recon")
                 for m in MODULES if m.startswith("sonarsim")}
    assert {m: v for m, v in offenders.items() if v} == {}



#: Reference code for the tests and benchmarks (CONTRIBUTING.md, "Reference code"): the
#: package itself never uses it.
REFERENCE_MODULES = ("recon.straightforward", "recon.synthetic")


def test_the_package_never_uses_its_reference_modules():
    assert all(m in MODULES for m in REFERENCE_MODULES)
    users = {m: sorted(i for i in imports_of(m) if i in REFERENCE_MODULES)
             for m in MODULES if m not in REFERENCE_MODULES}
    assert {m: v for m, v in users.items() if v} == {}

def test_plugins_depend_on_mitsuba_and_drjit_only():
    allowed = {"mitsuba", "drjit", "numpy", "__future__"} | set(sys.stdlib_module_names)
    for m in MODULES:
        if m.startswith("sonarsim.plugins"):
            bad = {i for i in imports_of(m) if i.split(".")[0] not in allowed
                   and not i.startswith("sonarsim.plugins")}    # a plugin's own helpers
            assert bad == set(), (m, bad)


def test_wheel_ships_plugins_and_scenes_and_works_installed(tmp_path):
    """A non-editable install from the wheel finds its scenes and registers its plugins."""
    import subprocess
    import zipfile

    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(tmp_path / "dist"), str(ROOT)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("sonarsim-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "sonarsim/plugins/sonar_transient.py" in names
    assert {f"sonarsim/scenes/{p.name}" for p in (ROOT / "scenes").glob("*.toml")} <= names
    assert not any(n.startswith(("plugins/", "scenes/")) for n in names)   # no top-level packages
    from sonarsim import data
    assert {f"sonarsim/data/{n}" for n in data.names()} <= names          # the shipped data
    assert {"sonarsim/batch/__init__.py", "sonarsim/batch/plan.py"} <= names

    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target",
                        str(site), str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    code = ("import sonarsim, sonarsim.scene as s; from sonarsim import runtime, data\n"
            "mi = runtime.mitsuba(); i = mi.load_dict({'type': 'sonar_transient'})\n"
            "print(sonarsim.__file__); print(s.resolve_scene_path('sphere')); print(type(i).__name__)\n"
            "print(data.path('meshes/bunny.obj'))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                       env={**__import__("os").environ, "PYTHONPATH": str(site)}, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    where, scene, cls, bunny = r.stdout.split()
    assert where.startswith(str(site)) and scene.startswith(str(site))
    assert cls == "SonarTransientIntegrator"
    assert bunny.startswith(str(site)) and Path(bunny).is_file()
@pytest.mark.parametrize("pkg", ["sonarsim.commands", "recon.commands"])
def test_commands_do_not_borrow_from_each_other(pkg):
    """A command module may use shared helpers (``_``-prefixed modules), not another command."""
    commands = {m for m in MODULES if m.startswith(pkg + ".") and not m.rsplit(".", 1)[1].startswith("_")}
    borrowed = {m: sorted(project_imports(m) & (commands - {m})) for m in commands}
    assert {m: v for m, v in borrowed.items() if v} == {}
