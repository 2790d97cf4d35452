"""What one client sends can cost that client its connection, never the server: nesting bounds on ?WATCH's
JSON, any exception inside one request's handling, and the request budget charged per command."""
import logging
import socket
import time

import pytest

from gravcal.daemon import protocol
from gravcal.daemon.server import ServerConfig, SocketServer

from test_server import Raw, wait_until


@pytest.fixture
def sockpath(tmp_path):
    return str(tmp_path / "gravcal.sock")


@pytest.fixture
def server(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(), status_provider=lambda: {"device": {"ok": 1}}).start()
    yield srv
    srv.stop()


@pytest.mark.parametrize("arg", ["[" * 1000, "{\"a\":" * 200, "[" * 65 + "]" * 65],
                         ids=["1000 [", "200 objects", "65 balanced"])
def test_deeply_nested_watch_argument_is_an_error_line_and_the_server_lives(server, sockpath, arg):
    c = Raw(sockpath)
    assert c.line()["class"] == "VERSION"
    line = b"?WATCH=" + arg.encode() + b"\n"
    assert len(line) <= protocol.MAX_REQUEST_BYTES
    c.send(line)
    err = c.line()
    assert err["class"] == "ERROR" and "nested deeper than 64 levels" in err["message"], err
    c.send(b"?VERSION;\n")
    assert c.line()["class"] == "VERSION"
    assert server.alive


def test_nesting_within_the_bound_is_parsed():
    # 64 levels inside the object's own: the bound counts every bracket, the object's included
    arg = '{"enable":true,"x":' + "[" * 63 + "]" * 63 + "}"
    (req,) = protocol.parse_requests("?WATCH=" + arg)
    assert isinstance(req, protocol.Request) and req.args["enable"] is True


def test_an_exception_inside_one_request_costs_that_client_only(server, sockpath, monkeypatch, caplog):
    caplog.set_level(logging.INFO, "gravcal.server")
    real = server._execute

    def broken(c, req, out):
        if req.command == "POLL":
            raise RuntimeError("a bug reached by ?POLL")
        return real(c, req, out)

    monkeypatch.setattr(server, "_execute", broken)
    bad, good = Raw(sockpath), Raw(sockpath)
    assert bad.line()["class"] == good.line()["class"] == "VERSION"
    bad.send(b"?POLL;\n")
    reply = bad.line()
    assert reply["class"] == "ERROR" and "internal error" in reply["message"], reply
    bad.send(b"?VERSION;\n")  # the client keeps its connection: the fault is the server's
    assert bad.line()["class"] == "VERSION"
    good.send(b"?VERSION;\n")
    assert good.line()["class"] == "VERSION" and server.alive
    logged = [r for r in caplog.records if "a bug reached by ?POLL" in r.getMessage()]
    assert len(logged) == 1 and logged[0].getMessage().count("\n") == 0, [r.getMessage() for r in logged]


def test_a_line_of_many_commands_is_answered_in_one_send(server, sockpath, monkeypatch):
    # each reply sent on its own was a system call per command: a line of 90 cost 90 sends
    flushes = []
    real = server._flush
    monkeypatch.setattr(server, "_flush", lambda c: (flushes.append(c.id), real(c)))
    client = Raw(sockpath)
    assert client.line()["class"] == "VERSION"
    flushes.clear()
    client.send(b"?STATUS;?POLL;?CALIB;" * 30 + b"\n")  # 90 commands: within the default burst of 100
    classes = [client.line()["class"] for _ in range(90)]
    assert classes == ["STATUS", "POLL", "CALIB"] * 30
    assert len(flushes) == 1, flushes


def test_an_exception_while_reading_one_client_closes_that_client_only(server, sockpath, monkeypatch, caplog):
    caplog.set_level(logging.INFO, "gravcal.server")

    def broken(line):
        raise MemoryError("parsing ran out")

    monkeypatch.setattr(protocol, "parse_requests", broken)
    bad = Raw(sockpath)
    assert bad.line()["class"] == "VERSION"
    bad.send(b"?POLL;\n")
    with pytest.raises((EOFError, ConnectionResetError)):
        while True:
            bad.line()
    monkeypatch.undo()
    good = Raw(sockpath)
    assert good.line()["class"] == "VERSION" and server.alive
    assert sum("parsing ran out" in r.getMessage() for r in caplog.records) == 1


def _flood(sockpath, line, lines_per_s, seconds):
    """Send ``line`` at ``lines_per_s`` for up to ``seconds``; (answers other than ERROR, seconds until the server
    hung up or None)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(sockpath)
    s.setblocking(False)
    buf, t0, next_send, closed_at = b"", time.monotonic(), time.monotonic(), None
    while time.monotonic() - t0 < seconds:
        now = time.monotonic()
        try:
            if now >= next_send:
                next_send += 1.0 / lines_per_s
                s.send(line)
            d = s.recv(1 << 20)
            if not d:
                closed_at = now - t0
                break
            buf += d
        except BlockingIOError:
            time.sleep(0.005)
        except OSError:
            closed_at = now - t0
            break
    s.close()
    answers = [m for m in buf.split(b"\n")[1:] if m and not m.startswith(b'{"class":"ERROR"')]
    return len(answers), closed_at


@pytest.mark.xdist_group("realtime")  # a per-second budget: one real-time test at a time under xdist
def test_the_budget_is_charged_per_command_so_a_multi_command_flooder_is_cut_off(sockpath):
    """Ten lines a second is half the line rate the budget allows, but each carries 144 commands: the budget
    counts commands, so the client gets at most burst + rate x time answers and is disconnected once it has
    flooded for flood_timeout_s."""
    rate, burst, timeout = 20.0, 10, 1.0
    srv = SocketServer(sockpath, config=ServerConfig(request_rate_hz=rate, request_burst=burst,
                                                     flood_timeout_s=timeout),
                       status_provider=lambda: {"device": {"ok": 1}}).start()
    try:
        line = b"?STATUS;?POLL;" * 72 + b"\n"
        assert len(line) <= protocol.MAX_REQUEST_BYTES
        answers, closed_at = _flood(sockpath, line, lines_per_s=10, seconds=6.0)
        assert closed_at is not None, f"never cut off ({answers} answers in 6 s)"
        # paused reads resume after at least 0.25 s: the cut comes within one pause of the flood timeout
        assert closed_at < timeout + 1.0, closed_at
        assert answers <= burst + rate * closed_at + 1, (answers, closed_at)
        assert srv.clients_flooding == 1 and srv.requests_refused >= 144
        ok = Raw(sockpath)  # one command per line within the budget is served as before
        assert ok.line()["class"] == "VERSION"
        for _ in range(burst):
            ok.send(b"?VERSION;\n")
            assert ok.line()["class"] == "VERSION"
    finally:
        srv.stop()


def test_a_client_within_its_budget_after_a_flood_is_not_cut_off_for_it_later(sockpath):
    rate, burst, timeout = 20.0, 5, 1.0
    srv = SocketServer(sockpath, config=ServerConfig(request_rate_hz=rate, request_burst=burst,
                                                     flood_timeout_s=timeout)).start()
    try:
        c = Raw(sockpath)
        assert c.line()["class"] == "VERSION"
        c.send(b"?VERSION;" * (burst + 3) + b"\n")  # over the burst once: refused, reads paused
        replies = [c.line()["class"] for _ in range(burst + 1)]
        assert replies == ["VERSION"] * burst + ["ERROR"], replies
        for _ in range(int(2 * timeout / 0.1)):  # then well within the budget for twice the flood timeout
            time.sleep(0.1)
            c.send(b"?VERSION;\n")
            assert c.line()["class"] == "VERSION"
        c.send(b"?VERSION;" * (burst + 20) + b"\n")  # one more burst is refused, not a disconnection
        replies = [c.line()["class"]]
        while replies[-1] != "ERROR":
            replies.append(c.line()["class"])
        assert len(replies) <= burst + 1
        c.send(b"?VERSION;\n")
        time.sleep(0.3)
        assert c.line()["class"] == "VERSION" and srv.clients_flooding == 0
    finally:
        srv.stop()
