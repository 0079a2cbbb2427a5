"""The solver's ensemble (``ensemble`` K): K fits with the seeds seed … seed + K − 1, solids
majority-voted, fields averaged; per-member checkpoints and resume; bad values refused."""
import numpy as np
import pytest

from recon import gradient_descent as gd
from recon import solver
from recon.grid import Grid
from recon.solver.loop import combine_members, member_checkpoint
from sonarsim.errors import InputError

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
                               **SMALL),
                      gd.solve(point_target_scan, GRID, iterations=6, seed=seed, progress=False,
                               **dict(SMALL, **SOLID)))
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
