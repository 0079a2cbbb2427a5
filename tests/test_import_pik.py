"""sonarsim.importers.pik: safe loading and field mapping of reference system_data.pik files.

The pickles are built here with stand-in classes in a fake module ``data_schemas`` (the
reference's module name), shaped as the reference code's data_schemas.py (values in ``_data``).
"""
from __future__ import annotations

import os
import pickle
import sys
import types

import numpy as np
import pytest
import scipy.signal

from sonarsim.errors import FormatError
from sonarsim.importers import pik
from sonarsim.importers.pik import SchemaRecord, import_pik, load_system_pickle


class _Schema:
    """Like the reference's schema objects: values in a ``_data`` dict."""

    def __init__(self, **values):
        self._data = dict(values)

    def __setstate__(self, state):
        # Would run if the importer used the real class instead of its inert holder.
        open(os.environ["SONARSIM_TEST_MARKER"], "w").close()
        self.__dict__.update(state)


def _stand_in_module() -> types.ModuleType:
    module = types.ModuleType("data_schemas")
    for name in ("SASDataSchema", "SysParams", "WfmParams", "Geometry", "WfmCropSettings"):
        cls = type(name, (_Schema,), {"__module__": "data_schemas", "__qualname__": name})
        setattr(module, name, cls)
    return module


@pytest.fixture()
def schemas(monkeypatch, tmp_path):
    module = _stand_in_module()
    monkeypatch.setitem(sys.modules, "data_schemas", module)
    marker = tmp_path / "setstate_ran"
    monkeypatch.setenv("SONARSIM_TEST_MARKER", str(marker))
    yield module
    assert not marker.exists(), "the stand-in class's code ran during import"


def _system(m, *, n=6, samples=40, cropped=True, with_wfm=True, rng_seed=0):
    rng = np.random.default_rng(rng_seed)
    angles = np.deg2rad(np.arange(n) * 10.0)
    tx = np.stack([0.8485 * np.sin(angles), -0.8485 * np.cos(angles), np.full(n, 0.1)], 1)
    rx = tx + np.array([0.0, -0.013, -0.038])
    corners = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (-0.2, 0.2) for z in (0.0, 0.3)])
    data = dict(
        wfm_data=rng.standard_normal((n, samples)),
        wfm_rc=np.zeros((n, samples), complex),
        tx_coords=tx, rx_coords=rx,
        temps=np.linspace(21.0, 22.0, n),
        speed_of_sound=np.float64(344.973),
        sys_params=m.SysParams(tx_pos=np.array([0, -0.8485, 0.285]), rx_pos=[0, -0.8615, 0.247],
                               center=np.array([0, 0, 0.1775]), group_delay=62.329317,
                               sampling_frequency=100e3, center_frequency=20e3),
        wfm_params=m.WfmParams(f_start=30000, f_stop=10000, t_dur=1e-3, win_ratio=0.1),
        geometry=m.Geometry(corners=corners, num_x=125, num_y=125, num_z=94),
        crop_settings=m.WfmCropSettings(min_sample=217, num_samples=samples if cropped else 718,
                                        min_dist=0.7486, max_dist=3.2255),
    )
    if with_wfm:
        data["wfm"] = np.hanning(100)
    return m.SASDataSchema(**data), data


def _dump(tmp_path, obj, protocol=4, name="system_data.pik"):
    path = tmp_path / name
    path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return path


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_fields_map_to_dataset(schemas, tmp_path, protocol):
    obj, data = _system(schemas)
    ds = import_pik(_dump(tmp_path, obj, protocol))
    np.testing.assert_array_equal(ds.waveforms, data["wfm_data"].astype(np.float32))
    np.testing.assert_array_equal(ds.tx, data["tx_coords"])
    np.testing.assert_array_equal(ds.rx, data["rx_coords"])
    np.testing.assert_array_equal(ds.temperatures, data["temps"])
    np.testing.assert_array_equal(ds.pulse, data["wfm"])
    assert ds.fs == 100e3 and ds.sound_speed == 344.973
    # Cropped waveforms (length == crop num_samples) start at crop min_sample.
    assert ds.start_sample == 217
    # Beams point at the centre of the geometry corners: (0, 0, 0.15).
    expect = np.array([0, 0, 0.15]) - data["tx_coords"]
    np.testing.assert_allclose(ds.boresight, expect / np.linalg.norm(expect, axis=1)[:, None],
                               atol=1e-12)
    assert ds.source == "pik:system_data.pik"
    assert ds.meta["sys_group_delay"] == pytest.approx(62.329317)
    assert ds.meta["crop_max_dist"] == pytest.approx(3.2255)


def test_full_length_waveforms_start_at_zero_and_pulse_from_wfm_params(schemas, tmp_path):
    obj, _ = _system(schemas, cropped=False, with_wfm=False)
    ds = import_pik(_dump(tmp_path, obj))
    assert ds.start_sample == 0
    t = np.arange(100) / 100e3
    chirp = scipy.signal.chirp(t, 30e3, 1e-3, 10e3) * scipy.signal.windows.tukey(100, 0.1)
    np.testing.assert_allclose(ds.pulse, chirp, atol=1e-12)


def test_written_dataset_round_trips(schemas, tmp_path):
    from sonarsim.cli import main
    from sonarsim.dataset import SonarDataset

    obj, data = _system(schemas)
    out = tmp_path / "d.h5"
    assert main(["import-pik", str(_dump(tmp_path, obj)), "--out", str(out)]) == 0
    back = SonarDataset.read(out)
    np.testing.assert_array_equal(back.waveforms, data["wfm_data"].astype(np.float32))
    assert back.start_sample == 217


def test_loader_returns_inert_holders(schemas, tmp_path):
    obj, _ = _system(schemas)
    schema = load_system_pickle(_dump(tmp_path, obj))
    assert isinstance(schema, SchemaRecord) and not isinstance(schema, schemas.SASDataSchema)
    assert isinstance(schema.get("sys_params"), pik.HOLDERS["SysParams"])


class _RunsShell:
    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


class _RunsEval:
    def __init__(self, code):
        self.code = code

    def __reduce__(self):
        import builtins
        return builtins.eval, (self.code,)


@pytest.mark.parametrize("make", [
    lambda marker: _RunsShell(f"touch {marker}"),
    lambda marker: _RunsEval(f"open({str(marker)!r}, 'w').close()"),
], ids=["os.system", "builtins.eval"])
@pytest.mark.parametrize("protocol", [2, 4])
def test_code_in_pickle_is_refused_and_never_runs(schemas, tmp_path, make, protocol):
    marker = tmp_path / "pwned"
    obj, _ = _system(schemas)
    obj._data["wfm_params"] = make(marker)
    path = _dump(tmp_path, obj, protocol)
    with pytest.raises(FormatError, match=r"system_data\.pik: refused to load "
                                          r"(posix|os|nt|builtins)\.(system|eval)"):
        import_pik(path)
    assert not marker.exists()


def test_other_numpy_functions_are_refused(tmp_path):
    marker = tmp_path / "made"

    class _Saves:
        def __reduce__(self):
            return np.save, (str(marker), np.zeros(1))

    path = _dump(tmp_path, {"wfm_data": _Saves()})
    with pytest.raises(FormatError, match="refused to load numpy.*save"):
        load_system_pickle(path)
    assert not marker.with_suffix(".npy").exists()


def test_truncated_and_foreign_files(schemas, tmp_path):
    obj, _ = _system(schemas)
    blob = pickle.dumps(obj, protocol=4)
    cut = tmp_path / "cut.pik"
    cut.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(FormatError, match=r"cut\.pik: not a readable pickle"):
        import_pik(cut)
    text = tmp_path / "text.pik"
    text.write_text("hello, this is not a pickle\n")
    with pytest.raises(FormatError, match=r"text\.pik"):
        import_pik(text)
    with pytest.raises(FormatError, match="file not found"):
        import_pik(tmp_path / "absent.pik")
    other = _dump(tmp_path, [1, 2, 3], name="list.pik")
    with pytest.raises(FormatError, match="expected data_schemas.SASDataSchema"):
        import_pik(other)


def test_missing_and_inconsistent_fields(schemas, tmp_path):
    obj, _ = _system(schemas)
    del obj._data["wfm_data"]
    with pytest.raises(FormatError, match="'wfm_data' is missing"):
        import_pik(_dump(tmp_path, obj, name="a.pik"))
    obj, _ = _system(schemas)
    obj._data["rx_coords"] = obj._data["rx_coords"][:3]
    with pytest.raises(FormatError, match=r"'rx_coords' has shape \(3, 3\)"):
        import_pik(_dump(tmp_path, obj, name="b.pik"))


def test_boresights_from_vectors_or_given_box(schemas, tmp_path):
    from sonarsim.geometry import SceneBox

    obj, data = _system(schemas)
    down = np.tile([0.0, 0.0, -2.0], (len(data["tx_coords"]), 1))
    obj._data["tx_vectors"] = down
    ds = import_pik(_dump(tmp_path, obj, name="svss.pik"))
    np.testing.assert_allclose(ds.boresight, down / 2.0)
    obj, data = _system(schemas)
    box = SceneBox((-0.1, -0.1, 0.0), (0.1, 0.1, 0.1))
    ds = import_pik(_dump(tmp_path, obj, name="c.pik"), box=box)
    aim = np.array([0.0, 0.0, 0.05]) - data["rx_coords"]
    np.testing.assert_allclose(ds.receiver_boresight, aim / np.linalg.norm(aim, axis=1)[:, None],
                               atol=1e-12)
    assert ds.meta["box"] == [[-0.1, 0.1], [-0.1, 0.1], [0.0, 0.1]]
