"""Targets and sampling of one run: the fitted complex data, the range bins each ping can
reach, and the host-side random draws of pings, bins and ray rolls (§4.2)."""
from __future__ import annotations

import numpy as np

from sonarsim.errors import InputError

from .. import forward, measurements
from ..grid import Grid
from .settings import SolverSettings


def target_kind(dataset, settings: SolverSettings) -> str:
    """The kind of data fitted: 'auto' resolves to 'deconvolved' for a deconvolved dataset
    (``recon deconvolve``), else 'matched'. 'matched' and 'analytic' of a deconvolved dataset
    are its stored signals: the matched-filter ablation runs on the original dataset."""
    deconvolved = measurements.is_deconvolved(dataset)
    if settings.data == "auto":
        return "deconvolved" if deconvolved else "matched"
    if settings.data == "deconvolved" and not deconvolved:
        raise InputError("data 'deconvolved': the dataset is not deconvolved (run recon deconvolve)")
    return settings.data


def targets(dataset, settings: SolverSettings) -> np.ndarray:
    """Complex targets [N, T] complex64: the chosen analytic data normalised to max 1, times
    ``scale_factor`` (|·| for the incoherent ablation)."""
    kind = target_kind(dataset, settings)
    if kind == "matched":
        s = measurements.matched_filtered(dataset)
    elif kind == "deconvolved":
        s = measurements.complex_signals(dataset)
    else:
        s = measurements.analytic_waveforms(dataset)
    peak = float(np.abs(s).max())
    if not peak > 0:
        raise InputError("dataset waveforms: all zero, nothing to fit")
    s = s * (settings.scale_factor / peak)
    if settings.incoherent:
        s = np.abs(s)
    return s.astype(np.complex64)


def target_energy(tgt: np.ndarray, first: np.ndarray, last: np.ndarray) -> float:
    """Mean over pings of the mean |s|² over each ping's reachable samples first..last: the
    data term of an empty scene (what :func:`recon.solver.in_scene_units` scales the priors
    by)."""
    power = np.abs(tgt).astype(np.float64) ** 2
    cum = np.concatenate([np.zeros((len(power), 1)), np.cumsum(power, axis=1)], axis=1)
    rows = np.arange(len(power))
    sums = cum[rows, np.asarray(last) + 1] - cum[rows, np.asarray(first)]
    return float(np.mean(sums / (np.asarray(last) - np.asarray(first) + 1)))


def reachable_bins(dataset, grid: Grid, speeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ping the first and last waveform sample [N] whose ellipsoid can meet the grid box."""
    corners = np.array(np.meshgrid(*grid.bounds, indexing="ij")).reshape(3, -1).T
    tx, rx = np.asarray(dataset.tx), np.asarray(dataset.rx)
    paths = (np.linalg.norm(corners[None] - tx[:, None], axis=2)
             + np.linalg.norm(corners[None] - rx[:, None], axis=2))
    # Closest point of the box may be nearer than every corner (sensor inside the box's span).
    near = np.linalg.norm(np.clip(tx, grid.bounds[:, 0], grid.bounds[:, 1]) - tx, axis=1) \
        + np.linalg.norm(np.clip(rx, grid.bounds[:, 0], grid.bounds[:, 1]) - rx, axis=1)
    lo = np.minimum(paths.min(axis=1), near)
    hi = paths.max(axis=1)
    n_t = np.asarray(dataset.waveforms).shape[1]
    first = np.floor(lo / speeds * dataset.fs - dataset.start_sample).astype(int)
    last = np.ceil(hi / speeds * dataset.fs - dataset.start_sample).astype(int)
    return np.clip(first, 0, n_t - 1), np.clip(last, 0, n_t - 1)


class Sampler:
    """Host-side random choices of one run (NumPy generator; fully determined by the seed)."""

    def __init__(self, tgt: np.ndarray, first: np.ndarray, last: np.ndarray,
                 settings: SolverSettings, rng: np.random.Generator):
        self.tgt, self.first, self.last, self.s, self.rng = tgt, first, last, settings, rng
        self.active = np.flatnonzero(last >= first)
        if len(self.active) == 0:
            raise InputError("no ping's echo window overlaps the grid: check bounds and dataset")
        self.schedule = (stratified_pings(self.active,
                                          settings.iterations * settings.pings_per_iteration,
                                          np.random.default_rng([settings.seed, 2]))
                         if settings.ping_sampling == "stratified" else None)

    def draw(self, iteration: int | None = None):
        """(pings [P], bins [P, K] sorted per ping, roll [P] radians). With ``ping_sampling``
        'stratified' and an ``iteration``, the pings are that iteration's share of
        :func:`stratified_pings`; otherwise P pings drawn uniformly."""
        s, rng = self.s, self.rng
        if self.schedule is not None and iteration is not None:
            pings = self.schedule[iteration * s.pings_per_iteration:
                                  (iteration + 1) * s.pings_per_iteration]
        else:
            pings = rng.choice(self.active, size=s.pings_per_iteration,
                               replace=len(self.active) < s.pings_per_iteration)
        bins = np.empty((len(pings), s.bins_per_ping), dtype=np.int64)
        for i, p in enumerate(pings):
            cand = np.arange(self.first[p], self.last[p] + 1)
            w = np.abs(self.tgt[p, cand]).astype(np.float64) ** s.sampling_uniformity + 1e-12
            if len(cand) <= s.bins_per_ping:
                # Every candidate once; the remaining slots repeat bins drawn by magnitude.
                extra = rng.choice(cand, size=s.bins_per_ping - len(cand), p=w / w.sum())
                bins[i] = np.sort(np.concatenate([cand, extra]))
            else:
                bins[i] = np.sort(rng.choice(cand, size=s.bins_per_ping, replace=False,
                                             p=w / w.sum()))
        roll = rng.uniform(0, 2 * np.pi, len(pings)) if s.ray_jitter else np.zeros(len(pings))
        return pings, bins, roll


def stratified_pings(active: np.ndarray, draws: int, rng: np.random.Generator) -> np.ndarray:
    """A run's whole sequence of ``draws`` pings from ``active`` (in scan order) [draws]:
    every ping once per full pass (random permutations) while draws cover the scan, then one
    ping drawn uniformly from each of the remaining draws' equal, contiguous strata of the scan
    order; the sequence is shuffled. Every seed so sees the aperture evenly (a uniform draw of
    1 500 of 54 000 pings leaves some look directions out by chance; docs/reconstruction.md,
    "Stratified pings"). Its own generator, so a resumed run draws the same sequence."""
    n = len(active)
    passes, rest = divmod(int(draws), n)
    parts = [rng.permutation(active) for _ in range(passes)]
    if rest:
        edges = (np.arange(rest + 1) * n) // rest
        parts.append(active[edges[:-1] + (rng.random(rest) * np.diff(edges)).astype(np.int64)])
    seq = np.concatenate(parts) if parts else np.empty(0, np.int64)
    return seq[rng.permutation(len(seq))]


def rolled_frames(boresight: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Per-ping local→world matrices [P, 3, 3]: boresight frames rolled by ``roll`` (rad)."""
    f = forward.boresight_frames(boresight)
    c, s = np.cos(roll), np.sin(roll)
    rot = np.zeros((len(roll), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    return f @ rot
