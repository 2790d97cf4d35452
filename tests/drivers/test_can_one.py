"""The frame kernel's one-sample writer under the one-frame continuation rule (tests/support/sequence_reference.py):
the row the C kernel writes is the numpy block form's (records_to_samples), bit for bit, with the same
unwrapping and counters, over streams with losses, duplicates, strays, partial samples and missing
or reserved ADC codes."""
import numpy as np
import pytest

from gravcal.drivers.can import _ALL, _RECORD, records_to_samples
from support.sequence_reference import record_to_sample
from gravcal.drivers.sequence import SeqUnwrapper


def _records(rng: np.random.Generator, n: int) -> list[tuple]:
    out, seq, tick = [], int(rng.integers(0, 1 << 16)), int(rng.integers(0, 1 << 32))
    for _ in range(n):
        r = rng.random()
        if r < 0.03:
            step = int(rng.integers(2, 80))  # lost samples (beyond the stray limit now and then)
        elif r < 0.05:
            step = 0  # a duplicate
        elif r < 0.06:
            step = int(rng.integers(1 << 15, 1 << 16))  # a stray from far away
        else:
            step = 1
        seq, tick = (seq + step) & 0xFFFF, (tick + 5000 * max(step, 1)) & 0xFFFFFFFF
        present = _ALL if rng.random() < 0.9 else int(rng.integers(1, _ALL))
        codes = rng.choice([0, 1, 2047, 4095, 4096, 0xFFFE, 0xFFFF], 2)
        out.append((seq, tick, int(rng.integers(0, 1 << 16)), [int(v) for v in rng.integers(0, 1 << 16, 4)],
                    [int(v) for v in rng.choice([0, 1, 40000, 65535], 2)], int(codes[0]), int(codes[1]), present))
    return out


def _decode(records: list[tuple], one_path: bool) -> tuple[bytes, dict, int]:
    u, rows, fast = SeqUnwrapper(), [], 0
    for r in records:
        row = record_to_sample(r, u) if one_path else None
        if row is None:
            row = records_to_samples(np.array([r], dtype=_RECORD), u)
        else:
            fast += 1
        rows.append(row)
    counters = {k: getattr(u, k) for k in ("gaps", "missing", "duplicates", "strays", "restarts")}
    return np.concatenate(rows).tobytes(), counters, fast


@pytest.mark.parametrize("seed", range(4))
def test_one_record_path_gives_the_block_forms_bytes_and_counters(seed):
    records = _records(np.random.default_rng(seed), 3000)
    fast, fast_counters, n_fast = _decode(records, True)
    slow, slow_counters, _ = _decode(records, False)
    assert n_fast > 2000  # the C path is the one taken
    assert fast == slow
    assert fast_counters == slow_counters
    assert slow_counters["gaps"] > 0 and slow_counters["duplicates"] > 0 and slow_counters["strays"] > 0


def test_sample_kernel_rejects_wrong_buffers_and_out_of_range_fields():
    from gravcal.drivers._framekernel import sample_to_row

    with pytest.raises(ValueError, match="56-byte SAMPLE_DTYPE"):
        sample_to_row(bytearray(48), 0, 0, 0, (0, 0, 0, 0), (0, 0), 0, 0, 0)
    with pytest.raises(ValueError, match="16 bits"):
        sample_to_row(bytearray(56), 0, 0, 1 << 16, (0, 0, 0, 0), (0, 0), 0, 0, 0)
    with pytest.raises(TypeError):  # t1 needs four counts
        sample_to_row(bytearray(56), 0, 0, 0, (0, 0, 0), (0, 0), 0, 0, 0)
