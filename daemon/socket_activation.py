"""Where gravcald's listening socket comes from: bound at a path, or inherited from systemd.

Socket path rules (:func:`bind_unix_socket`): a live socket at the path means another
gravcald is running (refuse); a dead one is stale (removed); anything else is refused and
named. Under systemd socket activation the listening socket is inherited instead
(:func:`listen_fds`, the sd_listen_fds_with_names protocol).
"""
from __future__ import annotations

import errno
import logging
import os
import socket
import stat

log = logging.getLogger("gravcal.server")

SD_LISTEN_FDS_START = 3


class SocketPathError(OSError):
    """The socket path cannot be used (in use, not a socket, no directory, ...)."""


# -- socket path and activation ------------------------------------------------------


def bind_unix_socket(path: str, *, mode: int | None = 0o660, group: str = "",
                     backlog: int = socket.SOMAXCONN) -> socket.socket:
    """A listening, non-blocking AF_UNIX stream socket bound at ``path``.

    The backlog is the system maximum, far above ServerConfig.max_clients: a burst of clients
    beyond the limit is accepted and told "too many clients" (an ERROR line) by the server,
    instead of failing in connect() with EAGAIN before the server ever sees it.

    An existing path that is a live socket -> SocketPathError("another gravcald is running
    on PATH"); a socket nobody listens on (stale, left by a crash) is removed and rebound;
    an existing non-socket is never removed: SocketPathError naming it. ``group`` (a name) owns
    the socket, so that mode 0660 lets exactly its members connect.
    """
    path = os.fspath(path)
    gid = -1
    if group:
        import grp

        try:
            gid = grp.getgrnam(group).gr_gid
        except KeyError:
            raise SocketPathError(f"[socket] group {group!r}: no such group (create it: groupadd --system {group})") from None
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise SocketPathError(f"cannot create socket {path}: directory {parent} does not exist")
    if len(os.fsencode(path)) >= 108:
        raise SocketPathError(f"socket path too long for AF_UNIX (max 107 bytes): {path}")
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None:
        if not stat.S_ISSOCK(st.st_mode):
            raise SocketPathError(f"{path} exists and is not a socket; refusing to replace it (remove it or choose another --socket)")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(path)
        except (ConnectionRefusedError, FileNotFoundError):
            log.info("removing stale socket %s (nothing listening)", path)
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass
        except OSError as exc:
            raise SocketPathError(f"cannot check existing socket {path}: {exc.strerror or exc}") from exc
        else:
            raise SocketPathError(f"another gravcald is running on {path} (a process accepts connections there)")
        finally:
            probe.close()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(path)
        if gid >= 0:
            os.chown(path, -1, gid)
        if mode is not None:
            os.chmod(path, mode)
        sock.listen(backlog)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise SocketPathError(f"another gravcald is running on {path} (bound while we checked)") from exc
        raise SocketPathError(f"cannot bind socket {path}: {exc.strerror or exc}") from exc
    sock.setblocking(False)
    return sock


def listen_fds(*, unset_environment: bool = True, environ: dict[str, str] | None = None) -> dict[str, list[socket.socket]]:
    """Sockets passed by systemd socket activation, by FileDescriptorName= (sd_listen_fds_with_names).

    Protocol: LISTEN_PID must be our pid, LISTEN_FDS = n fds starting at fd 3,
    LISTEN_FDNAMES = colon-separated names ("unknown" when absent). Empty dict when not
    activated. The variables are removed so children do not inherit them.
    """
    env = os.environ if environ is None else environ
    pid, n, names = env.get("LISTEN_PID"), env.get("LISTEN_FDS"), env.get("LISTEN_FDNAMES")
    if unset_environment:
        for key in ("LISTEN_PID", "LISTEN_FDS", "LISTEN_FDNAMES"):
            env.pop(key, None)
    if not pid or not n:
        return {}
    try:
        if int(pid) != os.getpid():
            return {}  # meant for another process (e.g. our parent)
        count = int(n)
    except ValueError:
        log.warning("ignoring malformed LISTEN_PID=%r LISTEN_FDS=%r", pid, n)
        return {}
    name_list = names.split(":") if names else []
    if len(name_list) != count:
        name_list = ["unknown"] * count
    out: dict[str, list[socket.socket]] = {}
    for i in range(count):
        fd = SD_LISTEN_FDS_START + i
        os.set_inheritable(fd, False)  # FD_CLOEXEC, as sd_listen_fds does
        out.setdefault(name_list[i], []).append(socket.socket(fileno=fd))
    return out


def activated_socket(name: str = "gravcal", *, environ: dict[str, str] | None = None) -> socket.socket | None:
    """The listening socket systemd passed under ``name`` (or the only one, if unnamed).

    None when not socket-activated. Raises SocketPathError if what was passed is not a
    listening AF_UNIX stream socket.
    """
    fds = listen_fds(environ=environ)
    if not fds:
        return None
    if name in fds:
        sock = fds[name][0]
    elif list(fds) == ["unknown"] and len(fds["unknown"]) == 1:
        sock = fds["unknown"][0]
    else:
        raise SocketPathError(
            f"socket activation passed fds named {sorted(fds)}, none named {name!r} (set FileDescriptorName={name})"
        )
    if sock.family != socket.AF_UNIX or sock.type != socket.SOCK_STREAM:
        raise SocketPathError(f"socket activation passed a {sock.family.name}/{sock.type.name} socket; need AF_UNIX stream (ListenStream=)")
    if not sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
        raise SocketPathError("socket activation passed a socket that is not listening (use ListenStream=, Accept=no)")
    sock.setblocking(False)
    return sock


# -- clients -------------------------------------------------------------------------
