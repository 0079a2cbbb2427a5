"""Data shipped with sonarsim: find it by name (provenance and licences: docs/data.md).

- ``meshes/bunny.obj``, ``cube.obj``, ``cylinder.obj``: ground-truth meshes of the reference's
  simulated scenes (metres, standing on z = 0; Reed et al. 2023, repository
  Neural-Volumetric-Reconstruction-for-Coherent-SAS, branch main2, ``data/gt_meshes``).
- ``pulses/airsas_20khz_measured.npy``, ``airsas_5khz_measured.npy``: measured AirSAS pulses at
  100 kHz, float64 [603] (same repository, ``data/wfm``; the reference uses the first 100 samples).
- ``airsas_real/small_features_cutout_5k.h5``: a real AirSAS circular scan (360 pings at one
  height, 5 kHz LFM) of a flat cut-out target, background subtracted: a sonarsim dataset, as
  ``sonarsim import-airsas SCAN --background BG`` writes it (:func:`real_scan`).
- ``airsas_real/bg_5k.h5``: the empty-turntable scan of the same session, no background
  subtracted; it holds the direct TX -> RX arrival (:func:`empty_scan`).
- ``airsas_real/small_features_cutout_5k/``, ``airsas_real/bg_5k/``: the first 6 raw LabVIEW
  flights of both scans (CSV; ``Coordinates.csv`` cut to them), for the importer.

The scans come from Reed et al.'s repository CSAS_Deconvolution_INR
(``airsas_deconv_pipeline/airsas_data``). ``SHA256SUMS`` lists every file's digest.

Example: ``data.path("bunny.obj")`` is the path of ``meshes/bunny.obj`` (a unique file name or
a path relative to the data folder). A scene TOML may name a shipped mesh
(``mesh = "bunny.obj"``) where no file of that name lies next to it; from a shell,
``sonarsim data NAME`` prints a path and ``sonarsim data`` lists them all.
"""
from __future__ import annotations

import importlib.resources
from pathlib import Path

from ..errors import FormatError

#: Suffixes of the data files (the package's Python and text files are not data).
DATA_SUFFIXES = (".obj", ".npy", ".h5", ".csv")
#: The real scan (background subtracted) and the empty-turntable scan, as sonarsim datasets.
REAL_SCAN = "airsas_real/small_features_cutout_5k.h5"
EMPTY_SCAN = "airsas_real/bg_5k.h5"


def root() -> Path:
    """The folder of the shipped data (inside the installed package or the repository)."""
    return Path(str(importlib.resources.files(__name__)))


def names() -> list[str]:
    """Every shipped data file as a path relative to :func:`root` (POSIX form), sorted."""
    base = root()
    return sorted(p.relative_to(base).as_posix() for p in base.rglob("*")
                  if p.is_file() and p.suffix in DATA_SUFFIXES)


def find(name: str | Path) -> Path | None:
    """The shipped file ``name`` (a relative path such as ``meshes/bunny.obj``, or a file name
    that is unique among the shipped files, such as ``bunny.obj``), or None."""
    name = Path(name).as_posix()
    if not name or name.startswith(("/", "../")) or "/../" in name:
        return None
    direct = root() / name
    if direct.is_file() and direct.suffix in DATA_SUFFIXES:
        return direct
    if "/" in name:
        return None
    matches = [n for n in names() if n.rsplit("/", 1)[-1] == name]
    return root() / matches[0] if len(matches) == 1 else None


def path(name: str | Path) -> Path:
    """Like :func:`find`, but a name that is not shipped is a :class:`FormatError` that lists
    the shipped files."""
    found = find(name)
    if found is None:
        raise FormatError(f"{name}: not a shipped data file (shipped: "
                          f"{', '.join(n for n in names() if not n.endswith('.csv'))}, "
                          "and raw AirSAS excerpts under airsas_real/)")
    return found


def mesh_names() -> list[str]:
    """File names of the shipped meshes (``bunny.obj``, ...)."""
    return [n.split("/", 1)[1] for n in names() if n.startswith("meshes/")]


def real_scan():
    """The real AirSAS scan of the cut-out target, background subtracted
    (:class:`sonarsim.dataset.SonarDataset`, 360 pings x 1000 samples at 100 kHz)."""
    from ..dataset import SonarDataset
    return SonarDataset.read(path(REAL_SCAN))


def empty_scan():
    """The empty-turntable scan (no background subtracted), a :class:`SonarDataset`."""
    from ..dataset import SonarDataset
    return SonarDataset.read(path(EMPTY_SCAN))
