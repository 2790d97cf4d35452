"""The fake logger at the kernel interface: ``/dev/i2c-N`` and its ioctls, answered from this process.

gravcald's I2C driver opens ``/dev/i2c-N`` and talks to it with ioctls through smbus2 (I2C_FUNCS, I2C_SLAVE,
I2C_SMBUS, I2C_RDWR). There is no kernel I2C here (no i2c-dev, no i2c-stub, no CUSE), so the host process runs
under umockdev's preload library (Debian package ``umockdev``: ``LD_PRELOAD=libumockdev-preload.so.0`` and
``UMOCKDEV_DIR=TESTBED``): its ``open("/dev/i2c-N")`` finds ``TESTBED/dev/i2c-N`` and its ioctls on that file
go, over the Unix socket ``TESTBED/ioctl/dev/i2c-N``, to the process serving it, which reads and writes the
host's ioctl arguments through the same socket. :class:`I2CDevServer` is that process's side: the I2C adapter
in front of :class:`~.fake_i2c.FakeI2CDevice` (its register map and FIFO, the semantics of
:class:`~.fake_i2c.FakeSMBus`), so the host runs its production read path and pays only for its own system
calls, while the device's work is this process's CPU.

The socket protocol (umockdev's src/libumockdev-preload.c ``remote_emulate``, unchanged since umockdev 0.16):
every message is three native unsigned longs ``(cmd, arg1, arg2)``. The host sends IOCTL (1, request, arg),
READ (7, buf, len) or WRITE (8, buf, len); the server answers with any number of READ_MEM (5, addr, len: the
host sends ``len`` bytes of its memory at ``addr``) and WRITE_MEM (6, addr, len, then ``len`` bytes the host
stores at ``addr``), then DONE (3, result, errno).
"""
from __future__ import annotations

import ctypes.util
import errno
import os
import shutil
import socket
import struct
import tempfile
import threading

from smbus2.smbus2 import I2C_M_RD, I2cFunc, i2c_msg

from .fake_i2c import I2C_RDWR_IOCTL_MAX_MSGS, I2C_RDWR_MAX_LEN, FakeI2CDevice, FakeSMBus

PRELOAD_LIBRARY = "libumockdev-preload.so.0"
INSTALL_HINT = "the emulated I2C bus needs umockdev's preload library (Debian: apt-get install umockdev)"

# linux/i2c-dev.h, linux/i2c.h
I2C_SLAVE, I2C_SLAVE_FORCE, I2C_FUNCS, I2C_RDWR, I2C_PEC, I2C_SMBUS = 0x0703, 0x0706, 0x0705, 0x0707, 0x0708, 0x0720
I2C_SMBUS_READ = 1
I2C_SMBUS_BYTE_DATA, I2C_SMBUS_WORD_DATA, I2C_SMBUS_I2C_BLOCK_DATA = 2, 3, 8
I2C_SMBUS_BLOCK_MAX = 32
FUNCS = (I2cFunc.I2C | I2cFunc.SMBUS_READ_BYTE_DATA | I2cFunc.SMBUS_WRITE_BYTE_DATA | I2cFunc.SMBUS_READ_WORD_DATA
         | I2cFunc.SMBUS_WRITE_WORD_DATA | I2cFunc.SMBUS_READ_I2C_BLOCK | I2cFunc.SMBUS_WRITE_I2C_BLOCK)

# umockdev's socket protocol
REQ_IOCTL, REQ_READ, REQ_WRITE = 1, 7, 8
RES_DONE, RES_READ_MEM, RES_WRITE_MEM = 3, 5, 6
_WORDS = struct.Struct("@3L")
_ULONG_MASK = (1 << (8 * _WORDS.size // 3)) - 1
_RDWR = struct.Struct("@PI")  # struct i2c_rdwr_ioctl_data: msgs, nmsgs
_MSG = struct.Struct("@HHHP")  # struct i2c_msg: addr, flags, len, buf
_SMBUS = struct.Struct("@BBIP")  # struct i2c_smbus_ioctl_data: read_write, command, size, data
SUN_PATH_MAX = 108  # sys/un.h: sockaddr_un.sun_path


def preload_library() -> str | None:
    """The preload library's name if the dynamic linker can find it, else None."""
    return PRELOAD_LIBRARY if ctypes.util.find_library("umockdev-preload") else None


def preload_env(testbed: str, env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default os.environ) for a host process that opens the testbed's ``/dev/i2c-N``."""
    env = dict(os.environ if env is None else env)
    if preload_library() is None:
        raise OSError(errno.ENOENT, INSTALL_HINT)
    preloads = [p for p in env.get("LD_PRELOAD", "").split(":") if p and PRELOAD_LIBRARY not in p]
    env["LD_PRELOAD"] = ":".join([PRELOAD_LIBRARY, *preloads])
    env["UMOCKDEV_DIR"] = testbed
    return env


def preloaded(env: dict[str, str] | None = None) -> bool:
    """Whether a process with ``env`` (default this one's) runs under the preload library."""
    return PRELOAD_LIBRARY in (os.environ if env is None else env).get("LD_PRELOAD", "")


class _Closed(Exception):
    """The host closed its end (it closed the device, or exited)."""


class _Client:
    """One open file description of ``/dev/i2c-N`` in the host: its socket and its I2C_SLAVE address."""

    def __init__(self, sock: socket.socket, smbus: FakeSMBus):
        self.sock, self.smbus = sock, smbus
        self.address: int | None = None

    # -- the protocol ---------------------------------------------------------------
    def _recv(self, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            got = self.sock.recv(n - len(buf))
            if not got:
                raise _Closed
            buf += got
        return bytes(buf)

    def read_mem(self, addr: int, n: int) -> bytes:
        self.sock.sendall(_WORDS.pack(RES_READ_MEM, addr, n))
        return self._recv(n)

    def write_mem(self, addr: int, data: bytes) -> None:
        self.sock.sendall(_WORDS.pack(RES_WRITE_MEM, addr, len(data)) + data)

    def serve(self) -> None:
        try:
            while True:
                cmd, arg1, arg2 = _WORDS.unpack(self._recv(_WORDS.size))
                if cmd == REQ_IOCTL:
                    try:
                        result, err = self.ioctl(arg1, arg2), 0
                    except OSError as exc:
                        result, err = -1, exc.errno or errno.EIO
                else:  # read()/write() on i2c-dev: a plain transfer the driver never uses
                    result, err = -1, errno.EOPNOTSUPP
                self.sock.sendall(_WORDS.pack(RES_DONE, result & _ULONG_MASK, err))
        except (_Closed, OSError):
            pass
        finally:
            self.sock.close()

    # -- i2c-dev --------------------------------------------------------------------
    def ioctl(self, request: int, arg: int) -> int:
        if request in (I2C_SLAVE, I2C_SLAVE_FORCE):
            if not 0 <= arg <= 0x7F:
                raise OSError(errno.EINVAL, "Invalid argument")
            self.address = arg
            return 0
        if request == I2C_FUNCS:
            self.write_mem(arg, struct.pack("@L", FUNCS))
            return 0
        if request == I2C_PEC:
            return 0
        if request == I2C_RDWR:
            return self.rdwr(arg)
        if request == I2C_SMBUS:
            return self.smbus_transfer(arg)
        raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")

    def rdwr(self, arg: int) -> int:
        """I2C_RDWR: the messages in one combined transfer; read buffers are written back only when it all
        succeeded (as i2c-dev does)."""
        msgs_addr, nmsgs = _RDWR.unpack(self.read_mem(arg, _RDWR.size))
        if not 0 < nmsgs <= I2C_RDWR_IOCTL_MAX_MSGS:
            raise OSError(errno.EINVAL, "Invalid argument")
        raw = self.read_mem(msgs_addr, nmsgs * _MSG.size)
        fields = [_MSG.unpack_from(raw, i * _MSG.size) for i in range(nmsgs)]
        if any(length > I2C_RDWR_MAX_LEN for _a, _f, length, _b in fields):
            raise OSError(errno.EINVAL, "Invalid argument")
        local = []
        for addr, flags, length, buf in fields:
            if flags & I2C_M_RD:
                m = i2c_msg.read(addr, length)
            else:
                m = i2c_msg.write(addr, self.read_mem(buf, length) if length else b"")
            m.flags = flags
            local.append(m)
        self.smbus.i2c_rdwr(*local)
        for (_addr, flags, length, buf), m in zip(fields, local):
            if flags & I2C_M_RD and length:
                self.write_mem(buf, bytes(m))
        return nmsgs

    def smbus_transfer(self, arg: int) -> int:
        """I2C_SMBUS: the byte, word and I2C-block register accesses."""
        read_write, command, size, data = _SMBUS.unpack(self.read_mem(arg, _SMBUS.size))
        if self.address is None:
            raise OSError(errno.EINVAL, "Invalid argument (no I2C_SLAVE address set)")
        dev = self.smbus._dev(self.address)
        reading = read_write == I2C_SMBUS_READ
        if size == I2C_SMBUS_BYTE_DATA:
            n, value = 1, None if reading else self.read_mem(data, 1)
        elif size == I2C_SMBUS_WORD_DATA:
            n, value = 2, None if reading else self.read_mem(data, 2)
        elif size == I2C_SMBUS_I2C_BLOCK_DATA:
            n = self.read_mem(data, 1)[0]
            if not 1 <= n <= I2C_SMBUS_BLOCK_MAX:
                raise OSError(errno.EINVAL, "Invalid argument")
            value = None if reading else self.read_mem(data + 1, n)
        else:
            raise OSError(errno.EOPNOTSUPP, "Operation not supported (SMBus transfer size)")
        if not reading:
            dev.write_registers(command, value)
            return 0
        got = dev.read_registers(command, n)
        self.write_mem(data, bytes([n]) + got if size == I2C_SMBUS_I2C_BLOCK_DATA else got)
        return 0


class I2CDevServer:
    """``/dev/i2c-{bus}`` in a umockdev testbed directory, with ``devices`` (FakeI2CDevice, or a dict address ->
    FakeI2CDevice) on it, served by threads of this process. ``testbed``: the directory (created if missing;
    default a new temporary one, removed by :meth:`close`). A host reaches it with :func:`preload_env`."""

    def __init__(self, devices: FakeI2CDevice | dict[int, FakeI2CDevice], *, bus: int = 1,
                 testbed: str | None = None):
        self.smbus = FakeSMBus(devices, bus)
        self.bus = int(bus)
        self._own_dir = testbed is None
        self.testbed = testbed or tempfile.mkdtemp(prefix="gravcal-i2c-")
        self.dev_path = f"/dev/i2c-{self.bus}"
        self.node_path = os.path.join(self.testbed, "dev", f"i2c-{self.bus}")
        self.socket_path = os.path.join(self.testbed, "ioctl", "dev", f"i2c-{self.bus}")
        if len(os.fsencode(self.socket_path)) >= SUN_PATH_MAX:  # a Unix socket's address holds 107 bytes
            raise ValueError(f"the testbed path {self.testbed!r} is too long for its ioctl socket "
                             f"(at most {SUN_PATH_MAX - 1 - len('/ioctl/dev/i2c-') - len(str(self.bus))} bytes)")
        os.makedirs(os.path.dirname(self.node_path), exist_ok=True)
        os.makedirs(os.path.dirname(self.socket_path), exist_ok=True)
        if os.path.exists(self.socket_path):
            os.unlink(self.socket_path)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(self.socket_path)
        self._listener.listen(8)
        self._thread = threading.Thread(target=self._accept, name="i2c-dev-server", daemon=True)
        self._thread.start()
        # the node last: the preload connects to the socket when the host opens the node (and exits the host
        # when it cannot), so the node exists only while the socket is served
        with open(self.node_path, "wb"):
            pass

    def env(self, env: dict[str, str] | None = None) -> dict[str, str]:
        return preload_env(self.testbed, env)

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except OSError:  # closed
                return
            threading.Thread(target=_Client(sock, self.smbus).serve, name="i2c-dev-client", daemon=True).start()

    def close(self) -> None:
        """No new host opens the device (it is gone from the testbed: ENOENT). Hosts that have it open keep being
        served while this process lives: the preload aborts a host whose ioctl finds the socket closed."""
        try:
            os.unlink(self.node_path)
        except OSError:
            pass
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._listener.close()
        self._thread.join(2.0)
        try:
            os.unlink(self.socket_path)
        except OSError:
            pass
        if self._own_dir:
            shutil.rmtree(self.testbed, ignore_errors=True)

    def __enter__(self) -> "I2CDevServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
