"""kill -9 while the calibration state is written (issue 8 item 5): the state always loads,
old or new, never corrupt; the temp file of an interrupted save never accumulates. A forked
writer saves through StateStore in a loop and is SIGKILLed at random moments. Long mode
(1000 kills): ``python bench/bench_faults.py --long --only state_kill``."""

from support import faults_state as bf


def test_sigkill_during_state_writes_never_leaves_a_corrupt_state(tmp_path):
    fig = bf.run_state_kill(80, seed=3, directory=str(tmp_path))
    assert fig["kills"] == 80
    assert fig["loads_ok"] == 80 and fig["loads_corrupt"] == 0 and fig["moved_aside"] == 0
    assert fig["revision_out_of_range"] == 0
    assert fig["loaded_old"] + fig["loaded_new"] == 80
    # the kills really landed inside writes (a temp file was left) and the next load removed it
    assert fig["temps_left_by_kills"] > 0
    assert fig["max_temps_seen"] <= 1 and fig["temps_after_load"] == 0
