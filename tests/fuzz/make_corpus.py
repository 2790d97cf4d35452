"""Writes the seed corpus (tests/fuzz/corpus/TARGET/NAME): valid and near-valid inputs of every boundary, small.
Crashes found by a fuzzer are added beside them by hand (named after what they found) and kept."""
from __future__ import annotations

import gzip
import io
import json
import sys
import zipfile
from pathlib import Path

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.daemon.config import example_toml
from gravcal.daemon.persistence import CalibrationState
from gravcal.drivers.can import pack_frames
from gravcal.drivers.codec import encode_frames
from gravcal.drivers.rigs.sources import pattern_blocks

ROOT = Path(__file__).with_name("corpus")


def put(target: str, name: str, data: bytes) -> None:
    (ROOT / target).mkdir(parents=True, exist_ok=True)
    (ROOT / target / name).write_bytes(data)


def main() -> int:
    s = np.concatenate(list(pattern_blocks(seed=1, fs=200, duration=0.05)))  # 10 samples
    frames = encode_frames(s)
    # frame_decoder: byte 0 where the stream is cut, byte 1 the mode (bit 0 seal, bit 1 consecutive seq)
    put("frame_decoder", "ten_frames", b"\xa5\x00" + frames)
    put("frame_decoder", "garbage_between", b"\xa5\x00" + frames[:29] + b"\x7e\x00junk" + frames[29:87] + frames[60:])
    put("frame_decoder", "truncated", b"\xa5\x00" + frames[:-5])
    noise = np.random.default_rng(29).integers(0, 256, 29 * 6 + 11, dtype=np.uint8).tobytes()
    put("frame_decoder", "sealed_noise", b"\x3a\x01" + noise)
    put("frame_decoder", "sealed_consecutive", b"\x3a\x03" + noise)
    lines = b"".join(b"t%03X%d%s\r" % (0x100 + k, len(d), d.hex().upper().encode())
                     for parts in pack_frames(s[:3]) for k, d in enumerate(parts))
    seq0 = int(s["seq"][0]).to_bytes(2, "little")
    put("slcan_lines", "three_samples", seq0 + lines)
    put("slcan_lines", "garbled", seq0 + lines[:30] + b"t12\rx1\rB3B\rt10G8\r\a" + lines[30:])
    put("slcan_lines", "lower_case", seq0 + lines.lower().replace(b"T", b"t"))
    put("socket_request", "every_command", b"?VERSION;?STATUS;?DEVICES;?POLL;?CALIB;\n")
    put("socket_request", "watch", b'?WATCH={"enable":true,"raw":true,"rate":10};\n?WATCH={"enable":false}\n')
    put("socket_request", "nested", b"?WATCH=" + b"[" * 1000 + b"\n")
    put("socket_request", "multi", b"?STATUS;?POLL;" * 72 + b"\n")
    put("socket_request", "oversized", b"?" + b"A" * 2000 + b"\n")
    put("socket_request", "hang_up_after_partial_line", b'?WATCH={"enable":true,"raw":true};?VERSION;\n?POLL;?CALIB\x04')
    # imu_line: a SAMPLE_DTYPE row, acc 3 float64, gyro float64, the static code (int8), raw (bit 0)
    acc = np.array([0.1, -9.81, 0.25])
    put("imu_line", "raw", s[:1].tobytes() + acc.tobytes() + np.float64(0.01).tobytes() + b"\x01\x01")
    put("imu_line", "uncalibrated_gyro", s[1:2].tobytes() + acc.tobytes() + np.float64(np.nan).tobytes() + b"\xff\x00")
    edge = s[2:3].copy()
    edge["t"], edge["temp"], edge["t2"] = 1.7976931348623157e308, -np.inf, 0
    put("imu_line", "edges", edge.tobytes() + np.array([-0.0, 5e-324, 2.5e-6]).tobytes() + np.float64(1e300).tobytes()
        + b"\x05\x01")
    put("config_file", "example", example_toml().encode())
    put("config_file", "nested", b"[socket]\npath = " + b"[" * 100 + b"]" * 100 + b"\n")
    cal = Calibration.nominal(np.full(3, 0.5), 0.125, model="6")
    put("state_file", "valid", json.dumps(CalibrationState(cal, 3, 1.0, True, {"k": [1, 2]}).to_dict()).encode())
    put("state_file", "nested", b"[" * 200)
    put("calibration_json", "nominal", cal.to_json().encode())
    put("calibration_json", "report", json.dumps({"model": "6", "offset": [0.5] * 3, "sensitivity": np.eye(3).tolist(),
                                                  "std": {"o1": 0.01}}).encode())
    csv = b"t,ax,ay,az\n" + b"".join(b"%.3f,0.5,0.5,%.3f\n" % (i / 100, 0.625 + 0.001 * (i % 7)) for i in range(40))
    put("recording", "csv", b"\x00" + csv)
    put("recording", "csv_gz", b"\x01" + gzip.compress(csv))
    buf = io.BytesIO()
    np.save(buf, np.column_stack([np.arange(40) / 100, np.full((40, 3), 0.5)]))
    put("recording", "npy", b"\x02" + buf.getvalue())
    z = io.BytesIO()
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as f:
        f.writestr("info.txt", "Sample Rate: 30\nStart Date: 637517662200000000\nStop Date: 637517665200000000\n")
        f.writestr("log.bin", b"\x1e" + bytes(40))
    put("recording", "gt3x", b"\x03" + z.getvalue())
    put("recording", "cwa_head", b"\x05MD\xfc\x03" + bytes(60))
    put("recording", "geneactiv_head", b"\x06Device Identity\r\nDevice Unique Serial Code:1\r\nGENEActiv\r\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
