"""Least privilege for gravcald: never keep root by accident.

Started as root, gravcald either drops to ``[daemon] user`` (and ``group``) once the device and the
socket are open, or refuses to start unless ``[daemon] allow_root`` / ``--allow-root`` says root is
meant. Under systemd none of this applies: the unit runs it as a dynamic user (docs/daemon.md).
"""
from __future__ import annotations

import grp
import logging
import os
import pwd
from dataclasses import dataclass
from typing import Iterable

from ..errors import InputError

log = logging.getLogger("gravcal.gravcald")


@dataclass(frozen=True)
class Identity:
    user: str
    uid: int
    gid: int
    groups: tuple[int, ...]

    def describe(self) -> str:
        return f"{self.user} (uid {self.uid}, gid {self.gid})"


def resolve(user: str, group: str = "") -> Identity:
    """The uid, primary gid (``group`` or the user's own) and supplementary groups of ``user``."""
    try:
        pw = pwd.getpwnam(user)
    except KeyError:
        raise InputError(f"[daemon] user {user!r}: no such user (create it: useradd --system {user})") from None
    gid = pw.pw_gid
    if group:
        try:
            gid = grp.getgrnam(group).gr_gid
        except KeyError:
            raise InputError(f"[daemon] group {group!r}: no such group (create it: groupadd --system {group})") from None
    groups = tuple(sorted(set(os.getgrouplist(user, gid))))  # dialout, i2c ... of that user
    return Identity(user, pw.pw_uid, gid, groups)


def check_start(euid: int, user: str, group: str, allow_root: bool) -> Identity | None:
    """Before anything is opened: the identity to drop to, None to stay as is; InputError if root
    is neither meant nor to be dropped."""
    if euid != 0:
        if user:
            log.info("[daemon] user %r ignored: not started as root", user)
        return None
    if user:
        return resolve(user, group)
    if allow_root:
        log.warning("running as root with all its privileges (allow_root); prefer [daemon] user")
        return None
    raise InputError("refusing to run as root: set [daemon] user (e.g. \"gravcal\") to drop privileges once the "
                     "device and socket are open, or pass --allow-root (or [daemon] allow_root = true)")


def drop(identity: Identity, hand_over: Iterable[str] = ()) -> None:
    """Become ``identity`` for good: its groups, gid, then uid (root's capabilities go with the uid).
    Each existing path of ``hand_over`` (the state directory) is given to it first."""
    for path in hand_over:
        if os.path.exists(path):
            os.chown(path, identity.uid, identity.gid)
    os.setgroups(list(identity.groups))
    os.setgid(identity.gid)
    os.setuid(identity.uid)
    try:
        os.setuid(0)
    except PermissionError:
        pass
    else:  # pragma: no cover - a kernel that let us back would make the drop meaningless
        raise RuntimeError("privileges could not be dropped: setuid(0) succeeded afterwards")
    log.info("dropped privileges to %s, groups %s", identity.describe(), ",".join(map(str, identity.groups)))
    for path in unreadable_code():
        log.warning("%s cannot read %s: modules imported later (on first use) will fail; install gravcal where "
                    "that user can read it (docs/daemon.md, a virtualenv in /opt/gravcal)", identity.user, path)


def unreadable_code() -> list[str]:
    """The directories of the Python installation (the standard library, numpy, gravcal) this process
    cannot read: a module first imported after a privilege drop would fail to load from there."""
    import numpy

    dirs = {os.path.dirname(os.__file__), os.path.dirname(numpy.__file__),
            os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
    return sorted(d for d in dirs if not os.access(d, os.R_OK | os.X_OK))
