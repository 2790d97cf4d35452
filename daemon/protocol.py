"""The gravcald socket protocol (gpsd's JSON style): requests in, JSON lines out.

Every message the server sends is one JSON object on one line with a ``class``. Clients
send gpsd-style commands, one or more per line::

    ?WATCH={"enable":true,"raw":false,"rate":50};
    ?POLL;  ?CALIB;  ?STATUS;  ?DEVICES;  ?VERSION;

This module is pure (no sockets): it parses requests into :class:`Request` objects and
encodes messages to bytes. docs/socket-protocol.md documents every class and field.
Units on the socket are SI: acceleration in m/s², angular rate in rad/s, time in s.
"""
from __future__ import annotations

import functools
import json
import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..jsonbounds import MAX_DEPTH, JSONInputError, raw_decode
from ._linekernel import imu_line, imu_lines

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 1  # additions only; docs/socket-protocol.md lists what each minor version brings

STANDARD_GRAVITY = 9.80665  # m/s² per g (CGPM 1901)

MAX_REQUEST_BYTES = 1024
MAX_REQUEST_DEPTH = MAX_DEPTH  # brackets in one ?WATCH argument, its own braces included
"""Default bound on one request line (bytes, without the newline)."""

COMMANDS = ("WATCH", "POLL", "CALIB", "STATUS", "DEVICES", "VERSION")
WATCH_FIELDS = ("enable", "raw", "rate", "json")


class ProtocolError(ValueError):
    """A request the server cannot honour; the message is sent to the client as ERROR."""


@functools.cache  # importlib.metadata parses the package's METADATA: ~2 ms, paid per client and per ?VERSION
def gravcal_version() -> str:
    try:
        from importlib.metadata import version

        return version("gravcal")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


# -- requests ------------------------------------------------------------------------


@dataclass
class Request:
    """One parsed command. ``args`` is the JSON object of ``?WATCH={...}`` (None if absent)."""

    command: str
    args: dict[str, Any] | None = None


@dataclass
class WatchPolicy:
    """A client's subscription: what it receives and how often.

    ``rate`` [Hz] bounds IMU messages to at most one per 1/rate seconds of sample time
    (0 = every sample).
    """

    enable: bool = False
    raw: bool = False
    rate: float = 0.0

    def updated(self, args: dict[str, Any] | None) -> "WatchPolicy":
        """A new policy with the fields present in ``args`` changed (gpsd semantics:
        absent fields keep their value). Raises ProtocolError naming a bad field."""
        new = WatchPolicy(self.enable, self.raw, self.rate)
        if args is None:
            return new
        unknown = [k for k in args if k not in WATCH_FIELDS]
        if unknown:
            raise ProtocolError(
                f"?WATCH: unknown field {unknown[0]!r}; known fields: {', '.join(WATCH_FIELDS)}"
            )
        for name in ("enable", "raw"):
            if name in args:
                if not isinstance(args[name], bool):
                    raise ProtocolError(f"?WATCH: field {name!r} must be true or false, got {json.dumps(args[name])}")
                setattr(new, name, args[name])
        if "json" in args and args["json"] is not True:
            # Accepted for gpsd habits; JSON is the only encoding there is.
            raise ProtocolError("?WATCH: field 'json' can only be true (gravcald speaks JSON only)")
        if "rate" in args:
            rate = args["rate"]
            if rate is None:
                rate = 0.0
            if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate < 0:
                raise ProtocolError(
                    f"?WATCH: field 'rate' must be a number of Hz >= 0 (0 = every sample), got {json.dumps(rate)}"
                )
            new.rate = float(rate)
        return new

    def to_message(self) -> dict[str, Any]:
        return {"class": "WATCH", "enable": self.enable, "raw": self.raw, "rate": self.rate}


def _excerpt(text: str, n: int = 80) -> str:
    return text if len(text) <= n else text[:n] + "..."


def parse_requests(line: bytes | str) -> list[Request | ProtocolError]:
    """Parse one request line into commands, in order.

    A bad command yields a ProtocolError in its place; parsing stops at the first bad
    command because its end cannot be trusted. Empty lines give an empty list.
    """
    if isinstance(line, bytes):
        try:
            text = line.decode("utf-8")
        except UnicodeDecodeError:
            return [ProtocolError("request is not valid UTF-8")]
    else:
        text = line
    text = text.strip()
    if _PLAIN.fullmatch(text.strip(" \t\r;")):  # the common case, commands without arguments: no walk through it
        names = [m.upper() for m in _PLAIN_NAME.findall(text)]
        if all(name in COMMANDS for name in names):
            return [Request(name) for name in names]
    return _parse_walk(text)


def _parse_walk(text: str) -> list[Request | ProtocolError]:
    """parse_requests' general case: command by command, JSON arguments, the first error."""
    out: list[Request | ProtocolError] = []
    pos, n = 0, len(text)
    while True:
        pos = _GAP.match(text, pos).end()
        if pos >= n:
            return out
        if text[pos] != "?":
            out.append(ProtocolError(f"requests start with '?', e.g. ?WATCH={{\"enable\":true}}; got {_excerpt(text[pos:])!r}"))
            return out
        end = _NAME.match(text, pos + 1).end()
        name = text[pos + 1 : end].upper()
        if name not in COMMANDS:
            shown = text[pos:end] or text[pos : pos + 10]
            out.append(ProtocolError(f"unknown command {shown!r}; known: {', '.join('?' + c for c in COMMANDS)}"))
            return out
        args = None
        pos = end
        if pos < n and text[pos] == "=":
            if name != "WATCH":
                out.append(ProtocolError(f"?{name} takes no arguments"))
                return out
            try:
                args, pos = raw_decode(text, pos + 1, max_depth=MAX_REQUEST_DEPTH)
            except JSONInputError as exc:
                out.append(ProtocolError(f"?{name}: argument is {exc}"))
                return out
            if not isinstance(args, dict):
                out.append(ProtocolError(f"?{name}: argument must be a JSON object, got {type(args).__name__}"))
                return out
        if pos < n and text[pos] not in " \t\r;":
            out.append(ProtocolError(f"?{name}: unexpected text after the command: {_excerpt(text[pos:])!r}"))
            return out
        out.append(Request(name, args))


# "?STATUS;?POLL", "?VERSION" (separators at the ends stripped: every one left is followed by a "?", so the match
# is linear in the line, whatever it holds)
_PLAIN = re.compile(r"(?:\?[A-Za-z]+(?:[ \t\r;]+\?[A-Za-z]+)*)?")
_PLAIN_NAME = re.compile(r"\?([A-Za-z]+)")
_GAP = re.compile(r"[ \t\r;]*")  # between commands
_NAME = re.compile(r"\w*")  # a command's name: str.isalnum() or "_", as \w is for str patterns


# -- messages ------------------------------------------------------------------------


_ENCODE = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode  # json.dumps with these builds one per call


def encode(message: dict[str, Any]) -> bytes:
    """One message as a JSON line (non-finite floats become null, numpy scalars and arrays plain JSON)."""
    try:  # most messages hold neither: encoded as they are, not walked first
        text = _ENCODE(message)
    except (ValueError, TypeError):  # a NaN or an infinity, a numpy value
        text = _ENCODE(_finite(message))
    return (text + "\n").encode()


def _finite(x: Any) -> Any:
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, np.generic):
        return _finite(x.item())
    if isinstance(x, np.ndarray):
        return _finite(x.tolist())
    return x


@functools.cache  # every client gets it on connecting: encoded once
def version_line() -> bytes:
    return encode(version_message())


def version_message() -> dict[str, Any]:
    return {
        "class": "VERSION",
        "release": gravcal_version(),
        "proto_major": PROTOCOL_MAJOR,
        "proto_minor": PROTOCOL_MINOR,
    }


NO_CALIB_LINE = encode({"class": "CALIB", "revision": 0, "accepted": False, "model": None,
                        "message": "no calibration yet"})
"""?CALIB's answer before the first calibration."""


DEVICE_FIELDS = ("bus", "device", "connected", "rate_hz", "samples", "reconnects")
"""The STATUS ``device`` fields a DEVICE entry repeats (beside ``path``, the driver spec)."""


def status_reply(command: str, status_line: bytes) -> bytes:
    """The reply to ?STATUS (the encoded STATUS itself) or ?DEVICES (gpsd's request, for clients that ask it:
    the one device gravcald reads, from that STATUS)."""
    if command == "STATUS":
        return status_line
    dev = json.loads(status_line).get("device") or {}
    entry = {"class": "DEVICE", "path": dev.get("spec"), **{k: dev[k] for k in DEVICE_FIELDS if k in dev}}
    return encode({"class": "DEVICES", "devices": [entry]})


def error_message(message: str, request: str | None = None) -> dict[str, Any]:
    msg: dict[str, Any] = {"class": "ERROR", "message": message}
    if request:
        msg["request"] = _excerpt(request)
    return msg


def dropped_message(count: int, total: int) -> dict[str, Any]:
    """Notice to a slow client: ``count`` of its oldest queued messages were discarded
    since the previous notice (``total`` since it connected)."""
    return {"class": "DROPPED", "count": int(count), "total": int(total)}


def calib_message(
    calibration: Any,
    *,
    revision: int,
    updated: float | None,
    accepted: bool,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """CALIB payload from a core Calibration (raw = sensitivity @ a[g] + offset).

    ``updated`` is Unix time [s] of the last estimator update (None: never).
    """
    msg: dict[str, Any] = {
        "class": "CALIB",
        "revision": int(revision),
        "model": str(calibration.model),
        "accepted": bool(accepted),
        "converged": bool(calibration.converged),
        "observable": bool(calibration.observable),
        "n_windows": int(calibration.n_windows),
        "updated": updated,
        "offset": np.asarray(calibration.offset, dtype=float).tolist(),
        "sensitivity": np.asarray(calibration.sensitivity, dtype=float).tolist(),
        "std": dict(calibration.std),
        "message": str(calibration.message),
    }
    if extra:
        msg.update(extra)
    return msg


STATIC_UNKNOWN = -1  # a static code: the detector has no decision recent enough for this sample (JSON null)


def static_codes(static: np.ndarray, n: int) -> np.ndarray:
    """The per-sample ``static`` as int8 codes: a bool array (true, false), or int codes 1 (still), 0 (moving) and
    STATIC_UNKNOWN (null: no decision recent enough, see daemon/processing.Processor.correct), clipped to -1..1."""
    st = np.asarray(static).reshape(n)
    if st.dtype == bool:
        return st.astype(np.int8)
    return np.clip(st.astype(np.int64), -1, 1).astype(np.int8)


def encode_imu_joined(
    samples: np.ndarray,
    acc_ms2: np.ndarray,
    gyro_rads: np.ndarray,
    static: np.ndarray,
    *,
    raw: bool = False,
) -> bytes:
    """The IMU lines of a block of samples (SAMPLE_DTYPE) as one byte string, by the line kernel
    (daemon/_linekernel.c, the C step's own writer: both paths send the same bytes). Its fields and their
    formats, as %-templates, and their numpy form (the kernel's oracle) are in tests/support/line_reference.py.

    acc_ms2 (N, 3) calibrated specific force [m/s²]; gyro_rads (N,) rate [rad/s] (NaN: not
    calibrated -> null); static (N,) bool or codes (:func:`static_codes`). ``raw`` adds the
    driver's raw fields. Missing values (NaN, e.g. a channel with T2 = 0) are null.
    """
    n = samples.shape[0]
    if n == 1:  # one sample: the static code as a Python scalar, without the block's array conversions
        return imu_line(samples, np.ascontiguousarray(acc_ms2, dtype=float), np.asarray(gyro_rads).item(),
                        np.asarray(static).item(), raw)
    return imu_lines(np.ascontiguousarray(samples), np.ascontiguousarray(acc_ms2, dtype=float).reshape(n, 3),
                     np.ascontiguousarray(gyro_rads, dtype=float).reshape(n), static_codes(static, n), raw)


def encode_imu(
    samples: np.ndarray,
    acc_ms2: np.ndarray,
    gyro_rads: np.ndarray,
    static: np.ndarray,
    *,
    raw: bool = False,
) -> list[bytes]:
    """The IMU lines of :func:`encode_imu_joined`, one per sample."""
    return encode_imu_joined(samples, acc_ms2, gyro_rads, static, raw=raw).splitlines(keepends=True)


REWIND_S = 2.0  # sample time stepping back further than this is a restart, which resets decimation


def decimation_mask(t: np.ndarray, rate: float, last_bucket: float) -> tuple[np.ndarray, float]:
    """Which samples a client with ``rate`` [Hz] receives, and its new last bucket.

    Sample time is cut into buckets of 1/rate s; the first sample of each bucket later than the
    last one sent goes out, so at most ``rate`` messages per second of sample time go out, and
    every bucket that holds a sample yields one (no beat pattern with the sampling rate). Time
    that jitters backwards cannot reopen a bucket already sent; a step back of more than
    max(REWIND_S, 1/rate) (a replay or device restarting) starts afresh instead of silencing the client.
    """
    if rate <= 0 or t.size == 0:
        return np.ones(t.shape[0], dtype=bool), last_bucket
    buckets = np.floor(np.asarray(t, dtype=float) * rate)
    rewind = max(REWIND_S * rate, 1.0)
    if np.all(np.diff(buckets) >= 0) and not buckets[0] < last_bucket - rewind:
        high = np.maximum.accumulate(np.concatenate(([last_bucket], buckets)))
        mask = buckets > high[:-1]
        return mask, float(high[-1])
    mask = np.zeros(buckets.shape[0], dtype=bool)
    for i, b in enumerate(buckets.tolist()):  # rare: time went backwards inside the block
        if b > last_bucket or b < last_bucket - rewind:
            mask[i] = True
            last_bucket = b
    return mask, float(last_bucket)


class ImuBlock:
    """A block handed from acquisition to the server (all arrays length N), with its encoded
    lines cached per encoding (index: raw) and shared by every client. A plain class with slots:
    one is made per sample on the latency path."""

    __slots__ = ("samples", "acc_ms2", "gyro_rads", "static", "_lines", "_joined")

    def __init__(self, samples: np.ndarray, acc_ms2: np.ndarray, gyro_rads: np.ndarray, static: np.ndarray):
        self.samples, self.acc_ms2, self.gyro_rads, self.static = samples, acc_ms2, gyro_rads, static
        self._lines: list[list[bytes] | None] = [None, None]
        self._joined: list[bytes | None] = [None, None]

    def lines(self, raw: bool) -> list[bytes]:
        """Encoded IMU lines, computed once per encoding and shared by every client."""
        got = self._lines[raw]
        if got is None:
            got = self._lines[raw] = self.joined(raw).splitlines(keepends=True)
        return got

    def joined(self, raw: bool) -> bytes:
        """All lines as one byte string (what a full-rate client is sent), encoded once."""
        got = self._joined[raw]
        if got is None:
            got = self._joined[raw] = encode_imu_joined(self.samples, self.acc_ms2, self.gyro_rads, self.static,
                                                        raw=raw)
        return got

    def lines_at(self, raw: bool, idx: np.ndarray) -> list[bytes]:
        """The lines of the samples at ``idx`` (decimated clients). When every watcher is
        decimated only these samples are encoded, not the whole block."""
        got = self._lines[raw]
        if got is not None:
            return [got[i] for i in idx.tolist()]
        return encode_imu(self.samples[idx], self.acc_ms2[idx], self.gyro_rads[idx], self.static[idx], raw=raw)

    def last_message(self, raw: bool = False) -> dict[str, Any] | None:
        if self.samples.shape[0] == 0:
            return None
        return json.loads(self.lines(raw)[-1])
