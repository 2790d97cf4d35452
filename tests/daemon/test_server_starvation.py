"""No local client can starve acquisition: 8 clients flooding ?STATUS and 20 slow readers beside a
good client watching every sample of a real-time 200 Hz gravcald (emulated serial).
The same figures, longer: ``python bench/bench_starvation.py``."""

import pytest

from support.faults_starvation import run_starvation

# measures rates, wake-ups or deadlines in real time: under pytest-xdist (--dist loadgroup) it runs on one
# worker, after the other real-time tests rather than beside them
pytestmark = pytest.mark.xdist_group("realtime")


def test_floods_and_slow_readers_do_not_starve_acquisition_or_a_good_client():
    fig = run_starvation(quiet_s=3.0, abuse_s=6.0, flooders=8, slow_readers=20)
    assert fig["daemon_exit_code"] == 0, fig
    # the device lost nothing and the server never fell behind acquisition
    assert fig["device_gaps"] == 0 and fig["emulator_overruns"] == 0, fig
    assert fig["inbox_overruns"] == 0 and fig["ring_overwritten"] == 0, fig
    # the good client got every sample, in order, at the device's rate
    assert fig["seq_gaps"] == 0 and fig["seq_backwards"] == 0 and fig["good_client_dropped"] == 0, fig
    assert abs(fig["rate_abused_hz"] - fig["expected_hz"]) < 0.05 * fig["expected_hz"], fig
    # and not late: a shared 2-core machine adds scheduling noise, seconds of lag would be starvation
    assert fig["lag_ms_p99_abused"] < 250 and fig["lag_ms_max_abused"] < 1000, fig
    # the flooders were refused and told so, while their in-budget requests were answered
    assert fig["requests_refused"] > 0.5 * fig["flood_requests_sent"], fig
    assert fig["flood_errors_seen"] > 0 and fig["flood_status_answers"] > 0, fig
    # everyone left took their slot and their memory with them
    assert fig["clients_after"] == 1, fig
    assert fig["rss_kb_after"] - fig["rss_kb_quiet"] < 32 * 1024, fig
