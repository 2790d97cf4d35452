"""Bad input the daemon must name precisely: unreadable state, a client that never reads,
`gravcald` option mistakes. (Malformed/oversized requests, socket paths in use or stale,
corrupt state and wrong config types: test_server.py, test_server_daemon.py, test_config.py,
test_persistence.py and test_e2e.py.)"""
import logging
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from gravcal.core.samples import empty
from gravcal.daemon.config import Config
from gravcal.daemon.gravcald import main
from gravcal.daemon.service import Gravcald
from gravcal.daemon.persistence import StateStore
from gravcal.daemon.server import ServerConfig, SocketServer
from support.silent_driver import SilentDriver


def test_unreadable_state_is_moved_aside_with_the_reason(tmp_path):
    # A directory where the state file should be: unreadable for root too (EISDIR).
    (tmp_path / "state.json").mkdir()
    res = StateStore(tmp_path).load()
    assert res.state is None and res.moved_to is not None
    assert res.notes == [f"state file {tmp_path / 'state.json'} is unusable (Is a directory); "
                         f"moved it to {res.moved_to}; starting from defaults"]
    assert os.path.isdir(res.moved_to) and not os.path.exists(tmp_path / "state.json")


def _notes_of_a_start(tmp_path):
    """The STATUS notes of a gravcald started (and stopped) on the state directory tmp_path/state."""
    cfg = Config()
    cfg.socket.path = str(tmp_path / "g.sock")
    cfg.state.directory = str(tmp_path / "state")
    d = Gravcald(cfg, driver=SilentDriver(), environ={})
    d.start()
    try:
        return d.status()["notes"]
    finally:
        d.request_stop()
        d.shutdown()


def test_daemon_reports_an_unreadable_state_in_status_notes(tmp_path):
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "state.json").mkdir()
    notes = _notes_of_a_start(tmp_path)
    assert any("is unusable (Is a directory); moved it to" in n for n in notes), notes
    assert "starting from ADXL210 datasheet values (no saved state, no lab calibration)" in notes


def test_daemon_moves_a_deeply_nested_state_aside_and_starts(tmp_path):
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "state.json").write_bytes(b"[" * 100_000)
    notes = _notes_of_a_start(tmp_path)
    assert any("is unusable (JSON nested deeper than 64 levels); moved it to" in n for n in notes), notes
    assert [p.name[:19] for p in (tmp_path / "state").iterdir()] == ["state.json.corrupt-"]


def test_a_client_that_never_reads_is_disconnected_and_logged(tmp_path, caplog):
    srv = SocketServer(str(tmp_path / "g.sock"), config=ServerConfig(queue_messages=100, stall_timeout_s=0.5)).start()
    try:
        mute = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        mute.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        mute.connect(str(tmp_path / "g.sock"))
        mute.sendall(b'?WATCH={"enable":true};\n')
        caplog.set_level(logging.INFO, logger="gravcal.server")
        deadline, seq = time.monotonic() + 30, 0
        while srv.stats()["clients_stalled"] == 0 and time.monotonic() < deadline:
            b = empty(100)
            b["seq"] = np.arange(seq, seq + 100)
            b["t"] = b["seq"] / 200.0
            b["t2"] = 20000
            b["t1"] = 10000
            srv.publish(b, np.zeros((100, 3)), np.full(100, np.nan), np.zeros(100, bool))
            seq += 100
            time.sleep(0.01)
        # the server thread counts the stall, then closes and logs it: wait for all three
        def logged() -> list[str]:
            return [r.getMessage() for r in caplog.records if "disconnected" in r.getMessage()]

        while not (srv.n_clients == 0 and logged()) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert srv.stats()["clients_stalled"] == 1 and srv.n_clients == 0
        msgs = logged()
        assert any("stalled: no reads for" in m and "with output pending" in m for m in msgs), msgs
        mute.close()
    finally:
        srv.stop()


@pytest.mark.parametrize("argv,message", [
    (["--speed", "3"], "gravcald: error: --speed needs --emulate"),
    (["--bus", "can", "--seed", "2"], "gravcald: error: --bus, --seed need --emulate"),
    (["--emulate", "--device", "serial:///dev/ttyUSB0"],
     "gravcald: error: --device and --emulate exclude each other (the emulator is the device)"),
    (["--emulate", "--duration", "0"], "gravcald: error: --duration must be a positive number of seconds, got 0.0"),
])
def test_gravcald_option_mistakes_are_one_line_and_status_2(argv, message, capsys):
    assert main(argv, environ={}) == 2
    assert capsys.readouterr().err.strip() == message


@pytest.mark.parametrize("argv,message", [
    (["--emulate", "--speed", "0"], "argument --speed: speed must be > 0, got '0'"),
    (["--emulate", "--disconnect-at", "5"], "argument --disconnect-at: expected T:DUR in seconds (e.g. 30:5), got '5'"),
])
def test_gravcald_bad_option_values_are_named(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv, environ={})
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_emulate_with_an_unknown_scenario_is_a_clear_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--scenario", "nope",
                           "--socket", str(tmp_path / "g.sock"), "--state-dir", str(tmp_path / "s")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("gravcald: error: --emulate: emulator did not start:")
    assert "unknown scenario 'nope'; choose one of" in last
    assert not os.path.exists(tmp_path / "g.sock")  # the socket it bound is gone again
