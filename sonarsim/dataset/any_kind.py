"""Functions that accept a sonarsim file of any kind."""
from __future__ import annotations

import contextlib
from typing import Iterator

import numpy as np

from .h5io import KIND_DATASET, KIND_TRANSIENTS, KIND_VOLUME, PathLike
from .reader import open_checked
from .sonar_dataset import SonarDataset
from .transients import Transients
from .volume import Volume

_CLASSES = {KIND_TRANSIENTS: Transients, KIND_DATASET: SonarDataset, KIND_VOLUME: Volume}


def file_kind(path: PathLike) -> str:
    """The ``format`` of a sonarsim file ('sonarsim.dataset', ...), validated."""
    with open_checked(path) as (kind, _):
        return kind


def read_any(path: PathLike) -> Transients | SonarDataset | Volume:
    """Read a sonarsim file of any of the three kinds."""
    with open_checked(path) as (kind, rd):
        if kind == KIND_DATASET:
            return SonarDataset._from_reader(rd)
        return rd.construct(_CLASSES[kind], _CLASSES[kind]._read_fields(rd))


@contextlib.contextmanager
def inspect(path: PathLike, allow_partial: bool = False,
            expected: str | None = None) -> Iterator[tuple[str, dict]]:
    """Open a file and validate its schema without loading the large arrays; yield
    (kind, fields) where ``transients``/``waveforms``/``volume`` are open h5py.Dataset
    objects (valid inside the ``with`` block), everything else is loaded, and
    ``fields['format_version']`` is the file's version.  For a dataset file,
    ``fields['transients']`` is a fields dict of the same form or None.  With
    ``allow_partial`` an unfinished ``.partial`` file is accepted too: then
    ``fields['complete']`` is False and ``fields['pings_done']`` counts the pings written.
    ``expected``: the kind the caller needs (e.g. ``KIND_DATASET``); another kind is a
    one-line FormatError saying what the file is ("this is a volume file, ...")."""
    with open_checked(path, expected, allow_partial=allow_partial) as (kind, rd):
        fields_ = _CLASSES[kind]._read_fields(rd, load=False)
        fields_["format_version"] = rd.version
        fields_["complete"] = rd.attr("", "complete", "bool", optional=True) is not False
        if not fields_["complete"] and "stream/done" in rd.f:
            fields_["pings_done"] = int(np.count_nonzero(rd.f["stream/done"][()]))
        yield kind, fields_
