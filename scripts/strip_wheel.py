"""Strip a wheel for the device machine's 64 MiB carry limit (docs/differentiable.md
"Variants"): drop the members a rule names, drop their RECORD lines, re-zip (deflate 9).

    python scripts/strip_wheel.py IN.whl OUT.whl {mitsuba|gpytoolbox|scs} [VARIANT]

mitsuba keeps the Python modules of VARIANT (default cuda_ad_mono) and of scalar_rgb (which
mitsuba's own import needs), the plugins sonarsim's scenes and tests load, and drops the
other variants, the data it does not read, headers, CMake files and the executable (62.6 MB
-> 21.3 MB for 3.9.1); gpytoolbox drops a duplicate wgpu library; scs drops its MKL build.
"""
from __future__ import annotations

import re
import sys
import zipfile

PLUGINS = frozenset("diffuse gaussian independent merge obj ply rectangle twosided uniform "
                    "sphere srgb box perspective spot hdrfilm path cube disk constant area "
                    "point direct tent stratified".split())
DROPPED_DIRS = ("mitsuba/data/ior/", "mitsuba/data/sunsky/", "mitsuba/include/", "share/",
                "mitsuba/cmake/", "mitsuba/pkgconfig/")
DROPPED_FILES = ("mitsuba/mitsuba", "mitsuba/__init__.pyi", "mitsuba/data/srgb.coeff")


def dropped(name: str, kind: str, variant: str = "cuda_ad_mono") -> bool:
    """Whether the wheel member ``name`` goes (``kind``: which wheel)."""
    if kind == "mitsuba":
        module = re.match(r"mitsuba/([a-z_]+)\.cpython-3\d+-x86_64-linux-gnu\.so$", name)
        if module:
            return module.group(1) not in {variant, "scalar_rgb", "mitsuba_ext", "mitsuba_alias"}
        if name.startswith("mitsuba/plugins/"):
            return name[len("mitsuba/plugins/"):].rsplit(".", 1)[0] not in PLUGINS
        return (name.startswith(DROPPED_DIRS) or name in DROPPED_FILES
                or name.endswith("libIlmImfUtil-mitsuba.so"))
    if kind == "gpytoolbox":
        return name == "libwgpu_native.so"
    if kind == "scs":
        return name.startswith("scs/_scs_mkl") or name.endswith("LICENSE-INTEL-MKL.txt")
    raise SystemExit(f"strip_wheel: unknown wheel kind {kind!r} (mitsuba, gpytoolbox, scs)")


def strip(src: str, dst: str, kind: str, variant: str = "cuda_ad_mono") -> tuple[int, int]:
    """Write ``src`` without its dropped members to ``dst``; (dropped, members)."""
    with zipfile.ZipFile(src) as zin:
        infos = zin.infolist()
        gone = {i.filename for i in infos if dropped(i.filename, kind, variant)}
        with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
            for info in infos:
                if info.filename in gone:
                    continue
                data = zin.read(info.filename)
                if info.filename.endswith(".dist-info/RECORD"):
                    lines = data.decode().splitlines(keepends=True)
                    data = "".join(line for line in lines
                                   if line.split(",")[0] not in gone).encode()
                out = zipfile.ZipInfo(info.filename, info.date_time)
                out.external_attr = info.external_attr
                out.compress_type = zipfile.ZIP_DEFLATED
                zout.writestr(out, data, compresslevel=9)
    return len(gone), len(infos)


def main(argv: list[str]) -> int:
    if len(argv) not in (3, 4):
        print(__doc__.strip().splitlines()[3].strip(), file=sys.stderr)
        return 2
    n_gone, n_all = strip(*argv)
    print(f"{argv[0]} -> {argv[1]}: dropped {n_gone} of {n_all} members")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
