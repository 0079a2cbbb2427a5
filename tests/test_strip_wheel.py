"""scripts/strip_wheel.py: the variant, plugins and RECORD lines a stripped mitsuba wheel keeps."""
from __future__ import annotations

import importlib.util
import zipfile
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "strip_wheel.py"


def _module():
    spec = importlib.util.spec_from_file_location("strip_wheel", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_stripped_mitsuba_wheel_keeps_its_variant_plugins_and_record(tmp_path):
    """Kept: the asked variant, scalar_rgb, a used plugin, the Python package; dropped: the
    other variant, an unused plugin, headers; RECORD lists exactly the kept members (fails when
    the RECORD is not filtered or a rule drops the asked variant)."""
    so = ".cpython-312-x86_64-linux-gnu.so"
    members = {f"mitsuba/cuda_ad_mono{so}": b"c", f"mitsuba/llvm_ad_mono{so}": b"l",
               f"mitsuba/scalar_rgb{so}": b"s", "mitsuba/plugins/ply.so": b"p",
               "mitsuba/plugins/blendbsdf.so": b"b", "mitsuba/include/x.h": b"h",
               "mitsuba/__init__.py": b"i"}
    record = "".join(f"{n},sha256=x,1\n" for n in members) + "mitsuba-3.9.1.dist-info/RECORD,,\n"
    src, dst = tmp_path / "in.whl", tmp_path / "out.whl"
    with zipfile.ZipFile(src, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
        z.writestr("mitsuba-3.9.1.dist-info/RECORD", record)
    gone, total = _module().strip(str(src), str(dst), "mitsuba", "cuda_ad_mono")
    kept = {f"mitsuba/cuda_ad_mono{so}", f"mitsuba/scalar_rgb{so}", "mitsuba/plugins/ply.so",
            "mitsuba/__init__.py"}
    with zipfile.ZipFile(dst) as z:
        assert z.testzip() is None
        names = set(z.namelist())
        assert names == kept | {"mitsuba-3.9.1.dist-info/RECORD"}
        listed = {line.split(",")[0] for line in
                  z.read("mitsuba-3.9.1.dist-info/RECORD").decode().splitlines()}
    assert listed == names
    assert (gone, total) == (3, 8)
