"""Unplug/replug under a running gravcald: `gravcald --emulate` as a
subprocess, its emulated serial device (a real pty) and slcan CAN adapter (python-can over a
pty) unplugged and replugged 5 times each (--disconnect-at). The daemon reconnects every time,
each gap is flagged (FLAG_RECONNECT|FLAG_GAP_BEFORE, seq jump) to a raw socket watcher, nothing
before the unplug or after the replug is lost. Long mode (100 cycles each):
``python bench/bench_faults.py --long --only replug_serial`` / ``replug_can``."""

import pytest
from support import faults_replug as bf


@pytest.mark.parametrize("bus", ["serial", "can"])
def test_every_unplug_is_survived_and_flagged(bus):
    fig = bf.run_replug(bus, 5)
    assert fig["daemon_exit_code"] == 0
    assert fig["unplugs_seen_by_client"] == 5, fig
    assert fig["gaps_matching_unplugs"] == fig["gaps_flagged_reconnect"] == 5, fig
    # any other gap is one the emulator reported as an overrun of its link (the host read too late on a loaded
    # machine), and is flagged as a gap: the flags are tested here, the daemon's latency in bench/
    assert fig["unexpected_gaps"] <= fig["emulator_overruns"], fig
    assert fig["unexpected_gaps_flagged"] == fig["unexpected_gaps"] and fig["backwards_steps"] == 0, fig
    assert fig["daemon_reconnects"] >= 5 and fig["daemon_read_errors"] == 0
    # nothing lost around the gap beyond what was in flight at the unplug (the pty's buffer)
    # and what the emulator sent before the driver's backoff reopened the device
    assert 0 <= fig["max_lost_before_unplug_s"] < 1.0, fig
    assert fig["max_replug_to_first_sample_s"] <= fig["replug_bound_s"], fig
