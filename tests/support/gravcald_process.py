"""``python -m gravcal.daemon.gravcald --emulate ...`` as a child process, its log in a file."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gravcal.clients.client import Client, ClientError

# the environment of the test run must not make the child think systemd started it
SYSTEMD_VARIABLES = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "LISTEN_FDS", "LISTEN_PID")


class GravcaldProcess:
    """One emulated-bus gravcald. ``directory`` holds the socket, state and log (a temporary one when
    None, removed at stop()); ``env`` adds variables (and keeps those of SYSTEMD_VARIABLES it names);
    ``fs`` None leaves the configured sample rate."""

    def __init__(self, directory: Path | None, *args: str, seed: int = 0, fs: float | None = 100.0,
                 env: dict | None = None, config: str | None = None, state: Path | None = None,
                 sock: Path | None = None):
        self._tmp = tempfile.TemporaryDirectory(prefix="gravcald-test-") if directory is None else None
        self.dir = Path(self._tmp.name) if self._tmp is not None else Path(directory)
        self.sock = str(sock or self.dir / "g.sock")
        self.state = state or self.dir / "state"
        self.config = self.dir / "gravcald.toml"
        cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--seed", str(seed),
               "--socket", self.sock, "--state-dir", str(self.state), "--log-level", "info", *args]
        if fs is not None:
            cmd += ["--fs", str(fs)]
        if config is not None:
            self.config.write_text(config)
            cmd += ["--config", str(self.config)]
        self.log_path = self.dir / f"gravcald-{time.monotonic_ns()}.log"
        environ = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        for k in SYSTEMD_VARIABLES:
            if not env or k not in env:
                environ.pop(k, None)
        with open(self.log_path, "w") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=environ)

    def log(self) -> str:
        return self.log_path.read_text()

    def wait_serving(self, timeout: float = 90.0) -> None:
        """Until the socket answers and the emulated device is connected; raises with the log tail."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"gravcald exited ({self.proc.returncode}):\n{self.log()[-3000:]}")
            if os.path.exists(self.sock):
                try:
                    with Client(self.sock, timeout=5) as c:
                        if c.status()["device"].get("connected"):
                            return
                except (ClientError, OSError):
                    pass
            time.sleep(0.05)
        raise RuntimeError(f"gravcald not serving within {timeout} s:\n{self.log()[-3000:]}")

    def client(self, timeout: float = 30.0) -> Client:
        return Client(self.sock, timeout=timeout)

    def status(self) -> dict:
        with self.client() as c:
            return c.status()

    def stop(self, timeout: float = 60.0) -> int:
        """SIGTERM and the exit status; a daemon that does not stop within ``timeout`` is killed and
        this raises with the log tail."""
        try:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
            try:
                return self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                raise RuntimeError(f"gravcald did not stop within {timeout} s after SIGTERM:\n{self.log()[-3000:]}")
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()


def overrun_events(status: dict) -> list[str]:
    """The emulator's reports of samples its link dropped because the host did not read in time."""
    return [e for e in status.get("emulator", {}).get("events", []) if e.startswith("overrun")]


def rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def cpu_s(pid: int) -> float:
    """CPU time [s] (user + system) the process has used so far."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def poll(condition, timeout: float, what: str, interval: float = 0.1):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = condition()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")
