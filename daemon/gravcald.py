"""gravcald: the in-use calibration service.

Wiring (each arrow a hand-off that never blocks the side before it)::

    driver.read() --[acquisition thread]--> RingBuffer --[processing thread]-->
        quasi-static detector -> recursive estimator -> correction (K^-1 (raw - o)) ->
        SocketServer.publish()  --[server thread]--> clients
                                 \\-> RateLimitedSaver --[saver thread]--> state.json

The acquisition thread only reads the driver and pushes into the ring buffer (which
overwrites the oldest samples, counted, if processing ever falls behind). Clients are
served by the server thread; the state is written by the saver thread. The main thread
handles signals (SIGTERM/SIGINT: clean stop with the state saved; SIGHUP: reload the
configuration), feeds the systemd watchdog only while samples flow, and updates STATUS=.

Calibration life cycle: a saved state resumes the recursive estimator where it stopped
(parameters and covariance). Without one, the start is the lab calibration (if configured)
or the ADXL210 datasheet values; the first ``min_windows`` quasi-static windows are then
fitted in batch (LottersBatch) before the recursion takes over, so a wrong start does not
have to be within the linearisation's reach. A calibration is *accepted* -- used for the
published samples and saved -- when it converged, is observable and rests on at least
``min_windows`` windows.

Entry point: ``gravcal.daemon.gravcald:main`` (console script ``gravcald``).
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Sequence

import numpy as np

from ..core.calibration import Calibration
from ..core.ringbuffer import RingBuffer
from ..core.samples import SAMPLE_DTYPE, raw_triad
from ..core.windows import Window, WindowSet
from . import config as config_mod
from .config import Config, ConfigError
from .persistence import CalibrationState, RateLimitedSaver, StateStore, load_lab_calibration
from .protocol import STANDARD_GRAVITY, calib_message
from .sdnotify import Notifier, WatchdogPolicy, watchdog_interval
from .server import ServerConfig, SocketPathError, SocketServer, activated_socket

log = logging.getLogger("gravcal.gravcald")

# ADXL210 datasheet: 50 % duty cycle at 0 g, 12.5 % per g (the T1/T2 output, see core/samples.py).
NOMINAL_OFFSET = 0.5
NOMINAL_SENSITIVITY = 0.125

MAX_BOOTSTRAP_WINDOWS = 200  # windows kept for the initial batch fit (oldest dropped)

# Settings that only take effect at start (SIGHUP says so instead of half-applying them).
RESTART_KEYS = {
    "device": ("spec", "fs_hz", "ring_capacity"),
    "estimator": ("model",),
    "socket": ("path", "mode", "activation_name"),
    "state": ("directory", "lab_calibration"),
}


def nominal_calibration(model: str = "6") -> Calibration:
    cal = Calibration.nominal(np.full(3, NOMINAL_OFFSET), NOMINAL_SENSITIVITY, model=model)
    cal.converged = False
    cal.observable = False
    return cal


# -- processing (numerics only; runs in the processing thread) -------------------------


class Processor:
    """Detector -> estimator -> correction for one stream of sample blocks.

    ``detector`` and the estimators are built from gravcal.core lazily (they are separate
    modules); tests may pass their own ``detector``.
    """

    def __init__(self, cfg: Config, start: CalibrationState, *, resumed: bool, detector: Any = None):
        self.cfg = cfg
        self.state = start
        self.start = start.calibration  # the batch fit's starting point
        self.applied = start.calibration  # what corrects the published samples until an update is accepted
        self.windows_base = int(start.calibration.n_windows) if resumed else 0
        self._pending: list[Window] = []  # windows collected for the initial batch fit
        self.estimator: Any = None
        if resumed:
            self.estimator = self._recursive(start.calibration)
        self.detector = detector if detector is not None else self._make_detector()
        self.detector.to_g = self.applied
        self.windows_seen = 0
        self.windows_rejected = 0
        self.changed = False

    # construction -------------------------------------------------------------------
    def _make_detector(self) -> Any:
        from ..core.detectors import MovingVarianceDetector, QuasiStaticDetector

        d, fs = self.cfg.detector, self.cfg.device.fs_hz
        if d.method == "variance":
            return MovingVarianceDetector(fs, window_s=d.window_s, threshold_g=d.threshold_g,
                                          min_duration_s=d.min_duration_s, max_duration_s=d.max_duration_s)
        return QuasiStaticDetector(fs, hp_hz=d.hp_hz, lp_hz=d.lp_hz, threshold_g=d.threshold_g,
                                   min_duration_s=d.min_duration_s, max_duration_s=d.max_duration_s)

    def _recursive(self, start: Calibration) -> Any:
        from ..core.estimators.lotters import LottersRecursive

        q = self.cfg.estimator.process_noise
        return LottersRecursive(start, model=self.cfg.estimator.model, process_noise=q if q > 0 else None)

    def reconfigure(self, cfg: Config) -> None:
        """Live changes (SIGHUP): detector settings rebuild the detector."""
        old = self.cfg
        self.cfg = cfg
        if cfg.detector != old.detector:
            self.detector = self._make_detector()
            self.detector.to_g = self.applied

    # per block ------------------------------------------------------------------------
    def process(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(acc [m/s²] (N, 3), gyro [rad/s] (N,), static (N,) bool) for a sample block;
        sets ``self.changed`` when the calibration state changed."""
        raw = raw_triad(block)
        acc = self.applied.apply(raw) * STANDARD_GRAVITY  # corrected with the accepted calibration
        g = self.cfg.gyro
        gyro = (block["gyro"].astype(float) - g.zero_counts) / g.counts_per_rad_s  # NaN when not configured
        windows = self.detector.update(block["t"], raw, block["temp"].astype(float)[:, None])
        det = getattr(self.detector, "last_detection", None)
        if det is not None and det.shape[0] == block.shape[0]:
            static = det < self.detector.threshold_g
        else:
            static = np.zeros(block.shape[0], dtype=bool)
        self.changed = False
        for w in windows:
            self._window(w)
        return acc, gyro, static

    def _window(self, w: Window) -> None:
        self.windows_seen += 1
        cfg = self.cfg.estimator
        if self.estimator is None:
            cal = self._initial_fit(w)
            if cal is None:
                return
        else:
            before = self.estimator.n_rejected
            cal = self.estimator.update(w)
            if self.estimator.n_rejected > before:
                self.windows_rejected += 1
                return
            cal.n_windows = self.windows_base + self.estimator.n_updates
        accepted = bool(cal.converged and cal.observable and cal.n_windows >= cfg.min_windows)
        self.state = CalibrationState(cal, self.state.revision + 1, time.time(), accepted, dict(self.state.extra))
        if accepted:
            self.applied = cal
            self.detector.to_g = cal
        self.changed = True

    def _initial_fit(self, w: Window) -> Calibration | None:
        """Batch fit (eq. 11a) over the windows so far; the recursion takes over once it is
        converged and observable. Until then the candidate is published, not applied."""
        from ..core.estimators.lotters import LottersBatch

        need = max(self.cfg.estimator.min_windows, 1)
        self._pending.append(w)
        del self._pending[: -MAX_BOOTSTRAP_WINDOWS]
        if len(self._pending) < need:
            return None
        try:
            cal = LottersBatch(self.cfg.estimator.model).fit(WindowSet.from_windows(self._pending), start=self.start)
        except ValueError as exc:  # e.g. too few distinct orientations yet
            log.debug("initial batch fit not possible yet: %s", exc)
            return None
        if cal.converged and cal.observable:
            self.windows_base = cal.n_windows
            self._pending = []
            self.estimator = self._recursive(cal)
        return cal


# -- the service -------------------------------------------------------------------------


class Gravcald:
    """The running service. ``driver`` (tests) replaces opening ``cfg.device.spec``."""

    def __init__(self, cfg: Config, *, driver: Any = None, notifier: Notifier | None = None,
                 environ: dict[str, str] | None = None, detector: Any = None, config_path: str | None = None,
                 overrides: dict[str, Any] | None = None):
        self.cfg = cfg
        self.config_path = config_path
        self.overrides = overrides or {}
        self.environ = os.environ if environ is None else environ
        self.notifier = notifier or Notifier(self.environ)
        self.watchdog = WatchdogPolicy(self.notifier, watchdog_interval(self.environ))
        self._driver = driver
        self._detector = detector
        self.ring = RingBuffer(cfg.device.ring_capacity, SAMPLE_DTYPE)
        self.store = StateStore(cfg.state.directory)
        self.saver: RateLimitedSaver | None = None
        self.server: SocketServer | None = None
        self.processor: Processor | None = None
        self.notes: list[str] = []
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._data = threading.Event()
        self._acq_stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.samples_in = 0
        self.read_errors = 0
        self.exit_code = 0
        self._rate_hz = 0.0
        self._rate_mark = (time.monotonic(), 0)

    # -- start ---------------------------------------------------------------------------
    def _initial_state(self) -> tuple[CalibrationState, bool]:
        self.store.ensure_directory()
        loaded = self.store.load()
        self.notes += loaded.notes
        for note in loaded.notes:
            log.info("%s", note)
        model = self.cfg.estimator.model
        if loaded.state is not None:
            if loaded.state.model == model:
                return loaded.state, True
            note = (f"saved calibration has model {loaded.state.model!r}, configuration asks for {model!r}: "
                    f"using its values as the start, estimation restarts")
            log.warning("%s", note)
            self.notes.append(note)
            return CalibrationState(loaded.state.calibration, loaded.state.revision, loaded.state.updated, False), False
        if self.cfg.state.lab_calibration:
            cal = load_lab_calibration(self.cfg.state.lab_calibration)
            note = f"starting from lab calibration {self.cfg.state.lab_calibration} (model {cal.model})"
            log.info("%s", note)
            self.notes.append(note)
            return CalibrationState(cal, 0, None, False, {"source": self.cfg.state.lab_calibration}), False
        self.notes.append("starting from ADXL210 datasheet values (no saved state, no lab calibration)")
        return CalibrationState(nominal_calibration(model), 0, None, False, {"source": "datasheet"}), False

    def _open_server(self) -> SocketServer:
        s = self.cfg.socket
        scfg = ServerConfig(max_clients=s.max_clients, queue_messages=s.queue_messages,
                            stall_timeout_s=s.stall_timeout_s, max_request_bytes=s.max_request_bytes)
        sock = activated_socket(s.activation_name, environ=self.environ)
        if sock is not None:
            log.info("using the socket passed by systemd (%s)", s.activation_name)
            return SocketServer(sock=sock, config=scfg, status_provider=self.status)
        return SocketServer(s.path, config=scfg, socket_mode=s.mode, status_provider=self.status)

    def _open_driver(self) -> Any:
        if self._driver is not None:
            return self._driver
        from ..drivers.base import open_driver  # lazy: the drivers are a separate layer

        return open_driver(self.cfg.device.spec)  # opened; DriverError names a missing device / group

    def start(self) -> None:
        self.server = self._open_server()  # first: a socket in use fails fast, before any numerics load
        state, resumed = self._initial_state()
        self.processor = Processor(self.cfg, state, resumed=resumed, detector=self._detector)
        self.saver = RateLimitedSaver(self.store, self.cfg.state.save_interval_s)
        self.server.start()
        self.server.set_calibration(self._calib_message())
        self.driver = self._open_driver()
        for name, target in (("gravcal-acquisition", self._acquire), ("gravcal-processing", self._process)):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        where = self.server.address if isinstance(self.server.address, str) else repr(self.server.address)
        self.notifier.ready(f"reading {self.cfg.device.spec}, serving {where}")
        log.info("gravcald ready: device %s, socket %s, state %s", self.cfg.device.spec, where, self.store.path)

    def _calib_message(self) -> dict[str, Any]:
        st = self.processor.state
        return calib_message(st.calibration, revision=st.revision, updated=st.updated, accepted=st.accepted,
                             extra={"applied_revision": st.revision if st.accepted else None})

    # -- threads -------------------------------------------------------------------------
    def _acquire(self) -> None:
        """Read the driver into the ring buffer. Nothing else: no clients, no disk."""
        d = self.cfg.device
        backoff = 0.05
        while not self._acq_stop.is_set():
            try:
                block = self.driver.read(max_samples=d.read_block, timeout=d.read_timeout_s)
            except Exception as exc:  # the driver should absorb bus errors; survive anything else
                self.read_errors += 1
                log.error("driver read failed: %s", exc)
                self._acq_stop.wait(backoff)
                backoff = min(backoff * 2, 2.0)
                continue
            backoff = 0.05
            n = block.shape[0]
            if n:
                self.ring.push(block)
                self.samples_in += n
                self.watchdog.samples_arrived(n)
                self._data.set()

    def _process(self) -> None:
        p = self.processor
        while True:
            self._data.wait(0.2)
            self._data.clear()
            block = self.ring.pop()
            if block.shape[0]:
                try:
                    acc, gyro, static = p.process(block)
                except Exception:  # a numerics bug must not take the service down silently
                    log.exception("processing a block of %d samples failed", block.shape[0])
                    continue
                self.server.publish(block, acc, gyro, static)
                if p.changed:
                    self.server.set_calibration(self._calib_message())
                    if p.state.accepted:
                        self.saver.offer(p.state)
            elif self._stop.is_set() and not any(t.is_alive() for t in self._threads[:1]):
                return

    # -- status --------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """?STATUS payload (called from the server thread)."""
        p = self.processor
        drv_stats: dict[str, Any] = {}
        try:
            drv_stats = dict(self.driver.stats()) if getattr(self, "driver", None) is not None else {}
        except Exception as exc:
            drv_stats = {"error": str(exc)}
        det_stats: dict[str, Any] = {}
        try:
            det_stats = dict(p.detector.stats()) if hasattr(p.detector, "stats") else {}
        except Exception as exc:
            det_stats = {"error": str(exc)}
        st = p.state
        return {
            "device": {"spec": self.cfg.device.spec, "rate_hz": round(self._rate_hz, 2), "samples": self.samples_in,
                       "read_errors": self.read_errors, **drv_stats},
            "ring": self.ring.stats(),
            "detector": {"method": self.cfg.detector.method, "windows": p.windows_seen, **det_stats},
            "calibration": {"model": st.model, "revision": st.revision, "accepted": st.accepted,
                            "n_windows": st.calibration.n_windows, "rejected_windows": p.windows_rejected,
                            "updated": st.updated},
            "state": {"path": self.store.path, "saves": self.saver.saves if self.saver else 0,
                      "save_failures": self.saver.failures if self.saver else 0,
                      "last_error": self.saver.last_error if self.saver else None},
            "watchdog": {"interval_s": self.watchdog.interval_s, "feeds": self.watchdog.feeds,
                         "withheld": self.watchdog.withheld},
            "notes": list(self.notes),
        }

    def _status_text(self) -> str:
        st = self.processor.state
        return (f"{self._rate_hz:.1f} samples/s, calibration rev {st.revision} "
                f"({'accepted' if st.accepted else 'not accepted'}, {st.calibration.n_windows} windows), "
                f"{self.server.n_clients} clients")

    # -- main loop -------------------------------------------------------------------------
    def request_stop(self, *_: Any) -> None:
        self._stop.set()

    def request_reload(self, *_: Any) -> None:
        self._reload.set()

    def run(self) -> int:
        """Main-thread loop until stop; returns the exit code."""
        period = 0.5 if self.watchdog.period_s is None else min(0.5, self.watchdog.period_s / 4)
        next_status = 0.0
        while not self._stop.wait(period):
            self.watchdog.tick()
            now = time.monotonic()
            t0, n0 = self._rate_mark
            if now - t0 >= 1.0:
                self._rate_hz = (self.samples_in - n0) / (now - t0)
                self._rate_mark = (now, self.samples_in)
            if now >= next_status:
                self.notifier.status(self._status_text())
                next_status = now + self.cfg.daemon.status_interval_s
            if self._reload.is_set():
                self._reload.clear()
                self.reload()
            dead = [t.name for t in self._threads if not t.is_alive()]
            if dead or not self.server.alive:
                log.error("internal thread stopped (%s); exiting so the service manager restarts us",
                          ", ".join(dead) or "server")
                self.exit_code = 1
                break
        self.shutdown()
        return self.exit_code

    def reload(self) -> None:
        """SIGHUP: re-read the configuration file; keep the old one if it is bad."""
        self.notifier.reloading()
        try:
            new = config_mod.load_config(self.config_path, self.overrides, required=False) if self.config_path \
                else config_mod.load_config(None, self.overrides)
        except ConfigError as exc:
            log.error("reload: %s; keeping the running configuration", exc)
            self.notifier.ready(f"reload failed: {exc}")
            return
        old = self.cfg
        for section, keys in RESTART_KEYS.items():
            for key in keys:
                if getattr(getattr(old, section), key) != getattr(getattr(new, section), key):
                    log.warning("reload: [%s] %s changed; it takes effect after a restart", section, key)
                    setattr(getattr(new, section), key, getattr(getattr(old, section), key))
        logging.getLogger("gravcal").setLevel(new.daemon.log_level.upper())
        self.saver.min_interval_s = new.state.save_interval_s
        s = new.socket
        self.server.config.max_clients = s.max_clients
        self.server.config.queue_messages = s.queue_messages
        self.server.config.stall_timeout_s = s.stall_timeout_s
        self.server.config.max_request_bytes = s.max_request_bytes
        self.processor.reconfigure(new)  # the processing thread reads it at the next block
        self.cfg = new
        log.info("configuration reloaded from %s", self.config_path or "(defaults and command line)")
        self.notifier.ready(self._status_text())

    def shutdown(self) -> None:
        """Stop acquisition, drain processing, save the state, close clients and the socket."""
        self.notifier.stopping("stopping: saving the calibration")
        self._stop.set()
        self._acq_stop.set()
        if self._threads:
            self._threads[0].join(5.0)
        try:
            if getattr(self, "driver", None) is not None:
                self.driver.close()
        except Exception as exc:
            log.warning("closing the driver: %s", exc)
        self._data.set()
        for t in self._threads[1:]:
            t.join(5.0)
        if self.saver is not None:
            if self.processor is not None and self.processor.state.accepted:
                self.saver.offer(self.processor.state)
            if not self.saver.close(10.0):
                log.error("final state save failed: %s", self.saver.last_error)
                self.exit_code = self.exit_code or 1
        if self.server is not None:
            self.server.stop()
        log.info("gravcald stopped")


# -- command line ---------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gravcald", description="gravcal in-use calibration daemon (serves calibrated IMU samples on a Unix socket).")
    p.add_argument("--config", metavar="FILE", help=f"TOML configuration (default: {config_mod.DEFAULT_CONFIG_PATH} if it exists)")
    p.add_argument("--device", metavar="SPEC", help="driver spec, e.g. serial:///dev/ttyUSB0?baudrate=460800")
    p.add_argument("--fs", metavar="HZ", type=float, help="nominal sample rate [Hz]")
    p.add_argument("--model", choices=("offsets", "6", "9", "12"), help="calibration model order")
    p.add_argument("--socket", metavar="PATH", help="socket path when not socket-activated")
    p.add_argument("--state-dir", metavar="DIR", help="state directory")
    p.add_argument("--lab-calibration", metavar="FILE", help="start from this calibration JSON when there is no saved state")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"))
    p.add_argument("--print-config", action="store_true", help="print the effective configuration as TOML and exit")
    return p


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "device.spec": args.device,
        "device.fs_hz": args.fs,
        "estimator.model": args.model,
        "socket.path": args.socket,
        "state.directory": args.state_dir,
        "state.lab_calibration": args.lab_calibration,
        "daemon.log_level": args.log_level,
    }


def default_config_path(environ: dict[str, str] | os._Environ) -> str:
    conf_dir = environ.get("CONFIGURATION_DIRECTORY")  # set by ConfigurationDirectory=
    return os.path.join(conf_dir.split(":")[0], "gravcald.toml") if conf_dir else config_mod.DEFAULT_CONFIG_PATH


def _setup_logging(level: str, environ: Any) -> None:
    under_journal = bool(environ.get("JOURNAL_STREAM") or environ.get("INVOCATION_ID"))
    fmt = "%(levelname)s %(name)s: %(message)s" if under_journal else "%(asctime)s gravcald %(levelname)s %(name)s: %(message)s"
    logging.basicConfig(stream=sys.stderr, format=fmt, force=True)
    logging.getLogger("gravcal").setLevel(level.upper())


def main(argv: Sequence[str] | None = None, *, driver: Any = None, environ: dict[str, str] | None = None) -> int:
    """``gravcald`` entry point. Exit status: 0 clean stop, 1 runtime failure, 2 bad
    configuration or arguments (one line on stderr)."""
    env = os.environ if environ is None else environ
    args = build_parser().parse_args(argv)
    overrides = overrides_from_args(args)
    config_path = args.config
    try:
        if config_path is None:
            candidate = default_config_path(env)
            cfg = config_mod.load_config(candidate if os.path.exists(candidate) else None, overrides)
            config_path = candidate if os.path.exists(candidate) else None
        else:
            cfg = config_mod.load_config(config_path, overrides)
    except ConfigError as exc:
        print(f"gravcald: error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print(config_mod.example_toml(cfg))
        return 0
    _setup_logging(cfg.daemon.log_level, env)
    daemon = Gravcald(cfg, driver=driver, environ=env, config_path=config_path, overrides=overrides)
    signal.signal(signal.SIGTERM, daemon.request_stop)
    signal.signal(signal.SIGINT, daemon.request_stop)
    signal.signal(signal.SIGHUP, daemon.request_reload)
    try:
        daemon.start()
    except (ConfigError, ValueError, SocketPathError) as exc:
        daemon.shutdown()
        print(f"gravcald: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except Exception as exc:  # e.g. DriverError: the device is missing; systemd restarts us
        daemon.shutdown()
        print(f"gravcald: error: {type(exc).__name__}: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    return daemon.run()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
