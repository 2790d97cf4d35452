"""gravcald's processing: detector -> online calibrator -> correction, for one stream of sample blocks.

Wiring only: the quasi-static detector cuts windows from the sample blocks, the online calibrator
(core/estimators/online.py, ``OnlineCalibrator.feed``) makes every decision from a window to an accepted
calibration (core/estimators/online_policy.py), and this module publishes what comes back (a new
revision of the calibration state, CALIB fields) and corrects the published samples with the accepted
calibration. The gyro's own online calibration (core.gyro) runs beside it on the same windows.

The published samples are corrected by the per-sample engine (daemon/_engine.c, in C), for the C step and for
the blocks the Python path publishes alike; this module is its control plane: every change of what corrects
and labels a sample (the accepted calibration, the gyro's correction, the detector's latest decision) is one
call of the engine's one setter, Engine.set_params, with the whole parameter vector.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Any, Callable

import numpy as np

from ..core.calibration import Calibration
from ..core.estimators.online import OnlineCalibrator
from ..core.estimators.online_policy import OnlineStep
from ..core.correction import CP_N, correction_params
from ..core.samples import raw_triad
from ..core.windows import Window
from ._fastpath import EP_N, Engine
from .config import Config
from .persistence import CalibrationState
from .protocol import STANDARD_GRAVITY

log = logging.getLogger("gravcal.gravcald")

# ADXL210E datasheet: 50 % duty cycle at 0 g, 4 % per g (the T1/T2 output, see core/samples.py and
# core/model/datasheet.py).
NOMINAL_OFFSET = 0.5
NOMINAL_SENSITIVITY = 0.04
# A published sample's `static` is the detector's latest decision only while that decision is at most this much
# sensor time older than the sample (null beyond): it is one analysis block old when the processing thread keeps
# up, and the detection signal is itself a 0.5 Hz low-pass; a starved processing thread (a loaded host, a
# time-lapse emulator) would otherwise label seconds of later motion with an old "still".
STATIC_MAX_AGE_S = 2.0
# The engine's parameter vector (daemon/_engine.h): the correction's CP_N slots (core/correction.py), then these
EP_GYRO_BIAS, EP_GYRO_SENS, EP_LAST_SEQ, EP_HAVE_LAST, EP_STILL, EP_MAX_AGE = range(CP_N, CP_N + 6)
assert EP_MAX_AGE + 1 == EP_N, "daemon/_engine.h and processing.py disagree on the engine's parameters"


def engine_params(cal: Calibration, fs_hz: float, gyro: tuple[float, float] = (math.nan, math.nan),
                  analysed: tuple[int | None, bool] = (None, False)) -> np.ndarray:
    """The engine's whole parameter vector: ``cal`` corrected in m/s² (every term it carries), the gyro's (bias
    [counts], sensitivity [counts per rad/s]), the detector's latest decision (seq or None, still)."""
    v = np.zeros(EP_N)
    v[:CP_N] = correction_params(cal, STANDARD_GRAVITY, fs_hz)
    v[EP_GYRO_BIAS:EP_GYRO_SENS + 1] = gyro
    v[EP_LAST_SEQ:EP_STILL + 1] = _decision_slots(analysed)
    v[EP_MAX_AGE] = STATIC_MAX_AGE_S * fs_hz
    return v


def _decision_slots(analysed: tuple[int | None, bool]) -> tuple[float, float, float]:
    last, still = analysed
    return 0.0 if last is None else float(last), float(last is not None), float(still)

# The emulated/reference board's gyro path (docs/gyro.md, core/model/enc03j.py): ENC-03J on the
# board's y axis, 0.3 Hz high-pass conditioning, ±300 °/s, 12-bit ADC. The start sensitivity is
# the datasheet chain (0.67 mV/°/s x 7.5 gain on 12 bits at 3.3 V) when [gyro] gives none.
GYRO_AXIS = (0.0, 1.0, 0.0)
GYRO_HP_HZ = 0.3
GYRO_RANGE_RAD_S = math.radians(300.0)
GYRO_RAILS = (0, 4095)
GYRO_NOMINAL_COUNTS_PER_RAD_S = 357.36


def nominal_calibration(model: str = "6") -> Calibration:
    cal = Calibration.nominal(np.full(3, NOMINAL_OFFSET), NOMINAL_SENSITIVITY, model=model)
    cal.converged = False
    cal.observable = False
    return cal


class Processor:
    """Detector -> online calibrator -> correction for one stream of sample blocks.

    ``start`` is the calibration state to start from, ``resumed`` whether it is a saved state the
    estimator continues, ``lab`` the lab calibration when configured (its frame makes the full order
    "12"). ``detector`` may be given by tests; it is built from the configuration otherwise.
    ``window_sink`` receives each window before it is fed (``--record-windows``: an offline replay).
    """

    def __init__(self, cfg: Config, start: CalibrationState, *, resumed: bool, detector: Any = None,
                 lab: Calibration | None = None, window_sink: Callable[[Window], None] | None = None):
        self.cfg = cfg
        self.state = start
        self.lab = lab
        self.window_sink = window_sink
        # the per-sample engine and its parameters: written whole (under the lock) at each swap of correction,
        # gyro_correction or analysed; the engine copies them (Engine.set_params)
        self.engine = Engine()
        self._params = np.zeros(EP_N)
        self._params[EP_MAX_AGE] = STATIC_MAX_AGE_S * cfg.device.fs_hz
        self._params_lock = threading.Lock()
        # (seq of the last analysed sample, the detector's decision there): one tuple, swapped atomically, read by
        # correct() in the acquisition thread; seq None before any analysis
        self.analysed: tuple[int | None, bool] = (None, False)
        self.corrected_seq: int | None = None  # seq of the last sample corrected (the analysis lag is from it)
        self.static_unknown = 0  # corrected samples whose `static` was unknown (the detector too far behind)
        # Corrections the analysis changed, held until the acquisition thread takes them with the CALIB that
        # announces them (take_pending), so a client sees every sample after a CALIB corrected with it and none
        # before. Off: they apply at once (one thread, as in tests and offline use).
        self.defer_corrections = False
        self._pending: dict[str, Any] = {}
        self._pending_lock = threading.Lock()
        self.applied = start.calibration  # what corrects the published samples until an update is accepted
        self.applied_revision: int | None = start.revision if start.accepted else None
        saved_remount = start.extra.get("remount") if resumed else None
        e = cfg.estimator
        self.online = OnlineCalibrator.for_service(
            start.calibration, model=e.model, extended_terms=e.extended_terms, lab=lab, resumed=resumed,
            min_windows=e.min_windows, fs=cfg.device.fs_hz, process_noise=e.process_noise if e.process_noise > 0 else None,
            windows_base=int(start.calibration.n_windows) if resumed else 0,
            remount_events=list(saved_remount) if isinstance(saved_remount, list) else None)
        self.policy = self.online.policy
        self.detector = detector if detector is not None else self._make_detector()
        self.detector.to_g = self.applied
        self.changed = False
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
        self.gyro_json: dict[str, Any] = self._gyro_json(self.gyro_cal.calibration, self.gyro_start)
        # (bias [counts], sensitivity [counts per rad/s]) used by correct() and the C step (daemon/fastpath.py):
        # one tuple, swapped atomically
        self.gyro_correction = self.gyro_start

    def _gyro_json(self, cal: Any, applied: tuple[float, float]) -> dict[str, Any]:
        """The ``gyro`` object of CALIB: the estimator's result plus what the published rate uses."""
        out = cal.to_json_dict()
        b, s = applied
        out["applied"] = {"bias": b if math.isfinite(b) else None, "sensitivity": s if math.isfinite(s) else None}
        return out

    def _gyro_window(self, w: Window) -> bool:
        """One window to the gyro calibration (its rule: core.gyro ``OnlineGyroCalibrator.feed``); True when
        it changed, and then the published rate's correction follows it."""
        if not self.gyro_cal.feed(w, self.applied):
            return False
        self._gyro_apply()
        return True

    def _gyro_apply(self) -> None:
        corr = self.gyro_cal.correction(self.gyro_start)
        self.gyro_json = self._gyro_json(self.gyro_cal.calibration, corr)
        self._swap("gyro_correction", corr)

    def _swap(self, name: str, value: Any) -> None:
        """Set a correction the published samples use (``correction`` or ``gyro_correction``): at once, or held
        for take_pending when ``defer_corrections``."""
        if not self.defer_corrections:
            setattr(self, name, value)
            return
        with self._pending_lock:
            self._pending[name] = value

    def stage_message(self, message: dict[str, Any]) -> None:
        """The CALIB that announces the held corrections (the latest replaces an untaken one)."""
        with self._pending_lock:
            self._pending["message"] = message

    @property
    def has_pending(self) -> bool:
        """A CALIB is staged: its corrections are taken with it, not before (an analysis block may accept a
        calibration long before it ends and the CALIB is made)."""
        return "message" in self._pending

    @property
    def corrections_pending(self) -> bool:
        return bool(self._pending) and not self.has_pending

    def take_pending(self) -> dict[str, Any] | None:
        """The held CALIB message (or None), after applying the held corrections. The caller pushes the message
        before it corrects another sample: the acquisition thread, so the stream orders them exactly."""
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        for name in ("correction", "gyro_correction"):
            if name in pending:
                setattr(self, name, pending[name])
        return pending.get("message")

    def reconfigure(self, cfg: Config) -> None:
        """Live changes (SIGHUP): detector settings rebuild the detector."""
        old = self.cfg
        self.cfg = cfg
        if cfg.detector != old.detector:
            self.detector = self._make_detector()
            self.detector.to_g = self.applied
        self.policy.s.min_windows = cfg.estimator.min_windows
        if cfg.gyro != old.gyro:  # new start values; estimated ones keep precedence
            g = cfg.gyro
            self.gyro_start = (float(g.zero_counts), float(g.counts_per_rad_s))
            self._gyro_apply()

    # what the engine corrects and labels the samples with (each swapped whole, then handed to the engine) ------
    def _set_params(self, at: int, values: Any) -> None:
        with self._params_lock:
            self._params[at:at + np.size(values)] = values
            self.engine.set_params(self._params)

    @property
    def analysed(self) -> tuple[int | None, bool]:
        return self._analysed

    @analysed.setter
    def analysed(self, value: tuple[int | None, bool]) -> None:
        self._analysed = value
        self._set_params(EP_LAST_SEQ, _decision_slots(value))

    @property
    def correction(self) -> np.ndarray:
        """The accepted calibration as the engine's correction vector (core/correction.py correction_params)."""
        return self._correction

    @correction.setter
    def correction(self, value: np.ndarray) -> None:
        self._correction = value
        self._set_params(0, value)

    @property
    def gyro_correction(self) -> tuple[float, float]:
        return self._gyro_correction

    @gyro_correction.setter
    def gyro_correction(self, value: tuple[float, float]) -> None:
        self._gyro_correction = value
        self._set_params(EP_GYRO_BIAS, value)

    # per block ------------------------------------------------------------------------
    @property
    def applied(self) -> Calibration:
        """The accepted calibration that corrects the published samples."""
        return self._applied

    @applied.setter
    def applied(self, cal: Calibration) -> None:
        self._applied = cal
        # every term the calibration carries, at each sample's covariates, in the engine (a calibration whose terms
        # need the samples' history is refused here: UncorrectableTerm names it)
        self._swap("correction", correction_params(cal, STANDARD_GRAVITY, self.cfg.device.fs_hz))

    @property
    def static_now(self) -> bool:
        """The detector's latest per-sample decision."""
        return self.analysed[1]

    def correct(self, block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Python path's blocks, corrected by the engine as the C step corrects its own: (acc [m/s²] (N, 3)
        with the accepted calibration and its terms at each sample's covariates, gyro [rad/s] (N,) NaN when not
        configured, static (N,) codes: the detector's latest decision, or unknown when that is more than
        STATIC_MAX_AGE_S of data old)."""
        block = np.ascontiguousarray(block)
        n = block.shape[0]
        acc, gyro, static = np.empty((n, 3)), np.empty(n), np.empty(n, dtype=np.int8)
        self.static_unknown += self.engine.correct(block, acc, gyro, static)
        if n:
            self.corrected_seq = int(block["seq"][-1])
        return acc, gyro, static

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
        """Feed one window to the online calibrator and publish what comes back."""
        if self.window_sink is not None:
            self.window_sink(w)
        step = self.online.feed(w)
        if step.remount is not None:
            self.changed = True
        if step.calibration is not None:
            self._publish(step)

    def _publish(self, step: OnlineStep) -> None:
        """A new revision of the calibration state; an accepted one corrects the published samples."""
        extra = dict(self.state.extra)
        if self.policy.remount_events:
            extra["remount"] = list(self.policy.remount_events)
        self.state = CalibrationState(step.calibration, self.state.revision + 1, time.time(), step.accepted, extra)
        if step.accepted:
            self.applied = step.calibration
            self.applied_revision = self.state.revision
            self.detector.to_g = step.calibration
        self.changed = True

    @property
    def remount_events(self) -> list[dict[str, Any]]:
        return self.policy.remount_events

    def calib_extra(self) -> dict[str, Any]:
        """CALIB fields beyond the calibration: the extended parameters (model name, names, values, per-term
        magnitudes with std) when the calibration has extended terms, every extended candidate's status
        (chosen / not warranted / not observable / untestable, with the reason), and the re-mount events."""
        cal = self.state.calibration
        # the sample the estimator had analysed up to when it made this revision (a client can tell which data a
        # calibration rests on; it lags the published samples when the processing thread falls behind)
        out: dict[str, Any] = {"remount": list(self.policy.remount_events), "data_through_seq": self.analysed[0]}
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
        return {"model": st["model"], "reason": st["reason"], "seeded": self.policy.seeded,
                "refitting": self.policy.refitting, "stored_windows": st["stored"], "reseeds": st["n_reseeds"],
                "extended_terms": st["extended_terms"]}
