"""gravcald: the in-use calibration service.

Wiring (each arrow a hand-off that never blocks the side before it)::

    driver.read() --[acquisition thread]--> correction a = K^-1 (raw - o) --> SocketServer.publish()
         |                                                          --[server thread]--> clients
         \\--> RingBuffer --[processing thread, every 50 ms of data]--> quasi-static detector
                 -> recursive estimator -> accepted calibration (used by the correction)
                 -> CALIB push, RateLimitedSaver --[saver thread]--> state.json

The acquisition thread reads the driver, corrects each block with the accepted calibration
and publishes it at once (publish() never blocks), then pushes it into the ring buffer for
the analysis (which overwrites the oldest samples, counted, if the analysis ever falls
behind; clients have them already). The main thread handles signals (SIGTERM/SIGINT: clean
stop with the state saved; SIGHUP: reload the configuration), feeds the systemd watchdog only
while samples flow, and updates STATUS=. ``--emulate`` puts the logger emulator in place of
the hardware (:class:`EmulatedBus`).

Calibration life cycle: the estimator is core.estimators.online.OnlineCalibrator (order and
extended terms -- e.g. a temperature offset -- by observability and evidence; bounded window
store; re-seeded recursion). A saved state resumes it where it stopped (parameters, covariance,
extended parameters). Without one, the start is the lab calibration (if configured) or the
ADXL210 datasheet values; until the online estimator has an order of its own, windows are also
pooled (:class:`SeedPool`) and fitted in batch (LottersBatch, eq. 11a) once there are two per
parameter; the first converged and observable fit seeds the recursion, so a wrong start does not
have to be within the linearisation's reach. Rejections by the recursion withdraw acceptance (3 of
the last 10) and, when it gives up (20 in a row or 10 of the last 20: a changed sensor), the
windows from then on are fitted afresh. A calibration is *accepted* -- used for the published
samples (at their temperature when it has a temperature term) and saved -- when it converged, is
observable, is not in doubt and rests on at least ``min_windows`` windows. A re-mount of the
sensor on the body (core/estimators/remount.py) is reported (CALIB/STATUS ``remount``), not
corrected: the calibration stays valid. docs/daemon.md describes running it.

Entry point: ``gravcal.daemon.gravcald:main`` (console script ``gravcald``).
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
from typing import Any, Sequence

import numpy as np

from ..core.calibration import Calibration
from ..core.ringbuffer import RingBuffer
from ..core.samples import SAMPLE_DTYPE, raw_triad
from ..core.windows import Window, WindowSet
from . import config as config_mod
from ..drivers.rigs.options import disconnect_arg, speed_arg
from .config import Config, ConfigError
from .persistence import CalibrationState, RateLimitedSaver, StateStore, load_lab_calibration
from .protocol import STANDARD_GRAVITY, STATIC_UNKNOWN, calib_message
from .sdnotify import Notifier, WatchdogPolicy, watchdog_interval
from .server import ServerConfig, SocketPathError, SocketServer, activated_socket

log = logging.getLogger("gravcal.gravcald")

# ADXL210E datasheet: 50 % duty cycle at 0 g, 4 % per g (the T1/T2 output, see core/samples.py and core/model/defaults.py).
NOMINAL_OFFSET = 0.5
NOMINAL_SENSITIVITY = 0.04

SUSPECT_REJECTIONS = 3  # rejected windows among the last SUSPECT_OF that withdraw acceptance until they agree again
SUSPECT_OF = 10
# The recursion "gives up" (a changed sensor: re-fit the windows from then on) after LottersRecursive's 20
# consecutive rejections, or when GIVE_UP_REJECTIONS of the last GIVE_UP_OF windows were rejected: a jump
# of one offset is invisible to windows with that axis horizontal, so rejections alternate with acceptances
# (and the accepted ones drag the other parameters along); a working recursion rejects ~none with a 5σ gate.
GIVE_UP_REJECTIONS, GIVE_UP_OF = 10, 20
SIGMA_FLOOR_G = 0.002  # quasi-static floor on each window's norm noise [g] (order.SIGMA_FLOOR_G)
MAX_SEED_WINDOWS = 300  # windows kept for the batch fit that seeds the recursion (see SeedPool)
REOPEN_AFTER_READ_ERRORS = 3  # a driver whose read() keeps raising is closed and reopened
ANALYSIS_BLOCK_S = 0.05  # samples collected before the detector and estimator run [s of data]
# A published sample's `static` is the detector's latest decision only while that decision is at most this much
# sensor time older than the sample (null beyond): it is ANALYSIS_BLOCK_S old when the processing thread keeps up,
# and the detection signal is itself a 0.5 Hz low-pass; a starved processing thread (a loaded host, a time-lapse
# emulator) would otherwise label seconds of later motion with an old "still".
STATIC_MAX_AGE_S = 2.0
SEED_OUTLIER_GATE_SIGMA = 5.0  # the seed fit's outlier gate (LottersBatch), as the recursion's gate_sigma
SEED_RETRY_EVERY = 10  # windows between seed fits when no new orientation arrived
# With as many windows as parameters a batch fit matches them exactly and can pass its own
# observability check while 30 % off (seen with 6 windows of the six-position scenario, seed 0);
# twice as many leave residual degrees of freedom to expose a wrong fit.
SEED_WINDOWS_PER_PARAM = 2

# The emulated/reference board's gyro path (docs/gyro.md, core/model/enc03j.py): ENC-03J on the
# board's y axis, 0.3 Hz high-pass conditioning, ±300 °/s, 12-bit ADC. The start sensitivity is
# the datasheet chain (0.67 mV/°/s x 7.5 gain on 12 bits at 3.3 V) when [gyro] gives none.
GYRO_AXIS = (0.0, 1.0, 0.0)
GYRO_HP_HZ = 0.3
GYRO_RANGE_RAD_S = math.radians(300.0)
GYRO_RAILS = (0, 4095)
GYRO_NOMINAL_COUNTS_PER_RAD_S = 357.36

# Settings that only take effect at start (SIGHUP says so instead of half-applying them).
RESTART_KEYS = {
    "device": ("spec", "fs_hz", "ring_capacity"),
    "estimator": ("model", "extended_terms"),
    "socket": ("path", "mode", "activation_name"),
    "state": ("directory", "lab_calibration"),
}


def nominal_calibration(model: str = "6") -> Calibration:
    cal = Calibration.nominal(np.full(3, NOMINAL_OFFSET), NOMINAL_SENSITIVITY, model=model)
    cal.converged = False
    cal.observable = False
    return cal


# -- processing (numerics only; runs in the processing thread) -------------------------


class SeedPool:
    """The windows kept for the batch fit that seeds (or re-seeds) the recursion.

    At most ``capacity`` windows. When full, the oldest window of the most crowded direction
    cell goes, so the rare orientations that make the parameters observable (a lie-down in a
    day of sitting and standing) stay in the pool instead of ageing out. Directions are taken
    under ``to_g`` (the start calibration: rough, but good enough to tell postures apart) and
    binned in cells of about 20°.
    """

    def __init__(self, capacity: int, to_g: Calibration):
        self.capacity = int(capacity)
        self.to_g = to_g
        self.windows: list[Window] = []
        self.cells: list[tuple[int, int, int]] = []
        self.new_cell = False  # the last add() opened a direction cell not seen before

    def __len__(self) -> int:
        return len(self.windows)

    def add(self, w: Window) -> None:
        a = self.to_g.apply_reference(np.asarray(w.mean, dtype=float)[None, :])[0]
        norm = float(np.linalg.norm(a))
        cell = tuple(int(v) for v in np.round(3.0 * a / norm)) if norm > 0 and np.isfinite(norm) else (0, 0, 0)
        self.new_cell = cell not in self.cells
        self.windows.append(w)
        self.cells.append(cell)
        if len(self.windows) > self.capacity:
            counts = collections.Counter(self.cells)
            crowded = max(counts, key=counts.__getitem__)
            i = self.cells.index(crowded)  # its oldest window
            del self.windows[i], self.cells[i]

    def window_set(self) -> WindowSet:
        return WindowSet.from_windows(self.windows)



class Processor:
    """Detector -> estimator -> correction for one stream of sample blocks.

    The estimator is core.estimators.online.OnlineCalibrator (model order and extended terms by
    observability and evidence, re-seeded recursion); ``start`` is its start calibration, ``lab``
    the lab calibration when configured (its frame makes the full order "12"), ``resumed`` a saved
    state it continues from. From a far-off start (the datasheet values) the recursion is
    bootstrapped by a batch fit of the pooled windows (:class:`SeedPool`, LottersBatch with its
    ellipsoid retry) once that is converged and observable; the same fit re-seeds it after the
    recursion gives up (a changed sensor). ``detector`` and the estimators are built from
    gravcal.core lazily; tests may pass their own ``detector``.
    """

    def __init__(self, cfg: Config, start: CalibrationState, *, resumed: bool, detector: Any = None,
                 lab: Calibration | None = None):
        from ..core.estimators.remount import RemountDetector

        self.cfg = cfg
        self.state = start
        self.lab = lab
        self.start = start.calibration  # the batch fit's starting point
        self.applied = start.calibration  # what corrects the published samples until an update is accepted
        # (seq of the last analysed sample, the detector's decision there): one tuple, swapped atomically, read by
        # correct() in the acquisition thread; seq None before any analysis
        self.analysed: tuple[int | None, bool] = (None, False)
        self.windows_base = int(start.calibration.n_windows) if resumed else 0
        self.pool = SeedPool(MAX_SEED_WINDOWS, start.calibration)  # for (re)seeding the recursion
        self._since_try = 0
        self.online = self._online(start.calibration, resumed)
        self.seeded = resumed  # the recursion runs from a batch fit (or a resumed state), not the raw start
        self.refitting = False  # the recursion gave up: a new pool of post-change windows is being fitted
        self.recent_rejections: collections.deque[bool] = collections.deque(maxlen=GIVE_UP_OF)
        self.detector = detector if detector is not None else self._make_detector()
        self.detector.to_g = self.applied
        self.windows_seen = 0
        self.windows_screened = 0  # moving more than pipeline.MAX_WINDOW_STD_G on an axis: not used
        self.windows_rejected = 0
        self.changed = False
        saved_remount = start.extra.get("remount") if resumed else None
        self.remount = RemountDetector()
        self.remount_events: list[dict[str, Any]] = list(saved_remount) if isinstance(saved_remount, list) else []
        self._init_gyro(start.extra.get("gyro") if resumed else None)

    # construction -------------------------------------------------------------------
    def _make_detector(self) -> Any:
        from ..core.detectors import MovingVarianceDetector, QuasiStaticDetector

        d, fs = self.cfg.detector, self.cfg.device.fs_hz
        if d.method == "variance":
            return MovingVarianceDetector(fs, window_s=d.window_s, threshold_g=d.threshold_g,
                                          min_duration_s=d.min_duration_s, max_duration_s=d.max_duration_s)
        return QuasiStaticDetector(fs, hp_hz=d.hp_hz, lp_hz=d.lp_hz, threshold_g=d.threshold_g,
                                   min_duration_s=d.min_duration_s, max_duration_s=d.max_duration_s)

    def candidates(self) -> tuple[str, ...]:
        """Orders the online estimator may choose: up to the configured one, plus the configured
        extended terms on every order >= 6 (config [estimator] extended_terms)."""
        return online_candidates(self.cfg.estimator.model, self.cfg.estimator.extended_terms)

    def _online(self, start: Calibration, resumed: bool) -> Any:
        from ..core.estimators.lotters import datasheet_held_uncertainty
        from ..core.estimators.online import OnlineCalibrator

        e = self.cfg.estimator
        lab = self.lab
        if lab is None and e.model == "12":
            lab = start  # a resumed or given 12-parameter calibration carries its frame
        if not resumed and start.covariance.size == 0 and self.lab is None:
            # a start without a stated uncertainty (the datasheet values): the order rule must see how
            # uncertain its held sensitivities are (lotters.datasheet_held_uncertainty)
            start = datasheet_held_uncertainty(start)
        q = e.process_noise
        # the quasi-static floor of the old fixed recursion (LottersRecursive's 2 mg): the emulated sensor's
        # windows are cleaner than its model errors, and a data-derived floor from a few windows undercuts them
        return OnlineCalibrator(start, lab=lab, resume=resumed, candidates=self.candidates(),
                                process_noise=q if q > 0 else None, sigma_floor_g=SIGMA_FLOOR_G)

    @property
    def estimator(self) -> Any:
        """The running recursion (LottersRecursive) or None before the first seed."""
        return self.online.recursive if self.seeded or self.online.model != "none" else None

    def _init_gyro(self, saved: Any) -> None:
        """The online gyro calibration (core.gyro, docs/gyro.md §6). Start values (bias [ADC
        counts], sensitivity [counts per rad/s]) are, in order: a resumed state's ``extra.gyro``,
        the [gyro] configuration, none (the published rate is null until the estimator has both)."""
        from ..core.gyro import OnlineGyroCalibrator

        g = self.cfg.gyro
        bias, sens = g.zero_counts, g.counts_per_rad_s
        if isinstance(saved, dict):
            try:
                sb, ss = float(saved["bias"][0]), float(saved["sensitivity"][0][0])
            except (KeyError, IndexError, TypeError, ValueError):
                sb, ss = math.nan, math.nan  # no determined value saved
            bias = sb if math.isfinite(sb) else bias
            sens = ss if math.isfinite(ss) and ss != 0 else sens
        self.gyro_start = (float(bias), float(sens))
        self.gyro_cal = OnlineGyroCalibrator(
            self.cfg.device.fs_hz, k=1, axis=GYRO_AXIS, hp_hz=GYRO_HP_HZ,
            start_sensitivity=sens if math.isfinite(sens) and sens != 0 else GYRO_NOMINAL_COUNTS_PER_RAD_S,
            range_rad_s=GYRO_RANGE_RAD_S, rails=GYRO_RAILS)
        self.gyro_json: dict[str, Any] = self._gyro_json(self.gyro_cal.calibration)
        # (bias [counts], sensitivity [counts per rad/s]) used by correct(): one tuple, swapped atomically
        self._gyro_correction = self.gyro_start

    def _gyro_json(self, cal: Any) -> dict[str, Any]:
        """The ``gyro`` object of CALIB: the estimator's result plus what the published rate uses."""
        out = cal.to_json_dict()
        b, s = getattr(self, "_gyro_correction", self.gyro_start)
        out["applied"] = {"bias": b if math.isfinite(b) else None, "sensitivity": s if math.isfinite(s) else None}
        return out

    def _gyro_window(self, w: Window) -> bool:
        """Fold a quasi-static window into the gyro calibration; True when it changed. Only with
        an accepted accelerometer calibration: the pose-to-pose sensitivity compares gravity
        directions, which the datasheet start gets wrong by up to ~0.9 g of offset."""
        est = self.gyro_cal
        if not self.applied.converged:
            return False
        before = (est.n_windows, est.n_windows_rejected, est.pose.n_pairs)
        try:
            est.window(w, self.applied)
        except (ValueError, np.linalg.LinAlgError) as exc:  # one window the gyro cannot use: never the rest of the block
            log.warning("window skipped by the gyro estimator: %s", exc)
            return False
        if (est.n_windows, est.n_windows_rejected, est.pose.n_pairs) == before:
            return False
        self._gyro_apply(est.calibration)
        return True

    def _gyro_apply(self, cal: Any) -> None:
        """The estimator's bias once it has a window, its sensitivity once determined; the start
        values until then."""
        bias, sens = self.gyro_start
        if cal.n_windows > 0 and np.all(np.isfinite(cal.bias)):
            bias = float(cal.bias[0])
        if cal.sensitivity is not None:
            sens = float(cal.sensitivity[0, 0])
        self._gyro_correction = (bias, sens)
        self.gyro_json = self._gyro_json(cal)

    def reconfigure(self, cfg: Config) -> None:
        """Live changes (SIGHUP): detector settings rebuild the detector."""
        old = self.cfg
        self.cfg = cfg
        if cfg.detector != old.detector:
            self.detector = self._make_detector()
            self.detector.to_g = self.applied
        if cfg.gyro != old.gyro:  # new start values; estimated ones keep precedence
            g = cfg.gyro
            self.gyro_start = (float(g.zero_counts), float(g.counts_per_rad_s))
            self._gyro_apply(self.gyro_cal.calibration)

    # per block ------------------------------------------------------------------------
    @property
    def applied(self) -> Calibration:
        """The accepted calibration that corrects the published samples."""
        return self._applied

    @applied.setter
    def applied(self, cal: Calibration) -> None:
        self._applied = cal
        # A plain calibration: a = K^-1 (raw - o) as one matrix product per block, the inverse taken once here.
        # An extended one applies its terms at each sample's covariates (Calibration.apply). One tuple, swapped
        # atomically: correct() runs in the acquisition thread.
        self._correction = (np.asarray(cal.offset, dtype=float),
                            np.linalg.inv(np.asarray(cal.sensitivity, dtype=float)).T * STANDARD_GRAVITY,
                            cal if cal.extended_terms else None)

    @property
    def static_now(self) -> bool:
        """The detector's latest per-sample decision."""
        return self.analysed[1]

    def static_codes(self, seq: np.ndarray) -> np.ndarray:
        """Each sample's ``static`` code (protocol.static_words): the detector's latest decision while it is at
        most STATIC_MAX_AGE_S of sensor time older than the sample, else STATIC_UNKNOWN (null)."""
        last, static = self.analysed
        codes = np.full(seq.shape[0], STATIC_UNKNOWN, dtype=np.int8)
        if last is not None:
            fresh = (seq.astype(np.int64) - last) <= STATIC_MAX_AGE_S * self.cfg.device.fs_hz
            codes[fresh] = int(static)
        return codes

    def correct(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fast path, per block as it arrives: (acc [m/s²] (N, 3) corrected with the accepted
        calibration, gyro [rad/s] (N,) NaN when not configured, static (N,) codes: the detector's
        latest decision, or unknown when that is more than STATIC_MAX_AGE_S of data old)."""
        offset, kinv_t, extended = self._correction
        if extended is not None:  # a sample without a covariate its terms need (NaN) gets NaN
            acc = extended.apply(raw_triad(block), temp=block["temp"].astype(float),
                                 vsupply=block["vsupply"].astype(float),
                                 t=block["seq"].astype(float) / self.cfg.device.fs_hz) * STANDARD_GRAVITY
        else:
            acc = (raw_triad(block) - offset) @ kinv_t
        bias, sens = self._gyro_correction
        gyro = (block["gyro"].astype(float) - bias) / sens  # NaN while either is unknown
        return acc, gyro, self.static_codes(block["seq"])

    def analyse(self, block: np.ndarray) -> np.ndarray:
        """Detector and estimator over a block (in arrival order, any split); returns the
        per-sample static decisions (N,) bool; sets ``self.changed`` when the calibration
        state changed."""
        raw = raw_triad(block)
        self.gyro_cal.push(block["gyro"])  # the same samples as the detector: window indices match
        # The detector runs on device time (unwrapped seq / fs), not on the host's reception
        # stamps: USB latency jitter (or an emulator's time-lapse) would read as time gaps and
        # cut every window, while lost samples still show as seq jumps.
        t_device = block["seq"].astype(np.float64) / self.cfg.device.fs_hz
        # the windows' aux channels, in AUX_COLUMNS order: temperature [°C], supply voltage [V]
        aux = np.column_stack([block["temp"].astype(float), block["vsupply"].astype(float)])
        windows = self.detector.update(t_device, raw, aux)
        det = getattr(self.detector, "last_detection", None)
        if det is not None and det.shape[0] == block.shape[0]:
            static = det < self.detector.threshold_g
        else:
            static = np.zeros(block.shape[0], dtype=bool)
        self.changed = False
        for w in windows:
            self._window(w)
            if self._gyro_window(w):
                extra = {**self.state.extra, "gyro": self.gyro_json}
                self.state = dataclasses.replace(self.state, extra=extra)
                self.changed = True
        if static.shape[0]:
            self.analysed = (int(block["seq"][-1]), bool(static[-1]))
        return static

    def process(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """correct() then analyse() on one block, with exact per-sample static flags."""
        acc, gyro, _ = self.correct(block)
        return acc, gyro, self.analyse(block)

    def _window(self, w: Window) -> None:
        from ..core.pipeline import MAX_WINDOW_STD_G, window_std_g

        self.windows_seen += 1
        # the offline pipeline's screen (pipeline.screen_windows): a window whose samples move more than
        # MAX_WINDOW_STD_G on an axis averages postures (a slow turn at constant |a|) and is not quasi-static
        if float(window_std_g(WindowSet.from_windows([w]), self.applied)[0]) > MAX_WINDOW_STD_G:
            self.windows_screened += 1
            return
        self.pool.add(w)
        self._since_try += 1
        self._remount_window(w)
        online = self.online
        rec = online.recursive
        before = rec.n_rejected if rec is not None else 0
        try:
            cal = online.update(w)
        except ValueError as exc:  # a window the estimator cannot use (non-finite): skip it, never crash
            log.warning("window skipped by the estimator: %s", exc)
            return
        rejected = online.recursive is not None and online.recursive is rec and rec.n_rejected > before
        if online.recursive is not rec:
            self.recent_rejections.clear()  # a new recursion (re-seed): its own record
        self.recent_rejections.append(rejected)
        if rejected:
            self.windows_rejected += 1
        if not self.seeded and not (online.model != "none" and not online.provisional):
            # bootstrap: the online order rule evaluated at a far-off start (datasheet offsets are up to ~1 g
            # off) cannot be trusted; a batch fit with the ellipsoid retry seeds the recursion instead
            seed = self._seed_fit()
            if seed is None:
                if online.model != "none":  # provisional offsets: published (not accepted), as information
                    self._publish(cal)
                return
            self.seeded = True
            self.windows_base = 0
            online.adopt(seed, windows=self.pool.window_set())
            cal = online.calibration
        elif self.refitting or (rejected and (not cal.converged or sum(self.recent_rejections) >= GIVE_UP_REJECTIONS)):
            # The recursion gave up (LottersRecursive.max_consecutive_rejections windows in a row contradict
            # it): the sensor changed, or a resumed state belongs to another sensor. Pool the windows from now
            # on and fit them afresh; keep the current values (not accepted) until that fit is usable.
            if not self.refitting:
                log.warning("the recursive estimator rejected %d of the last %d windows (%d in a row); fitting the "
                            "windows from now on afresh", sum(self.recent_rejections), len(self.recent_rejections),
                            online.recursive.consecutive_rejected)
                self.refitting = True
                self.pool = SeedPool(MAX_SEED_WINDOWS, self.applied)
                self.pool.add(w)
            refit = self._seed_fit()
            if refit is None or not (refit.converged and refit.observable):
                self._publish(cal, suspect=True)
                return
            log.warning("re-fitted after the recursion gave up: %d windows, order %s", refit.n_windows, refit.model)
            online.adopt(refit, clear_store=True, windows=self.pool.window_set())
            self.refitting = False
            self.recent_rejections.clear()
            cal = online.calibration
        elif rejected:
            if self._suspect() and self.state.accepted:
                self._publish(cal)  # several recent rejections: the calibration is in doubt, withdraw acceptance
            return  # an isolated outlier window: nothing changed
        self._publish(cal)

    def _suspect(self) -> bool:
        return sum(list(self.recent_rejections)[-SUSPECT_OF:]) >= SUSPECT_REJECTIONS

    def _publish(self, cal: Calibration, *, suspect: bool = False) -> None:
        cal.n_windows = self.windows_base + self.online.n_windows
        suspect = suspect or self._suspect()
        if suspect and cal.converged:
            n = sum(list(self.recent_rejections)[-SUSPECT_OF:])
            cal.message = "; ".join(m for m in (cal.message, f"{n} of the last {SUSPECT_OF} windows contradict "
                                                "this calibration (sensor changed?): not accepted until they agree "
                                                "again or a re-fit replaces it") if m)
        accepted = bool(cal.converged and cal.observable and not self.online.provisional and not suspect
                        and cal.n_windows >= self.cfg.estimator.min_windows and (self.seeded or self.online.model != "none"))
        extra = dict(self.state.extra)
        if self.remount_events:
            extra["remount"] = list(self.remount_events)
        self.state = CalibrationState(cal, self.state.revision + 1, time.time(), accepted, extra)
        if accepted:
            self.applied = cal
            self.detector.to_g = cal
        self.changed = True

    def _remount_window(self, w: Window) -> None:
        """Posture statistics for the re-mount detector (core/estimators/remount.py): the gravity direction of
        the window under the accepted calibration. A re-mount leaves the calibration valid (the norm does
        not see the housing's rotation on the body); it is reported, not corrected."""
        if not self.applied.converged:
            return
        a = self.applied.apply_reference(np.asarray(w.mean, dtype=float)[None, :])[0]
        dur = float(w.t_end - w.t_start) if w.t_end > w.t_start else max(w.n, 1) / self.cfg.device.fs_hz
        ev = self.remount.update(float(w.t_mid), a, dur)
        if ev is not None:
            d = ev.to_json_dict()
            self.remount_events = (self.remount_events + [d])[-20:]
            log.warning("sensor re-mount detected at sensor time %.0f s: the upright gravity direction turned by "
                        "%.0f° (%s rule); the calibration stays valid, posture/body-frame interpretations do not",
                        ev.t, ev.angle_deg, ev.rule)
            self.changed = True

    def calib_extra(self) -> dict[str, Any]:
        """CALIB fields beyond the calibration: the extended parameters (model name, names, values, per-term
        magnitudes with std) when the calibration has extended terms, every extended candidate's status
        (chosen / not warranted / not observable / untestable, with the reason), and the re-mount events."""
        cal = self.state.calibration
        # the sample the estimator had analysed up to when it made this revision (a client can tell which data a
        # calibration rests on; it lags the published samples when the processing thread falls behind)
        out: dict[str, Any] = {"remount": list(self.remount_events), "data_through_seq": self.analysed[0]}
        ext = cal.metadata.get("extended") if isinstance(cal.metadata, dict) else None
        if ext:
            params = cal.metadata.get("params") or {}
            out["extended"] = {"model": cal.model, "terms": list(ext.get("terms", [])),
                               "param_names": list(cal.param_names),
                               "values": [params.get(n) for n in cal.param_names],
                               "t_ref_c": ext.get("t_ref_c"), "t0_s": ext.get("t0_s"),
                               "magnitudes": ext.get("magnitudes")}
        terms = cal.metadata.get("extended_terms") if isinstance(cal.metadata, dict) else None
        if terms:
            out["extended_terms"] = {k: {"status": v.get("status"), "reason": v.get("reason")} for k, v in terms.items()}
        return out

    def online_status(self) -> dict[str, Any]:
        st = self.online.stats()
        return {"model": st["model"], "reason": st["reason"], "seeded": self.seeded, "refitting": self.refitting,
                "stored_windows": st["stored"], "reseeds": st["n_reseeds"], "extended_terms": st["extended_terms"]}

    def seed_windows_needed(self) -> int:
        """Windows before the batch fit that seeds the recursion is tried: at least
        SEED_WINDOWS_PER_PARAM per parameter, and at least ``min_windows``."""
        from ..core.estimators.lotters import resolve_parameterization

        n = resolve_parameterization(self.cfg.estimator.model, self.start).n_params
        return max(self.cfg.estimator.min_windows, SEED_WINDOWS_PER_PARAM * n, 1)

    def _seed_fit(self) -> Calibration | None:
        """Batch fit (eq. 11a) over the pooled windows; the recursion takes over once it is
        converged and observable (returned then, None otherwise)."""
        from ..core.estimators.lotters import LottersBatch

        if len(self.pool) < self.seed_windows_needed():
            return None
        if not (self.pool.new_cell or self._since_try >= SEED_RETRY_EVERY or self.refitting):
            return None  # the same postures again: the fit would not change its verdict
        self._since_try = 0
        model = self.cfg.estimator.model
        start = self.start
        if model == "12" and self.lab is None and start.model != "12":
            model = "9"  # no frame to hold: the online estimator's full order is 9
        try:  # from the start values; LottersBatch retries from an ellipsoid fit when they are far off
            cal = LottersBatch(model, outlier_gate_sigma=SEED_OUTLIER_GATE_SIGMA).fit(self.pool.window_set(), start=start)
        except ValueError as exc:  # e.g. too few distinct orientations yet
            log.debug("seed batch fit not possible yet: %s", exc)
            return None
        if not (cal.converged and cal.observable):
            return None
        if cal.model not in self.online.candidates:
            return None
        return cal


def online_candidates(model: str, extended_terms: str) -> tuple[str, ...]:
    """The OnlineCalibrator candidates for a configured order and the [estimator] extended_terms list."""
    ladder = {"offsets": ("offsets",), "6": ("offsets", "6"), "9": ("offsets", "6", "9"), "12": ("offsets", "6", "12")}
    base = ladder[model]
    terms = [t.strip() for t in extended_terms.split(",") if t.strip()]
    return base + tuple(f"{b}+{t}" for t in terms for b in base if b != "offsets")


# -- --emulate: the built-in emulator as the device ------------------------------------------


def emulated_truth(scenario: str, seed: int) -> Calibration | None:
    """The calibration an ideal estimator should find for the emulator's sensor (raw = K a + o,
    duty cycle units): the emulator draws the sensor with ``default_model`` from the seed's
    model stream, exactly as ``core.simulate.simulate_blocks`` does. None for the test pattern."""
    if scenario == "pattern":
        return None
    from ..core.model.defaults import default_model, triad_truth
    from ..core.simulate import _streams  # the seed -> (motion, model, sensor) split of the simulator

    return triad_truth(default_model(_streams(seed)[1]))


def _DetachedEmulator(args: Sequence[str], *, linger: float) -> Any:
    """drivers.hil.EmulatorProcess started in its own session, so that a Ctrl-C at the terminal
    reaches only the daemon, which then saves its state and stops the emulator itself."""
    import queue
    import subprocess
    from ..drivers.rigs.hil import EmulatorProcess

    class Detached(EmulatorProcess):
        def __enter__(self) -> "Detached":
            self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                         env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
            threading.Thread(target=self._pump, daemon=True).start()
            try:
                line = self._lines.get(timeout=self.start_timeout)
            except queue.Empty:
                line = None
            if not line:
                raise RuntimeError(f"emulator did not start: {self._stop().strip()[-2000:]}")
            self.spec = line.strip()
            return self

    return Detached(args, linger=linger)


class EmulatedBus:
    """``gravcald --emulate``: the logger emulator stands in for the hardware.

    serial/can: the emulator runs in a child process (drivers/hil.py) on a real pty (serial
    frames) or an slcan pty (python-can's slcan interface opens it); the daemon opens the device
    path like a USB adapter. i2c: the fake I2C device runs in this process behind the real
    I2CDriver (there is no kernel I2C to share). The sensor is drawn off-nominal from ``seed``;
    the daemon starts from the datasheet values as usual, i.e. deliberately wrong.

    With a time-lapse ``speed`` the device ticks run ``speed`` times faster than the host clock,
    so the drivers' host time stamps (``tick_hz`` scaled by ``speed``) stay monotonic; the
    estimator works on device time (seq / fs) and is unaffected.
    """

    def __init__(self, bus: str = "serial", *, scenario: str = "daily_living", seed: int = 0, speed: float = 1.0,
                 fs: float = 200.0, duration: float = 86400.0, disconnects: Sequence[tuple[float, float]] = (),
                 driver_options: str = ""):
        if bus not in ("serial", "can", "i2c"):
            raise ValueError(f"--bus must be serial, can or i2c, got {bus!r}")
        if not speed > 0:
            raise ValueError(f"--speed must be > 0, got {speed}")
        self.bus, self.scenario, self.seed, self.speed, self.fs = bus, scenario, int(seed), float(speed), float(fs)
        self.duration, self.disconnects = float(duration), tuple(disconnects)
        self.driver_options = driver_options.strip("&?")
        self.process: Any = None  # EmulatorProcess (serial/can)
        self.device: Any = None  # FakeI2CDevice (i2c)
        self.spec = ""
        self.truth: Calibration | None = None  # set by open() (imports the simulator: not before the socket is bound)

    def _tick_hz(self) -> float:
        from ..drivers.codec import TICK_HZ

        return TICK_HZ * self.speed if math.isfinite(self.speed) else 0.0  # 0: stamp blocks at reception

    def open(self) -> Any:
        """Start the emulator and return the opened driver."""
        self.truth = emulated_truth(self.scenario, self.seed)
        if self.bus == "i2c":
            return self._open_i2c()
        from ..drivers.base import open_driver

        args = ["--bus", self.bus, "--scenario", self.scenario, "--seed", str(self.seed),
                "--speed", "max" if math.isinf(self.speed) else repr(self.speed), "--fs", repr(self.fs),
                "--duration", repr(self.duration)]
        for start, dur in self.disconnects:
            args += ["--disconnect-at", f"{start!r}:{dur!r}"]
        proc = _DetachedEmulator(args, linger=-1.0)  # the device stays plugged in after the stream ends
        try:
            proc.__enter__()
        except RuntimeError as exc:
            raise ValueError(f"--emulate: {exc}") from None
        self.process = proc
        self.spec = proc.spec + ("&" if "?" in proc.spec else "?") + f"tick_hz={self._tick_hz():.0f}"
        if self.driver_options:
            self.spec += "&" + self.driver_options
        return open_driver(self.spec)

    def _open_i2c(self) -> Any:
        from ..drivers.rigs.emulator import Faults
        from ..drivers.rigs.fake_i2c import FakeI2CDevice, FakeSMBus
        from ..drivers.i2c import I2CDriver
        from ..drivers.rigs.sources import scenario_source

        speed = self.speed if math.isfinite(self.speed) else 100.0  # a FIFO fills at a finite pace
        source = scenario_source(self.scenario, seed=self.seed, fs=self.fs, duration=self.duration)
        depth = 255  # the deepest FIFO the register map allows: room for the host's scheduling jitter
        self.device = device = FakeI2CDevice(source.blocks, source.fs, speed=speed, fifo_depth=depth,
                                             faults=Faults(disconnects=self.disconnects, seed=self.seed))
        poll_s = max(0.001, depth / (source.fs * speed) / 4)  # a quarter of the FIFO's fill time
        driver = I2CDriver("fake", device.address, poll_s=poll_s, tick_hz=self._tick_hz(),
                           smbus_factory=lambda bus: FakeSMBus(device, bus))
        self.spec = (f"i2c://fake/0x{device.address:02X}?scenario={self.scenario}&seed={self.seed}"
                     f"&fs={self.fs:g}&speed={speed:g}&fifo_depth={depth}")
        return driver.open()

    def describe(self) -> str:
        where = {"serial": "a pty", "can": "an slcan pty", "i2c": "a fake I2C device (in process)"}[self.bus]
        pid = f", emulator pid {self.process.proc.pid}" if self.process is not None else ""
        return (f"emulated {self.bus} logger on {where}{pid}: scenario {self.scenario}, seed {self.seed}, "
                f"{self.fs:g} Hz, speed {self.speed:g}x; device {self.spec}")

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"bus": self.bus, "scenario": self.scenario, "seed": self.seed, "speed": self.speed,
                               "fs_hz": self.fs, "spec": self.spec}
        if self.process is not None:
            out["events"] = list(self.process.events)
            out["stream_done"] = self.process.done_line
        if self.truth is not None:  # what the estimate should converge to (raw = K a + o)
            out["truth"] = {"offset": self.truth.offset.tolist(), "sensitivity": self.truth.sensitivity.tolist()}
        return out

    def close(self) -> None:
        if self.process is not None:
            self.process.__exit__(None, None, None)
            err = (getattr(self.process, "stderr", "") or "").strip()
            if err:
                log.debug("emulator stderr: %s", err[-2000:])
            self.process = None


# -- the service -------------------------------------------------------------------------


class Gravcald:
    """The running service. ``driver`` (tests) replaces opening ``cfg.device.spec``."""

    def __init__(self, cfg: Config, *, driver: Any = None, notifier: Notifier | None = None,
                 environ: dict[str, str] | None = None, detector: Any = None, config_path: str | None = None,
                 overrides: dict[str, Any] | None = None, emulator: EmulatedBus | None = None):
        self.cfg = cfg
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
        self._reload = threading.Event()
        self._data = threading.Event()
        self._acq_stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.samples_in = 0
        self.last_seq: int | None = None  # seq of the last sample read (for the processing lag in STATUS)
        self.static_unknown = 0  # published samples whose `static` was null (the detector too far behind)
        self.read_errors = 0
        self.exit_code = 0
        self._rate_hz = 0.0
        self._rate_mark = (time.monotonic(), 0)
        self.reloads = 0  # successful SIGHUP reloads
        self.process_errors = 0  # sample blocks lost to an exception in the processing chain
        self.driver_reopens = 0  # reopened after REOPEN_AFTER_READ_ERRORS read exceptions in a row
        self.reload_error: str | None = None  # why the last reload was refused (None: it worked)

    # -- start ---------------------------------------------------------------------------
    def _initial_state(self) -> tuple[CalibrationState, bool]:
        self.store.ensure_directory()
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
        if self.emulator is not None:
            driver = self.emulator.open()
            self.cfg.device.spec = self.overrides["device.spec"] = self.emulator.spec  # SIGHUP keeps it
            return driver
        from ..drivers.base import open_driver  # lazy: the drivers are a separate layer

        return open_driver(self.cfg.device.spec)  # opened; DriverError names a missing device / group

    def start(self) -> None:
        self.server = self._open_server()  # first: a socket in use fails fast, before any numerics load
        state, resumed = self._initial_state()
        self.processor = Processor(self.cfg, state, resumed=resumed, detector=self._detector, lab=self._lab)
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
                             extra={"applied_revision": st.revision if st.accepted else None,
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
        while not self._acq_stop.is_set():
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
            if not n:
                continue
            self.samples_in += n
            self.last_seq = int(block["seq"][-1])
            self.watchdog.samples_arrived(n)
            try:
                acc, gyro, static = p.correct(block)
                self.static_unknown += int(np.count_nonzero(static == STATIC_UNKNOWN))
            except Exception:  # a numerics bug must not stop acquisition
                self.process_errors += 1
                log.exception("correcting a block of %d samples failed", n)
            else:
                self.server.publish(block, acc, gyro, static)
            self.ring.push(block)
            if len(self.ring) >= analysis_n:
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
            self._data.wait(0.2)
            self._data.clear()
            block = self.ring.pop()
            if block.shape[0]:
                self._analyse(block)
            elif self._stop.is_set() and not any(t.is_alive() for t in self._threads[:1]):
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
            self.server.set_calibration(self._calib_message())
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
                       "read_errors": self.read_errors, "reopens": self.driver_reopens, **drv_stats},
            "ring": self.ring.stats(),
            "processing": {"errors": self.process_errors, **self._lag()},
            "detector": {"method": self.cfg.detector.method, "threshold_g": self.cfg.detector.threshold_g,
                         "windows": p.windows_seen, "screened": p.windows_screened, **det_stats},
            "calibration": {"model": st.model, "revision": st.revision, "accepted": st.accepted,
                            "n_windows": st.calibration.n_windows, "rejected_windows": p.windows_rejected,
                            "updated": st.updated},
            "estimator": p.online_status(),
            "remount": {**p.remount.status(), "events": list(p.remount_events)},
            "state": {"path": self.store.path, "saves": self.saver.saves if self.saver else 0,
                      "save_failures": self.saver.failures if self.saver else 0,
                      "last_error": self.saver.last_error if self.saver else None},
            "watchdog": {"interval_s": self.watchdog.interval_s, "feeds": self.watchdog.feeds,
                         "withheld": self.watchdog.withheld},
            "config": {"path": self.config_path, "reloads": self.reloads, "reload_error": self.reload_error},
            "notes": list(self.notes),
            **({"emulator": self.emulator.status()} if self.emulator is not None else {}),
        }

    def _lag(self) -> dict[str, Any]:
        """How far the detector and estimator are behind acquisition, and the published samples whose
        `static` was unknown (null) because of it."""
        analysed = self.processor.analysed[0]
        lag = (self.last_seq - analysed) / self.cfg.device.fs_hz if analysed is not None and self.last_seq is not None else None
        return {"analysed_seq": analysed, "lag_s": lag, "static_unknown": self.static_unknown}

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
        self.server.config.max_clients = s.max_clients
        self.server.config.queue_messages = s.queue_messages
        self.server.config.stall_timeout_s = s.stall_timeout_s
        self.server.config.max_request_bytes = s.max_request_bytes
        self.processor.reconfigure(new)  # the processing thread reads it at the next block
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
    e = p.add_argument_group(
        "emulation", "--emulate runs the daemon against the built-in logger emulator instead of hardware: a sensor "
        "drawn off-nominal, a daemon starting from the datasheet values. The socket and state directory default to "
        "a fresh temporary directory (printed at start); /etc/gravcal/gravcald.toml is not read (use --config).")
    e.add_argument("--emulate", action="store_true", help="use the emulator as the device")
    e.add_argument("--bus", choices=("serial", "can", "i2c"), default="serial",
                   help="emulated bus: serial (pty), can (slcan on a pty) or i2c (fake device) (default serial)")
    e.add_argument("--speed", type=speed_arg, default=1.0, metavar="X",
                   help="time-lapse factor of the emulated logger (1 = real time, default; 'max' = no pacing)")
    e.add_argument("--seed", type=int, default=0, help="seed of the emulated sensor and wearer (default 0)")
    e.add_argument("--scenario", default="daily_living",
                   help="emulated motion: daily_living (default), loetters, six_position, static, or pattern")
    e.add_argument("--duration", type=float, default=86400.0, metavar="S",
                   help="emulated stream length [s of sensor time] (default 86400, a day; the motion is planned "
                        "ahead, so longer takes longer to start); then the bus goes silent")
    e.add_argument("--driver-options", default="", metavar="K=V&...",
                   help="serial/can: extra options for the driver's spec, e.g. batch_frames=1 (serial: a wake-up per "
                        "frame, lowest latency, more CPU; default 16 frames per wake-up)")
    e.add_argument("--disconnect-at", type=disconnect_arg, action="append", default=[], metavar="T:DUR",
                   help="unplug the emulated device at sensor time T for DUR seconds (repeatable)")
    return p


def emulation_defaults(args: argparse.Namespace, overrides: dict[str, Any]) -> list[str]:
    """--emulate without --socket/--state-dir: both in a fresh private temporary directory
    (under $XDG_RUNTIME_DIR when set). Fills ``overrides``; returns what to print."""
    if args.socket and args.state_dir:
        return []
    base = tempfile.mkdtemp(prefix="gravcald-emulate-", dir=os.environ.get("XDG_RUNTIME_DIR") or None)
    if not args.socket:
        overrides["socket.path"] = os.path.join(base, "gravcal.sock")
    if not args.state_dir:
        overrides["state.directory"] = os.path.join(base, "state")
    return [base]


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
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.emulate:
        given = [opt for opt, dest in (("--bus", "bus"), ("--speed", "speed"), ("--seed", "seed"),
                                       ("--scenario", "scenario"), ("--duration", "duration"),
                                       ("--disconnect-at", "disconnect_at"), ("--driver-options", "driver_options"))
                 if getattr(args, dest) != parser.get_default(dest)]
        if given:
            print(f"gravcald: error: {', '.join(given)} {'needs' if len(given) == 1 else 'need'} --emulate", file=sys.stderr)
            return 2
    elif args.device:
        print("gravcald: error: --device and --emulate exclude each other (the emulator is the device)", file=sys.stderr)
        return 2
    elif not (args.duration > 0 and math.isfinite(args.duration)):
        print(f"gravcald: error: --duration must be a positive number of seconds, got {args.duration}", file=sys.stderr)
        return 2
    overrides = overrides_from_args(args)
    config_path = args.config
    emulate_dirs = emulation_defaults(args, overrides) if args.emulate and not args.print_config else []
    try:
        if args.emulate:  # the emulator is self-contained: read a config file only when asked to
            cfg = config_mod.load_config(config_path, overrides)
        elif config_path is None:
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
    emulator = None
    if args.emulate and driver is None:
        try:
            emulator = EmulatedBus(args.bus, scenario=args.scenario, seed=args.seed, speed=args.speed,
                                   fs=cfg.device.fs_hz, duration=args.duration, disconnects=args.disconnect_at,
                                   driver_options=args.driver_options)
        except ValueError as exc:
            print(f"gravcald: error: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
    daemon = Gravcald(cfg, driver=driver, environ=env, config_path=config_path, overrides=overrides,
                      emulator=emulator)
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
    if emulator is not None:
        _announce_emulation(daemon, emulator, emulate_dirs)
    return daemon.run()


def _announce_emulation(daemon: Gravcald, emulator: EmulatedBus, dirs: list[str]) -> None:
    sock = daemon.server.address if isinstance(daemon.server.address, str) else daemon.cfg.socket.path
    temporary_state = bool(dirs) and daemon.store.directory == os.path.join(dirs[0], "state")
    lines = [f"gravcald --emulate: {emulator.describe()}",
             f"  socket: {sock}   (try: gravcal watch --socket {sock})",
             f"  state:  {daemon.store.directory}" + (f"   (new; --state-dir {daemon.store.directory} resumes it)"
                                                     if temporary_state else ""),
             "  start:  " + "; ".join(daemon.notes[-1:]) + "   (Ctrl-C stops and saves the state)"]
    if emulator.truth is not None:
        t = emulator.truth
        lines.append(f"  truth:  offset {np.round(t.offset, 5).tolist()} sensitivity "
                     f"{np.round(np.diag(t.sensitivity), 5).tolist()} [duty, duty/g] (what the estimate should reach)")
    print("\n".join(lines), flush=True)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
