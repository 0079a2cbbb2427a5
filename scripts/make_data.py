"""Build the data shipped in ``sonarsim/data`` from the public releases (docs/data.md).

Run once by a maintainer, never by users or tests:

    python scripts/make_data.py --meshes NVR/data/gt_meshes --pulses NVR/data/wfm \
        --scans CSAS/airsas_deconv_pipeline/airsas_data

``NVR`` is a checkout of awreed/Neural-Volumetric-Reconstruction-for-Coherent-SAS (branch
``main2`` for ``data/gt_meshes``; ``data/wfm`` is on ``main`` too), ``CSAS`` one of
awreed/CSAS_Deconvolution_INR. The meshes and pulses are copied byte for byte (pulses
renamed); the real AirSAS scan and its empty-turntable scan become sonarsim datasets
(``import-airsas``, gzip-compressed) plus raw excerpts of their first flights for the
importer tests; ``SHA256SUMS`` records every shipped file.
"""
from __future__ import annotations

import argparse
import hashlib
import shutil
from pathlib import Path

import h5py
import numpy as np

from sonarsim.dataset import SonarDataset
from sonarsim.importers.airsas import import_airsas

DATA = Path(__file__).resolve().parents[1] / "sonarsim" / "data"
MESHES = ("bunny.obj", "cube.obj", "cylinder.obj")
PULSES = {"20khz_bw_lfm.npy": "airsas_20khz_measured.npy",
          "5khz_bw_lfm.npy": "airsas_5khz_measured.npy"}
SCAN, BACKGROUND = "small_features_cutout_5k", "bg_5k"
EXCERPT_FLIGHTS = 6          # raw flights kept per scan (the importer tests need up to 6)
SOURCE_SCANS = "awreed/CSAS_Deconvolution_INR@4afb7e3:airsas_deconv_pipeline/airsas_data/"


def compressed_copy(src: Path, dst: Path) -> None:
    """Copy HDF5 file ``src`` to ``dst`` with every array chunked, shuffled and gzipped."""
    def copy(g_in: h5py.Group, g_out: h5py.Group) -> None:
        g_out.attrs.update(g_in.attrs)
        for name, item in g_in.items():
            if isinstance(item, h5py.Group):
                copy(item, g_out.create_group(name))
                continue
            opts = ({"compression": "gzip", "compression_opts": 9, "shuffle": True}
                    if item.size > 64 else {})
            g_out.create_dataset(name, data=item[()], **opts).attrs.update(item.attrs)
    tmp = dst.with_suffix(".tmp")
    with h5py.File(src, "r") as f_in, h5py.File(tmp, "w") as f_out:
        copy(f_in, f_out)
    tmp.replace(dst)


def scan_dataset(scan: Path, background: Path | None, out: Path) -> SonarDataset:
    ds = import_airsas(scan, background, progress=False)
    # Provenance instead of this machine's paths.
    ds.meta["scan_dir"] = SOURCE_SCANS + scan.name
    ds.meta["background_dir"] = SOURCE_SCANS + background.name if background else ""
    plain = out.with_name(out.stem + ".plain.h5")
    ds.write(plain)
    compressed_copy(plain, out)
    plain.unlink()
    again = SonarDataset.read(out)
    assert np.array_equal(again.waveforms, ds.waveforms) and np.array_equal(again.tx, ds.tx)
    return ds


def excerpt(scan: Path, dst: Path, n: int = EXCERPT_FLIGHTS) -> None:
    """The scan's parameter files and its first ``n`` flights, Coordinates.csv cut to match."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("SysParams.csv", "WaveformParams.csv", "Waveforms.csv"):
        shutil.copyfile(scan / name, dst / name)
    with open(scan / "Coordinates.csv", "rb") as f:
        lines = f.read().splitlines(keepends=True)[: n + 1]
    (dst / "Coordinates.csv").write_bytes(b"".join(lines))
    for i in range(1, n + 1):
        shutil.copyfile(scan / f"Flight-{i:06d}.csv", dst / f"Flight-{i:06d}.csv")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", type=Path, required=True, help="the reference's gt_meshes folder")
    ap.add_argument("--pulses", type=Path, required=True, help="the reference's data/wfm folder")
    ap.add_argument("--scans", type=Path, required=True,
                    help=f"folder holding the LabVIEW scans {SCAN}/ and {BACKGROUND}/")
    args = ap.parse_args()

    (DATA / "meshes").mkdir(parents=True, exist_ok=True)
    for name in MESHES:
        shutil.copyfile(args.meshes / name, DATA / "meshes" / name)
    (DATA / "pulses").mkdir(exist_ok=True)
    for src, dst in PULSES.items():
        src_path = args.pulses / src if (args.pulses / src).is_file() else args.pulses / dst
        shutil.copyfile(src_path, DATA / "pulses" / dst)

    real = DATA / "airsas_real"
    scan_dataset(args.scans / SCAN, args.scans / BACKGROUND, real / f"{SCAN}.h5")
    scan_dataset(args.scans / BACKGROUND, None, real / f"{BACKGROUND}.h5")
    for name in (SCAN, BACKGROUND):
        excerpt(args.scans / name, real / name)

    files = sorted(p for p in DATA.rglob("*") if p.is_file()
                   and p.suffix in {".obj", ".npy", ".h5", ".csv"})
    sums = [f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(DATA).as_posix()}"
            for p in files]
    (DATA / "SHA256SUMS").write_text("\n".join(sums) + "\n")
    total = sum(p.stat().st_size for p in files)
    print(f"{len(files)} files, {total / 1e6:.2f} MB in {DATA}")


if __name__ == "__main__":
    main()
