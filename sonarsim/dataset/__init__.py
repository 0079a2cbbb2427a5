"""sonarsim's three HDF5 files as typed objects: transients, sonar datasets, volumes.

* :class:`Transients` -- path-length histograms from ``sonarsim render``;
* :class:`SonarDataset` -- time-domain sonar waveforms plus geometry (``simulate``, importers);
* :class:`Volume` -- a complex voxel reconstruction (``recon ...``).

Each has ``.write(path)`` (atomic: a temporary file in the same directory, then
``os.replace``) and a validating classmethod ``.read(path)``; :func:`read_any` reads
whichever kind a file holds and :func:`inspect` validates a file without loading its
large arrays.  :class:`DatasetStreamWriter` writes a dataset ping chunk by ping chunk
into ``<path>.partial`` and can resume after an interruption.
Constructors raise :class:`InputError` for bad arrays or values; readers raise
:class:`FormatError` with one line naming the file and the offending field.
The full schema is in ``docs/formats.md``.

Modules: ``transients``, ``sonar_dataset``, ``volume`` (the file objects), ``any_kind``
(read_any, file_kind, inspect), ``stream`` (resumable writer), ``h5io`` (format ids,
atomic writes), ``attributes`` (meta/params encoding), ``reader`` (validating reader),
``checks`` (value checks), ``describe`` (summary and problems of any file, as
``sonarsim info`` prints them).
"""
from .any_kind import file_kind, inspect, read_any
from .describe import describe, describe_and_check
from .h5io import (FORMAT_VERSION, KIND_DATASET, KIND_NAMES, KIND_TRANSIENTS, KIND_VOLUME,
                   PARTIAL_SUFFIX, PathLike, atomic_write_h5)
from .sonar_dataset import SonarDataset, declared_scene_box
from .stream import DatasetStreamWriter, TransientsLayout, TransientsStreamWriter
from .transients import Transients
from .volume import Volume

__all__ = ["FORMAT_VERSION", "KIND_TRANSIENTS", "KIND_DATASET", "KIND_VOLUME", "Transients",
           "SonarDataset", "declared_scene_box", "Volume", "read_any", "file_kind", "inspect", "atomic_write_h5",
           "DatasetStreamWriter", "TransientsLayout", "TransientsStreamWriter", "describe",
           "describe_and_check"]
