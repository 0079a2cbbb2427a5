"""The solver's ensemble (``ensemble`` K): K fits with the seeds seed … seed + K − 1, solids
majority-voted, fields averaged; per-member checkpoints and resume; bad values refused."""
import numpy as np
import pytest

from recon import gradient_descent as gd
from recon import solver
from recon.grid import Grid
from recon.solver.loop import combine_members, member_checkpoint
from sonarsim.errors import FormatError, InputError

# The small point-target run of tests/test_gradient_descent.py (linear model, random start)
SMALL = dict(lambertian=False, occlusion_scale=0.0, sparsity=0.0, bins_per_ping=8, n_rays=300,
             beamwidth_deg=5.0, lr=3e-2, lr_final=None, pings_per_iteration=5, init="random",
             lr_units="absolute", output="field")
GRID = Grid([[-0.02, 0.02], [-0.02, 0.02], [0.08, 0.12]], (9, 9, 9))
SOLID = dict(output="solid", solid_threshold=1.2, solid_close=0)


def test_combine_members_votes_solids_and_averages_fields():
    a = np.zeros((2, 2, 1), np.complex64)
    b, c = a.copy(), a.copy()
    a[0, 0, 0] = b[0, 0, 0] = 1          # held by two of three: kept
    c[1, 1, 0] = 1                       # by one of three: dropped
    a[0, 1, 0] = b[0, 1, 0] = c[0, 1, 0] = 1
    vote = combine_members([a, b, c], "solid")
    assert vote.dtype == np.complex64
    np.testing.assert_array_equal(np.abs(vote) > 0.5, [[[True], [True]], [[False], [False]]])
    # an even count needs more than half: two of two, not one of two
    np.testing.assert_array_equal(np.abs(combine_members([a, c], "solid")) > 0.5,
                                  (np.abs(a) > 0.5) & (np.abs(c) > 0.5))
    f1 = np.full((2, 2, 1), 1 + 1j, np.complex64)
    f2 = np.full((2, 2, 1), 3 - 1j, np.complex64)
    np.testing.assert_allclose(combine_members([f1, f2], "field"), 2 + 0j)
    np.testing.assert_array_equal(combine_members([f1], "field"), f1)
    # a single member's solid (bool, as solve keeps them) comes back as its 0/1 volume
    one = combine_members([np.abs(a) > 0.5], "solid")
    assert one.dtype == np.complex64
    np.testing.assert_array_equal(one, a)


def test_member_checkpoints_sit_beside_the_first(tmp_path):
    ck = tmp_path / "run.npz"
    assert member_checkpoint(ck, 0) == ck
    assert member_checkpoint(ck, 2) == tmp_path / "run.member3.npz"
    assert member_checkpoint(None, 1) is None


@pytest.fixture(scope="module")
def members(point_target_scan):
    """Fields and solids of three single fits, seeds 4, 5, 6."""
    runs = {}
    for seed in (4, 5, 6):
        runs[seed] = (gd.solve(point_target_scan, GRID, iterations=6, seed=seed, progress=False,
                               ensemble=1, **SMALL),
                      gd.solve(point_target_scan, GRID, iterations=6, seed=seed, progress=False,
                               ensemble=1, **dict(SMALL, **SOLID)))
    return runs


def test_ensemble_solid_is_the_majority_of_its_members(point_target_scan, members):
    out = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=3, progress=False,
                   **dict(SMALL, **SOLID))
    solids = [np.abs(members[s][1].volume) > 0.5 for s in (4, 5, 6)]
    expected = sum(solids) >= 2
    # the members differ (else the vote would prove nothing) and the vote is not one of them
    assert any((a != b).any() for a in solids for b in solids)
    assert 0 < expected.sum() < expected.size
    np.testing.assert_array_equal(np.abs(out.volume) > 0.5, expected)
    assert out.params["ensemble_seeds"] == [4, 5, 6] and out.params["ensemble"] == 3
    assert out.params["ensemble_solid_voxels"] == [int(s.sum()) for s in solids]
    assert out.params["solid_voxels"] == int(expected.sum())
    # the loss entries are the first member's
    assert out.params["final_data_loss"] == members[4][1].params["final_data_loss"]


def test_ensemble_field_is_the_mean_of_its_members(point_target_scan, members):
    out = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=3, progress=False,
                   **SMALL)
    mean = np.mean([members[s][0].volume for s in (4, 5, 6)], axis=0)
    scale = np.abs(mean).max()
    assert scale > 0
    np.testing.assert_allclose(out.volume, mean, atol=1e-6 * scale)
    assert np.abs(out.volume - members[4][0].volume).max() > 1e-2 * scale


def test_ensemble_checkpoints_every_member_and_resumes(point_target_scan, tmp_path):
    ck = tmp_path / "run.npz"
    first = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=2, progress=False,
                     checkpoint=ck, checkpoint_every=3, **SMALL)
    assert ck.exists() and (tmp_path / "run.member2.npz").exists()
    resumed = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=2,
                       progress=False, checkpoint=ck, resume=True, **SMALL)
    np.testing.assert_allclose(resumed.volume, first.volume, atol=1e-6 * np.abs(first.volume).max())


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, solver.settings.MAX_ENSEMBLE + 1])
def test_bad_ensemble_sizes_are_refused(bad):
    with pytest.raises(InputError, match="ensemble"):
        gd.settings_for(ensemble=bad)


# ---------------------------------------------------------------- members in worker processes

def test_parallel_members_give_the_sequential_volumes_to_the_bit(point_target_scan, members):
    """Members fitted in worker processes (2 at a time) equal the same fits run in turn here,
    bit for bit, for a solid and a field; the callback hears every member's iterations."""
    seen = []
    out = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=3, progress=False,
                   callback=lambda i, r: seen.append((r["member"], i)), **SMALL)
    assert out.params["ensemble_seeds"] == [4, 5, 6]
    np.testing.assert_array_equal(
        out.volume, combine_members([members[s][0].volume for s in (4, 5, 6)], "field"))
    assert sorted(seen) == [(m, i) for m in range(3) for i in range(1, 7)]
    solid = gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=3,
                     progress=False, **dict(SMALL, **SOLID))
    np.testing.assert_array_equal(
        solid.volume, combine_members([members[s][1].volume for s in (4, 5, 6)], "solid"))


def test_parallel_network_members_equal_sequential_ones(point_target_scan):
    from recon import nbp
    kw = dict(iterations=3, seed=2, ensemble=2, progress=False, pings_per_iteration=4,
              bins_per_ping=8, n_rays=64, output="field", hash_levels=4, hash_log2_size=10,
              mlp_width=16, mlp_hidden=1)
    apart = nbp.solve(point_target_scan, GRID, **kw)
    here = nbp.solve(point_target_scan, GRID, parallel_members=False, **kw)
    assert np.abs(here.volume).max() > 0
    np.testing.assert_array_equal(apart.volume, here.volume)
    assert apart.params["ensemble_final_data_loss"] == here.params["ensemble_final_data_loss"]


def test_a_failing_member_stops_the_run_with_its_error(point_target_scan, tmp_path):
    """Member 2's checkpoint is not a checkpoint: its worker's one-line InputError comes
    back to the caller as itself."""
    ck = tmp_path / "run.npz"
    (tmp_path / "run.member2.npz").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="member2.npz: not a readable solver checkpoint"):
        gd.solve(point_target_scan, GRID, iterations=6, seed=4, ensemble=2, progress=False,
                 checkpoint=ck, resume=True, **SMALL)


def test_member_processes_respect_threads_cores_memory_and_timers(monkeypatch,
                                                                  point_target_scan):
    import drjit as dr
    from recon.solver import members as m
    from sonarsim import limits
    settings = gd.settings_for(ensemble=3)
    ds = point_target_scan
    monkeypatch.setattr(m, "available_cores", lambda: 8)
    threads = dr.thread_count()
    try:
        dr.set_thread_count(8)
        assert m.member_processes(3, settings, GRID, False, ds) == 3
        assert m.member_processes(1, settings, GRID, False, ds) == 1
        dr.set_thread_count(2)                             # --threads 2
        assert m.member_processes(3, settings, GRID, False, ds) == 2
        dr.set_thread_count(8)
        nondet = gd.settings_for(ensemble=3, deterministic=False)
        assert m.member_processes(3, nondet, GRID, False, ds) == 1
        one = solver.memory_estimate(GRID, settings, False) + ds.nbytes()  # a worker's copy
        limits.set_max_memory(2 * one + 1)
        assert m.member_processes(3, settings, GRID, False, ds) == 2
        limits.set_max_memory(2 * one - 1)               # two estimates fit, two datasets not
        assert m.member_processes(3, settings, GRID, False, ds) == 1
        limits.set_max_memory(None)
        assert m.member_processes(3, settings, GRID, False, ds, timer=solver.PhaseTimer()) == 1
    finally:
        dr.set_thread_count(threads)
        limits.set_max_memory(None)


def test_member_processes_follow_the_requested_variant_before_it_is_selected(monkeypatch,
                                                                            point_target_scan):
    """`SONARSIM_VARIANT=cuda_ad_mono recon nbp` plans its members before the variant is
    selected: they must be planned (one process) and started for the GPU, not as CPU workers
    of the default variant (they failed on a GPU machine without the CPU variant). Fails when
    the plan falls back to the default variant."""
    import drjit as dr
    from recon.solver import members as m
    from sonarsim import runtime
    settings = gd.settings_for(ensemble=3)
    monkeypatch.setattr(m, "available_cores", lambda: 8)
    monkeypatch.setitem(runtime._state, "variant", None)
    threads = dr.thread_count()
    try:
        dr.set_thread_count(8)
        monkeypatch.setenv(runtime.VARIANT_ENV, "cuda_ad_mono")
        assert m.run_variant() == "cuda_ad_mono"
        assert m.member_processes(3, settings, GRID, False, point_target_scan) == 1
        monkeypatch.delenv(runtime.VARIANT_ENV)
        assert m.run_variant() == runtime.DEFAULT_VARIANT
        assert m.member_processes(3, settings, GRID, False, point_target_scan) == 3
    finally:
        dr.set_thread_count(threads)


def test_command_line_members_side_by_side_write_their_checkpoints(point_target_scan, tmp_path):
    """`recon gd --ensemble 2 --checkpoint`: the command holds the checkpoint's lock for the
    whole run, and the worker that fits the first member writes that checkpoint under it
    (it once failed: "another process is writing this output"); a resumed run reproduces
    the volume."""
    import json

    import h5py
    from recon.cli import main as recon_main
    data = tmp_path / "d.h5"
    point_target_scan.write(data)
    ck = tmp_path / "ck.npz"
    args = ["gd", str(data), "--bounds", "-0.02", "0.02", "-0.02", "0.02", "0.08", "0.12",
            "--shape", "9", "9", "9", "--iterations", "4", "--n-rays", "50", "--bins-per-ping",
            "8", "--ensemble", "2", "--no-progress", "--checkpoint", str(ck)]
    assert recon_main([*args, "--out", str(tmp_path / "a.h5")]) == 0
    assert ck.exists() and (tmp_path / "ck.member2.npz").exists()
    assert recon_main([*args, "--out", str(tmp_path / "b.h5"), "--resume"]) == 0
    with h5py.File(tmp_path / "a.h5") as a, h5py.File(tmp_path / "b.h5") as b:
        np.testing.assert_array_equal(a["volume"][()], b["volume"][()])
        assert json.loads(a.attrs["ensemble_seeds"]) == [0, 1]
