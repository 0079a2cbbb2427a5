"""sonarsim.identity: one digest for every "same run?" question (simulate, batch, checkpoints)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sonarsim.identity import dataset_digest, digest


def test_numbers_by_value_and_types_apart():
    assert digest(20) == digest(20.0) == digest(np.int64(20)) == digest(np.float32(20))
    assert digest(0.1) != digest(0.1000001)
    assert digest(True) != digest(1)                 # a flag is not a count
    assert digest(None) != digest(0) != digest("0")
    assert digest(float("nan")) == digest(float("nan"))


def test_structure_is_part_of_the_identity():
    assert digest(["ab"]) != digest(["a", "b"])
    assert digest(["ab", "c"]) != digest(["a", "bc"])
    assert digest("a", "b") != digest("ab") != digest(["a", "b"])
    assert digest({"a": 1, "b": 2}) == digest({"b": 2, "a": 1})
    assert digest({"a": [1, 2]}) != digest({"a": [2, 1]})
    assert digest((1, 2)) == digest([1, 2])         # TOML lists and settings tuples agree


def test_arrays_by_dtype_shape_and_bytes():
    a = np.arange(6, dtype=np.float32)
    assert digest(a) == digest(a.copy())
    assert digest(a) != digest(a.astype(np.float64))
    assert digest(a) != digest(a.reshape(2, 3))
    b = a.copy()
    b[3] = np.nextafter(b[3], np.float32(10))
    assert digest(a) != digest(b)
    assert digest(a.reshape(2, 3).T) == digest(np.ascontiguousarray(a.reshape(2, 3).T))


def test_dataclasses_meshes_callables_and_unstable_reprs():
    @dataclasses.dataclass
    class S:
        x: float = 1.0
        log: object = print

    assert digest(S()) == digest(S(log=lambda m: None))      # callables never change outputs
    assert digest(S()) != digest(S(x=2.0))

    class Mesh:
        def __init__(self, v):
            self.vertices, self.faces = np.asarray(v, float), np.array([[0, 1, 2]])
    assert digest(Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]])) != \
        digest(Mesh([[0, 0, 0], [1, 0, 0], [0, 2, 0]]))
    with pytest.raises(TypeError, match="no stable value"):
        digest(object())


def test_length_and_dataset_digest():
    assert len(digest(1)) == 24 and len(digest(1, length=16)) == 16

    @dataclasses.dataclass
    class D:
        waveforms: np.ndarray
        tx: np.ndarray
        rx: np.ndarray
        pulse: np.ndarray
        boresight: np.ndarray
        fs: float = 100e3
        sound_speed: float = 343.0
        start_sample: int = 0
        rx_boresight: object = None
        temperatures: object = None
        waveform_kind: str = "real"

    rng = np.random.default_rng(0)
    d = D(rng.normal(size=(3, 8)).astype(np.float32), rng.normal(size=(3, 3)),
          rng.normal(size=(3, 3)), rng.normal(size=5), np.ones((3, 3)))
    base = dataset_digest(d)
    for change in (dict(start_sample=1), dict(fs=50e3), dict(waveform_kind="deconvolved"),
                   dict(temperatures=np.zeros(3))):
        assert dataset_digest(dataclasses.replace(d, **change)) != base, change
    w = d.waveforms.copy()
    w[2, 7] += 1e-3
    assert dataset_digest(dataclasses.replace(d, waveforms=w)) != base
