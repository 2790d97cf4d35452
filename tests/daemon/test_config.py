"""gravcald configuration: TOML, defaults, overrides, and errors that name file and key."""
import math
import sys
import tomllib

import pytest

from gravcal.daemon.config import Config, ConfigError, example_toml, load_config, parse_config
from support.concurrent_runs import run_together


def write(tmp_path, text, name="gravcald.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_defaults_without_file():
    cfg = load_config(None)
    assert cfg.socket.path == "/run/gravcal.sock"
    assert cfg.estimator.model == "6" and cfg.device.fs_hz == 200.0
    assert math.isnan(cfg.gyro.counts_per_rad_s)


def test_file_values_override_defaults_and_ints_become_floats(tmp_path):
    p = write(tmp_path, """
[device]
spec = "can://virtual/gravcal0"
fs_hz = 100
[detector]
threshold_g = 0.03
[socket]
mode = 0o600
queue_messages = 128
""")
    cfg = load_config(p)
    assert cfg.device.spec == "can://virtual/gravcal0"
    assert cfg.device.fs_hz == 100.0 and isinstance(cfg.device.fs_hz, float)
    assert cfg.detector.threshold_g == 0.03 and cfg.socket.mode == 0o600 and cfg.socket.queue_messages == 128
    assert cfg.detector.hp_hz == 0.5  # untouched keys keep their defaults
    assert cfg.source == str(p)


def test_command_line_overrides_file(tmp_path):
    p = write(tmp_path, '[socket]\npath = "/run/a.sock"\n[estimator]\nmodel = "12"\n')
    cfg = load_config(p, {"socket.path": "/tmp/b.sock", "estimator.model": None})
    assert cfg.socket.path == "/tmp/b.sock"  # the command line wins
    assert cfg.estimator.model == "12"  # None = option not given


@pytest.mark.parametrize(
    "text, message",
    [
        ('[detector]\nthreshold_g = "abc"\n', "[detector] threshold_g: expected a number, got 'abc'"),
        ("[detector]\nthreshold_g = true\n", "[detector] threshold_g: expected a number, got true"),
        ("[socket]\nmax_clients = 1.5\n", "[socket] max_clients: expected an integer, got 1.5"),
        ("[socket]\npath = 5\n", "[socket] path: expected a string, got 5"),
        ("[detector]\ntreshold_g = 0.1\n", "[detector] unknown key 'treshold_g'; known keys: method, threshold_g"),
        ("[detectors]\nthreshold_g = 0.1\n", "unknown section [detectors]; known sections: device, estimator"),
        ("threshold_g = 0.1\n", "key 'threshold_g' outside any section"),
        ("detector = 3\n", "detector: expected a table [detector], got 3"),
        ('[estimator]\nmodel = "7"\n', "[estimator] model: expected one of 'offsets', '6', '9', '12', got '7'"),
        ("[device]\nfs_hz = -200\n", "[device] fs_hz: expected a positive number, got -200.0"),
        ("[device]\nfs_hz = nan\n", "[device] fs_hz: expected a number, got nan"),
        ("[estimator]\nmin_windows = -1\n", "[estimator] min_windows: expected a number >= 0, got -1"),
        ("[detector]\nmin_duration_s = 5.0\nmax_duration_s = 2.0\n", "[detector] max_duration_s: must be >= min_duration_s"),
        ("[detector\nthreshold_g = 1\n", "invalid TOML"),
    ],
)
def test_errors_name_file_section_key_and_expectation(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value).startswith(f"{p}: ")
    assert message in str(e.value)
    assert "\n" not in str(e.value)


def test_the_briefs_example_message_verbatim():
    with pytest.raises(ConfigError) as e:
        parse_config(tomllib.loads('[detector]\nthreshold_g = "abc"\n'), "/etc/gravcal/gravcald.toml")
    assert str(e.value) == "/etc/gravcal/gravcald.toml: [detector] threshold_g: expected a number, got 'abc'"


def test_override_errors_say_command_line():
    with pytest.raises(ConfigError, match=r"^command line: \[device\] fs_hz: expected a positive number"):
        load_config(None, {"device.fs_hz": 0.0})
    with pytest.raises(ConfigError, match=r"^command line: \[socket\] unknown key 'paht'"):
        load_config(None, {"socket.paht": "/x"})
    with pytest.raises(ConfigError, match="must be section.key"):
        load_config(None, {"socketpath": "/x"})


def test_file_problems(tmp_path):
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "missing.toml")
    assert load_config(tmp_path / "missing.toml", required=False).socket.path == "/run/gravcal.sock"
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(b'[socket]\npath = "/run/\xe9.sock"\n')
    with pytest.raises(ConfigError, match=f"{bad}: invalid TOML"):
        load_config(bad)


@pytest.mark.parametrize("text", ["[socket]\npath = " + "[" * 2000 + "]" * 2000,
                                  "x = " + "{a = " * 500 + "1" + "}" * 500,
                                  "x = '\"'\ny = " + "[" * 100 + "]" * 100],
                         ids=["2000 arrays", "500 inline tables", "after a quote in a literal string"])
def test_deeply_nested_toml_is_a_one_line_error(tmp_path, text):
    p = tmp_path / "deep.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=f"^{p}: TOML nested deeper than 64 levels$"):
        load_config(p)


def test_example_toml_lists_every_key_and_parses_back_to_the_defaults():
    text = example_toml()
    back = parse_config(tomllib.loads(text), "example")
    assert back.to_dict().keys() == Config().to_dict().keys()
    for section, values in Config().to_dict().items():
        for key, value in values.items():
            got = back.to_dict()[section][key]
            assert (math.isnan(got) and math.isnan(value)) if isinstance(value, float) and math.isnan(value) else got == value
            assert f"{key} = " in text


def test_gravcald_rejects_bad_config_with_one_line_and_status_2(tmp_path):
    p = write(tmp_path, '[detector]\nthreshold_g = "abc"\n')
    write(tmp_path, '[socket]\npath = "/tmp/z.sock"\n', "ok.toml")
    gravcald = [sys.executable, "-m", "gravcal.daemon.gravcald"]
    bad_file, bad_option, missing, ok = run_together([
        [*gravcald, "--config", str(p)],
        [*gravcald, "--fs", "-5", "--print-config"],
        [*gravcald, "--config", str(tmp_path / "x.toml"), "--print-config"],
        [*gravcald, "--config", str(tmp_path / "ok.toml"), "--model", "12", "--print-config"],
    ])
    assert bad_file.returncode == 2
    assert bad_file.stderr.strip() == f"gravcald: error: {p}: [detector] threshold_g: expected a number, got 'abc'"
    assert bad_option.returncode == 2 and "command line: [device] fs_hz" in bad_option.stderr
    assert missing.returncode == 2 and "no such configuration file" in missing.stderr
    assert ok.returncode == 0
    printed = tomllib.loads(ok.stdout)
    assert printed["socket"]["path"] == "/tmp/z.sock" and printed["estimator"]["model"] == "12"


def test_offline_only_terms_are_refused_for_the_online_estimator(tmp_path):
    """A term whose rows need the window history cannot run one window at a time: the service refuses it by name."""
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

    offline = [t for t in CALIBRATION_TERMS if not calibration_view(t).per_window]
    assert offline, "the registry has no offline-only term to check"
    for term in offline:
        with pytest.raises(ConfigError, match=rf"offline-only term\(s\) \(they need the window history\) '{term}'"):
            load_config(tmp_path / "missing.toml", {"estimator.extended_terms": term}, required=False)
