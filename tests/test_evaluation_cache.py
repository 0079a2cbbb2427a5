"""The evaluation's shared work: one nearest-neighbour query per direction for Chamfer and
normals (against a brute-force reference), and the per-process GT cache (equal meshes share,
other meshes or arguments do not, and a warm cache gives the same metrics as a cold one)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon import metrics


def _brute(a, na, b, nb):
    """Chamfer and normal agreement by all-pairs distances (independent of cKDTree)."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    ia, ib = d.argmin(axis=1), d.argmin(axis=0)
    dab, dba = d.min(axis=1), d.min(axis=0)
    ab = np.clip(np.abs(np.sum(na * nb[ia], axis=1)), 0, 1)
    ba = np.clip(np.abs(np.sum(nb * na[ib], axis=1)), 0, 1)
    return (np.mean(dab ** 2) + np.mean(dba ** 2), 0.5 * (dab.mean() + dba.mean()),
            0.5 * (ab.mean() + ba.mean()),
            0.5 * (np.degrees(np.arccos(ab)).mean() + np.degrees(np.arccos(ba)).mean()))


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_surface_agreement_equals_brute_force_and_reuses_the_tree():
    rng = np.random.default_rng(3)
    a, b = rng.random((300, 3)), rng.random((200, 3)) * 0.5
    na, nb = _unit(rng, 300), _unit(rng, 200)
    sq, m, nc, angle = _brute(a, na, b, nb)
    gt = metrics.PointSet(a, na)
    for _ in range(2):                                   # the second call reuses gt's tree
        cm, c, e = metrics.surface_agreement(gt, metrics.PointSet(b, nb))
        assert cm["sq"] == pytest.approx(sq, rel=1e-12) and cm["m"] == pytest.approx(m, rel=1e-12)
        assert c == pytest.approx(nc, rel=1e-12) and e == pytest.approx(angle, rel=1e-12)
    assert metrics.chamfer(a, b) == cm
    assert metrics.normal_agreement(a, na, b, nb) == (c, e)
    assert metrics.surface_agreement(a, b[:0], na, nb[:0])[1:] == (None, None)


def test_gt_cache_shares_equal_meshes_only_and_changes_no_metric():
    metrics._GT_CACHE.clear()
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    calls = []

    def make(seed):
        calls.append(seed)
        return metrics.surface_samples(box, 50, seed)

    first = metrics.cached_gt("samples", box, (50, 0), lambda: make(0))
    same = metrics.cached_gt("samples", box.copy(), (50, 0), lambda: make(0))
    assert same is first and calls == [0]                # an equal mesh: computed once
    other = metrics.cached_gt("samples", box, (50, 1), lambda: make(1))
    moved = box.copy()
    moved.apply_translation((0.01, 0, 0))
    metrics.cached_gt("samples", moved, (50, 0), lambda: make(0))
    assert calls == [0, 1, 0] and not np.array_equal(other[0], first[0])
    assert not first[0].flags.writeable                  # shared arrays cannot be changed

    # a warm cache gives exactly the cold numbers (both protocols' GT paths)
    from recon import protocol_reference
    x, y, z = np.meshgrid(*[np.linspace(-0.2, 0.2, 21)] * 2, np.linspace(0, 0.3, 16),
                          indexing="ij")
    vol = np.exp(-((np.abs(x) - 0.05) ** 2 + y ** 2 + (z - 0.05) ** 2) / 0.002)
    bounds = np.array([[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]])
    gt = trimesh.creation.box((0.1, 0.1, 0.1))
    gt.apply_translation((0, 0, 0.05))

    def both():
        exact = metrics.evaluate(vol, bounds, gt, sweep=(0.2, 0.5), n_samples=500)
        ref, _ = protocol_reference.evaluate_reference(vol, bounds, gt, n_volume=2000,
                                                       n_surface=500, sweep=None,
                                                       chamfer_sweep=None)
        return exact, ref

    metrics._GT_CACHE.clear()
    cold = both()
    n_entries = len(metrics._GT_CACHE)
    warm = both()
    assert n_entries >= 3 and len(metrics._GT_CACHE) == n_entries
    assert warm == cold


def test_sweep_voxel_chamfer_equals_the_direct_one():
    """The sweep's shared voxel queries (Evaluator.prepare_sweep) give exactly the voxel
    Chamfer of each threshold's own occupied voxels, including thresholds whose nearest
    voxels lie beyond the shared neighbour lists (few voxels above a high threshold)."""
    from recon import export
    rng = np.random.default_rng(5)
    x, y, z = np.meshgrid(*[np.linspace(-0.2, 0.2, 25)] * 2, np.linspace(0, 0.3, 19),
                          indexing="ij")
    vol = np.exp(-(x ** 2 + y ** 2 + (z - 0.08) ** 2) / 0.004) + 0.3 * rng.random(x.shape)
    bounds = np.array([[-0.2, 0.2], [-0.2, 0.2], [0.0, 0.3]])
    gt = trimesh.creation.icosphere(2, 0.06)
    gt.apply_translation((0.02, 0, 0.08))
    metrics._GT_CACHE.clear()
    ev = metrics.Evaluator(vol, bounds, gt, n_samples=400)
    ev.prepare_sweep(0.05)
    assert ev._sweep["knn_dist"].shape[1] == metrics.Evaluator.SWEEP_NEIGHBOURS
    on_a_voxel = float(np.sort(ev.magnitude, axis=None)[-50])     # a tie: mag == t
    for t in (0.05, 0.3, 0.6, 0.95, 0.999, on_a_voxel):
        pts = export.occupied_points(ev.magnitude, ev.bounds, t)
        assert ev._voxel_chamfer(t, pts) == metrics.chamfer(ev.gt_surface, pts), t
