"""One solver, two scene representations: neural backprojection (Reed et al. 2023, §4) and
gradient descent on voxels (its ``--no_network`` special case, reference
``inr_reconstruction/reconstruct_scene.py``).

Per iteration (§4.2 of the paper's method, supplement Eq. 10–12):

1. draw ``pings_per_iteration`` pings and, per ping, ``bins_per_ping`` range bins without
   replacement with p_k ∝ |w_k|^u over the bins whose ellipsoids can reach the grid;
2. intersect a cone of ``n_rays`` rays leaving the TX around its boresight with each bin's
   ellipsoid (:class:`recon.forward.EllipsoidSamples`);
3. render ŵ(r_k) = Σ_j σ(x_kj)·L_kj·T_kj with :func:`recon.forward.render` (the one forward
   model: transmittance, Lambertian factor from ∇|σ|) for the *scene* — complex voxels
   (:class:`VoxelScene`) or a hash-grid + MLP field (:class:`recon.field.NetworkScene`);
4. L = mean|ŵ − w|² + [from ``reg_start``] sparsity, smoothness, phase and TV priors;
5. one Adam step (:class:`Adam`, state in plain arrays so checkpoints own it).

Pings are rendered ``pings_per_chunk`` at a time and their gradients accumulated before the
step (the reference's ``accum_grad``), which bounds memory for the network.

Checkpoints (``.npz``, atomic) carry the parameters, Adam moments, the host generator's
state, the loss history and the run's identity (dataset digest, grid, settings); resuming
with another identity is refused with a one-line error.

The package, along its seams: :mod:`.settings` (settings, help, presets), :mod:`.sampling`
(targets, reachable bins, random draws), :mod:`.voxels` (the voxel scene), :mod:`.priors`
(data term and priors), :mod:`.autocorrelation` (the matched-filter model),
:mod:`.profiling`, :mod:`.resources` (ranges and the memory estimate), :mod:`.checkpoints`,
:mod:`.loop` (fit and solve) and :mod:`.members` (ensemble members fitted side by side in
worker processes, :mod:`.member_worker`).
"""
from ..adam import Adam  # noqa: F401  (re-exported: recon.solver.Adam)
from .autocorrelation import convolve_rendered, expand_bins, pulse_autocorrelation  # noqa: F401
from .checkpoints import (check_checkpoint_path, dataset_digest, is_checkpoint,  # noqa: F401
                          load_checkpoint, save_checkpoint)
from .loop import (check_options, fit, loss_by_tenth, make_scene,  # noqa: F401
                   render_chunk, scaled_backprojection, solve)
from .priors import in_scene_units, loss_terms, random_directions  # noqa: F401
from .profiling import PhaseTimer  # noqa: F401
from .resources import check_resources, memory_estimate  # noqa: F401
from .sampling import (Sampler, reachable_bins, rolled_frames, target_energy,  # noqa: F401
                       target_kind, targets)
from .settings import (CHECKPOINT_EVERY, CHOICES, DEFAULT_PRESET, HELP,  # noqa: F401
                       NETWORK_DEFAULTS, NETWORK_ONLY, PRESETS, SolverSettings, applies_to,
                       default_preset, settings_for)
from .voxels import VoxelScene  # noqa: F401
