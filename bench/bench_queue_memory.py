"""Memory held for slow clients, and handed back when they leave (not a test).

    python bench/bench_queue_memory.py [--clients 20] [--queue-mb 8] [--no-trim]

A SocketServer in this process; ``--clients`` raw watchers at distinct rates (so no two share
encoded lines) never read, while 200 Hz blocks are published as fast as the server takes them
until every queue is at its byte bound. Prints this process's RSS before, at the bound, and
after the clients closed; ``--no-trim`` skips handing freed memory back (glibc malloc_trim) to
show what it is for.
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import time

import numpy as np

from gravcal.core.samples import empty
from gravcal.daemon import client_limits, server as server_mod
from gravcal.daemon.server import ServerConfig, SocketServer


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def block(n: int, seq0: int, fs: float = 200.0):
    s = empty(n)
    s["seq"] = seq0 + np.arange(n)
    s["t"] = s["seq"] / fs
    return s, np.tile([0.0, 0.0, 9.80665], (n, 1)), np.zeros(n), np.ones(n, dtype=bool)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clients", type=int, default=20)
    p.add_argument("--queue-mb", type=float, default=8.0)
    p.add_argument("--no-trim", action="store_true")
    args = p.parse_args()
    if args.no_trim:
        server_mod.return_memory_to_os = lambda: None
    qbytes = int(args.queue_mb * (1 << 20))
    path = os.path.join(tempfile.mkdtemp(prefix="bench-qmem-"), "g.sock")
    srv = SocketServer(path, config=ServerConfig(queue_bytes=qbytes, queue_messages=10**7, stall_timeout_s=600,
                                                 max_clients=args.clients + 1)).start()
    rss0 = rss_mb()
    socks = []
    for k in range(args.clients):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect(path)
        s.sendall(b'?WATCH={"enable":true,"raw":true,"rate":%d};\n' % (190 - k))
        socks.append(s)
    time.sleep(0.5)
    seq, t0 = 0, time.monotonic()
    while min((c["queued_bytes"] for c in srv.stats()["per_client"]), default=0) < 0.95 * qbytes:
        for _ in range(10):  # 20 s of 200 Hz data per round
            srv.publish(*block(400, seq))
            seq += 400
        while srv.backlog:
            time.sleep(0.01)
        if time.monotonic() - t0 > 300:
            break
    rss_full = rss_mb()
    queued = sum(c["queued_bytes"] for c in srv.stats()["per_client"]) / (1 << 20)
    for s in socks:
        s.close()
    deadline = time.monotonic() + 120
    while srv.n_clients and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    rss_after = rss_mb()
    if srv.n_clients:
        print(f"  {srv.n_clients} clients still connected", file=sys.stderr)
    srv.stop()
    print(f"{args.clients} never-reading raw watchers, queue bound {args.queue_mb:g} MiB each, "
          f"trim {'off' if args.no_trim else 'on'} ({'glibc' if client_limits._TRIM else 'unavailable'})")
    print(f"  RSS before {rss0:.0f} MB, queues full {rss_full:.0f} MB ({queued:.0f} MiB queued), "
          f"after they left {rss_after:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
