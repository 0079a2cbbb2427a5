"""The optimisation loop shared by both representations: the scaled-backprojection start,
``fit`` (sample, render, loss, backward, Adam step, checkpoint) and ``solve`` (settings →
Volume)."""
from __future__ import annotations

import dataclasses
from dataclasses import asdict
from pathlib import Path

import numpy as np

from sonarsim.errors import InputError
from sonarsim.progress import progress_bar

from .. import forward, measurements
from .._jit import jit
from ..adam import Adam
from ..grid import Grid
from .autocorrelation import convolve_rendered, expand_bins, pulse_autocorrelation
from .checkpoints import check_checkpoint_path, dataset_digest, load_checkpoint, save_checkpoint
from .members import fit_members, member_processes
from .priors import in_scene_units, loss_terms, random_directions
from .profiling import _no_timer
from .resources import check_resources
from .sampling import (Sampler, reachable_bins, rolled_frames, target_energy, target_kind,
                       targets)
from .settings import CHECKPOINT_EVERY, SolverSettings, applies_to, settings_for
from .voxels import VoxelScene


def render_chunk(scene, params, samples, settings: SolverSettings, eps: float, field=None):
    """The forward model of one chunk (shared by both representations): (ŷ_re, ŷ_im, σ_re,
    σ_im) at every lane, through :func:`recon.forward.render`. ``field``: ``scene.bind(params)``
    if the caller already has it (the voxels' packed buffer is then made once per chunk)."""
    field = scene.bind(params) if field is None else field
    if hasattr(field, "occupancy_and_amplitude"):
        return forward.render_occupancy(field, samples, occlusion=settings.occlusion_scale > 0)
    return forward.render(field, samples, lambertian_eps=eps if settings.lambertian else None,
                          occlusion_scale=settings.occlusion_scale, with_sigma=True)


def scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings) -> np.ndarray:
    """Backprojection times the complex factor α that best fits the targets through the
    linear model on a fixed batch of 4 × ``pings_per_iteration`` pings
    (α = ⟨A x, s⟩/‖A x‖²), rendered ``pings_per_chunk`` pings at a time like the iterations
    (so it needs no more memory than one of them)."""
    from .. import backprojection
    x = backprojection.backproject(dataset, grid, progress=False)
    if settings.incoherent:
        x = np.abs(x).astype(np.complex64)
    rng = np.random.default_rng([settings.seed, 1])
    batch = dataclasses.replace(settings, pings_per_iteration=4 * settings.pings_per_iteration)
    pings, bins, _ = Sampler(tgt, first, last, batch, rng).draw()
    chunk = settings.pings_per_chunk or settings.pings_per_iteration
    directions = forward.cone_directions(settings.n_rays, settings.beamwidth_deg)
    num, denom = 0.0, 0.0
    for c0 in range(0, len(pings), chunk):
        sl = slice(c0, c0 + chunk)
        op = forward.EllipsoidOperator(grid, forward.ping_geometry(dataset, pings[sl], bins[sl],
                                                                   speeds),
                                       directions=directions)
        ax = op.forward(x).astype(np.complex128)
        num += np.vdot(ax, tgt[pings[sl, None], bins[sl]])
        denom += float(np.vdot(ax, ax).real)
        del op
    alpha = num / denom if denom > 0 else 0.0
    if settings.incoherent:
        alpha = abs(alpha)
    return (x * alpha).astype(np.complex64)


def fit(dataset, grid: Grid, settings: SolverSettings, scene, *, checkpoint=None,
        checkpoint_every=CHECKPOINT_EVERY, resume=False, progress=True, callback=None, desc="fit",
        timer=None):
    """Optimise ``scene`` (a :class:`VoxelScene` or :class:`recon.field.NetworkScene`);
    returns (Adam parameters dict, history list of dicts, info dict). ``timer``: a
    :class:`PhaseTimer` to profile the iterations (it forces evaluation between phases)."""
    import drjit as dr
    if not isinstance(grid, Grid):
        raise InputError(f"grid: expected recon.grid.Grid, got {type(grid).__name__}")
    measurements.check_dataset(dataset)
    if checkpoint is not None:
        check_checkpoint_path(checkpoint, resume)
    threads = int(dr.thread_count())
    if settings.deterministic:
        dr.set_thread_count(1)
    try:
        return _fit(dataset, grid, settings, scene, checkpoint, checkpoint_every, resume,
                    progress, callback, desc, timer)
    finally:
        if settings.deterministic:
            dr.set_thread_count(threads)


def _fit(dataset, grid, settings, scene, checkpoint, checkpoint_every, resume, progress,
         callback, desc, timer=None):
    import drjit as dr
    m = jit()
    speeds = measurements.sound_speeds(dataset)
    tgt = targets(dataset, settings)
    first, last = reachable_bins(dataset, grid, speeds)
    identity = {"dataset": dataset_digest(dataset), "grid": {"bounds": grid.bounds.tolist(),
                "shape": list(grid.shape)}, "scene": scene.kind,
                "settings": {k: v for k, v in asdict(settings).items() if k != "iterations"}}
    rng = np.random.default_rng(settings.seed)
    params = scene.initial(rng, None)
    for k in params:
        if settings.init_scale > 0 and scene.kind == "voxels":
            params[k] = params[k] + (rng.standard_normal(params[k].shape)
                                     * settings.init_scale).astype(np.float32)
    scale = 1.0
    x0 = None
    if settings.init == "bp" or settings.lr_units == "relative" or settings.warm_start_iterations:
        x0 = scaled_backprojection(dataset, grid, tgt, first, last, speeds, settings)
        peak = float(np.abs(x0).max())
        if not peak > 0:
            import warnings
            warnings.warn("the backprojection could not be scaled through the model (no ray met "
                          "it); voxel scale set to scale_factor/n_rays", RuntimeWarning, stacklevel=3)
            peak = settings.scale_factor / settings.n_rays
        if settings.lr_units == "relative":
            scale = peak
    if x0 is not None and settings.init == "bp" and scene.kind == "voxels":
        params = scene.with_start(params, x0)
    lr0 = settings.lr * scale
    lr1 = None if settings.lr_final is None else settings.lr_final * scale
    info = {"voxel_scale": scale, "lr_absolute": lr0, "dataset_digest": identity["dataset"],
            "target_kind": target_kind(dataset, settings),
            "target_energy": target_energy(tgt, first, last)}
    model = in_scene_units(settings, scale, info["target_energy"])
    if x0 is not None and scene.kind != "voxels" and (settings.init == "bp"
                                                        or settings.warm_start_iterations):
        params = scene.warm_start(params, x0, max(settings.warm_start_iterations, 1), rng,
                                  lr=settings.warm_start_lr)
    opt = Adam(params, lr0, epsilon=settings.adam_epsilon)
    start, history = 0, []
    if resume:
        if checkpoint is None:
            raise InputError("resume: needs a checkpoint path")
        if Path(checkpoint).exists():
            start, history = load_checkpoint(checkpoint, opt, rng, identity, settings)
    sampler = Sampler(tgt, first, last, settings, rng)
    directions = forward.cone_directions(settings.n_rays, settings.beamwidth_deg)
    eps = 0.5 * float(np.min(scene.h))
    chunk = settings.pings_per_chunk or settings.pings_per_iteration
    taps = int(settings.autocorrelation_taps)
    if taps and info["target_kind"] != "matched":
        raise InputError("autocorrelation_taps: the pulse-autocorrelation model is for "
                         f"matched-filtered targets, this run fits {info['target_kind']} data")
    acf = pulse_autocorrelation(dataset, taps) if taps else None
    n_t = tgt.shape[1]
    bar = progress_bar(settings.iterations, progress, unit="it", desc=desc, initial=start,
                       leave=False)
    tick = timer if timer is not None else _no_timer
    tick("setup")
    at_iteration = getattr(scene, "at_iteration", None)
    for it in range(start, settings.iterations):
        if at_iteration is not None:
            at_iteration(it)
        pings, bins, roll = sampler.draw(it)
        reg_on = it >= settings.reg_start
        need_u = reg_on and (settings.smoothness > 0 or settings.phase > 0
                             or settings.surface_tv > 0)
        n_chunks = -(-len(pings) // chunk)
        u_seeds = rng.integers(0, 2 ** 63, n_chunks) if need_u else None
        frames = rolled_frames(np.asarray(dataset.boresight)[pings], roll)
        record = {}
        for c0 in range(0, len(pings), chunk):
            sl = slice(c0, c0 + chunk)
            render_bins, pos = (expand_bins(bins[sl], taps, n_t) if taps
                                else (bins[sl], None))
            geo = forward.ping_geometry(dataset, pings[sl], render_bins, speeds)
            samples = forward.EllipsoidSamples(geo, directions, frames=frames[sl])
            u_vec = None
            if need_u:
                u_vec = random_directions(m, dr.width(samples.points), int(u_seeds[c0 // chunk]))
            t = tgt[pings[sl, None], bins[sl]].ravel()
            t_re, t_im = m.Float(t.real.copy()), m.Float(t.imag.copy())
            tick("sampling", t_re, t_im, u_vec)
            field = scene.bind(opt.params)
            y_re, y_im, s_re, s_im = render_chunk(scene, opt.params, samples, model, eps,
                                                  field=field)
            if taps:
                y_re, y_im = convolve_rendered(m, y_re, y_im, pos, acf)
            tick("forward", y_re, y_im, s_re, s_im)
            terms = loss_terms(m, field, samples, s_re, s_im, y_re, y_im, t_re, t_im, model,
                               scene.h, reg_on, u_vec, weight=len(pings[sl]) / len(pings))
            loss = sum(terms.values())
            tick("loss", loss, *terms.values())
            dr.backward(loss)
            tick("backward", *(dr.grad(v) for v in opt.params.values()))
            for k, v in terms.items():
                record[k] = record.get(k, 0.0) + float(v[0])
            record["loss"] = record.get("loss", 0.0) + float(loss[0])
            tick("host")
        if lr1 is not None:
            frac = it / max(settings.iterations - 1, 1)
            opt.lr = float(lr0 * (lr1 / lr0) ** frac)
        opt.step()
        tick("adam")
        record["iteration"] = it + 1
        history.append(record)
        if callback is not None:
            callback(it + 1, record)
        bar.set_postfix(loss=f"{record['loss']:.3g}", refresh=False)
        bar.update(1)
        if checkpoint is not None and ((it + 1) % checkpoint_every == 0
                                       or it + 1 == settings.iterations):
            save_checkpoint(checkpoint, opt, rng, it + 1, history, identity, settings)
        tick("host", iteration_end=True)
    bar.close()
    return opt.params, history, info


def solid_volume(field: np.ndarray, settings: SolverSettings, sensors: np.ndarray | None = None,
                 bounds=None) -> tuple[np.ndarray, int, float]:
    """(complex64 volume 1 inside the solid of ``field`` and 0 outside, voxels of the field
    above step 1's cut, that cut as a fraction of the (smoothed) peak):
    :func:`recon.solid.solidify` with the run's settings (``sensors`` [N, 3] m: the scan's
    sensor positions, ``bounds`` [3, 2] m: the field's box, both used by ``solid_hidden``)."""
    from .. import solid
    occupied = solid.solidify(field, threshold=settings.solid_threshold,
                              min_fraction=settings.solid_min_fraction,
                              close=int(settings.solid_close), floor=settings.solid_ground,
                              hidden=int(settings.solid_hidden), sensors=sensors, bounds=bounds,
                              quorum=float(settings.solid_hidden_quorum),
                              cavity_floor=float(settings.solid_cavity_floor),
                              blur=float(settings.solid_blur),
                              threshold_mode=settings.solid_threshold_mode,
                              smooth=float(settings.solid_smooth),
                              part_volume=float(settings.solid_part_volume),
                              part_height=float(settings.solid_part_height))
    above, level = solid.step_one(field, settings.solid_threshold, float(settings.solid_blur),
                                  settings.solid_threshold_mode)
    return occupied.astype(np.complex64), int(np.count_nonzero(above)), level


def make_scene(grid: Grid, settings: SolverSettings, network: bool):
    """The scene representation: :class:`recon.field.NetworkScene` or :class:`VoxelScene`."""
    if network:
        from ..field import NetworkScene, OccupancyScene
        from ..scattering import make_scene as make_sh_scene
        sh = make_sh_scene(grid, settings)
        if sh is not None:
            return sh
        kind = OccupancyScene if settings.occupancy else NetworkScene
        return kind(grid, settings, incoherent=settings.incoherent)
    return VoxelScene(grid, settings, incoherent=settings.incoherent)


def loss_by_tenth(history: list[dict], key: str) -> list[float]:
    """Mean of ``key`` over each tenth of the run's iterations (at most 10 values, first to
    last): the convergence record a volume carries (a single step's loss is noisy: every step
    draws other pings, bins and rays)."""
    values = np.array([h[key] for h in history if key in h], dtype=np.float64)
    if values.size == 0:
        return []
    return [float(c.mean()) for c in np.array_split(values, min(10, values.size))]


def member_checkpoint(checkpoint, member: int):
    """The checkpoint path of ensemble member ``member`` (0-based): the path itself for the
    first, ``NAME.memberK.npz`` (K = member + 1) beside it for the others; None stays None."""
    if checkpoint is None or member == 0:
        return checkpoint
    p = Path(checkpoint)
    return p.with_name(f"{p.stem}.member{member + 1}{p.suffix}")


def combine_members(volumes: list, output: str) -> np.ndarray:
    """complex64 [nx, ny, nz]: one volume from the ensemble members' volumes [K][nx, ny, nz]:
    for solids (bool or 0/1) a voxel is 1 when more than half of the members hold it (majority
    vote; one member: its solid); for fields the mean of the complex fields."""
    # summed member by member: no stacked copy of all K volumes
    if output == "solid":
        votes = np.zeros(np.shape(volumes[0]), dtype=np.uint16)
        for v in volumes:
            votes += np.abs(v) > 0.5
        return (2 * votes > len(volumes)).astype(np.complex64)
    total = np.zeros(np.shape(volumes[0]), dtype=np.complex128)
    for v in volumes:
        total += v
    return (total / len(volumes)).astype(np.complex64)


def fit_member(dataset, grid: Grid, out_grid: Grid, settings: SolverSettings, network: bool,
               sensors, checkpoint, checkpoint_every: int, resume: bool, desc: str,
               progress: bool = True, callback=None, timer=None) -> tuple:
    """One fit of an ensemble (or the only one): (volume on ``out_grid`` — a bool solid
    [nx, ny, nz] for a solid output, else the complex64 field —, run dict with the history,
    info, scene kind and, for a solid, its voxel counts and cut)."""
    scene = make_scene(grid, settings, network)
    params, history, info = fit(dataset, grid, settings, scene, checkpoint=checkpoint,
                                checkpoint_every=checkpoint_every, resume=resume,
                                progress=progress, callback=callback, desc=desc, timer=timer)
    vol = scene.volume(params, out_grid)
    run = {"history": history, "info": info, "kind": scene.kind}
    if settings.output == "solid":
        vol, run["field_occupied_voxels"], run["solid_level"] = solid_volume(
            vol, settings, sensors, out_grid.bounds)
        vol = np.abs(vol) > 0.5         # a member's solid kept as bool: 1 byte a voxel
        run["solid_voxels"] = int(np.count_nonzero(vol))
    return vol, run


def solve(dataset, grid: Grid, *, network: bool, method: str, preset: str | None = None,
          checkpoint=None, checkpoint_every: int = CHECKPOINT_EVERY, resume: bool = False,
          progress: bool = True, callback=None, export_grid: Grid | None = None, timer=None,
          parallel_members: bool = True, **overrides):
    """Run the solver and return a :class:`~sonarsim.dataset.Volume` (``method``) on ``grid``
    (or the scene sampled on ``export_grid``), with the settings, final loss and info in
    ``params``. ``callback(iteration, record)`` gets each iteration's loss terms.

    With ``ensemble`` K > 1 the scene is fitted K times with the seeds ``seed`` … ``seed + K
    − 1`` and the members' volumes are combined (:func:`combine_members`); the loss entries
    of ``params`` are the first member's, ``ensemble_*`` lists hold every member's; member k
    checkpoints to :func:`member_checkpoint` (a resumed run skips the finished members);
    ``callback`` gets every member's iterations. Deterministic CPU fits run up to
    :func:`~recon.solver.members.member_processes` members at once in worker processes
    (the same volumes to the bit; their records then carry ``member`` and arrive
    interleaved); ``parallel_members=False`` fits them in turn in this process."""
    from sonarsim.dataset import Volume
    settings = settings_for(preset, network=network, **overrides)
    check_resources(grid, settings, network)
    out_grid = grid if export_grid is None else export_grid
    members = int(settings.ensemble)
    sensors = (0.5 * (np.asarray(dataset.tx) + np.asarray(dataset.rx))
               if settings.output == "solid" else None)
    jobs = [dict(dataset=dataset, grid=grid, out_grid=out_grid,
                 settings=dataclasses.replace(settings, seed=settings.seed + k),
                 network=network, sensors=sensors,
                 checkpoint=member_checkpoint(checkpoint, k), checkpoint_every=checkpoint_every,
                 resume=resume, desc=method if members == 1 else f"{method} {k + 1}/{members}")
            for k in range(members)]
    processes = (member_processes(members, settings, grid, network, dataset, timer)
                 if parallel_members else 1)
    if processes > 1:
        results = fit_members(jobs, processes, progress=progress, callback=callback,
                              desc=method, iterations=settings.iterations)
    else:
        results = [fit_member(**job, progress=progress, callback=callback, timer=timer)
                   for job in jobs]
    volumes = [vol for vol, _ in results]
    runs = [run for _, run in results]
    vol = combine_members(volumes, settings.output)
    first = runs[0]
    history = first["history"]
    p = {k: v for k, v in asdict(settings).items() if applies_to(k, network)}
    if settings.output == "solid":
        p["field_occupied_voxels"], p["solid_level"] = (first["field_occupied_voxels"],
                                                        first["solid_level"])
        p["solid_voxels"] = int(np.count_nonzero(vol))
    p["preset"] = preset or "none"
    p["scene"] = first["kind"]
    p["final_loss"] = float(history[-1]["loss"]) if history else float("nan")
    p["final_data_loss"] = float(history[-1]["data"]) if history else float("nan")
    p["data_loss_by_tenth"] = loss_by_tenth(history, "data")
    p["loss_by_tenth"] = loss_by_tenth(history, "loss")
    p["n_pings"] = int(len(dataset.waveforms))
    p.update(first["info"])
    if members > 1:
        p["ensemble_seeds"] = [settings.seed + k for k in range(members)]
        p["ensemble_final_data_loss"] = [float(r["history"][-1]["data"]) if r["history"]
                                         else float("nan") for r in runs]
        if settings.output == "solid":
            p["ensemble_solid_voxels"] = [r["solid_voxels"] for r in runs]
    return Volume(volume=vol, bounds=np.asarray(out_grid.bounds, dtype=np.float64), method=method,
                  params=p)


# Keywords of solve() that are not settings (checked elsewhere or not at all).
RUN_KEYWORDS = ("checkpoint", "checkpoint_every", "resume", "progress", "callback",
                "export_grid", "timer", "parallel_members")


def check_options(grid: Grid, network: bool, preset: str | None = None, **options) -> None:
    """Everything a run with these options would refuse before its work starts: unknown
    settings, ranges, the lane limit and the memory estimate (InputError, one line)."""
    fields = {k: v for k, v in options.items() if k not in RUN_KEYWORDS}
    check_resources(grid, settings_for(preset, network=network, **fields), network)
