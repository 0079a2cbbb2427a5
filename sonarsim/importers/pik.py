"""Import the reference's ``system_data.pik`` pickles (reference code ``data_schemas.py``) without running code.

A pickle can call any importable function while it loads. :class:`SafeUnpickler` therefore
resolves only

- the reference's schema classes (module ``data_schemas``: ``SASDataSchema``, ``SysParams``,
  ``WfmParams``, ``Geometry``, ``WfmCropSettings``), mapped to inert :class:`SchemaRecord`
  holders that merely keep the pickled state;
- the NumPy functions that rebuild arrays, dtypes and scalars
  (``numpy[._]core.multiarray._reconstruct``/``scalar``, ``numpy[._]core.numeric._frombuffer``,
  ``numpy.ndarray``, ``numpy.dtype``) and ``builtins.complex``;
- ``copyreg._reconstructor`` (protocol 0/1 objects), accepted only for the holders above,
  and ``_codecs.encode`` (how protocols 0–2 store bytes), accepted only for latin-1.

Every other global (``os.system``, ``builtins.eval``, ...) is refused with a
:class:`~sonarsim.errors.FormatError` before anything is called.

Allowed globals alone do not bound the *work*: a few hundred bytes of shared nested tuples
(each level referring twice to the one below) expand to 2^depth elements when hashed as a
dictionary key, converted by ``np.asarray`` or printed. The unpickler (Python's pure-Python
one, instrumented per opcode) therefore also refuses, before executing the opcode,

- more than :data:`MAX_OPCODES` opcodes or :data:`MAX_OBJECTS` containers;
- containers nested deeper than :data:`MAX_DEPTH` (shared references count at each use);
- dictionary keys and set members other than str, bytes, int, float, bool or None (the
  schema's dictionaries are keyed by field names), so nothing expensive is ever hashed;
- a length field larger than what remains of the file;

and the mapping accepts only the expected type at each schema field (NumPy arrays for the
array fields, numbers for the scalars, schema records for the sub-records), never
converting or printing anything else.
"""
from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from .. import geometry, signals
from ..errors import FormatError

SCHEMA_MODULE = "data_schemas"
SCHEMA_CLASSES = ("SASDataSchema", "SysParams", "WfmParams", "Geometry", "WfmCropSettings")


class SchemaRecord:
    """Inert stand-in for one of the reference's schema objects: it only stores state.

    ``fields`` is the object's ``_data`` dict (the reference keeps its values there) or,
    failing that, its whole attribute dict.
    """

    schema_class = "?"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict = {}

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:      # (dict, slots dict)
            merged = {}
            for part in state:
                if isinstance(part, dict):
                    merged.update(part)
            state = merged
        if not isinstance(state, dict):
            raise pickle.UnpicklingError(f"{self.schema_class}: unexpected state "
                                         f"of type {type(state).__name__}")
        self.state = dict(state)

    @property
    def fields(self) -> dict:
        data = self.state.get("_data")
        return data if isinstance(data, dict) else self.state

    def get(self, key: str, default: Any = None) -> Any:
        value = self.fields.get(key, default)
        return default if value is None else value

    def __repr__(self) -> str:
        return f"<{SCHEMA_MODULE}.{self.schema_class} fields={sorted(self.fields)}>"


HOLDERS: dict[str, type[SchemaRecord]] = {
    name: type(name, (SchemaRecord,), {"schema_class": name, "__module__": __name__})
    for name in SCHEMA_CLASSES
}


def _safe_reconstructor(cls, base, state):
    """``copyreg._reconstructor`` restricted to ``object.__new__`` of a schema holder."""
    if cls not in HOLDERS.values() or base is not object or state is not None:
        raise pickle.UnpicklingError("copyreg._reconstructor is allowed only for the "
                                     "reference's schema classes")
    return cls.__new__(cls)


def _latin1_encode(text, encoding="latin1"):
    """``_codecs.encode`` as protocol 0–2 pickles use it for bytes: latin-1 text → bytes."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("_codecs.encode is allowed only for latin-1 bytes")
    return text.encode("latin1")


def _numpy_function(module: str, name: str):
    import importlib
    for candidate in (module, module.replace("numpy.core", "numpy._core"),
                      module.replace("numpy._core", "numpy.core")):
        try:
            return getattr(importlib.import_module(candidate), name)
        except (ImportError, AttributeError):
            continue
    raise pickle.UnpicklingError(f"{module}.{name} is not available in this NumPy")


_NUMPY_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("numpy", "ndarray"), ("numpy", "dtype"),
}
_PY2_MODULES = {"__builtin__": "builtins", "copy_reg": "copyreg"}


class RefusedGlobal(pickle.UnpicklingError):
    """The pickle names a global outside the allow-list."""


MAX_OPCODES = 5_000_000     # the reference's system_data.pik needs a few hundred
MAX_OBJECTS = 1_000_000     # containers (tuples, lists, dicts, sets) built
MAX_DEPTH = 24              # nesting of containers; the schema needs about 6
_HASHABLE_OK = (str, bytes, int, float, bool, type(None))


class _BoundedFile:
    """A read-only file whose reads never ask for more than what remains of it."""

    def __init__(self, f):
        self._f = f
        f.seek(0, 2)
        self._size = f.tell()
        f.seek(0)

    def read(self, n: int = -1) -> bytes:
        remaining = self._size - self._f.tell()
        if n is None or n < 0 or n > remaining:
            if n is not None and n > remaining:
                raise pickle.UnpicklingError(
                    f"a length field asks for {n} bytes, only {remaining} remain")
            n = remaining
        return self._f.read(n)

    def readline(self) -> bytes:
        return self._f.readline(1 << 20)


def _container_ops() -> dict[int, str]:
    """Opcodes (byte values) that build or fill containers, by what they do."""
    names = {
        "TUPLE": "mark", "LIST": "mark", "DICT": "mark", "FROZENSET": "mark",
        "TUPLE1": "top1", "TUPLE2": "top2", "TUPLE3": "top3",
        "APPEND": "append", "APPENDS": "appends", "SETITEM": "setitem",
        "SETITEMS": "setitems", "ADDITEMS": "additems",
    }
    out = {}
    for name, what in names.items():
        code = getattr(pickle, name, None)
        if code is not None:
            out[code[0]] = what
    return out


_CONTAINER_OPS = _container_ops()


class SafeUnpickler(pickle._Unpickler):
    """Unpickler that resolves only the allow-listed globals and bounds its own work
    (both described in the module doc)."""

    def __init__(self, file, **kwargs):
        super().__init__(_BoundedFile(file), **kwargs)
        self._ops = 0
        self._objects = 0
        self._depth: dict[int, tuple[object, int]] = {}    # id -> (object kept alive, depth)

    # ---- bookkeeping of container depth
    def _depth_of(self, obj) -> int:
        entry = self._depth.get(id(obj))
        return entry[1] if entry is not None and entry[0] is obj else 0

    def _set_depth(self, obj, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise pickle.UnpicklingError(f"containers nested deeper than {MAX_DEPTH} levels")
        self._depth[id(obj)] = (obj, depth)

    def _new_container(self, obj, children) -> None:
        self._objects += 1
        if self._objects > MAX_OBJECTS:
            raise pickle.UnpicklingError(f"more than {MAX_OBJECTS} containers")
        self._set_depth(obj, 1 + max((self._depth_of(c) for c in children), default=0))

    @staticmethod
    def _check_keys(keys) -> None:
        for key in keys:
            if not isinstance(key, _HASHABLE_OK):
                raise pickle.UnpicklingError(
                    f"a dictionary key or set member of type {type(key).__name__}; the "
                    "schema's keys are names")

    def _checked(self, what: str, op):
        """Run opcode function ``op`` after the checks for ``what`` (see _CONTAINER_OPS)."""
        stack = self.stack
        if what == "setitem":
            self._check_keys([stack[-2]])
        elif what == "setitems":
            self._check_keys(stack[0::2])
        elif what == "additems":
            self._check_keys(stack)
        target = None
        if what == "append":
            target, children = stack[-2], stack[-1:]
        elif what == "setitem":
            target, children = stack[-3], stack[-2:]
        elif what in ("appends", "setitems", "additems"):
            target, children = self.metastack[-1][-1], list(stack)
        elif what == "mark":
            children = list(stack)
        else:  # top1/2/3
            children = stack[-int(what[-1]):]
        op(self)
        if target is not None:
            self._set_depth(target, max(self._depth_of(target),
                                        1 + max((self._depth_of(c) for c in children), default=0)))
        else:
            self._new_container(self.stack[-1], children)

    def _dispatch_one(self, code: int):
        self._ops += 1
        if self._ops > MAX_OPCODES:
            raise pickle.UnpicklingError(f"more than {MAX_OPCODES} pickle opcodes")
        op = pickle._Unpickler.dispatch[code]
        what = _CONTAINER_OPS.get(code)
        if what is None:
            return op(self)
        if what == "mark" and code == pickle.DICT[0]:
            self._check_keys(self.stack[0::2])
        if what == "mark" and code == pickle.FROZENSET[0]:
            self._check_keys(self.stack)
        return self._checked(what, op)

    def find_class(self, module: str, name: str):
        module = _PY2_MODULES.get(module, module)
        if module == SCHEMA_MODULE and name in HOLDERS:
            return HOLDERS[name]
        if (module, name) in _NUMPY_ALLOWED:
            return _numpy_function(module, name)
        if (module, name) == ("copyreg", "_reconstructor"):
            return _safe_reconstructor
        if (module, name) == ("_codecs", "encode"):
            return _latin1_encode
        if module == "builtins" and name in ("complex", "object"):
            return complex if name == "complex" else object
        raise RefusedGlobal(f"refused to load {module}.{name}: only the reference's "
                            f"{SCHEMA_MODULE} classes and NumPy arrays are allowed")

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("persistent references are not allowed")


class _Dispatch(dict):
    """``SafeUnpickler.dispatch``: every opcode goes through ``_dispatch_one``."""

    def __missing__(self, code):
        if code not in pickle._Unpickler.dispatch:
            raise KeyError(code)
        return lambda unpickler, _c=code: unpickler._dispatch_one(_c)


SafeUnpickler.dispatch = _Dispatch()


def load_system_pickle(path: str | Path) -> SchemaRecord:
    """Unpickle a ``system_data.pik`` safely; returns the ``SASDataSchema`` holder."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        with open(path, "rb") as f:
            obj = SafeUnpickler(io.BufferedReader(f)).load()
    except RefusedGlobal as exc:
        raise FormatError(f"{path}: {exc}") from None
    except (pickle.UnpicklingError, EOFError) as exc:
        raise FormatError(f"{path}: not a readable pickle ({exc or 'truncated'})") from None
    except (MemoryError, RecursionError):
        raise FormatError(f"{path}: pickle asks for more memory than available") from None
    except Exception as exc:          # malformed opcodes surface as many exception types
        raise FormatError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") \
            from None
    if isinstance(obj, dict):         # tolerate a plain dict of the same keys
        record = HOLDERS["SASDataSchema"]()
        record.state = {"_data": obj}
        obj = record
    if not isinstance(obj, HOLDERS["SASDataSchema"]):
        raise FormatError(f"{path}: top-level object is {type(obj).__name__}, "
                          "expected data_schemas.SASDataSchema")
    return obj


# --------------------------------------------------------------------------- mapping
def _array(record: SchemaRecord, key: str, path: Path, *, ndim: int | None = None,
           required: bool = True, real: bool = True) -> np.ndarray | None:
    value = record.get(key)
    if value is None:
        if required:
            raise FormatError(f"{path}: field {key!r} is missing")
        return None
    flat_numbers = isinstance(value, (list, tuple)) and len(value) <= 4096 and all(
        isinstance(v, (int, float, np.number)) and not isinstance(v, bool) for v in value)
    if not (isinstance(value, np.ndarray) or flat_numbers):
        # never convert (or print) anything else: nested shared tuples expand exponentially
        raise FormatError(f"{path}: field {key!r} is a {type(value).__name__}, expected a "
                          "NumPy array")
    arr = np.asarray(value)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise FormatError(f"{path}: field {key!r} has non-numeric dtype {arr.dtype}")
    if real and np.iscomplexobj(arr):
        raise FormatError(f"{path}: field {key!r} is complex, expected real values")
    if ndim is not None and arr.ndim != ndim:
        raise FormatError(f"{path}: field {key!r} has shape {arr.shape}, expected {ndim}-D")
    if not np.all(np.isfinite(arr)):
        raise FormatError(f"{path}: field {key!r} contains NaN or infinity")
    return arr


def _scalar(record: SchemaRecord | None, key: str, where: str, required: bool = True):
    value = None if record is None else record.get(key)
    if value is None:
        if required:
            raise FormatError(f"{where}: field {key!r} is missing")
        return None
    ok = (isinstance(value, (int, float, np.number)) and not isinstance(value, bool)) or \
        (isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind in "fiu")
    if not ok:                              # never convert (or print) anything else
        raise FormatError(f"{where}: field {key!r} is a {type(value).__name__}, expected a "
                          "number")
    out = float(np.asarray(value).reshape(()))
    if not np.isfinite(out):
        raise FormatError(f"{where}: field {key!r} is {out}")
    return out


def _sub(record: SchemaRecord, key: str) -> SchemaRecord | None:
    value = record.get(key)
    return value if isinstance(value, SchemaRecord) else None


def import_pik(path: str | Path, *, box: "geometry.SceneBox | None" = None):
    """Read a reference ``system_data.pik`` into a :class:`sonarsim.dataset.SonarDataset`.

    Mapping (reference code ``data_schemas.py``): ``wfm_data`` → waveforms [N, T] (float32); ``tx_coords``,
    ``rx_coords`` → tx, rx [N, 3] m; ``tx_vectors``/``rx_vectors`` → boresights when present,
    else the beams point at the centre of the scene box: ``box`` if given, else the box of
    ``geometry.corners``, else ``AIRSAS_REAL_BOX`` (the box is recorded in ``meta``);
    ``temps`` → temperatures; ``speed_of_sound`` (else 331.4 + 0.6·mean temps) → sound_speed;
    ``wfm`` → pulse (else the LFM of ``wfm_params``); ``sys_params.sampling_frequency`` → fs.
    Waveforms as long as ``crop_settings.num_samples`` are the cropped window (the simulated
    pickles), so ``start_sample = crop_settings.min_sample``; full-length ones start at 0.
    """
    from ..dataset import SonarDataset

    path = Path(path)
    schema = load_system_pickle(path)
    where = f"{path}"
    waveforms = _array(schema, "wfm_data", path, ndim=2)
    n, t = waveforms.shape
    tx = _array(schema, "tx_coords", path, ndim=2)
    rx = _array(schema, "rx_coords", path, ndim=2)
    for key, arr in (("tx_coords", tx), ("rx_coords", rx)):
        if arr.shape != (n, 3):
            raise FormatError(f"{path}: field {key!r} has shape {arr.shape}, expected ({n}, 3) "
                              "to match wfm_data")

    sys_params = _sub(schema, "sys_params")
    if sys_params is None:
        raise FormatError(f"{path}: field 'sys_params' is missing")
    fs = _scalar(sys_params, "sampling_frequency", f"{where}: sys_params")

    temps = _array(schema, "temps", path, ndim=1, required=False)
    if temps is not None and temps.shape[0] != n:
        raise FormatError(f"{path}: field 'temps' has {temps.shape[0]} values for {n} pings")
    sound_speed = _scalar(schema, "speed_of_sound", where, required=False)
    if sound_speed is None:
        if temps is None:
            raise FormatError(f"{path}: neither 'speed_of_sound' nor 'temps' is present")
        sound_speed = float(signals.sound_speed_air(float(np.mean(temps))))

    wfm_params = _sub(schema, "wfm_params")
    pulse = _array(schema, "wfm", path, ndim=1, required=False, real=False)
    pulse_source = "pik:wfm"
    if pulse is None:
        if wfm_params is None:
            raise FormatError(f"{path}: neither 'wfm' nor 'wfm_params' is present")
        w = f"{where}: wfm_params"
        pulse = signals.lfm(_scalar(wfm_params, "f_start", w), _scalar(wfm_params, "f_stop", w),
                            _scalar(wfm_params, "t_dur", w), fs,
                            window_ratio=_scalar(wfm_params, "win_ratio", w))
        pulse_source = "pik:wfm_params (LFM)"

    geom = _sub(schema, "geometry")
    corners = None if geom is None else _array(geom, "corners", path, ndim=2, required=False)
    if box is not None:
        box_lo, box_hi, box_from = box.lo, box.hi, "--box"
    elif corners is not None and corners.shape == (8, 3):
        box_lo, box_hi, box_from = corners.min(axis=0), corners.max(axis=0), "geometry.corners"
    else:
        box = geometry.AIRSAS_REAL_BOX
        box_lo, box_hi, box_from = box.lo, box.hi, "AIRSAS_REAL_BOX (default)"
    tx_vectors = _array(schema, "tx_vectors", path, ndim=2, required=False)
    if tx_vectors is not None and tx_vectors.shape == (n, 3):
        rx_vectors = _array(schema, "rx_vectors", path, ndim=2, required=False)
        if rx_vectors is None or rx_vectors.shape != (n, 3):
            rx_vectors = tx_vectors
        poses = geometry.Poses(tx, rx, tx_vectors, rx_vectors)
        aim = "tx_vectors/rx_vectors"
    else:
        centre = 0.5 * (np.asarray(box_lo, float) + np.asarray(box_hi, float))
        poses = geometry.Poses.pointing_at(tx, rx, centre)
        aim = f"centre of the scene box from {box_from}"

    crop = _sub(schema, "crop_settings")
    start_sample = 0
    meta: dict[str, Any] = {"pik_file": str(path.resolve()), "pulse_source": pulse_source,
                            "boresight_from": aim, "box_from": box_from,
                            # [[x0, x1], [y0, y1], [z0, z1]] m, the layout of Volume bounds
                            "box": np.stack([np.asarray(box_lo, float), np.asarray(box_hi, float)],
                                            axis=1).tolist()}
    if crop is not None:
        w = f"{where}: crop_settings"
        num = _scalar(crop, "num_samples", w, required=False)
        min_sample = _scalar(crop, "min_sample", w, required=False)
        if num is not None and min_sample is not None and int(num) == t:
            start_sample = int(min_sample)
        for key in ("min_sample", "num_samples", "min_dist", "max_dist"):
            value = _scalar(crop, key, w, required=False)
            if value is not None:
                meta[f"crop_{key}"] = value
    for prefix, record, keys in (
            ("sys", sys_params, ("group_delay", "center_frequency", "tx_bandwidth",
                                 "rx_bandwidth")),
            ("wfm", wfm_params, ("f_start", "f_stop", "t_dur", "win_ratio"))):
        for key in keys:
            value = _scalar(record, key, where, required=False) if record is not None else None
            if value is not None:
                meta[f"{prefix}_{key}"] = value
    if sys_params is not None:
        for key in ("tx_pos", "rx_pos", "center"):
            vec = _array(sys_params, key, path, required=False)
            if vec is not None and vec.size == 3:
                meta[f"sys_{key}"] = np.asarray(vec, float).reshape(3).tolist()

    return SonarDataset(
        waveforms=waveforms.astype(np.float32), tx=poses.tx, rx=poses.rx,
        boresight=poses.tx_boresight, rx_boresight=poses.rx_boresight,
        pulse=np.asarray(pulse, dtype=np.float64).real,
        fs=float(fs), sound_speed=float(sound_speed), source=f"pik:{path.name}",
        start_sample=start_sample,
        temperatures=None if temps is None else temps.astype(np.float64), meta=meta)
