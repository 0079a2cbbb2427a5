"""recon.solver.sampling: the run's ping schedule (uniform or stratified over the scan)."""
import numpy as np

from recon.solver import SolverSettings
from recon.solver.sampling import Sampler, stratified_pings


def test_fewer_draws_than_pings_take_one_ping_per_contiguous_stratum():
    active = np.arange(7, 1007)                     # 1 000 pings in scan order
    seq = stratified_pings(active, 100, np.random.default_rng(3))
    assert len(seq) == 100 and len(set(seq.tolist())) == 100
    counts, _ = np.histogram(seq, bins=100, range=(7, 1007))
    assert np.all(counts == 1)                      # every 10-ping stratum exactly once
    assert not np.all(np.diff(seq) > 0)             # shuffled, not in scan order
    # a uniform draw of the same size leaves strata empty
    uniform = np.random.default_rng(3).choice(active, 100)
    assert np.count_nonzero(np.histogram(uniform, bins=100, range=(7, 1007))[0] == 0) > 10


def test_more_draws_than_pings_use_every_ping_once_per_pass():
    active = np.array([2, 5, 6, 9, 11])
    seq = stratified_pings(active, 12, np.random.default_rng(0))
    counts = np.array([np.count_nonzero(seq == a) for a in active])
    assert len(seq) == 12 and set(seq.tolist()) <= set(active.tolist())
    assert counts.sum() == 12 and counts.min() == 2 and counts.max() == 3


def test_sampler_serves_each_iteration_its_share_of_the_schedule():
    tgt = np.ones((40, 8), np.complex64)
    first, last = np.zeros(40, int), np.full(40, 7)
    s = SolverSettings(iterations=4, pings_per_iteration=5, bins_per_ping=4, seed=9,
                       ping_sampling="stratified")
    a = Sampler(tgt, first, last, s, np.random.default_rng(0))
    b = Sampler(tgt, first, last, s, np.random.default_rng(1))   # another main generator
    drawn = [a.draw(it)[0] for it in range(4)]
    assert all(len(d) == 5 for d in drawn)
    # 20 draws of 40 pings: one from each pair of neighbours (2k, 2k + 1)
    assert np.array_equal(np.sort(np.concatenate(drawn)) // 2, np.arange(20))
    # the schedule depends on the seed only (not on the main generator, not on the order of
    # the calls): a resumed run draws the same pings
    assert all(np.array_equal(b.draw(it)[0], drawn[it]) for it in (3, 0, 2))
    # without an iteration (the scaled-backprojection batch) the draw stays uniform
    assert len(a.draw()[0]) == 5
