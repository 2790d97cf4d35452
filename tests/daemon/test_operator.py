"""What an operator meets first: a closed pipe ends quietly, a failed start leaves nothing behind."""
import os
import subprocess
import sys

import pytest


def run_into_closed_pipe(argv):
    r, w = os.pipe()
    os.close(r)  # the reader is gone before the first byte is written (`| head` that already quit)
    try:
        return subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", *argv], stdout=w,
                              stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(w)


def test_print_config_into_a_closed_pipe_ends_quietly():
    p = run_into_closed_pipe(["--print-config"])
    assert p.stderr == "" and p.returncode == 0, p.stderr


@pytest.mark.parametrize("argv", [["--version"], ["watch", "--help"], ["reproduce", "loetters", "--help"]])
def test_gravcal_into_a_closed_pipe_ends_quietly(argv):
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run([os.path.join(os.path.dirname(sys.executable), "gravcal"), *argv], stdout=w,
                           stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(w)
    assert p.stderr == "" and p.returncode == 0, p.stderr


def test_print_config_into_head_keeps_the_first_lines():
    p = subprocess.run(f"'{sys.executable}' -m gravcal.daemon.gravcald --print-config | head -2", shell=True,
                       capture_output=True, text=True, timeout=60)
    assert p.stdout.splitlines() == ["[device]", p.stdout.splitlines()[1]] and p.stdout.splitlines()[1].startswith("#")
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr


def test_a_failed_start_creates_no_state_directory_and_no_socket(tmp_path):
    state = tmp_path / "var" / "lib" / "gravcal"
    sock = tmp_path / "g.sock"
    p = subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", "--allow-root", "--device",
                        f"serial://{tmp_path}/no-such-tty?baudrate=460800", "--state-dir", str(state),
                        "--socket", str(sock)], capture_output=True, text=True, timeout=60)
    assert p.returncode != 0 and "no-such-tty" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "var").exists() and not sock.exists(), sorted(os.listdir(tmp_path))


def test_an_unwritable_state_directory_still_fails_the_start_at_once(tmp_path):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o500)
    try:
        if os.access(parent, os.W_OK):  # root ignores modes
            return
        p = subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", "--device", "serial:///dev/null",
                            "--state-dir", str(parent / "state"), "--socket", str(tmp_path / "g.sock")],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and "not writable" in p.stderr, p.stderr
        assert not (tmp_path / "g.sock").exists()
    finally:
        parent.chmod(0o700)
