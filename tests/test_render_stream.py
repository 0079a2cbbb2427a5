"""``sonarsim render`` streams: :func:`sonarsim.render.render_to_file` writes chunk by chunk.

References: the in-memory driver (:func:`sonarsim.render.render_poses` + ``Transients.write``)
for the content, and the number of chunks alive / the process's peak resident memory for
the claim that memory does not grow with the number of poses.
"""
from __future__ import annotations

import gc
import weakref
from pathlib import Path

import h5py
import numpy as np
import pytest

from sonarsim.dataset import Transients
from sonarsim.geometry import trajectory
from sonarsim.scene import load_scene


@pytest.fixture(scope="module")
def sphere():
    spec = load_scene("sphere")
    return spec, spec.to_mitsuba()


def _attrs(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in f.attrs.items()}


@pytest.mark.parametrize("bounce1", ["surface", "cone"])
def test_streamed_file_equals_in_memory_render(mi, sphere, tmp_path, bounce1):
    from sonarsim.render import render_poses, render_to_file
    spec, scene = sphere
    poses = trajectory("cylindrical:5:1", box=spec.box)
    kw = dict(paths_per_pose=400, bounces=2, seed=4, box=spec.box, chunk_size=2,
              progress=False, bounce1=bounce1)
    whole = render_poses(scene, poses, **kw)
    whole.meta.update(scene="sphere", note="x")
    ref = whole.write(tmp_path / "ref.h5")
    out, shape, window = render_to_file(scene, poses, tmp_path / "s.h5",
                                        meta={"scene": "sphere", "note": "x"}, **kw)
    assert out == tmp_path / "s.h5" and shape == whole.transients.shape
    assert window.path_start == whole.path_start and window.n_bins == whole.n_bins
    streamed = Transients.read(out)
    assert whole.transients[:, 0].sum() > 0
    assert streamed.transients.tobytes() == whole.transients.tobytes()   # bit-identical
    np.testing.assert_array_equal(streamed.tx, whole.tx)
    np.testing.assert_array_equal(streamed.rx, whole.rx)
    assert streamed.meta == Transients.read(ref).meta
    assert _attrs(out) == _attrs(ref)                 # complete = True, format, window
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ref.h5", "s.h5"]   # no leftovers


def test_at_most_one_chunk_alive(mi, sphere, tmp_path, monkeypatch):
    """Each chunk's histograms are released before the next chunk is rendered."""
    import sonarsim.render as render
    spec, scene = sphere
    poses = trajectory("cylindrical:7:1", box=spec.box)
    real = render.iter_render
    seen: list = []

    def spy(*args, **kwargs):
        for sl, hist in real(*args, **kwargs):
            gc.collect()
            assert all(ref() is None for ref in seen), "an earlier chunk is still held"
            seen.append(weakref.ref(hist))
            yield sl, hist

    monkeypatch.setattr(render, "iter_render", spy)
    render.render_to_file(scene, poses, tmp_path / "t.h5", paths_per_pose=100, bounces=1,
                          bounce1="cone", chunk_size=2, box=spec.box, progress=False)
    assert len(seen) == 4


def _peak_rss_since_reset(fn) -> int:
    """Peak resident memory (bytes) of this process while ``fn()`` runs (Linux VmHWM,
    reset through /proc/self/clear_refs)."""
    gc.collect()
    Path("/proc/self/clear_refs").write_text("5")
    fn()
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def test_peak_memory_does_not_grow_with_the_pose_count(mi, sphere, tmp_path):
    """8 poses and 64 poses of 0.9 MB histograms each, in chunks of 2: the peak resident
    memory of the longer render is not higher by anything like the 50 MB that its
    transients take (an in-memory render would hold them all)."""
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc/self/clear_refs")
    from sonarsim.render import render_to_file
    spec, scene = sphere
    all_poses = trajectory("cylindrical:64:1", box=spec.box)
    kw = dict(paths_per_pose=200, bounces=2, bounce1="cone", chunk_size=2,
              path_range=(0.5, 20.0), progress=False)

    def run(n, name):
        return lambda: render_to_file(scene, all_poses[:n], tmp_path / name, **kw)

    _, shape, _ = render_to_file(scene, all_poses[:4], tmp_path / "warm.h5", **kw)
    per_pose = 4 * shape[1] * shape[2]
    assert per_pose > 800_000
    short = _peak_rss_since_reset(run(8, "a.h5"))
    long = _peak_rss_since_reset(run(64, "b.h5"))
    held = 56 * per_pose                         # what 56 more poses would take in memory
    assert long - short < 0.25 * held, (short, long, held)
    with h5py.File(tmp_path / "b.h5", "r") as f:
        assert f["transients"].shape == (64,) + shape[1:]
        assert f["transients"][63].sum() > 0 and f.attrs["complete"]


def test_interrupted_render_leaves_no_file(mi, sphere, tmp_path, monkeypatch):
    import sonarsim.render as render
    spec, scene = sphere
    poses = trajectory("cylindrical:6:1", box=spec.box)
    real = render.iter_render

    def failing(*args, **kwargs):
        for i, item in enumerate(real(*args, **kwargs)):
            if i == 2:
                raise KeyboardInterrupt
            yield item

    monkeypatch.setattr(render, "iter_render", failing)
    out = tmp_path / "t.h5"
    out.write_bytes(b"older")
    with pytest.raises(KeyboardInterrupt):
        render.render_to_file(scene, poses, out, paths_per_pose=100, bounces=1,
                              bounce1="cone", chunk_size=2, box=spec.box, progress=False)
    assert out.read_bytes() == b"older"            # the old file untouched, nothing else left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.h5"]


def test_render_command_refuses_a_chunk_beyond_the_memory_limit(tmp_path, capsys):
    """The command checks one chunk's buffers (not the whole file) against --max-memory,
    before rendering, in one line."""
    from sonarsim.cli import main
    out = tmp_path / "t.h5"
    base = ["render", "sphere", "--poses", "cylindrical:3:1", "--paths-per-pose", "100",
            "--bounces", "1", "--oversample", "60", "--no-progress", "--out", str(out)]
    assert main(base + ["--max-memory", "1M"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the transient buffers of one chunk needs" in err[0], err
    assert not out.exists()
    assert main(base + ["--max-memory", "64M"]) == 0          # 3 poses fit in 64 MiB
    assert Transients.read(out).n_pings == 3
