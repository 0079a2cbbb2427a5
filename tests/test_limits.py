"""sonarsim.limits: the memory limit's boundary and message, and the outright bounds."""
from __future__ import annotations

import pytest

from sonarsim import limits
from sonarsim.errors import InputError


@pytest.fixture
def no_limit_set(monkeypatch):
    """No --max-memory and no environment variable: the machine's memory decides."""
    monkeypatch.delenv(limits.ENV_MAX_MEMORY, raising=False)
    limits.set_max_memory(None)
    yield
    limits.set_max_memory(None)


def test_a_need_equal_to_the_limit_passes_and_one_byte_more_is_refused(no_limit_set):
    limits.set_max_memory("1M")
    limits.check_memory(2**20, "the volume", "detail")
    with pytest.raises(InputError, match=r"^the volume needs 1\.0 MiB \(detail\) but "
                                         r"--max-memory is 1\.0 MiB; fewer \(see --max-memory\)$"):
        limits.check_memory(2**20 + 1, "the volume", "detail", "fewer")


def test_the_machine_limit_is_80_percent_and_the_message_shows_the_whole_machine(
        no_limit_set, monkeypatch):
    monkeypatch.setattr(limits, "machine_memory", lambda: 10 * 2**30)
    assert limits.memory_limit() == (8 * 2**30, "this machine has")
    limits.check_memory(8 * 2**30, "the transients", "d")
    with pytest.raises(InputError, match=r"^the transients need 8\.0 GiB \(d\) but this "
                                         r"machine has 10\.0 GiB \(see"):
        limits.check_memory(8 * 2**30 + 1, "the transients", "d")


def test_the_environment_sets_the_limit_and_the_option_overrides_it(no_limit_set, monkeypatch):
    monkeypatch.setenv(limits.ENV_MAX_MEMORY, "2K")
    assert limits.memory_limit() == (2048, f"{limits.ENV_MAX_MEMORY} is")
    limits.set_max_memory("3K")
    assert limits.memory_limit() == (3072, "--max-memory is")


@pytest.mark.parametrize("value, ok", [(1, True), (1024, True), (1025, False), (0, False),
                                       (1.5, False), (4.0, True)])
def test_upsample_is_an_integer_in_range(value, ok):
    if ok:
        assert limits.check_upsample(value) == int(value)
    else:
        with pytest.raises(InputError, match="--upsample must be an integer in 1..1024"):
            limits.check_upsample(value)


def test_sample_rate_and_pulse_length_bounds():
    assert limits.check_fs(100e6) == 100e6
    for bad in (0.0, -1.0, 100e6 * (1 + 1e-12), float("nan"), float("inf")):
        with pytest.raises(InputError, match=r"--fs must be in \(0, 1e\+08\] Hz"):
            limits.check_fs(bad)
    limits.check_pulse_length(100_000, 100e3)                   # exactly 1 s
    with pytest.raises(InputError, match="lasts 1.00001 s"):
        limits.check_pulse_length(100_001, 100e3)
