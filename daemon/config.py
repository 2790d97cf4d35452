"""gravcald configuration: a TOML file (tomllib) with defaults and command-line overrides.

Every key has a type and a default; the file only lists what differs. Errors name the file,
the section, the key and what was expected, e.g.::

    /etc/gravcal/gravcald.toml: [detector] threshold_g: expected a number, got 'abc'

Unknown sections and keys are errors too (a typo must not silently keep a default).
Command-line overrides are dotted keys ("socket.path") checked the same way, with
"command line" in place of the file name. An example with every key: docs/socket-protocol.md
(section "Configuration") and systemd/gravcald.toml.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from dataclasses import dataclass, field, fields
from typing import Any, get_type_hints

from gravcal.core.estimators.observability import ORDER_LADDER
from gravcal.core.model.terms import AUX_COLUMNS, CALIBRATION_TERMS, calibration_view

from ..errors import InputError
from ..jsonbounds import JSONInputError, check_bounds

ONLINE_TERMS = tuple(t for t in CALIBRATION_TERMS
                     if calibration_view(t).acts_on != "cross" and calibration_view(t).per_window)
"""Registered terms the online estimator may add (the cross-axis one is the order rule's: order 9; a term
whose rows need the window history is offline only)."""
# The default: the offset terms whose covariate the board itself measures (a column of every sample). A
# time-drift term is linear in time from its reference and would extrapolate for days in a long-running
# service; drift is followed by the recursion (process_noise) and by re-seeds instead. Offline,
# `gravcal calibrate --model auto` tests every term.
DEFAULT_ONLINE_TERMS = ",".join(t for t in ONLINE_TERMS if calibration_view(t).acts_on == "offset"
                                and calibration_view(t).covariate in AUX_COLUMNS)

DEFAULT_CONFIG_PATH = "/etc/gravcal/gravcald.toml"
MAX_CONFIG_BYTES = 1 << 20  # the example configuration with every key is ~4 kB


class ConfigError(InputError):
    """A configuration problem; the message names the file and key."""


def _meta(help: str, *, min: float | None = None, positive: bool = False, choices: tuple | None = None) -> dict:
    return {"help": help, "min": min, "positive": positive, "choices": choices}


@dataclass
class DeviceConfig:
    spec: str = field(default="serial:///dev/gravcal-logger?baudrate=460800",
                      metadata=_meta("driver spec: serial:///dev/..., can://..., i2c://BUS/ADDR (see docs/protocol.md)"))
    fs_hz: float = field(default=200.0, metadata=_meta("nominal sample rate [Hz]", positive=True))
    read_block: int = field(default=256, metadata=_meta("max samples per driver read", positive=True))
    read_timeout_s: float = field(default=0.1, metadata=_meta("driver read timeout [s]", positive=True))
    latency_budget_s: float = field(default=0.0, metadata=_meta(
        "longest a sample may wait in the driver so that later ones are published with it [s] (0: each sample as "
        "soon as it arrives; e.g. 0.005 at 800 Hz wakes once per 4 samples); I2C sets its FIFO watermark from it",
        min=0.0))
    ring_capacity: int = field(default=65536, metadata=_meta("ring buffer between acquisition and processing [samples]", positive=True))


@dataclass
class EstimatorConfig:
    model: str = field(default="6", metadata=_meta("model order", choices=tuple(ORDER_LADDER)))
    min_windows: int = field(default=6, metadata=_meta("windows before a calibration may be accepted (the first batch fit also waits for 2 per parameter)", min=0))
    process_noise: float = field(default=0.0, metadata=_meta("random-walk variance of each offset per second of sensor time added to P [raw²/s]; sensitivities walk 1/16 of it, extended-term coefficients not at all (0: none; a drifting sensor: 3e-12 to 1e-11, measured by bench/bench_soak.py)", min=0.0))
    extended_terms: str = field(default=DEFAULT_ONLINE_TERMS, metadata=_meta(
        f"extended terms the online estimator may add to orders >= 6, comma-separated ({', '.join(ONLINE_TERMS)}; "
        "\"\" for none); each is used only when the windows can test it (its covariate channel with a spread), "
        "determine it and the evidence warrants it"))


@dataclass
class DetectorConfig:
    method: str = field(default="lotters", metadata=_meta("quasi-static detector", choices=("lotters", "variance")))
    threshold_g: float = field(default=0.02, metadata=_meta("detection threshold [g] (also sets each sample's 'static' flag)", positive=True))
    hp_hz: float = field(default=0.5, metadata=_meta("high-pass corner of the detection signal [Hz] (lotters)", positive=True))
    lp_hz: float = field(default=0.5, metadata=_meta("low-pass corner of the detection signal [Hz] (lotters)", positive=True))
    window_s: float = field(default=1.0, metadata=_meta("moving-variance window [s] (variance)", positive=True))
    min_duration_s: float = field(default=1.0, metadata=_meta("shortest quasi-static window [s]", positive=True))
    max_duration_s: float = field(default=10.0, metadata=_meta("longest window before it is cut [s]", positive=True))


@dataclass
class GyroConfig:
    zero_counts: float = field(default=math.nan, metadata=_meta("gyro output at rest [ADC counts] (nan: uncalibrated, gyro null)"))
    counts_per_rad_s: float = field(default=math.nan, metadata=_meta("gyro scale [ADC counts per rad/s] (nan: uncalibrated)"))


@dataclass
class SocketConfig:
    path: str = field(default="/run/gravcal.sock", metadata=_meta("Unix socket path (when not socket-activated)"))
    mode: int = field(default=0o660, metadata=_meta("permission bits of a socket the daemon binds itself (e.g. 0o660)", min=0))
    group: str = field(default="", metadata=_meta("group owning a socket the daemon binds itself (with mode 0o660: only its members connect; \"\": unchanged)"))
    activation_name: str = field(default="gravcal", metadata=_meta("FileDescriptorName= of the activated socket"))
    max_clients: int = field(default=64, metadata=_meta("clients served at once", positive=True))
    queue_messages: int = field(default=4096, metadata=_meta("per-client queue [messages]; a slow client loses the oldest", positive=True))
    stall_timeout_s: float = field(default=10.0, metadata=_meta("disconnect a client that reads nothing for this long with output pending [s]", positive=True))
    queue_bytes: int = field(default=8 << 20, metadata=_meta("per-client queue [bytes]; a slow client loses the oldest (max_clients x queue_bytes bounds the queued memory)", positive=True))
    idle_timeout_s: float = field(default=60.0, metadata=_meta("disconnect a client that is not watching and sends no request for this long [s]", positive=True))
    request_rate_hz: float = field(default=50.0, metadata=_meta("requests per client and second; more are refused with an ERROR and the client's reading paused", positive=True))
    request_burst: int = field(default=100, metadata=_meta("requests a client may send at once before request_rate_hz applies", positive=True))
    flood_timeout_s: float = field(default=10.0, metadata=_meta("disconnect a client that stays over its request rate for this long [s]", positive=True))
    status_cache_s: float = field(default=0.2, metadata=_meta("?STATUS answers are built at most this often [s]", min=0.0))
    max_request_bytes: int = field(default=1024, metadata=_meta("longest request line [bytes]", positive=True))


@dataclass
class StateConfig:
    directory: str = field(default="/var/lib/gravcal", metadata=_meta("state directory (systemd: StateDirectory=gravcal)"))
    save_interval_s: float = field(default=60.0, metadata=_meta("at most one state write per this many seconds", min=0.0))
    lab_calibration: str = field(default="", metadata=_meta("calibration JSON used as the start when there is no saved state"))


@dataclass
class DaemonConfig:
    log_level: str = field(default="info", metadata=_meta("log level", choices=("debug", "info", "warning", "error")))
    status_interval_s: float = field(default=5.0, metadata=_meta("STATUS= text update period for systemd [s]", positive=True))
    user: str = field(default="", metadata=_meta("started as root: the user to become once the device and socket are open (\"\": none)"))
    group: str = field(default="", metadata=_meta("... and its group (\"\": the user's own); the user's other groups (dialout, i2c) are kept"))
    allow_root: bool = field(default=False, metadata=_meta("started as root without a user: run as root anyway (otherwise the start is refused)"))


@dataclass
class Config:
    device: DeviceConfig = field(default_factory=DeviceConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    gyro: GyroConfig = field(default_factory=GyroConfig)
    socket: SocketConfig = field(default_factory=SocketConfig)
    state: StateConfig = field(default_factory=StateConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    source: str = field(default="(defaults)", compare=False)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in fields(self) if f.name != "source"}


SECTIONS: dict[str, type] = {name: hint for name, hint in get_type_hints(Config).items() if name != "source"}


def _describe(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return repr(value)


def _check_value(source: str, section: str, key: str, typ: type, meta: dict, value: Any) -> Any:
    where = f"{source}: [{section}] {key}"
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {_describe(value)}")
        value = float(value)
    elif typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {_describe(value)}")
    elif typ is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {_describe(value)}")
    elif typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {_describe(value)}")
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where}: expected one of {', '.join(map(repr, meta['choices']))}, got {_describe(value)}")
    if isinstance(value, float) and math.isnan(value) and not math.isnan(getattr(getattr(_DEFAULTS, section), key)):
        raise ConfigError(f"{where}: expected a number, got nan")
    if meta.get("positive") and not value > 0:
        raise ConfigError(f"{where}: expected a positive number, got {_describe(value)}")
    if meta.get("min") is not None and value < meta["min"]:
        raise ConfigError(f"{where}: expected a number >= {meta['min']}, got {_describe(value)}")
    return value


_DEFAULTS = Config()


def _apply(cfg: Config, source: str, section: str, key: str, value: Any) -> None:
    if section not in SECTIONS:
        raise ConfigError(f"{source}: unknown section [{section}]; known sections: {', '.join(SECTIONS)}")
    cls = SECTIONS[section]
    hints = get_type_hints(cls)
    by_name = {f.name: f for f in fields(cls)}
    if key not in by_name:
        raise ConfigError(f"{source}: [{section}] unknown key {key!r}; known keys: {', '.join(by_name)}")
    value = _check_value(source, section, key, hints[key], dict(by_name[key].metadata), value)
    setattr(getattr(cfg, section), key, value)




def _validate_whole(cfg: Config, source: str) -> None:
    terms = [t.strip() for t in cfg.estimator.extended_terms.split(",") if t.strip()]
    bad = [t for t in terms if t not in ONLINE_TERMS]
    if bad:
        offline = [t for t in bad if t in CALIBRATION_TERMS]
        kind = "offline-only term(s) (they need the window history)" if offline == bad else "unknown term(s)"
        raise ConfigError(f"{source}: [estimator] extended_terms: {kind} {', '.join(map(repr, bad))}; "
                          f"expected a comma-separated list of {', '.join(ONLINE_TERMS)} (or \"\" for none)")
    d = cfg.detector
    if d.max_duration_s < d.min_duration_s:
        raise ConfigError(
            f"{source}: [detector] max_duration_s: must be >= min_duration_s ({d.min_duration_s:g}), got {d.max_duration_s:g}"
        )


def parse_config(data: dict[str, Any], source: str, base: Config | None = None) -> Config:
    """A Config from a parsed TOML table (``source`` names it in errors)."""
    cfg = dataclasses.replace(base) if base is not None else Config()
    if base is not None:  # deep copy of the sections
        for name in SECTIONS:
            setattr(cfg, name, dataclasses.replace(getattr(base, name)))
    for section, table in data.items():
        if section not in SECTIONS and not isinstance(table, dict):
            raise ConfigError(f"{source}: key {section!r} outside any section; keys belong in a [section] "
                              f"({', '.join(SECTIONS)})")
        if section not in SECTIONS:
            raise ConfigError(f"{source}: unknown section [{section}]; known sections: {', '.join(SECTIONS)}")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: {section}: expected a table [{section}], got {_describe(table)}")
        for key, value in table.items():
            _apply(cfg, source, section, key, value)
    _validate_whole(cfg, source)
    cfg.source = source
    return cfg


def load_config(path: str | os.PathLike | None = None, overrides: dict[str, Any] | None = None, *,
                required: bool | None = None) -> Config:
    """Defaults <- TOML file at ``path`` <- ``overrides`` {"section.key": value}.

    A missing file is an error when ``required`` (default: whenever a path is given);
    with path=None nothing is read.
    """
    cfg = Config()
    if path is not None:
        path = os.fspath(path)
        required = True if required is None else required
        try:
            with open(path, "rb") as fh:
                raw = fh.read(MAX_CONFIG_BYTES + 1)
            check_bounds(raw, max_bytes=MAX_CONFIG_BYTES, syntax="toml")  # tomllib recurses per nesting level
            data = tomllib.loads(raw.decode("utf-8"))
        except FileNotFoundError:
            if required:
                raise ConfigError(f"{path}: no such configuration file") from None
            data = None
        except PermissionError:
            raise ConfigError(f"{path}: permission denied reading the configuration") from None
        except IsADirectoryError:
            raise ConfigError(f"{path}: is a directory, expected a TOML file") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: {exc}") from None
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: not UTF-8 ({exc.reason})") from None
        except JSONInputError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        if data is not None:
            cfg = parse_config(data, path)
    if overrides:
        for dotted, value in overrides.items():
            if value is None:
                continue
            section, _, key = dotted.partition(".")
            if not key:
                raise ConfigError(f"command line: override {dotted!r} must be section.key")
            _apply(cfg, "command line", section, key, value)
        _validate_whole(cfg, "command line")
    return cfg


def example_toml(cfg: Config | None = None) -> str:
    """A TOML text with every key, its default and its help (for docs and --print-config)."""
    cfg = cfg or Config()
    lines = []
    for section, cls in SECTIONS.items():
        lines.append(f"[{section}]")
        for f in fields(cls):
            value = getattr(getattr(cfg, section), f.name)
            lines.append(f"# {f.metadata['help']}")
            lines.append(f"{f.name} = {_toml_value(value, f.name)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any, name: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else repr(value)
    if isinstance(value, int):
        return oct(value) if name == "mode" else str(value)
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'
