"""gravcald's service: acquisition, processing and serving threads, signals, watchdog, reload, shutdown.

Wiring (each arrow a hand-off that never blocks the side before it)::

    driver.read() --[acquisition thread]--> correction (Processor.correct) --> SocketServer.publish()
         |                                                          --[server thread]--> clients
         \\--> RingBuffer --[processing thread, every ANALYSIS_BLOCK_S of data]--> Processor.analyse:
                 quasi-static detector -> OnlineCalibrator.feed -> accepted calibration (used by the correction)
                 -> CALIB push, RateLimitedSaver --[saver thread]--> state.json

The acquisition thread reads the driver, corrects each block with the accepted calibration and
publishes it at once (publish() never blocks), then pushes it into the ring buffer for the analysis
(which overwrites the oldest samples, counted, if the analysis ever falls behind; clients have them
already). The main thread handles signals (SIGTERM/SIGINT: clean stop with the state saved; SIGHUP:
reload the configuration), feeds the systemd watchdog only while samples flow, and updates STATUS=.
docs/daemon.md describes running it.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
import time
from typing import Any

import numpy as np

from ..core.calibration import Calibration
from ..core.estimators.online_policy import online_candidates
from ..core.ringbuffer import RingBuffer
from ..core.samples import SAMPLE_DTYPE
from . import config as config_mod
from . import privileges
from .config import Config, ConfigError
from .emulation import EmulatedBus
from .fastpath import FastPath
from .persistence import CalibrationState, RateLimitedSaver, StateStore, load_lab_calibration
from .processing import Processor, nominal_calibration
from .protocol import calib_message
from .sdnotify import Notifier, WatchdogPolicy, watchdog_interval
from .wakeup import SelfPipeWake
from .server import ServerConfig, SocketServer
from .socket_activation import activated_socket

log = logging.getLogger("gravcal.gravcald")

REOPEN_AFTER_READ_ERRORS = 3  # a driver whose read() keeps raising is closed and reopened
# samples collected before the detector and estimator run [s of data]: their per-call overhead (~0.2 ms)
# is paid this often; the published `static` is this much (plus the analysis time) older than the sample
ANALYSIS_BLOCK_S = 0.25
MAIN_PERIOD_S = 1.0  # the main thread's housekeeping (rate estimate, status text, thread check) at most this often

# Settings that only take effect at start (SIGHUP says so instead of half-applying them).
RESTART_KEYS = {
    "device": ("spec", "fs_hz", "ring_capacity", "latency_budget_s"),
    "estimator": ("model", "extended_terms"),
    "socket": ("path", "mode", "group", "activation_name"),
    "state": ("directory", "lab_calibration"),
    "daemon": ("user", "group", "allow_root"),
}


class Gravcald:
    """The running service. ``driver`` (tests) replaces opening ``cfg.device.spec``."""

    def __init__(self, cfg: Config, *, driver: Any = None, notifier: Notifier | None = None,
                 environ: dict[str, str] | None = None, detector: Any = None, config_path: str | None = None,
                 overrides: dict[str, Any] | None = None, emulator: EmulatedBus | None = None,
                 window_sink: Any = None, identity: Any = None):
        self.cfg = cfg
        self.identity = identity  # privileges.Identity to become once the device and socket are open
        self.window_sink = window_sink  # each window fed to the calibrator (daemon/window_log.py)
        self.emulator = emulator
        self.config_path = config_path
        self.overrides = overrides or {}
        self.environ = os.environ if environ is None else environ
        self.notifier = notifier or Notifier(self.environ)
        self.watchdog = WatchdogPolicy(self.notifier, watchdog_interval(self.environ))
        self._driver = driver
        self._detector = detector
        self._lab: Calibration | None = None  # the lab calibration, when the start is one
        self.ring = RingBuffer(cfg.device.ring_capacity, SAMPLE_DTYPE)
        self.store = StateStore(cfg.state.directory)
        self.saver: RateLimitedSaver | None = None
        self.server: SocketServer | None = None
        self.processor: Processor | None = None
        self.notes: list[str] = []
        self._stop = threading.Event()
        # stop and reload requests: flags and a self-pipe only, since signal handlers set them (wakeup.py)
        self._stop_requested = False
        self._reload_requested = False
        self._main_wake = SelfPipeWake()
        self._data = threading.Event()
        self._acq_stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._device_connected = True  # as last told to watchers (DEVICE)
        self.samples_in = 0
        self.read_errors = 0
        self.exit_code = 0
        self._rate_hz = 0.0
        self._rate_mark = (time.monotonic(), 0)
        self.reloads = 0  # successful SIGHUP reloads
        self.process_errors = 0  # sample blocks lost to an exception in the processing chain
        self.driver_reopens = 0  # reopened after REOPEN_AFTER_READ_ERRORS read exceptions in a row
        self.reload_error: str | None = None  # why the last reload was refused (None: it worked)
        self.fast_path = True  # the latency path's common case in C (daemon/fastpath.py); False: all in Python
        self._fast: FastPath | None = None

    # -- start ---------------------------------------------------------------------------
    def _initial_state(self) -> tuple[CalibrationState, bool]:
        self.store.check_directory()
        loaded = self.store.load()
        self.notes += loaded.notes
        for note in loaded.notes:
            log.info("%s", note)
        model = self.cfg.estimator.model
        if loaded.state is not None:
            # an order up to the configured one, with or without the allowed extended terms, resumes
            allowed = online_candidates(model, self.cfg.estimator.extended_terms)
            if loaded.state.model == model or (loaded.state.model in allowed and loaded.state.accepted):
                return loaded.state, True
            note = (f"saved calibration has model {loaded.state.model!r}, configuration asks for {model!r} "
                    f"(allowed online: {', '.join(allowed)}): using its values as the start, estimation restarts")
            log.warning("%s", note)
            self.notes.append(note)
            return CalibrationState(loaded.state.calibration, loaded.state.revision, loaded.state.updated, False), False
        if self.cfg.state.lab_calibration:
            cal = load_lab_calibration(self.cfg.state.lab_calibration)
            self._lab = cal
            note = f"starting from lab calibration {self.cfg.state.lab_calibration} (model {cal.model})"
            log.info("%s", note)
            self.notes.append(note)
            return CalibrationState(cal, 0, None, False, {"source": self.cfg.state.lab_calibration}), False
        self.notes.append("starting from ADXL210 datasheet values (no saved state, no lab calibration)")
        return CalibrationState(nominal_calibration(model), 0, None, False, {"source": "datasheet"}), False

    def _open_server(self) -> SocketServer:
        s = self.cfg.socket
        scfg = ServerConfig.from_section(s)
        sock = activated_socket(s.activation_name, environ=self.environ)
        if sock is not None:
            log.info("using the socket passed by systemd (%s)", s.activation_name)
            return SocketServer(sock=sock, config=scfg, status_provider=self.status)
        return SocketServer(s.path, config=scfg, socket_mode=s.mode, socket_group=s.group, status_provider=self.status)

    def _open_driver(self) -> Any:
        if self._driver is not None:
            return self._driver
        budget = self.cfg.device.latency_budget_s
        if self.emulator is not None:
            driver = self.emulator.open(latency_budget_s=budget)
            self.cfg.device.spec = self.overrides["device.spec"] = self.emulator.spec  # SIGHUP keeps it
            return driver
        from ..drivers.base import open_driver  # lazy: the drivers are a separate layer

        driver = open_driver(self.cfg.device.spec, open=False)
        driver.latency_budget_s = budget
        return driver.open()  # DriverError names a missing device / group

    def start(self) -> None:
        self.server = self._open_server()  # first: a socket in use fails fast, before any numerics load
        state, resumed = self._initial_state()
        self.processor = Processor(self.cfg, state, resumed=resumed, detector=self._detector, lab=self._lab,
                                   window_sink=self.window_sink)
        self.saver = RateLimitedSaver(self.store, self.cfg.state.save_interval_s)
        self.server.start()
        self.server.set_calibration(self._calib_message())
        self.driver = self._open_driver()
        if self.identity is not None:  # root until here: the device and socket are open
            self.store.ensure_directory()
            privileges.drop(self.identity, hand_over=[self.store.directory])
        self.processor.defer_corrections = True  # the acquisition thread takes them with their CALIB
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
                             extra={"applied_revision": self.processor.applied_revision,
                                    "gyro": self.processor.gyro_json, **self.processor.calib_extra()})

    # -- threads -------------------------------------------------------------------------
    def _acquire(self) -> None:
        """Read the driver; correct and publish each block at once (the latency path: the
        server's publish() never blocks); hand it to the processing thread through the ring
        buffer. Nothing here waits for clients, disk or the estimator."""
        d = self.cfg.device
        p = self.processor
        analysis_n = max(1, round(d.fs_hz * ANALYSIS_BLOCK_S))
        backoff, failures = 0.05, 0
        # samples for the analysis, as bytes until a block's worth: one ring-buffer write per
        # ANALYSIS_BLOCK_S instead of a structured-array copy per sample (the analysis runs no sooner)
        staged = bytearray()
        stage_bytes = analysis_n * SAMPLE_DTYPE.itemsize
        fast = self._fast = FastPath.for_driver(self.driver, p, self.server, max_frames=d.read_block,
                                                stage_bytes=stage_bytes) if self.fast_path else None
        while not self._acq_stop.is_set():
            if p.has_pending:
                self._take_calibration()
            if fast is not None:  # the common case in C, until a case it does not take (daemon/fastpath.py)
                try:
                    n, read_next = fast.run(staged)
                except Exception:  # a bug there must not stop acquisition: the Python path carries on
                    log.exception("the C step of the latency path failed; continuing without it")
                    fast, n, read_next = None, 0, True
                if n:
                    self.samples_in += n
                    self.watchdog.samples_arrived(n)
                if len(staged) >= stage_bytes or not (n or read_next):
                    self._stage_for_analysis(staged)
                if not read_next:
                    continue
            try:
                block = self.driver.read(max_samples=d.read_block, timeout=d.read_timeout_s)
            except Exception as exc:  # the driver should absorb bus errors; survive anything else
                self.read_errors += 1
                failures += 1
                log.error("driver read failed: %s", exc)
                if failures % REOPEN_AFTER_READ_ERRORS == 0:  # e.g. a parser stuck on a garbled line
                    self._reopen_driver()
                self._acq_stop.wait(backoff)
                backoff = min(backoff * 2, 2.0)
                continue
            backoff, failures = 0.05, 0
            n = block.shape[0]
            if not n:  # the bus went quiet (a stop, an unplug): the analysis gets what is staged now
                self._stage_for_analysis(staged)
                self._device_notice(self._driver_connected())
                continue
            if not self._device_connected:
                self._device_notice(True)
            self.samples_in += n
            self.watchdog.samples_arrived(n)
            try:
                acc, gyro, static = p.correct(block)
            except Exception:  # a numerics bug must not stop acquisition
                self.process_errors += 1
                log.exception("correcting a block of %d samples failed", n)
            else:
                self.server.publish(block, acc, gyro, static)
            staged += block.data  # its bytes (a driver's block is C-contiguous)
            if len(staged) >= stage_bytes:
                self._stage_for_analysis(staged)
        self._stage_for_analysis(staged)
        self._take_calibration()

    def _driver_connected(self) -> bool:
        try:
            return bool(self.driver.stats().get("connected", True))
        except Exception:  # a driver's counters must not stop acquisition
            return True

    def _device_notice(self, connected: bool) -> None:
        """Tell watchers when the device goes away and when it is back, before its next sample (gpsd's DEVICE
        push): meanwhile no IMU arrive, and a client can tell a lost bus from a hung daemon."""
        if connected != self._device_connected:
            self._device_connected = connected
            self.server.notify({"class": "DEVICE", "path": self.cfg.device.spec, "connected": connected})

    def _take_calibration(self) -> None:
        """Push a CALIB the analysis staged, then switch to the corrections it announces; in the acquisition
        thread while it runs, so every IMU line after a CALIB is corrected with it and none before."""
        message = self.processor.take_pending()
        if message is not None:
            self.server.set_calibration(message)

    def _stage_for_analysis(self, staged: bytearray) -> None:
        if staged:
            self.ring.push(np.frombuffer(bytes(staged), dtype=SAMPLE_DTYPE))
            staged.clear()
            self._data.set()

    def _reopen_driver(self) -> None:
        log.warning("%d driver read errors in a row: closing and reopening %s", REOPEN_AFTER_READ_ERRORS,
                    self.cfg.device.spec)
        self.driver_reopens += 1
        try:
            self.driver.close()
            self.driver.open()
        except Exception as exc:
            log.error("reopening the device failed: %s", exc)

    def _process(self) -> None:
        """The detector and the estimator, on every ANALYSIS_BLOCK_S of samples collected
        (their per-call overhead, ~0.2 ms, would otherwise be paid per sample at low rates).
        If this thread falls behind, the ring buffer drops the oldest samples from the
        analysis (counted); clients have them already."""
        while True:
            # woken by each staged block and by shutdown(): no polling in between (the timeout is only a guard)
            self._data.wait(2.0)
            self._data.clear()
            block = self.ring.pop()
            if block.shape[0]:
                self._analyse(block)
            elif self._stop.is_set() and not any(t.is_alive() for t in self._threads[:1]):
                self._take_calibration()  # one staged as the acquisition thread ended
                return

    def _analyse(self, block: np.ndarray) -> None:
        p = self.processor
        try:
            p.analyse(block)
        except Exception:
            self.process_errors += 1
            log.exception("analysing a block of %d samples failed", block.shape[0])
            return
        if p.changed:
            p.stage_message(self._calib_message())
            if not self._threads or not self._threads[0].is_alive():  # no acquisition thread left to take it
                self._take_calibration()
            if p.state.accepted:
                self.saver.offer(p.state)

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
                       "samples_in_c": self._fast.taken if self._fast is not None else 0,
                       "batches_without_gil": self._fast.nogil if self._fast is not None else 0,
                       "read_errors": self.read_errors, "reopens": self.driver_reopens, **drv_stats},
            "ring": self.ring.stats(),
            "processing": {"errors": self.process_errors, **self._lag()},
            "detector": {"method": self.cfg.detector.method, "threshold_g": self.cfg.detector.threshold_g,
                         "windows": p.policy.windows_seen, "screened": p.policy.windows_screened, **det_stats},
            "calibration": {"model": st.model, "revision": st.revision, "accepted": st.accepted,
                            "n_windows": st.calibration.n_windows, "rejected_windows": p.policy.windows_rejected,
                            "updated": st.updated},
            "estimator": p.online_status(),
            "remount": {**p.policy.remount.status(), "events": list(p.policy.remount_events)},
            "state": {"path": self.store.path, "saves": self.saver.saves if self.saver else 0,
                      "save_failures": self.saver.failures if self.saver else 0,
                      "last_error": self.saver.last_error if self.saver else None},
            "watchdog": {"interval_s": self.watchdog.interval_s, "feeds": self.watchdog.feeds,
                         "withheld": self.watchdog.withheld},
            "config": {"path": self.config_path, "reloads": self.reloads, "reload_error": self.reload_error},
            "notes": list(self.notes),
            # OS thread ids by name, so a profiler can split the process's CPU by thread (/proc/PID/task/TID)
            "threads": {t.name: t.native_id for t in threading.enumerate()},
            **({"emulator": self.emulator.status()} if self.emulator is not None else {}),
        }

    def _lag(self) -> dict[str, Any]:
        """How far the detector and estimator are behind acquisition, and the published samples whose
        `static` was unknown (null) because of it."""
        p = self.processor
        analysed, last = p.analysed[0], p.corrected_seq
        lag = (last - analysed) / self.cfg.device.fs_hz if analysed is not None and last is not None else None
        return {"analysed_seq": analysed, "lag_s": lag, "static_unknown": p.static_unknown}

    def _status_text(self) -> str:
        st = self.processor.state
        return (f"{self._rate_hz:.1f} samples/s, calibration rev {st.revision} "
                f"({'accepted' if st.accepted else 'not accepted'}, {st.calibration.n_windows} windows), "
                f"{self.server.n_clients} clients")

    # -- main loop -------------------------------------------------------------------------
    def request_stop(self, *_: Any) -> None:
        self._stop_requested = True
        self._main_wake.poke()

    def request_reload(self, *_: Any) -> None:
        self._reload_requested = True
        self._main_wake.poke()

    def install_signal_handlers(self) -> None:
        """SIGTERM/SIGINT stop, SIGHUP reloads; a signal delivered to any thread wakes the main loop at once."""
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        signal.signal(signal.SIGHUP, self.request_reload)
        self._main_wake.install_for_signals()

    def run(self) -> int:
        """Main-thread loop until stop; returns the exit code."""
        # the rate estimate and the dead-thread check need no more than once a second; a watchdog, its quarter
        # period (stop and reload requests wake the loop at once)
        period = MAIN_PERIOD_S if self.watchdog.period_s is None else min(MAIN_PERIOD_S, self.watchdog.period_s / 4)
        next_status = 0.0
        while not self._stop.is_set():
            self._main_wake.wait(period)
            if self._stop_requested:
                break
            self.watchdog.tick()
            now = time.monotonic()
            t0, n0 = self._rate_mark
            if now - t0 >= 1.0:
                self._rate_hz = (self.samples_in - n0) / (now - t0)
                self._rate_mark = (now, self.samples_in)
            if now >= next_status:
                self.notifier.status(self._status_text())
                next_status = now + self.cfg.daemon.status_interval_s
            if self._reload_requested:
                self._reload_requested = False
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
            self.reload_error = str(exc)
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
        self.server.reconfigure(s)
        self.processor.reconfigure(new)  # the processing thread reads it at the next block
        if self.processor.corrections_pending:  # new gyro start values: published with their CALIB
            self.processor.stage_message(self._calib_message())
        self.cfg = new
        self.reloads += 1
        self.reload_error = None
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
        if self.emulator is not None:
            self.emulator.close()
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
        self._main_wake.close()
        log.info("gravcald stopped")

