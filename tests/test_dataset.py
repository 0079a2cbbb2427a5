"""Tests of sonarsim.dataset (the three HDF5 formats, atomic and streaming writes) and
of ``sonarsim info``."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from sonarsim import dataset as fmt
from sonarsim.cli import main
from sonarsim.dataset import (DatasetStreamWriter, SonarDataset, Transients,
                              TransientsLayout, Volume, read_any)
from sonarsim.errors import FormatError, InputError

C, FS, K = 344.973, 100e3, 20


def make_transients(n=6, b=3, t=50, seed=0, meta=None, tx=None, rx=None) -> Transients:
    rng = np.random.default_rng(seed)
    return Transients(rng.random((n, b, t), dtype=np.float32), 0.45, C / (FS * K), C, FS, K,
                      rng.normal(size=(n, 3)) if tx is None else tx,
                      rng.normal(size=(n, 3)) if rx is None else rx,
                      {"scene": "bunny", "paths_per_pose": 1000, "seed": seed,
                       "beams": {"tx": "cone", "tx_beamwidth": 30.0}, "flag": True,
                       "weights": np.arange(4.0)} if meta is None else meta)


def make_dataset(n=6, t=80, seed=0, full=True) -> SonarDataset:
    rng = np.random.default_rng(seed + 1)
    tx, rx = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    optional = dict(
        temperatures=20 + rng.random(n), gt_vertices=rng.random((5, 3)),
        gt_faces=np.array([[0, 1, 2], [2, 3, 4]]), snr_db=15.0, seed=seed,
        transients=make_transients(n, seed=seed, tx=tx, rx=rx),
        meta={"scene": "bunny", "pulse": "lfm-20k"},
        rx_boresight=rng.normal(size=(n, 3))) if full else {}
    return SonarDataset(rng.normal(size=(n, t)).astype(np.float32), tx, rx,
                        rng.normal(size=(n, 3)),
                        np.sin(np.linspace(0, 40, 100)), FS, C, "simulated",
                        start_sample=17 if full else 0, **optional)


def make_volume(shape=(4, 5, 6), params=None) -> Volume:
    rng = np.random.default_rng(3)
    vol = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    return Volume(vol, [[-0.2, 0.2], [-0.1, 0.1], [0.0, 0.3]], "backprojection",
                  {"upsample": 5, "interpolation": "linear", "shape": list(shape),
                   "incoherent": False} if params is None else params)


def assert_meta_equal(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert a[key] == b[key] and type(a[key]) is type(b[key]), key


def assert_transients_equal(a: Transients, b: Transients):
    assert b.transients.dtype == np.float32 and b.tx.dtype == np.float64
    np.testing.assert_array_equal(a.transients, b.transients)
    np.testing.assert_array_equal(a.tx, b.tx)
    np.testing.assert_array_equal(a.rx, b.rx)
    for name in ("path_start", "path_bin_width", "sound_speed", "fs", "oversample"):
        assert getattr(a, name) == getattr(b, name)
    assert isinstance(b.oversample, int)
    assert_meta_equal(a.meta, b.meta)


def assert_datasets_equal(a: SonarDataset, b: SonarDataset):
    assert b.waveforms.dtype == np.float32
    for name in ("waveforms", "tx", "rx", "boresight", "pulse"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("temperatures", "gt_vertices", "gt_faces", "rx_boresight"):
        if getattr(a, name) is None:
            assert getattr(b, name) is None
        else:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("fs", "sound_speed", "source", "start_sample", "snr_db", "seed"):
        assert getattr(a, name) == getattr(b, name)
    assert_meta_equal(a.meta, b.meta)
    assert (a.transients is None) == (b.transients is None)
    if a.transients is not None:
        assert_transients_equal(a.transients, b.transients)


# ---- round trips

def test_transients_round_trip(tmp_path):
    t = make_transients()
    t.write(tmp_path / "T.h5")
    back = Transients.read(tmp_path / "T.h5")
    assert_transients_equal(t, back)
    assert back.meta["beams"] == {"tx": "cone", "tx_beamwidth": 30.0}
    assert back.meta["flag"] is True
    with h5py.File(tmp_path / "T.h5") as f:
        assert f.attrs["format"] == "sonarsim.transients" and f.attrs["format_version"] == 1
        assert f["transients"].dtype == np.float32 and f["pings/tx"].shape == (6, 3)


def test_transients_path_axis():
    t = make_transients(t=50)
    w = C / (FS * K)
    lengths = t.path_lengths()
    assert lengths.shape == (50,)
    np.testing.assert_allclose(lengths[0], 0.45 + w / 2)
    np.testing.assert_allclose(np.diff(lengths), w)
    np.testing.assert_allclose(t.path_end, 0.45 + 50 * w)
    np.testing.assert_allclose(t.times(), lengths / C)


def test_dataset_round_trip_all_fields(tmp_path):
    ds = make_dataset()
    ds.write(tmp_path / "D.h5")
    back = SonarDataset.read(tmp_path / "D.h5")
    assert_datasets_equal(ds, back)
    np.testing.assert_allclose(np.linalg.norm(back.boresight, axis=1), 1.0)
    with h5py.File(tmp_path / "D.h5") as f:
        assert {"pings/temperature", "pings/rx_boresight", "gt/vertices", "gt/faces",
                "transients/transients"} <= set(_all_names(f))
        assert f["transients"].attrs["format"] == "sonarsim.transients"
    no_t = SonarDataset.read(tmp_path / "D.h5", transients=False)
    assert no_t.transients is None and no_t.n_pings == 6


def test_dataset_round_trip_without_optional_fields(tmp_path):
    ds = make_dataset(full=False)
    ds.write(tmp_path / "D.h5")
    back = read_any(tmp_path / "D.h5")
    assert isinstance(back, SonarDataset)
    assert_datasets_equal(ds, back)
    assert back.start_sample == 0 and back.snr_db is None and back.seed is None
    np.testing.assert_array_equal(back.receiver_boresight, back.boresight)
    with h5py.File(tmp_path / "D.h5") as f:
        assert "gt" not in f and "transients" not in f and "snr_db" not in f.attrs


def test_dataset_sample_times_and_select():
    ds = make_dataset(n=6, t=80)
    times = ds.sample_times()
    assert times.shape == (80,) and ds.n_samples == 80 and ds.n_pings == 6
    np.testing.assert_allclose(times[0], 17 / FS)
    np.testing.assert_allclose(np.diff(times), 1 / FS)
    np.testing.assert_allclose(ds.sample_path_lengths(), times * C)
    sub = ds.select([4, 1])
    assert sub.n_pings == 2 and sub.transients.n_pings == 2
    np.testing.assert_array_equal(sub.waveforms, ds.waveforms[[4, 1]])
    np.testing.assert_array_equal(sub.tx, ds.tx[[4, 1]])
    np.testing.assert_array_equal(sub.temperatures, ds.temperatures[[4, 1]])
    np.testing.assert_array_equal(sub.transients.transients, ds.transients.transients[[4, 1]])
    np.testing.assert_array_equal(sub.gt_faces, ds.gt_faces)
    assert ds.select(slice(0, 3)).n_pings == 3


def test_volume_round_trip_and_axes(tmp_path):
    v = make_volume()
    v.write(tmp_path / "V.h5")
    back = Volume.read(tmp_path / "V.h5")
    assert back.volume.dtype == np.complex64
    np.testing.assert_array_equal(back.volume, v.volume)
    np.testing.assert_array_equal(back.bounds, v.bounds)
    assert back.method == "backprojection"
    assert back.params == {"upsample": 5, "interpolation": "linear", "shape": [4, 5, 6],
                           "incoherent": False}
    x, y, z = back.voxel_centers()
    assert (x[0], x[-1], len(x)) == (-0.2, 0.2, 4) and len(y) == 5 and z[-1] == 0.3
    np.testing.assert_allclose(back.voxel_size(), [0.4 / 3, 0.2 / 4, 0.3 / 5])
    mag = back.magnitude()
    assert mag.dtype == np.float32 and mag.max() == pytest.approx(1.0)
    np.testing.assert_allclose(back.magnitude(normalised=False), np.abs(v.volume))


def test_volume_without_params_and_single_voxel_axis(tmp_path):
    v = Volume(np.ones((3, 1, 2)), [[0, 1], [0.5, 0.5], [0, 1]], "gd")
    v.write(tmp_path / "V.h5")
    back = read_any(tmp_path / "V.h5")
    assert isinstance(back, Volume) and back.params == {}
    assert back.voxel_centers()[1].tolist() == [0.5]
    assert np.isnan(back.voxel_size()[1])


def _all_names(f: h5py.File) -> list[str]:
    names = []
    f.visit(names.append)
    return names


# ---- constructor validation

@pytest.mark.parametrize("change, field", [
    (dict(waveforms=np.zeros((6, 80, 2))), "waveforms"),
    (dict(tx=np.zeros((5, 3))), "tx"),
    (dict(rx=np.zeros((6, 2))), "rx"),
    (dict(boresight=np.zeros((6, 3))), "boresight"),
    (dict(pulse=[]), "pulse"),
    (dict(fs=-1.0), "fs"),
    (dict(sound_speed=float("nan")), "sound_speed"),
    (dict(waveforms=np.full((6, 80), np.nan)), "waveforms"),
    (dict(waveforms=np.ones((6, 80), complex)), "waveforms"),
    (dict(gt_faces=np.array([[0, 1, 9]])), "gt_faces"),
    (dict(gt_faces=None), "gt_faces"),
    (dict(meta={"fs": 1}), "fs"),
    (dict(meta={"x": object()}), "meta['x']"),
    (dict(seed=-3), "seed"),
    (dict(transients=make_transients(6)), "transients.tx"),
    (dict(transients=make_transients(5)), "transients"),
])
def test_dataset_constructor_rejects_bad_input(change, field):
    ds = make_dataset()
    kwargs = {name: getattr(ds, name) for name in ds.__dataclass_fields__}
    kwargs.update(change)
    with pytest.raises(InputError, match=field.replace("[", r"\[")):
        SonarDataset(**kwargs)


def test_transients_and_volume_constructors_reject_bad_input():
    t = make_transients()
    with pytest.raises(InputError, match="path_bin_width"):
        Transients(t.transients, 0.0, 2 * t.path_bin_width, C, FS, K, t.tx, t.rx)
    with pytest.raises(InputError, match="rx"):
        Transients(t.transients, 0.0, t.path_bin_width, C, FS, K, t.tx, t.rx[:-1])
    with pytest.raises(InputError, match="bounds"):
        Volume(np.ones((2, 2, 2)), [[1, 0], [0, 1], [0, 1]], "bp")
    with pytest.raises(InputError, match="volume"):
        Volume(np.ones((2, 2)), [[0, 1], [0, 1], [0, 1]], "bp")
    with pytest.raises(InputError, match="volume"):
        Volume(np.full((2, 2, 2), np.inf), [[0, 1], [0, 1], [0, 1]], "bp")


# ---- bad files

def _fails(path, match, reader=read_any):
    with pytest.raises(FormatError) as info:
        reader(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path)), message
    assert match in message, message
    return message


def test_missing_empty_text_and_directory(tmp_path):
    _fails(tmp_path / "nope.h5", "no such file")
    (tmp_path / "empty.h5").write_bytes(b"")
    _fails(tmp_path / "empty.h5", "empty file")
    (tmp_path / "text.h5").write_text("tx,rx\n1,2\n")
    _fails(tmp_path / "text.h5", "not an HDF5 file")
    _fails(tmp_path, "directory")


@pytest.mark.parametrize("maker, reader", [
    (make_dataset, SonarDataset.read), (make_volume, Volume.read),
    (make_transients, Transients.read)])
def test_truncated_file(tmp_path, maker, reader):
    path = tmp_path / "X.h5"
    maker().write(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _fails(path, "truncated", reader)


def test_hdf5_without_sonarsim_fields(tmp_path):
    path = tmp_path / "plain.h5"
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3)
    _fails(path, "attribute 'format'")


@pytest.mark.parametrize("edit, match", [
    (lambda f: f.__delitem__("pings/boresight"), "missing dataset 'pings/boresight'"),
    (lambda f: f.attrs.__delitem__("fs"), "missing attribute 'fs'"),
    (lambda f: f.attrs.__setitem__("fs", "fast"), "attribute 'fs'"),
    (lambda f: f.attrs.__delitem__("format_version"), "attribute 'format_version'"),
    (lambda f: f.attrs.__setitem__("format_version", 2), "newer"),
    (lambda f: f.attrs.__setitem__("format", "other.thing"), "attribute 'format'"),
    (lambda f: f.attrs.__setitem__("complete", False), "incomplete"),
    (lambda f: _replace(f, "pings/tx", np.zeros((6, 2))),
     "dataset 'pings/tx' has shape (6, 2), expected (N, 3)"),
    (lambda f: _replace(f, "pings/rx", np.zeros((5, 3))),
     "dataset 'pings/rx' has shape (5, 3), expected (N, 3) with N = 6"),
    (lambda f: _replace(f, "waveforms", np.zeros((6, 80))), "dataset 'waveforms' has dtype"),
    (lambda f: _replace(f, "waveforms", np.full((6, 80), np.nan, np.float32)), "NaN"),
    (lambda f: _replace(f, "gt/faces", np.zeros((2, 3))), "dataset 'gt/faces' has dtype"),
    (lambda f: f.__delitem__("gt/faces"), "gt/faces"),
    (lambda f: _replace(f, "transients/pings/tx", np.zeros((6, 4))),
     "dataset 'transients/pings/tx' has shape (6, 4)"),
    (lambda f: f["transients"].attrs.__delitem__("oversample"),
     "attribute 'oversample' of group 'transients'"),
    (lambda f: f["transients"].attrs.__setitem__("oversample", 7), "path_bin_width"),
])
def test_corrupted_dataset_fields(tmp_path, edit, match):
    path = tmp_path / "D.h5"
    make_dataset().write(path)
    with h5py.File(path, "r+") as f:
        edit(f)
    _fails(path, match, SonarDataset.read)


def test_corrupted_volume_fields(tmp_path):
    path = tmp_path / "V.h5"
    make_volume().write(path)
    with h5py.File(path, "r+") as f:
        f.attrs["bounds"] = np.zeros((2, 2))
    _fails(path, "attribute 'bounds'")
    with h5py.File(path, "r+") as f:
        f.attrs["bounds"] = np.zeros((3, 2))
        _replace(f, "volume", np.zeros((2, 2, 2), np.float32))
    _fails(path, "dataset 'volume' has dtype float32, expected complex64")


def _replace(f: h5py.File, name: str, value: np.ndarray) -> None:
    del f[name]
    f[name] = value


def test_wrong_kind_names_both(tmp_path):
    make_volume().write(tmp_path / "V.h5")
    msg = _fails(tmp_path / "V.h5", "attribute 'format'", SonarDataset.read)
    assert "sonarsim.volume" in msg and "sonarsim.dataset" in msg
    make_dataset().write(tmp_path / "D.h5")
    _fails(tmp_path / "D.h5", "sonarsim.dataset", Transients.read)
    _fails(tmp_path / "D.h5", "volume", Volume.read)


# ---- atomic writes

class Boom(RuntimeError):
    pass


def _failing_fill(f):
    f["partial"] = np.zeros(1000)
    raise Boom("writer died midway")


def test_atomic_write_failure_leaves_no_file(tmp_path):
    with pytest.raises(Boom):
        fmt.atomic_write_h5(tmp_path / "D.h5", _failing_fill)
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_failure_keeps_old_file(tmp_path):
    path = tmp_path / "D.h5"
    old = make_dataset(seed=5)
    old.write(path)
    before = path.read_bytes()
    with pytest.raises(Boom):
        fmt.atomic_write_h5(path, _failing_fill)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["D.h5"]
    assert_datasets_equal(old, SonarDataset.read(path))


def test_write_failure_inside_dataset_write(tmp_path, monkeypatch):
    path = tmp_path / "D.h5"
    make_volume().write(path)
    before = path.read_bytes()
    ds = make_dataset()

    def broken(self, g, data=True):
        raise Boom("disk full")
    monkeypatch.setattr(Transients, "_write_group", broken)
    with pytest.raises(Boom):
        ds.write(path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["D.h5"]


def test_write_replaces_existing_file(tmp_path):
    path = tmp_path / "V.h5"
    make_volume((2, 2, 2)).write(path)
    make_volume((3, 3, 3)).write(path)
    assert Volume.read(path).shape == (3, 3, 3)
    assert os.listdir(tmp_path) == ["V.h5"]


# ---- streaming writer

def _stream_kwargs(ds: SonarDataset) -> dict:
    t = ds.transients
    return dict(n_samples=ds.n_samples, tx=ds.tx, rx=ds.rx, boresight=ds.boresight,
                pulse=ds.pulse, fs=ds.fs, sound_speed=ds.sound_speed, source=ds.source,
                start_sample=ds.start_sample, temperatures=ds.temperatures,
                gt_vertices=ds.gt_vertices, gt_faces=ds.gt_faces, snr_db=ds.snr_db,
                seed=ds.seed, meta=ds.meta, rx_boresight=ds.rx_boresight,
                transients=None if t is None else TransientsLayout(
                    t.n_bounces, t.n_bins, t.path_start, t.path_bin_width, t.sound_speed,
                    t.fs, t.oversample, t.meta))


def _h5_contents(path: Path) -> dict:
    out = {}
    with h5py.File(path) as f:
        def visit(name, obj):
            out[name] = (obj[()].tobytes() if isinstance(obj, h5py.Dataset) else None,
                         {k: str(v) for k, v in obj.attrs.items()})
        f.visititems(visit)
        out["/"] = (None, {k: str(v) for k, v in f.attrs.items()})
    return out


@pytest.mark.parametrize("full", [True, False])
def test_stream_writer_resumes_and_matches_one_shot(tmp_path, full):
    ds = make_dataset(n=10, full=full)
    ds.write(tmp_path / "oneshot.h5")
    target = tmp_path / "D.h5"
    t = ds.transients

    def chunk(start, stop):
        return ds.waveforms[start:stop], None if t is None else t.transients[start:stop]

    with DatasetStreamWriter(target, **_stream_kwargs(ds)) as w:
        assert not w.resumed and w.missing_ranges(4) == [(0, 4), (4, 8), (8, 10)]
        w.write(0, *chunk(0, 4))
        w.write(8, *chunk(8, 10))
    # "interrupted": only the partial file exists and no reader accepts it
    assert sorted(os.listdir(tmp_path)) == ["D.h5.partial", "oneshot.h5"]
    _fails(Path(str(target) + ".partial"), "incomplete", SonarDataset.read)

    with DatasetStreamWriter(target, **_stream_kwargs(ds)) as w:
        assert w.resumed and w.n_done == 6
        assert w.missing_ranges(3) == [(4, 7), (7, 8)]
        with pytest.raises(InputError, match="not written"):
            w.finish()
        for start, stop in w.missing_ranges(3):
            w.write(start, *chunk(start, stop))
        assert w.finish() == target
    assert sorted(os.listdir(tmp_path)) == ["D.h5", "oneshot.h5"]
    assert_datasets_equal(ds, SonarDataset.read(target))
    assert _h5_contents(target) == _h5_contents(tmp_path / "oneshot.h5")


def test_stream_writer_refuses_other_settings_and_restarts_without_resume(tmp_path):
    ds = make_dataset(n=4, full=False)
    kwargs = _stream_kwargs(ds)
    with DatasetStreamWriter(tmp_path / "D.h5", **kwargs) as w:
        w.write(0, ds.waveforms[:2])
    with pytest.raises(FormatError, match="'fs'"):
        DatasetStreamWriter(tmp_path / "D.h5", **(kwargs | {"fs": 50e3}))
    with DatasetStreamWriter(tmp_path / "D.h5", resume=False, **(kwargs | {"fs": 50e3})) as w:
        assert not w.resumed and w.n_done == 0
        with pytest.raises(InputError, match="waveforms"):
            w.write(0, np.zeros((2, ds.n_samples + 1)))
        with pytest.raises(InputError, match="exceed"):
            w.write(3, np.zeros((2, ds.n_samples)))
        w.discard()
    assert os.listdir(tmp_path) == []


def test_stream_writer_restarts_from_corrupt_partial(tmp_path):
    ds = make_dataset(n=3, full=False)
    Path(str(tmp_path / "D.h5") + ".partial").write_bytes(b"garbage from a killed run")
    with DatasetStreamWriter(tmp_path / "D.h5", **_stream_kwargs(ds)) as w:
        assert not w.resumed
        w.write(0, ds.waveforms)
        w.finish()
    assert_datasets_equal(ds, SonarDataset.read(tmp_path / "D.h5"))


# ---- sonarsim info

@pytest.mark.parametrize("maker, words", [
    (make_transients, ["transients", "N = 6 pings x B = 3 bounces x T = 50 bins",
                       "path length", "meta.scene"]),
    (make_dataset, ["sonar dataset", "N = 6 pings x T = 80 samples", "fs = 100000 Hz",
                    "SNR 15 dB", "transients.shape", "pulse", "ground truth"]),
    (make_volume, ["volume", "4 x 5 x 6 voxels", "backprojection", "|v| max",
                   "params.upsample"]),
])
def test_info_each_kind(tmp_path, capsys, maker, words):
    path = tmp_path / "F.h5"
    maker().write(path)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    for word in words:
        assert word in out, word


def test_info_reports_dataset_numbers(tmp_path, capsys):
    ds = make_dataset(full=False)
    ds.write(tmp_path / "D.h5")
    main(["info", str(tmp_path / "D.h5")])
    out = capsys.readouterr().out
    peak = float(np.abs(ds.waveforms).max())
    assert f"peak |x| {peak:.4g}" in out
    assert f"0.000 .. {79 / FS * 1e3:.3f} ms" in out
    assert "transients             not stored" in out


def test_info_volume_peak_location(tmp_path, capsys):
    vol = np.zeros((3, 4, 5), np.complex64)
    vol[2, 1, 4] = 3 - 4j
    Volume(vol, [[0, 1], [0, 3], [0, 4]], "bp").write(tmp_path / "V.h5")
    main(["info", str(tmp_path / "V.h5")])
    assert "|v| max                5 at voxel (2, 1, 4) = (+1.0000, +1.0000, +4.0000) m" \
        in capsys.readouterr().out


@pytest.mark.parametrize("content", [b"just some text\n", b""])
def test_info_on_non_hdf5(tmp_path, capsys, content):
    path = tmp_path / "notes.h5"
    path.write_bytes(content)
    assert main(["info", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0]


def test_info_on_partial_file_reports_progress(tmp_path, capsys):
    ds = make_dataset(n=5, full=False)
    with DatasetStreamWriter(tmp_path / "D.h5", **_stream_kwargs(ds)) as w:
        w.write(1, ds.waveforms[1:3])
    assert main(["info", str(tmp_path / "D.h5.partial")]) == 1     # readers refuse it
    out = capsys.readouterr().out
    assert "INCOMPLETE" in out and "2 pings written so far" in out


# ---- compressed layout and the transients stream writer (rails, issue 24 item 3)

def test_per_ping_arrays_are_compressed_and_read_back_exactly(tmp_path):
    import h5py
    from sonarsim.dataset import TransientsStreamWriter
    t = make_transients(n=40, b=2, t=3000)
    t.transients[:, :, 1000:] = 0                    # mostly empty, as real histograms
    t.write(tmp_path / "one.h5")
    with h5py.File(tmp_path / "one.h5") as f:
        assert f["transients"].compression == "gzip" and f["transients"].chunks[1:] == (2, 3000)
    assert (tmp_path / "one.h5").stat().st_size < 0.6 * t.transients.nbytes
    header = Transients(t.transients[:, :, :1], t.path_start, t.path_bin_width, C, FS, K,
                        t.tx, t.rx, dict(t.meta))
    with TransientsStreamWriter(tmp_path / "streamed.h5", header, 3000) as w:
        w.write(25, t.transients[25:])                # any order
        w.write(0, t.transients[:25])
    back = Transients.read(tmp_path / "streamed.h5")
    assert np.array_equal(back.transients, t.transients)
    assert np.array_equal(back.transients, Transients.read(tmp_path / "one.h5").transients)
    d = make_dataset(n=7, t=300)
    d.write(tmp_path / "d.h5")
    with h5py.File(tmp_path / "d.h5") as f:
        assert f["waveforms"].compression == "gzip"
    assert np.array_equal(SonarDataset.read(tmp_path / "d.h5").waveforms, d.waveforms)


def test_transients_stream_writer_leaves_nothing_when_it_fails(tmp_path):
    from sonarsim.dataset import TransientsStreamWriter
    t = make_transients(n=10, b=1, t=64)
    header = Transients(t.transients[:, :, :1], t.path_start, t.path_bin_width, C, FS, K,
                        t.tx, t.rx)
    with pytest.raises(InputError, match="3 poses not written"):
        with TransientsStreamWriter(tmp_path / "T.h5", header, 64) as w:
            w.write(0, t.transients[:7])
    with pytest.raises(RuntimeError, match="interrupted"):
        with TransientsStreamWriter(tmp_path / "T.h5", header, 64) as w:
            w.write(0, t.transients[:5])
            raise RuntimeError("interrupted")
    with pytest.raises(InputError, match="exceed the file's 10"):
        with TransientsStreamWriter(tmp_path / "T.h5", header, 64) as w:
            w.write(8, t.transients[:5])
    assert list(tmp_path.iterdir()) == []
