"""A scenario's blocks made in a child process equal the blocks made in this one."""
import numpy as np
import pytest

from gravcal.drivers.rigs.block_pipe import PipedBlocks
from gravcal.drivers.rigs.sources import scenario_source


@pytest.mark.parametrize("scenario,seed", [("six_position", 3), ("daily_living", 7)])
def test_piped_blocks_equal_the_in_process_source(scenario, seed):
    kw = dict(seed=seed, fs=200.0, duration=12.0)
    want = np.concatenate(list(scenario_source(scenario, **kw).blocks))
    piped = PipedBlocks(scenario, **kw)
    try:
        got = np.concatenate(list(piped))
    finally:
        piped.close()
    assert got.dtype == want.dtype and got.shape == want.shape
    for name in want.dtype.names:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_closing_early_stops_the_child():
    piped = PipedBlocks("six_position", seed=1, fs=200.0, duration=86400.0)
    first = next(iter(piped))
    assert first.shape[0] > 0
    piped.close()
    assert piped.proc.poll() is not None  # gone, not left writing into a closed pipe


def test_unknown_scenario_is_named_before_any_child_starts():
    with pytest.raises(ValueError, match="unknown scenario 'nope'"):
        PipedBlocks("nope", seed=0, fs=200.0, duration=1.0)
