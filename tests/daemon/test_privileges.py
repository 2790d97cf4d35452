"""Least privilege: root is refused unless meant, or dropped once the device and socket are open."""
import grp
import os
import pwd
import socket
import stat
import subprocess
import sys

import pytest

from gravcal.daemon import privileges
from gravcal.errors import InputError
from gravcal.daemon.socket_activation import SocketPathError, bind_unix_socket

from support.gravcald_process import GravcaldProcess

as_root = pytest.mark.skipif(os.geteuid() != 0, reason="needs root (the situation under test)")


def test_check_start_decides_from_the_effective_user():
    assert privileges.check_start(1000, "", "", False) is None  # not root: nothing to do
    assert privileges.check_start(1000, "nobody", "", False) is None
    with pytest.raises(InputError, match="refusing to run as root.*--allow-root"):
        privileges.check_start(0, "", "", False)
    assert privileges.check_start(0, "", "", True) is None
    ident = privileges.check_start(0, "nobody", "", False)
    assert ident.uid == pwd.getpwnam("nobody").pw_uid and ident.gid in ident.groups
    with pytest.raises(InputError, match="no such user"):
        privileges.check_start(0, "no-such-gravcal-user", "", False)
    with pytest.raises(InputError, match="no such group"):
        privileges.check_start(0, "nobody", "no-such-gravcal-group", False)


def test_socket_gets_its_group_and_mode(tmp_path):
    group = grp.getgrgid(os.getgid() if os.getgid() else 1)  # a group that exists here
    path = str(tmp_path / "g.sock")
    s = bind_unix_socket(path, mode=0o660, group=group.gr_name)
    try:
        st = os.stat(path)
        assert stat.S_IMODE(st.st_mode) == 0o660 and st.st_gid == group.gr_gid
    finally:
        s.close()
    with pytest.raises(SocketPathError, match="no such group"):
        bind_unix_socket(str(tmp_path / "h.sock"), group="no-such-gravcal-group")
    assert not os.path.exists(tmp_path / "h.sock")


@as_root
def test_root_without_a_user_is_refused_and_nothing_is_created(tmp_path):
    p = subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", "--device", "serial:///dev/null",
                        "--state-dir", str(tmp_path / "state"), "--socket", str(tmp_path / "g.sock")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "refusing to run as root" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert os.listdir(tmp_path) == []


def _proc_ids(pid):
    fields = dict(line.split(":", 1) for line in open(f"/proc/{pid}/status").read().splitlines() if ":" in line)
    return ([int(x) for x in fields["Uid"].split()], [int(x) for x in fields["Gid"].split()],
            int(fields["CapEff"].strip(), 16), int(fields["CapPrm"].strip(), 16))


@as_root
def test_root_with_a_user_drops_to_it_after_opening_device_and_socket(tmp_path):
    nobody = pwd.getpwnam("nobody")
    d = GravcaldProcess(tmp_path, "--bus", "serial", "--scenario", "static", "--speed", "1",
                        config='[daemon]\nuser = "nobody"\n')
    try:
        d.wait_serving()
        uids, gids, cap_eff, cap_prm = _proc_ids(d.proc.pid)
        assert uids == [nobody.pw_uid] * 4 and gids == [nobody.pw_gid] * 4
        assert cap_eff == 0 and cap_prm == 0
        with d.client() as c:  # the socket and device opened as root keep serving
            c.set_watch(enable=True, rate=0)
            assert any(c.read_message()["class"] == "IMU" for _ in range(20))
        assert "dropped privileges to nobody" in d.log()
        assert os.stat(d.state).st_uid == nobody.pw_uid
        # an installation nobody cannot read (a Python under /root) is named: modules loaded later would fail
        assert ("nobody cannot read" in d.log()) == any(not _others_can_read(p) for p in _code_dirs()), d.log()
        emulator_pid = int(d.log().split("emulator pid ")[1].split(":")[0])
    finally:
        code = d.stop()
    # the emulator child, started as root, cannot be signalled after the drop: it still stops, and so does gravcald
    assert code == 0, d.log()[-2000:]
    assert "Traceback" not in d.log()
    assert not os.path.exists(f"/proc/{emulator_pid}") or "zombie" in open(f"/proc/{emulator_pid}/status").read()


def _code_dirs():
    import numpy

    import gravcal

    return [os.path.dirname(os.__file__), os.path.dirname(numpy.__file__), os.path.dirname(gravcal.__file__)]


def _others_can_read(path):
    """What os.access would say for a user that is neither owner nor in the group of any component."""
    parts = os.path.abspath(path).split(os.sep)
    for k in range(1, len(parts) + 1):
        mode = os.stat(os.sep + os.path.join(*parts[1:k]) if k > 1 else os.sep).st_mode
        if mode & 0o001 == 0 or (k == len(parts) and mode & 0o004 == 0):
            return False
    return True
