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


def test_plugins_depend_on_mitsuba_and_drjit_only():
    allowed = {"mitsuba", "drjit", "numpy", "__future__"} | set(sys.stdlib_module_names)
    for m in MODULES:
        if m.startswith("sonarsim.plugins"):
            bad = {i for i in imports_of(m) if i.split(".")[0] not in allowed}
            assert bad == set(), (m, bad)
