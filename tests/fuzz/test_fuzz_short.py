"""The short, deterministic run of every fuzz target (fuzz_targets.py) the suite makes: each seed-corpus entry,
then a fixed number of Hypothesis examples (derandomized: the same inputs every run) that mutate corpus entries
or are raw bytes. A few seconds per target; the long coverage-guided runs are `python tests/fuzz/run.py NAME`
(atheris, docs/daemon.md Security)."""
from __future__ import annotations

import logging

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fuzz_targets as ft

# executions per target beyond its corpus (each run takes a few seconds at most on the CI host)
EXAMPLES = {"frame_decoder": 400, "slcan_lines": 400, "socket_request": 150, "imu_line": 400, "config_file": 300,
            "state_file": 300, "calibration_json": 300, "recording": 60}


@pytest.fixture(scope="module", autouse=True)
def quiet_and_clean():
    logging.getLogger("gravcal").setLevel(logging.CRITICAL)  # each moved-aside state file logs a warning
    yield
    logging.getLogger("gravcal").setLevel(logging.NOTSET)
    ft.cleanup()


@st.composite
def mutated(draw, seeds: list[bytes]) -> bytes:
    """A corpus entry with a few byte-level edits (flip, insert, delete, repeat a slice, splice another entry),
    or raw bytes."""
    if not seeds or draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=2048))
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.integers(0, 4))
        at = draw(st.integers(0, len(data)))
        if op == 0 and data:
            i = min(at, len(data) - 1)
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == 1:
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif op == 2:
            del data[at:at + draw(st.integers(1, 64))]
        elif op == 3:
            data[at:at] = data[at:at + draw(st.integers(1, 64))] * draw(st.integers(1, 8))
        else:
            other = draw(st.sampled_from(seeds))
            data[at:] = other[draw(st.integers(0, len(other))):]
    return bytes(data)


@pytest.mark.parametrize("name", list(ft.TARGETS))
def test_the_seed_corpus_passes(name):
    seeds = ft.corpus(name)
    assert seeds, f"tests/fuzz/corpus/{name} is empty"
    for data in seeds:
        ft.TARGETS[name](data)


@pytest.mark.parametrize("name", list(ft.TARGETS))
def test_mutated_inputs_pass(name):
    seeds = ft.corpus(name)

    @settings(max_examples=EXAMPLES[name], derandomize=True, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(mutated(seeds))
    def run(data):
        ft.TARGETS[name](data)

    run()
