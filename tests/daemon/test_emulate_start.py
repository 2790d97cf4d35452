"""`gravcald --emulate` without --socket/--state-dir makes a temporary directory for both: a start that fails
leaves none behind, and one holding a saved state is kept (it resumes with --state-dir)."""
import os
import subprocess
import sys

import pytest

from gravcal.daemon import gravcald
from gravcal.daemon.emulation import discard_if_empty
from support.umockdev import require_umockdev


@pytest.mark.parametrize("argv", [["--fs", "-5"], ["--config", "/nonexistent/gravcald.toml"],
                                  ["--bus", "serial", "--driver-options", "baudrate=fast"]],
                         ids=["bad-rate", "missing-config", "bad-driver-option"])
def test_a_failed_emulated_start_creates_nothing(tmp_path, monkeypatch, capsys, argv):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    code = gravcald.main(["--emulate", "--allow-root", *argv])
    err = capsys.readouterr().err
    assert code != 0 and "gravcald: error:" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_only_empty_directories_are_discarded(tmp_path):
    empty, kept = tmp_path / "gravcald-emulate-a", tmp_path / "gravcald-emulate-b"
    (empty / "state").mkdir(parents=True)
    (kept / "state").mkdir(parents=True)
    (kept / "state" / "state.json").write_text("{}")
    discard_if_empty([str(empty), str(kept), str(tmp_path / "gone")])
    assert not empty.exists() and (kept / "state" / "state.json").exists()


def test_the_scenario_help_names_every_scenario_the_emulator_takes():
    from gravcal.core.scenarios import SCENARIOS
    from gravcal.drivers.rigs.sources import PATTERN

    help_text = next(a.help for a in gravcald.build_parser()._actions if "--scenario" in a.option_strings)
    assert all(name in help_text for name in [*SCENARIOS, PATTERN]), help_text


def test_a_bad_i2c_driver_option_is_refused_and_leaves_nothing_behind(short_tmp_path):
    require_umockdev()
    # a subprocess: gravcald starts again under umockdev's preload library for the emulated I2C bus
    runtime, testbeds = short_tmp_path / "run", short_tmp_path / "tmp"
    runtime.mkdir()
    testbeds.mkdir()
    p = subprocess.run([sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--allow-root", "--bus", "i2c",
                        "--driver-options", "burst_frames=many"], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "XDG_RUNTIME_DIR": str(runtime), "TMPDIR": str(testbeds)})
    assert p.returncode != 0 and "gravcald: error:" in p.stderr and "burst_frames" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert list(runtime.iterdir()) == [] and list(testbeds.iterdir()) == []  # no state dir, no umockdev testbed


def test_the_emulated_i2c_bus_is_refused_without_the_preload_library(capsys, monkeypatch, short_tmp_path):
    monkeypatch.delenv("LD_PRELOAD", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(short_tmp_path))
    code = gravcald.main(["--emulate", "--allow-root", "--bus", "i2c"])  # in process: no start again
    err = capsys.readouterr().err
    assert code == 2 and "umockdev's preload library" in err and "Traceback" not in err
    assert list(short_tmp_path.iterdir()) == []
