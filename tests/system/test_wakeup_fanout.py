"""bench/wakeup_fanout.c, the floor bench_fanout_floor.py reports: in both modes every client must be woken once
per sample, or the floor would understate what waking N clients costs."""
from __future__ import annotations

import subprocess

import pytest

from tests.support.bench_c import build_bench_program

# measures rates, wake-ups or deadlines in real time: under pytest-xdist (--dist loadgroup) it runs on one
# worker, after the other real-time tests rather than beside them
pytestmark = pytest.mark.xdist_group("realtime")

@pytest.fixture(scope="module")
def fanout(tmp_path_factory) -> str:
    return build_bench_program("wakeup_fanout", tmp_path_factory.mktemp("fanout"))


@pytest.mark.parametrize("mode", ["send", "futex"])
def test_every_client_is_woken_once_per_sample(fanout, mode):
    out = subprocess.run([fanout, mode, "4", "1.0", "100"], check=True, capture_output=True, text=True,
                         timeout=60).stdout.split()
    got = {k: float(v) for k, v in zip(out[::2], out[1::2])}
    # a client late for one sample takes two in one wake-up: a little under 1 on a loaded machine, never over
    assert 0.8 <= got["client_wakeups_per_sample"] <= 1.0
    assert got["cpu_percent"] > 0 and got["us_per_sample"] > 0


def test_bad_arguments_are_refused_with_usage(fanout):
    r = subprocess.run([fanout, "smoke", "4", "1"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2 and "usage" in r.stderr
