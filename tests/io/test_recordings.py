"""Recording I/O: the CSV/.npy formats gravcal calibrate reads and gravcal simulate writes,
and the validation messages for bad input (each names the problem and where it is)."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from gravcal.core.samples import FLAG_SATURATED, SAMPLE_DTYPE, duty_ratios, raw_triad
from gravcal.errors import InputError
from gravcal.io.recordings import (
    RECORDING_DTYPE, read_recording, to_recording_array, truth_path, write_recording, write_truth,
)

FS = 100.0
T2 = 20000  # timer counts per period (5 ms at 4 MHz)


def make_samples(n: int = 2000, seed: int = 0, fs: float = FS) -> np.ndarray:
    """SAMPLE_DTYPE rows of a sensor at 0.5 duty + 0.04 duty/g, tumbling slowly (independent of core.simulate)."""
    rng = np.random.default_rng(seed)
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = 10.0 + np.arange(n) / fs
    s["seq"] = np.arange(n)
    phase = np.linspace(0, 3 * np.pi, n)
    a = np.column_stack([np.cos(phase), np.sin(phase) * 0.6, np.sin(phase) * 0.8, np.cos(phase)])
    duty = 0.5 + 0.04 * a + 1e-4 * rng.standard_normal((n, 4))
    s["t2"] = T2 + rng.integers(-3, 4, (n, 2))
    s["t1"] = np.round(duty * s["t2"][:, [0, 0, 1, 1]]).astype(np.uint32)
    s["gyro"] = 2048 + rng.integers(-5, 6, n)
    s["temp"] = 25.0 + 0.001 * np.arange(n)
    s["vsupply"] = 3.3
    return s


def write_csv(path, header: str, rows: list[str]) -> None:
    path.write_text(header + "\n" + "".join(r + "\n" for r in rows), encoding="utf-8")


def simple_rows(n: int = 100) -> list[str]:
    return [f"{i / FS:.2f},{0.5 + 0.01 * np.sin(i):.6f},{0.51 + 0.01 * np.cos(i):.6f},{0.49 + 0.001 * i:.6f}" for i in range(n)]


# -- round trips ---------------------------------------------------------------------------------
def test_csv_round_trip_keeps_triad_and_channels(tmp_path):
    s = make_samples()
    path = tmp_path / "rec.csv"
    assert write_recording(path, s) == len(s)
    rec = read_recording(path)
    np.testing.assert_allclose(rec.raw, raw_triad(s), rtol=1e-9)  # %.10g keeps 10 significant digits
    np.testing.assert_allclose(rec.t, s["t"], atol=5e-7)
    np.testing.assert_allclose(rec.temp, s["temp"], atol=5e-4)
    assert rec.fs == pytest.approx(FS, rel=1e-6)
    assert rec.gyro is None  # the single-axis "gyro" column (ADC counts) is not gx/gy/gz
    assert rec.n_dropped == 0 and rec.n_saturated == 0 and rec.warnings == []
    # the extra channels are there for other tools: redundant ax2 and the raw timer counts
    header = path.read_text().splitlines()[0].split(",")
    assert header == list(RECORDING_DTYPE.names)
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(data[:, header.index("ax2")], duty_ratios(s)[:, 3], rtol=1e-9)
    np.testing.assert_array_equal(data[:, header.index("t1_az")], s["t1"][:, 2])
    np.testing.assert_array_equal(data[:, header.index("t2_b")], s["t2"][:, 1])


def test_npy_round_trip_is_memory_mapped_and_equals_csv(tmp_path):
    s = make_samples()
    write_recording(tmp_path / "rec.csv", s)
    blocks = [s[i:i + 300] for i in range(0, len(s), 300)]  # written block by block through a memmap
    assert write_recording(tmp_path / "rec.npy", iter(blocks), n_total=len(s)) == len(s)
    a = read_recording(tmp_path / "rec.csv")
    b = read_recording(tmp_path / "rec.npy")
    np.testing.assert_array_equal(b.raw, raw_triad(s))  # exact: float64 in the .npy
    np.testing.assert_allclose(a.raw, b.raw, rtol=1e-9)
    assert isinstance(b.raw.base, np.ndarray) or b.raw.base is not None
    # raw is an (N, 3) view into the memory map, not a copy
    mm = np.load(tmp_path / "rec.npy", mmap_mode="r")
    assert b.raw.strides == (mm.strides[0], 8)
    assert not b.raw.flags.owndata


def test_npy_accepts_minimal_float32_layout(tmp_path):
    n = 500
    arr = np.zeros(n, dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
    arr["t"] = np.arange(n) / 50.0
    arr["ax"], arr["ay"], arr["az"] = 1.0, 2.0, np.linspace(0, 1, n)
    np.save(tmp_path / "min.npy", arr)
    rec = read_recording(tmp_path / "min.npy")
    assert rec.raw.shape == (n, 3) and rec.fs == pytest.approx(50.0)
    np.testing.assert_array_equal(rec.raw[:, 2], arr["az"])


def test_truth_json_beside_the_recording(tmp_path):
    out = write_truth(tmp_path / "sim.csv", {"seed": np.int64(3), "x": np.array([1.0, np.nan])})
    assert out == truth_path(tmp_path / "sim.csv") == tmp_path / "sim.truth.json"
    assert json.loads(out.read_text()) == {"seed": 3, "x": [1.0, None]}


def test_comments_blank_lines_semicolons_and_extra_columns(tmp_path):
    p = tmp_path / "x.csv"
    lines = [f"99;{r.replace(',', ';')};30.5" for r in simple_rows(60)]
    lines.insert(10, "")
    p.write_text("# logger v2\nTime_ignored;T;AX;ay;az;TEMP\n" + "\n".join(lines) + "\n")
    rec = read_recording(p)
    assert rec.n_samples == 60
    np.testing.assert_allclose(rec.temp, 30.5)
    assert rec.raw[0, 1] == pytest.approx(0.51 + 0.01)


# -- bad input: each message names the problem ---------------------------------------------------
def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_recording(tmp_path / "nope.csv")
    with pytest.raises(InputError, match="is a directory"):
        read_recording(tmp_path)


def test_empty_file_and_header_only(tmp_path):
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(InputError, match="empty file"):
        read_recording(tmp_path / "e.csv")
    (tmp_path / "h.csv").write_text("t,ax,ay,az\n")
    with pytest.raises(InputError, match="header but no samples"):
        read_recording(tmp_path / "h.csv")


def test_no_header(tmp_path):
    p = tmp_path / "n.csv"
    p.write_text("\n".join(simple_rows(60)) + "\n")
    with pytest.raises(InputError, match="no header row"):
        read_recording(p)


def test_missing_columns_are_named_and_found_ones_listed(tmp_path):
    p = tmp_path / "m.csv"
    write_csv(p, "time,x,y,az", simple_rows(60))
    with pytest.raises(InputError) as e:
        read_recording(p)
    msg = str(e.value)
    assert "missing columns t, ax, ay" in msg and "found: time, x, y, az" in msg


def test_text_in_numbers_gives_line_and_column(tmp_path):
    p = tmp_path / "t.csv"
    rows = simple_rows(80)
    rows[41] = rows[41].split(",")[0] + ",0.5,oops,0.5"
    p.write_text("# comment line\nt,ax,ay,az\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError) as e:
        read_recording(p)
    # comment (line 1) + header (line 2) + 41 rows before it -> line 44
    assert "line 44" in str(e.value) and "'ay'" in str(e.value) and "'oops' is not a number" in str(e.value)


def test_short_line_is_named(tmp_path):
    p = tmp_path / "s.csv"
    rows = simple_rows(80)
    rows[5] = "0.05,0.5"
    write_csv(p, "t,ax,ay,az", rows)
    with pytest.raises(InputError, match="line 7 has 2 fields"):
        read_recording(p)


def test_few_nan_rows_are_dropped_with_a_warning(tmp_path, caplog):
    p = tmp_path / "f.csv"
    rows = simple_rows(200)
    for i in (20, 21, 150):
        rows[i] = rows[i].rsplit(",", 1)[0] + ",nan"
    rows[30] = rows[30].split(",")[0] + ",,0.5,0.5"  # an empty field is a missing value
    write_csv(p, "t,ax,ay,az", rows)
    with caplog.at_level(logging.WARNING):
        rec = read_recording(p)
    assert rec.n_dropped == 4 and rec.n_samples == 196
    assert np.isfinite(rec.raw).all()
    assert "4 of 200 samples" in rec.warnings[0] and "first at line 22" in rec.warnings[0]
    assert "NaN/inf" in caplog.text


def test_mostly_inf_is_refused(tmp_path):
    p = tmp_path / "i.csv"
    rows = [r.rsplit(",", 1)[0] + (",inf" if i % 4 else ",0.5") for i, r in enumerate(simple_rows(200))]
    write_csv(p, "t,ax,ay,az", rows)
    with pytest.raises(InputError, match=r"150 of 200 samples \(75.0 %\) hold NaN/inf.*too many"):
        read_recording(p)


def test_time_backwards_and_duplicated(tmp_path):
    rows = simple_rows(100)
    r = list(rows)
    r[50], r[51] = r[51], r[50]
    write_csv(tmp_path / "b.csv", "t,ax,ay,az", r)
    with pytest.raises(InputError, match="time goes backwards at line 53"):
        read_recording(tmp_path / "b.csv")
    r = list(rows)
    r[61] = r[60].split(",")[0] + "," + r[61].split(",", 1)[1]
    write_csv(tmp_path / "d.csv", "t,ax,ay,az", r)
    with pytest.raises(InputError, match=r"duplicated time t=0.6 s at line 62 and line 63"):
        read_recording(tmp_path / "d.csv")


def test_too_few_samples(tmp_path):
    write_csv(tmp_path / "few.csv", "t,ax,ay,az", simple_rows(12))
    with pytest.raises(InputError, match="too few samples: 12; need at least 50"):
        read_recording(tmp_path / "few.csv")


def test_plain_2d_npy_says_which_layout(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((100, 4)))
    with pytest.raises(InputError, match=r"plain float64 array of shape \(100, 4\); expected a structured array with fields t, ax, ay, az"):
        read_recording(tmp_path / "p.npy")
    arr = np.zeros(100, dtype=[("t", "f8"), ("x", "f8")])
    np.save(tmp_path / "q.npy", arr)
    with pytest.raises(InputError, match="missing fields ax, ay, az; found: t, x"):
        read_recording(tmp_path / "q.npy")
    (tmp_path / "garbage.npy").write_bytes(b"not numpy at all")
    with pytest.raises(InputError, match="not a readable .npy"):
        read_recording(tmp_path / "garbage.npy")


# -- saturation ----------------------------------------------------------------------------------
def _clipped(n: int, clip_fraction_of_time: float, seed: int = 0):
    s = make_samples(n, seed)
    raw = raw_triad(s)
    level = np.quantile(raw[:, 2], 1 - clip_fraction_of_time)
    t = s["t"]
    raw = raw.copy()
    raw[:, 2] = np.minimum(raw[:, 2], level)  # az clipped at its rail
    return t, raw, level


@pytest.mark.parametrize("fraction, refused", [(0.02, False), (0.2, True)])
def test_clipped_channel_detected(tmp_path, fraction, refused):
    t, raw, level = _clipped(4000, fraction)
    p = tmp_path / "c.csv"
    np.savetxt(p, np.column_stack([t, raw]), delimiter=",", header="t,ax,ay,az", comments="", fmt="%.10g")
    if refused:
        with pytest.raises(InputError, match=r"saturated .*az sits at its maximum.*too many to drop"):
            read_recording(p)
    else:
        rec = read_recording(p)
        n_at_rail = int(np.sum(raw[:, 2] == raw[:, 2].max()))
        assert rec.n_saturated == n_at_rail and n_at_rail >= 0.019 * 4000
        assert rec.raw[:, 2].max() < float(np.float64(f"{level:.10g}"))
    # the check can be turned off (e.g. for data known to be only quantised)
    rec = read_recording(p, check_saturation=False)
    assert rec.n_saturated == 0 and rec.n_samples == 4000


def test_flags_column_marks_saturation(tmp_path):
    s = make_samples(3000)
    s["flags"][100:110] = FLAG_SATURATED
    write_recording(tmp_path / "f.npy", s)
    rec = read_recording(tmp_path / "f.npy")
    assert rec.n_saturated == 10 and rec.n_samples == 2990
    assert "flagged saturated by the logger" in rec.warnings[0]


def test_coarse_quantisation_is_not_mistaken_for_saturation(tmp_path):
    # an 8-bit-like recording: few distinct values, the extremes repeat legitimately
    n = 3000
    rng = np.random.default_rng(1)
    t = np.arange(n) / FS
    raw = np.round(128 + 40 * np.sign(np.sin(t[:, None] * [0.3, 0.5, 0.7])) + rng.normal(0, 0.6, (n, 3)))
    p = tmp_path / "q.csv"
    np.savetxt(p, np.column_stack([t, raw]), delimiter=",", header="t,ax,ay,az", comments="", fmt="%.6g")
    rec = read_recording(p)
    assert rec.n_saturated == 0 and rec.n_samples == n


def test_to_recording_array_fields():
    s = make_samples(10)
    arr = to_recording_array(s)
    np.testing.assert_array_equal(arr["t1_ax2"], s["t1"][:, 3])
    np.testing.assert_array_equal(np.column_stack([arr["ax"], arr["ay"], arr["az"]]), raw_triad(s))


@pytest.mark.parametrize("seed", range(5))
def test_chunked_filler_search_finds_what_flat_stretches_finds_on_the_triad(monkeypatch, seed):
    """The chunked filler search gives flat_stretches' own runs on the triad, runs across chunk borders included."""
    from gravcal.core.diagnosis.noise import flat_stretches
    from gravcal.io import recordings

    monkeypatch.setattr(recordings, "SCAN_CHUNK", 997)
    rng = np.random.default_rng(seed)
    raw = rng.integers(0, 40, size=(20_000, 3)).astype(np.float32)  # coarse: chance repeats happen
    for start in rng.integers(0, 19_000, 6):
        raw[start:start + rng.integers(20, 900)] = raw[start]
    want = flat_stretches(raw)
    got = recordings._filler_stretches(raw)
    assert want.runs and got.runs == want.runs and got.repeat_prob == want.repeat_prob
