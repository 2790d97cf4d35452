"""The socket protocol without sockets: request parsing, IMU encoding, decimation."""
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gravcal.core.calibration import Calibration
from gravcal.core.samples import empty
from gravcal.daemon import protocol
from gravcal.daemon.protocol import ProtocolError, Request, WatchPolicy, parse_requests


def test_parse_single_and_multiple_commands():
    assert parse_requests(b"?POLL;") == [Request("POLL")]
    assert parse_requests("?calib") == [Request("CALIB")]  # case-insensitive, ';' optional
    got = parse_requests(b'?WATCH={"enable":true,"rate":50};?STATUS;  ?VERSION;\r')
    assert got == [Request("WATCH", {"enable": True, "rate": 50}), Request("STATUS"), Request("VERSION")]
    assert parse_requests(b"   ") == []


def test_json_with_semicolon_inside_string_is_parsed_by_json_not_split():
    (req,) = parse_requests(b'?WATCH={"enable":true,"x":"a;b"};')
    assert req.args == {"enable": True, "x": "a;b"}  # rejected later by WatchPolicy, not mangled here
    with pytest.raises(ProtocolError, match="unknown field 'x'"):
        WatchPolicy().updated(req.args)


@pytest.mark.parametrize(
    "line, message",
    [
        (b"POLL;", "requests start with '?'"),
        (b"?FOO;", "unknown command '?FOO'"),
        (b"?POLL=1;", "?POLL takes no arguments"),
        (b"?WATCH={enable:true};", "not valid JSON"),
        (b"?WATCH=[1,2];", "must be a JSON object"),
        (b"?WATCH={}x;", "unexpected text"),
        (b"\xff\xfe?POLL;", "not valid UTF-8"),
    ],
)
def test_bad_requests_give_precise_errors(line, message):
    got = parse_requests(line)
    assert isinstance(got[-1], ProtocolError)
    assert message in str(got[-1])


def test_parse_stops_after_first_bad_command_but_keeps_earlier_ones():
    got = parse_requests(b"?POLL;?NOPE;?STATUS;")
    assert got[0] == Request("POLL")
    assert isinstance(got[1], ProtocolError) and len(got) == 2


def test_watch_policy_merges_and_validates():
    p = WatchPolicy().updated({"enable": True, "rate": 25})
    assert (p.enable, p.raw, p.rate) == (True, False, 25.0)
    p2 = p.updated({"raw": True})  # absent fields keep their value (gpsd)
    assert (p2.enable, p2.raw, p2.rate) == (True, True, 25.0)
    assert p2.updated({"rate": None}).rate == 0.0
    assert p2.updated({"json": True}).enable  # gpsd habit accepted
    for bad, msg in [({"enable": 1}, "'enable' must be true or false"), ({"rate": -1}, "'rate' must be a number"),
                     ({"rate": True}, "'rate' must be a number"), ({"rate": "5"}, "'rate' must be a number"),
                     ({"json": False}, "'json' can only be true"), ({"nmea": True}, "unknown field 'nmea'")]:
        with pytest.raises(ProtocolError, match=msg):
            p.updated(bad)


def _block(n, t0=0.0, fs=200.0):
    s = empty(n)
    s["t"] = t0 + np.arange(n) / fs
    s["seq"] = np.arange(n) + int(round(t0 * fs))
    s["t2"] = [20000, 21000]
    s["t1"] = np.column_stack([np.full(n, 10000 + i * 100) for i in range(4)])
    s["gyro"] = 2048
    s["temp"] = 24.5
    s["vsupply"] = 3.3
    s["flags"] = 4
    return s


def test_encode_imu_roundtrips_values_and_units():
    s = _block(4)
    acc = np.array([[0.1, -0.2, 9.80665]] * 4)
    gyro = np.array([0.5, np.nan, 0.0, -1.25])
    static = np.array([True, False, True, False])
    lines = protocol.encode_imu(s, acc, gyro, static)
    msgs = [json.loads(x) for x in lines]
    assert [m["seq"] for m in msgs] == [0, 1, 2, 3]
    assert msgs[1]["t"] == pytest.approx(0.005, abs=1e-6)
    assert msgs[0]["acc"] == pytest.approx([0.1, -0.2, 9.80665], abs=1e-5)
    assert [m["gyro"] for m in msgs] == [0.5, None, 0.0, -1.25]
    assert [m["static"] for m in msgs] == [True, False, True, False]
    assert msgs[0]["temp"] == pytest.approx(24.5) and msgs[0]["vsupply"] == pytest.approx(3.3, abs=1e-3)
    assert "duty" not in msgs[0]
    raw = [json.loads(x) for x in protocol.encode_imu(s, acc, gyro, static, raw=True)]
    assert raw[0]["t1"] == [10000, 10100, 10200, 10300] and raw[0]["t2"] == [20000, 21000]
    # duty = T1 / T2 of each channel's chip: ax, ay on chip A (20000), az, ax2 on chip B (21000)
    assert raw[0]["duty"] == pytest.approx([0.5, 10100 / 20000, 10200 / 21000, 10300 / 21000], abs=1e-6)
    assert raw[0]["flags"] == 4 and raw[0]["gyro_counts"] == 2048


def test_encode_imu_nonfinite_become_null_and_stay_valid_json():
    s = _block(2)
    s["t2"][1] = [0, 0]  # missing periods -> NaN duty -> NaN acceleration
    acc = np.array([[0.0, 0.0, 9.8], [np.nan, np.nan, np.nan]])
    msgs = [json.loads(x) for x in protocol.encode_imu(s, acc, np.zeros(2), np.zeros(2, bool), raw=True)]
    assert msgs[0]["acc"] == pytest.approx([0.0, 0.0, 9.8])
    assert msgs[1]["acc"] == [None, None, None]
    assert msgs[1]["duty"] == [None, None, None, None]


def test_encode_imu_infinities_and_partly_missing_gyro_are_null_and_values_unchanged():
    s = _block(3)
    s["t"][2] = np.inf
    s["temp"][0] = np.nan
    acc = np.array([[0.1, -np.inf, 9.80665], [np.inf, 0.25, -1.5], [0.0, 0.0, 9.8]])
    gyro = np.array([np.nan, -0.75, np.inf])  # calibrated samples beside missing ones
    joined = protocol.encode_imu_joined(s, acc, gyro, np.zeros(3, bool), raw=True)
    lines = protocol.encode_imu(s, acc, gyro, np.zeros(3, bool), raw=True)
    assert b"".join(lines) == joined and len(lines) == 3
    msgs = [json.loads(x) for x in lines]
    assert [m["acc"] for m in msgs] == [[0.1, None, 9.80665], [None, 0.25, -1.5], [0.0, 0.0, 9.8]]
    assert [m["gyro"] for m in msgs] == [None, -0.75, None]
    assert [m["t"] for m in msgs] == [0.0, pytest.approx(0.005), None]
    assert msgs[0]["temp"] is None and msgs[1]["temp"] == pytest.approx(24.5)
    assert msgs[2]["duty"] == pytest.approx([0.5, 10100 / 20000, 10200 / 21000, 10300 / 21000], abs=1e-6)


def test_encode_message_replaces_nan_with_null():
    line = protocol.encode({"class": "X", "a": float("nan"), "b": [1.0, float("inf")], "c": np.float32(2.5)})
    assert json.loads(line) == {"class": "X", "a": None, "b": [1.0, None], "c": 2.5}
    assert line.endswith(b"\n") and line.count(b"\n") == 1


def test_calib_message_fields():
    cal = Calibration(model="6", offset=[0.5, 0.51, 0.49], sensitivity=np.diag([0.125, 0.126, 0.124]),
                      covariance=np.diag([1e-6] * 6), param_names=["s_x", "s_y", "s_z", "o_x", "o_y", "o_z"],
                      n_windows=9)
    m = protocol.calib_message(cal, revision=3, updated=1.5e9, accepted=True)
    assert m["class"] == "CALIB" and m["revision"] == 3 and m["accepted"] is True and m["n_windows"] == 9
    assert m["offset"] == [0.5, 0.51, 0.49]
    assert m["std"]["o_x"] == pytest.approx(1e-3)


@pytest.mark.parametrize("rate, fs, expected", [(50.0, 200.0, 50), (10.0, 200.0, 10), (200.0, 100.0, 100), (0.0, 200.0, 200)])
def test_decimation_gives_at_most_rate_per_second_for_any_block_split(rate, fs, expected):
    rng = np.random.default_rng(1)
    t = 100.0 + np.arange(int(fs * 4)) / fs + rng.uniform(-1e-4, 1e-4, int(fs * 4))  # 4 s with jitter
    cuts = np.sort(rng.choice(np.arange(1, t.size), size=7, replace=False))
    last, sent = -np.inf, []
    for part in np.split(t, cuts):
        mask, last = protocol.decimation_mask(part, rate, last)
        sent.append(part[mask])
    sent = np.concatenate(sent)
    assert abs(sent.size - 4 * expected) <= 1
    if rate > 0 and rate < fs:
        gaps = np.diff(sent)
        assert gaps.min() > 1.0 / rate - 2.0 / fs  # never faster than the requested rate (within a sample)


@pytest.mark.parametrize("raw", [False, True])
@pytest.mark.parametrize("nan_acc", [False, True])  # all values finite, or one missing (null)
def test_static_codes_encode_true_false_and_null(raw, nan_acc):
    s = _block(3)
    acc = np.array([[0.1, -0.2, 9.80665]] * 3)
    if nan_acc:
        acc[1, 0] = np.nan
    codes = np.array([1, 0, protocol.STATIC_UNKNOWN], dtype=np.int8)
    msgs = [json.loads(x) for x in protocol.encode_imu_joined(s, acc, np.zeros(3), codes, raw=raw).splitlines()]
    assert [m["static"] for m in msgs] == [True, False, None]


def _parsed(requests):
    return [(type(r).__name__, r.command, r.args) if isinstance(r, Request) else ("error", str(r)) for r in requests]


@settings(max_examples=400, derandomize=True, database=None)
@given(st.lists(st.sampled_from(["?POLL", "?poll", "?Status", "?VERSION", "?calib", "?DEVICES", "?WATCH", "?x", "?",
                                 "POLL", "=", "{}", '{"enable":true}', ";", " ", "\t", "\r", "x", "_", "1", "ſ", "ı",
                                 "²", "\u00a0"]), max_size=12).map("".join))
def test_the_plain_command_shortcut_parses_as_the_general_walk(text):
    # lines of commands without arguments take a regular expression; every line parses as the walk would
    assert _parsed(parse_requests(text)) == _parsed(protocol._parse_walk(text.strip()))
