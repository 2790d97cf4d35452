"""Two writers per client socket (the publishing thread and the server thread): lines never mix,
order holds, and what a slow client loses is counted and announced."""
import json
import socket
import threading
import time

import numpy as np
import pytest

from gravcal.daemon.server import ServerConfig, SocketServer

from test_server import block, wait_until


def _read_all(sock: socket.socket, stop: threading.Event, out: list, pace_s: float) -> None:
    """Every complete line until EOF or stop (slowly when ``pace_s``: the socket fills up)."""
    buf = b""
    sock.settimeout(0.5)
    while not stop.is_set():
        try:
            data = sock.recv(4096 if pace_s else 1 << 16)
        except socket.timeout:
            continue
        if not data:
            break
        *lines, buf = (buf + data).split(b"\n")
        out.extend(lines)
        if pace_s:
            time.sleep(pace_s)


@pytest.mark.parametrize("pace_s", [0.0, 0.002])
def test_lines_stay_whole_and_in_order_with_requests_calib_changes_and_a_full_socket(tmp_path, pace_s):
    srv = SocketServer(str(tmp_path / "g.sock"),
                       config=ServerConfig(queue_messages=300, request_rate_hz=1000, request_burst=1000)).start()
    total, revisions = 6000, 30
    try:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(srv.address)
        sock.sendall(b'?WATCH={"enable":true,"raw":true};\n')
        assert wait_until(lambda: srv.stats()["per_client"] and srv.stats()["per_client"][0]["watching"])
        lines: list = []
        stop = threading.Event()
        reader = threading.Thread(target=_read_all, args=(sock, stop, lines, pace_s))
        reader.start()

        def calib() -> None:  # the processing thread's CALIB changes, concurrent with the samples
            for r in range(1, revisions + 1):
                srv.set_calibration({"revision": r, "accepted": True})
                time.sleep(0.002)

        side = threading.Thread(target=calib)
        side.start()
        for start in range(0, total, 2):
            srv.publish(*block(2, start))
            if start % 200 == 0:
                sock.sendall(b"?POLL;?VERSION;\n")  # replies written by the server thread
        side.join()
        assert wait_until(lambda: not srv.stats()["per_client"][0]["queued"], timeout=30)
        time.sleep(0.3)
        stop.set()
        reader.join(10)
        msgs = [json.loads(line) for line in lines]  # a line mixed with another does not parse
        seqs = [m["seq"] for m in msgs if m["class"] == "IMU"]
        dropped = sum(m["count"] for m in msgs if m["class"] == "DROPPED")
        revs = [m["revision"] for m in msgs if m["class"] == "CALIB"]
        others = sum(m["class"] in ("CALIB", "POLL", "VERSION") for m in msgs)
        assert np.all(np.diff(seqs) > 0), "IMU lines out of order"
        assert revs == sorted(revs), "CALIB changes out of order"
        # every message was received or counted as dropped, none twice (1: the greeting VERSION)
        expected = total + revisions + 2 * (total // 200) + 1
        assert len(seqs) + others + dropped == expected, (len(seqs), others, dropped)
        if not dropped:
            assert revs == list(range(1, revisions + 1))
        per = srv.stats()["per_client"][0]
        assert per["dropped"] == dropped
        if pace_s:  # the slow reader did overflow its bounded queue
            assert dropped > 0
        sock.close()
    finally:
        srv.stop()
