"""Socket abuse against a running gravcald (issue 8 item 5): never-reading watchers, garbage,
2000 bad commands, megabyte lines, 100 connections at once. A well-behaved watcher receives
every sample in order with no seq gap, acquisition loses nothing, ?POLL stays answered, RSS
stays bounded. Long mode (10^4 bad commands, 10 MB lines, 8 MB garbage):
``python bench/bench_faults.py --long --only socket_abuse`` (latency p99 with/without)."""

import pytest

from support import faults_socket as bf

# measures rates, wake-ups or deadlines in real time: under pytest-xdist (--dist loadgroup) it runs on one
# worker, after the other real-time tests rather than beside them
pytestmark = pytest.mark.xdist_group("realtime")


def test_abusers_do_not_touch_acquisition_or_a_well_behaved_client():
    fig = bf.run_socket_abuse(seconds=4.0, bad_commands=2000, mb_lines=3, connections=100, never_read=4)
    assert fig["daemon_exit_code"] == 0
    assert fig["bad_commands"] == 2000 and fig["megabyte_lines"] + fig["megabyte_lines_cut_off"] == 3
    # 100 at once, limit 64: every connect() succeeds (listen backlog above the limit) and each
    # client over the limit is told so by the server with an ERROR line, none left silent
    assert fig["connections"] == 100 and fig["connections_refused"] == 0, fig
    assert fig["crowd_accepted"] + fig["crowd_told_too_many"] == 100 and fig["crowd_no_answer"] == 0, fig
    assert fig["crowd_told_too_many"] >= 100 - 64 and fig["clients_rejected"] >= fig["crowd_told_too_many"], fig
    assert fig["seq_gaps"] == 0 and fig["seq_backwards"] == 0
    # the watcher kept up with the stream (within a read's batching) while being abused
    assert fig["samples_during_abuse"] >= 0.9 * fig["expected_during_abuse"], fig
    assert fig["inbox_overruns"] == 0 and fig["ring_overwritten"] == 0 and fig["device_gaps"] == 0
    assert fig["polls"] > 10 and fig["poll_rtt_ms_p99"] < 1000
    # memory: queues are bounded; megabyte lines are discarded, not buffered
    assert fig["rss_kb_abused"] - fig["rss_kb_before"] < 64 * 1024, fig
