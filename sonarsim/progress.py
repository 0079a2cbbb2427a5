"""Progress bars for long runs (tqdm), shared by the simulator and the reconstructors."""
from __future__ import annotations


def progress_bar(total: int, enabled: bool, *, unit: str, desc: str, initial: int = 0,
                 leave: bool = True):
    """A tqdm bar over ``total`` steps; a silent one when ``enabled`` is false.

    When enabled, tqdm still hides the bar if stderr is not a terminal (``disable=None``).
    """
    from tqdm import tqdm
    return tqdm(total=total, initial=initial, unit=unit, desc=desc, leave=leave,
                dynamic_ncols=True, disable=None if enabled else True)
