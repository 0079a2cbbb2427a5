"""Refuse work that cannot fit before allocating anything: memory estimates and size bounds.

Every command estimates the peak memory of its run from the sizes it is about to use
(poses x bins, voxels x pings, ...) and calls :func:`check_memory` before any large array
exists. The limit is 80 % of this machine's memory (the smaller of physical memory and a
cgroup limit), or what ``--max-memory`` (every command has it) or the environment variable
``SONARSIM_MAX_MEMORY`` say, e.g. ``--max-memory 8G``. A refusal is one line in the style::

    the transients need 1749.4 GiB (54000 poses x 3 bounces x 2899 bins) but this machine
    has 23.5 GiB; render fewer poses, ...

Besides memory, a few values are bounded outright because no sonar needs them and they only
arise from typos (:data:`MAX_FS`, :data:`MAX_PULSE_SECONDS`, :data:`MAX_UPSAMPLE`).
"""
from __future__ import annotations

import math
import os
import re

from .errors import InputError

MAX_FS = 100e6                 # Hz; AirSAS samples at 100 kHz, imaging sonars at a few MHz
MAX_PULSE_SECONDS = 1.0        # s; sonar pulses last micro- to milliseconds
MAX_UPSAMPLE = 1024            # FFT upsampling factor of the reconstructors (reference: 5)
MAX_BOUNCES = 64               # the integrator's limit (plugins/sonar_transient.py MAX_BOUNCES_LIMIT)
MACHINE_FRACTION = 0.8         # share of the machine's memory a run may plan to use
ENV_MAX_MEMORY = "SONARSIM_MAX_MEMORY"

_state: dict = {"max_memory": None}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([kKmMgGtT]?)(i?[bB])?\s*$")
_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_size(text: str | int | float) -> int:
    """Bytes of a size like ``8G``, ``512M``, ``1.5GiB``, ``2e9`` (K/M/G/T are powers of 1024)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value, unit = float(text), ""
    else:
        m = _SIZE.match(str(text))
        if not m:
            raise InputError(f"--max-memory: expected a size such as 8G, 512M or 2e9 (bytes), "
                             f"got {text!r}")
        value, unit = float(m.group(1)), m.group(2).lower()
    out = value * _UNITS[unit]
    if not (math.isfinite(out) and out >= 1):
        raise InputError(f"--max-memory: must be a positive size, got {text!r}")
    return int(out)


def machine_memory() -> int | None:
    """Bytes of memory this process may use: physical memory, capped by a cgroup limit."""
    total = None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as f:
                limit = int(f.read().strip())
        except (OSError, ValueError):
            continue
        if 0 < limit < (total or 2**62):
            total = limit
    return total


def set_max_memory(value: str | int | None) -> None:
    """Set the limit used by :func:`check_memory` (``None``: environment, else the machine)."""
    _state["max_memory"] = None if value is None else parse_size(value)


def memory_limit() -> tuple[int | None, str]:
    """(bytes a run may use, how to describe it in a message); bytes None when unknown."""
    if _state["max_memory"] is not None:
        return _state["max_memory"], "--max-memory is"
    env = os.environ.get(ENV_MAX_MEMORY, "").strip()
    if env:
        return parse_size(env), f"{ENV_MAX_MEMORY} is"
    total = machine_memory()
    if total is None:
        return None, ""
    return int(MACHINE_FRACTION * total), "this machine has"


def gib(nbytes: float) -> str:
    """A size for messages: GiB, or MiB below 1 GiB."""
    if nbytes < 2**30:
        return f"{nbytes / 2**20:.1f} MiB"
    return f"{nbytes / 2**30:.1f} GiB"


def check_memory(need: float, what: str, detail: str, hint: str = "") -> None:
    """Raise a one-line :class:`InputError` when ``need`` bytes exceed the memory limit.

    ``what`` names the data ("the transients", "backprojection"), ``detail`` how the
    estimate is made up ("54000 poses x 3 bounces x 2899 bins"), ``hint`` what to change.
    """
    limit, source = memory_limit()
    if limit is None or need <= limit:
        return
    shown = limit / MACHINE_FRACTION if source == "this machine has" else limit
    raise InputError(f"{what} need{'s' if not what.endswith('s') else ''} {gib(need)} "
                     f"({detail}) but {source} {gib(shown)}"
                     + (f"; {hint}" if hint else "") + " (see --max-memory)")


def check_fs(fs: float, option: str = "--fs") -> float:
    """A sample rate in (0, MAX_FS] Hz."""
    if not (math.isfinite(fs) and 0 < fs <= MAX_FS):
        raise InputError(f"{option} must be in (0, {MAX_FS:g}] Hz, got {fs:g}")
    return float(fs)


def check_pulse_length(n_samples: int, fs: float, what: str = "pulse") -> None:
    """A pulse of at most MAX_PULSE_SECONDS."""
    if n_samples / fs > MAX_PULSE_SECONDS:
        raise InputError(f"{what} lasts {n_samples / fs:g} s ({n_samples} samples at "
                         f"{fs:g} Hz); pulses longer than {MAX_PULSE_SECONDS:g} s are refused")


def check_upsample(upsample: int, option: str = "--upsample") -> int:
    """An FFT upsampling factor in 1..MAX_UPSAMPLE."""
    if int(upsample) != upsample or not 1 <= upsample <= MAX_UPSAMPLE:
        raise InputError(f"{option} must be an integer in 1..{MAX_UPSAMPLE}, got {upsample}")
    return int(upsample)


# ----------------------------------------------------------------------------- estimates

#: Bytes per histogram bin of a pose while rendered: two half-estimates, each a float64
#: Dr.Jit buffer, its float32 copy and NumPy copies (sonarsim.render's 20 bytes, twice).
SIM_BYTES_PER_BIN = 40
#: Bytes per FFT sample of the pulse convolution: float64 input, complex128 spectrum, float64
#: result.
SIM_BYTES_PER_FFT_SAMPLE = 32


def simulate_memory(n_poses: int, bounces: int, n_bins: int, n_samples: int,
                    pulse_samples: int, oversample: int, chunk_size: int | None = None,
                    convolve_block: int = 128) -> tuple[int, str]:
    """(peak bytes, how they are made up) of ``sonarsim simulate``: one chunk of histograms
    (at least one pose, whatever the memory budget), the FFT convolution of a block of
    pings at fs·oversample, and the N x T waveforms the noise pass holds."""
    chunk = max(1, min(n_poses, chunk_size or 1))
    hist = chunk * bounces * n_bins * SIM_BYTES_PER_BIN
    n_fft = n_bins + pulse_samples * oversample
    block = max(1, min(n_poses, convolve_block))
    conv = block * n_fft * SIM_BYTES_PER_FFT_SAMPLE
    waves = n_poses * n_samples * 12
    detail = (f"{chunk} poses x {bounces} bounces x {n_bins} bins x {SIM_BYTES_PER_BIN} bytes"
              f" + {block} pings x {n_fft} FFT samples x {SIM_BYTES_PER_FFT_SAMPLE} bytes"
              f" + {n_poses} pings x {n_samples} samples x 12 bytes")
    return hist + conv + waves, detail
