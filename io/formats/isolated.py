"""Third-party native readers run in a child process: one that ends its process on a damaged file (a Fortran
runtime error, an abort, a segfault) costs that file one InputError line, never `gravcal calibrate` or a study's
worker.

One child per process, started on first use and kept (the readers' imports, seconds for scikit-digital-health,
are paid once, not per file), started again after one died. It takes requests on its stdin, one JSON line each:
READER ("module:function", taking (path, Sniffed) and returning (columns, meta) as the in-process readers do),
the file, a directory; it writes each column there as NAME.npy and the rest as meta.json, or the reader's
InputError as error.txt (any other exception, a bug, as raised.txt: raised here as RuntimeError), then answers
one line on its own pipe (its stdout is the readers'). The parent loads the columns: no pickled copies. A
subprocess, not multiprocessing: a study's dask workers are daemonic processes, which multiprocessing forbids to
have children.
"""
from __future__ import annotations

import atexit
import importlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from .sniff import Sniffed, sniff

STDERR_TAIL = 2048  # bytes of the child's stderr kept to say how it ended
SHM = "/dev/shm"
COLUMN_BYTES_PER_FILE_BYTE = 16  # float64 columns per byte of a .cwa (packed samples) or a .bin (hex text), bounded
SHM_MARGIN = 64 << 20  # bytes /dev/shm keeps free beyond a file's columns


class _Child:
    """The reader child of this process (one request at a time)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.proc: subprocess.Popen | None = None
        self.replies: Any = None
        self.stderr: Any = None

    def _start(self) -> None:
        self.stderr = tempfile.TemporaryFile()
        r, w = os.pipe()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))  # this process's gravcal
        try:
            # its own session: a Ctrl-C at the terminal interrupts the parent, which decides, not the child mid-read
            # (taken for the file's fault); the child ends when its stdin closes
            self.proc = subprocess.Popen([sys.executable, "-m", __name__, str(w)], stdin=subprocess.PIPE,
                                         stdout=subprocess.DEVNULL, stderr=self.stderr, env=env, pass_fds=(w,),
                                         start_new_session=True)
        finally:
            os.close(w)
        self.replies = os.fdopen(r, "rb")

    def run(self, reader: str, path: Path, out: Path) -> tuple[int, bytes] | None:
        """None once the child has answered; (its exit status, the tail of its stderr) if it died on the way."""
        with self.lock:
            if self.proc is None or self.proc.poll() is not None:
                self._start()
            assert self.proc is not None and self.proc.stdin is not None
            self.stderr.seek(0)
            self.stderr.truncate()
            try:
                self.proc.stdin.write(json.dumps({"reader": reader, "path": str(path), "out": str(out),
                                                       "cwd": os.getcwd()}).encode()
                                      + b"\n")
                self.proc.stdin.flush()
                answered = self.replies.readline() == b"done\n"
            except (BrokenPipeError, ConnectionResetError):
                answered = False
            except BaseException:  # interrupted (Ctrl-C): its answer would be taken for the next request's
                self.close(kill=True)
                raise
            if answered:
                return None
            status = self.proc.wait()
            size = self.stderr.seek(0, os.SEEK_END)
            self.stderr.seek(max(0, size - STDERR_TAIL))
            tail = self.stderr.read()
            self.close()
            return status, tail

    def close(self, kill: bool = False) -> None:
        if self.proc is not None:
            if kill:
                self.proc.kill()
            for f in (self.proc.stdin, self.replies, self.stderr):
                try:
                    f.close()
                except OSError:
                    pass
            try:
                self.proc.wait(timeout=5)  # its stdin closed: it ends
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None


_CHILD = _Child()
atexit.register(_CHILD.close)


def read_in_child(reader: str, path: Path, found: Sniffed, name: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``reader(path, found)`` run in this process's reader child; InputError naming the file and ``name`` (the
    reader, for the user) if the child ended without a result."""
    with tempfile.TemporaryDirectory(prefix="gravcal-reader-", dir=_transfer_dir(path)) as tmp:
        out = Path(tmp)
        died = _CHILD.run(reader, path, out)
        if died is not None:
            raise InputError(f"{path}: {found.what} that {name} could not read: its reader ended the process "
                             f"({_how(died[0])}{_last_line(died[1])}); not read")
        if (out / "error.txt").exists():
            raise InputError((out / "error.txt").read_text("utf-8", "replace").strip())
        if (out / "raised.txt").exists():  # as the reader in this process would have raised it
            raise RuntimeError(f"{reader} raised {(out / 'raised.txt').read_text('utf-8', 'replace')}")
        done = json.loads((out / "meta.json").read_text("utf-8"))
        cols = {c: np.load(out / f"{c}.npy", allow_pickle=False) for c in done["columns"]}
        return cols, done["meta"]


def _transfer_dir(path: Path) -> str | None:
    """/dev/shm (the columns through memory) when it has room for them, else the temporary directory's disk: a
    full tmpfs would otherwise end the child (and be taken for the file's fault)."""
    try:
        st = os.statvfs(SHM)
        need = COLUMN_BYTES_PER_FILE_BYTE * os.path.getsize(path) + SHM_MARGIN
        return SHM if st.f_bavail * st.f_frsize >= need and os.access(SHM, os.W_OK) else None
    except OSError:
        return None


def _how(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"signal {signal.Signals(-returncode).name}"
        except ValueError:
            return f"signal {-returncode}"
    return f"exit status {returncode}"


def _last_line(tail: bytes) -> str:
    """The reader's last word on stderr (e.g. "Fortran runtime error: End of file"), printable and short."""
    lines = [ln.strip() for ln in tail.decode("utf-8", "replace").splitlines() if ln.strip()]
    if not lines:
        return ""
    text = "".join(c if c.isprintable() and c.isascii() else "?" for c in lines[-1])
    return f': "{text[:120]}"'


def _read_one(reader: str, path: str, out: str) -> None:
    module, _, function = reader.partition(":")
    read = getattr(importlib.import_module(module), function)
    p, dest = Path(path), Path(out)
    try:
        cols, meta = read(p, sniff(p))
    except InputError as exc:
        (dest / "error.txt").write_text(" ".join(str(exc).split()), "utf-8")
        return
    except Exception as exc:  # noqa: BLE001 - a bug (the readers turn the file's faults into InputError): raised
        (dest / "raised.txt").write_text(" ".join(f"{type(exc).__name__}: {exc}".split())[:500], "utf-8")
        return
    for c, values in cols.items():
        np.save(dest / f"{c}.npy", np.ascontiguousarray(values), allow_pickle=False)
    (dest / "meta.json").write_text(json.dumps({"columns": list(cols), "meta": meta}), "utf-8")


def _serve(reply_fd: int) -> int:
    """The child: one request per stdin line until stdin closes."""
    with os.fdopen(reply_fd, "wb", buffering=0) as replies:
        for line in sys.stdin.buffer:
            req = json.loads(line)
            os.chdir(req["cwd"])  # a relative path means what it means to the parent now
            _read_one(req["reader"], req["path"], req["out"])
            replies.write(b"done\n")
    return 0


if __name__ == "__main__":
    sys.exit(_serve(int(sys.argv[1])))
