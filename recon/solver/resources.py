"""Ranges and a memory estimate of a solver run, checked before any work (one-line
:class:`~sonarsim.errors.InputError`, the same for ``recon gd|nbp``, ``sonarsim batch`` and the
Python API).

The estimate (bytes) of one run is

    lanes · bytes_per_lane + voxels · bytes_per_voxel + network parameters · 20

with lanes = the sample points of one backward pass (``pings_per_chunk`` × ``bins_per_ping``
× ``n_rays``, × (2·taps + 1) for the autocorrelation model), which must also stay below
Dr.Jit's 2³² lanes per launch. bytes_per_lane was measured on the CPU (peak RSS against
``n_rays`` at fixed everything else, 2026-11-25): ≈ 100 for voxels (200 is charged) and
806 / 1 912 / 4 250 for the network at MLP 32×1, 64×2 and 128×3 with 24–28 hash features,
i.e. ≈ 250 + 12·width·hidden + 8·features (charged; 20 % above the largest measured).
"""
from __future__ import annotations

from sonarsim.errors import InputError

from ..grid import Grid
from .settings import SolverSettings

LANE_LIMIT = 2 ** 32                 # Dr.Jit: lanes per kernel launch
VOXEL_BYTES_PER_LANE = 200
NETWORK_BYTES_PER_LANE = 250
BYTES_PER_MLP_UNIT = 12              # per hidden unit and layer, per lane
BYTES_PER_FEATURE = 8                # per hash-grid output feature, per lane
BYTES_PER_PARAMETER = 20             # value, gradient, Adam's two moments, the update
# Per voxel of the grid: the backprojection start (56, recon.backprojection), its scaled copy
# and the exported volume (complex64 each), and for voxels the parameters and their optimiser
# state (re, im × value, gradient, m, v, update) and the packed lookup buffer per thread.
GD_BYTES_PER_VOXEL = 56 + 16 + 40 + 16 * 3
NBP_BYTES_PER_VOXEL = 56 + 16 + 32


def lanes_per_pass(settings: SolverSettings) -> int:
    """Sample points rendered by one backward pass (Python int: no overflow)."""
    chunk = int(settings.pings_per_chunk or settings.pings_per_iteration)
    taps = int(settings.autocorrelation_taps)
    return chunk * int(settings.bins_per_ping) * (2 * taps + 1) * int(settings.n_rays)


def network_parameters(settings: SolverSettings) -> int:
    """Parameters of the network (:meth:`recon.field.NetworkSettings.network_parameters`)."""
    from ..scattering import n_outputs
    return settings.network_parameters(n_outputs(settings))


def bytes_per_lane(settings: SolverSettings, network: bool) -> int:
    if not network:
        return VOXEL_BYTES_PER_LANE
    return (NETWORK_BYTES_PER_LANE
            + BYTES_PER_MLP_UNIT * int(settings.mlp_width) * int(settings.mlp_hidden)
            + BYTES_PER_FEATURE * int(settings.hash_levels) * int(settings.hash_features))


def memory_estimate(grid: Grid, settings: SolverSettings, network: bool) -> int:
    """Estimated peak bytes of a run (see the module docstring)."""
    voxels = int(grid.shape[0]) * int(grid.shape[1]) * int(grid.shape[2])
    per_voxel = NBP_BYTES_PER_VOXEL if network else GD_BYTES_PER_VOXEL
    params = network_parameters(settings) if network else 0
    return (lanes_per_pass(settings) * bytes_per_lane(settings, network) + voxels * per_voxel
            + params * BYTES_PER_PARAMETER)


def check_ranges(settings: SolverSettings, network: bool) -> None:
    """Ranges beyond :meth:`SolverSettings.validate` that would crash or overflow a run."""
    if network:
        settings.validate_network()
    lanes = lanes_per_pass(settings)
    if lanes >= LANE_LIMIT:
        raise InputError(
            f"{lanes} sample points per pass (pings_per_chunk × bins_per_ping × n_rays"
            f"{' × (2·taps + 1)' if settings.autocorrelation_taps else ''}) exceed Dr.Jit's "
            f"2^32 per launch; lower --n-rays, --bins-per-ping or --pings-per-chunk")


def check_resources(grid: Grid, settings: SolverSettings, network: bool) -> None:
    """Ranges, the lane limit and the memory estimate against ``--max-memory`` (or 80 % of
    the machine): one line naming what to lower."""
    from sonarsim import limits
    check_ranges(settings, network)
    need = memory_estimate(grid, settings, network)
    detail = (f"{lanes_per_pass(settings)} sample points per pass x "
              f"{bytes_per_lane(settings, network)} bytes")
    if network:
        detail += f", {network_parameters(settings)} network parameters"
    limits.check_memory(need, "recon nbp" if network else "recon gd", detail,
                        "lower --pings-per-chunk, --n-rays or --bins-per-ping"
                        + (", --mlp-width or --hash-log2-size" if network else ""))
