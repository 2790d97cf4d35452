"""The online policy: every decision from a quasi-static window to an accepted calibration.

``OnlineCalibrator.feed(window)`` runs it (``core/estimators/online.py`` holds the order-selecting,
re-seeded recursion it drives); the service (gravcald), ``gravcal demo`` and an offline replay all
feed windows and publish what comes back, so they make the same decisions on the same windows.

Per window, in this order:

1. **Screen.** A window with a NaN/inf mean, covariance, sample count or time (``validate_windows``)
   reaches neither the seed pool, the re-mount detector nor the recursion: one such window in the pool
   would make every seed fit refuse the pool. A NaN covariate (aux) mean is not screened: it leaves the
   terms that need that covariate untestable. A window whose samples move more than ``MAX_WINDOW_STD_G``
   on an axis averages postures (a slow turn at constant |a|) and is not quasi-static. Both: counted, not used.
2. **Re-mount.** The gravity direction under the accepted calibration feeds the re-mount detector
   (core/estimators/remount.py); an event is reported, the calibration stays valid.
3. **Update** the recursion (``OnlineCalibrator.update``: order by observability, extended terms by
   evidence, re-seeds). A window its 5 sigma gate rejects is counted.
4. **Bootstrap.** From a far-off start (the datasheet values are up to ~1 g off) the order rule at that
   start cannot be trusted: windows are pooled (:class:`SeedPool`) and, from ``SEED_WINDOWS_PER_PARAM``
   per parameter on, fitted in batch (LottersBatch, eq. 11a, with its outlier gate); the first converged
   and observable fit seeds the recursion. The recursion's own re-seeds are not gated: with drifting
   parameters the oldest stored windows sit off a fit of the whole store.
5. **Give up.** When the recursion rejects 20 windows in a row or ``GIVE_UP_REJECTIONS`` of the last
   ``GIVE_UP_OF`` (a changed sensor, or a resumed state of another sensor), the windows from then on are
   pooled and fitted afresh; until that fit is usable the current values are published, not accepted.
6. **Accept.** A calibration is accepted -- used for the corrected samples and saved -- when it
   converged, is observable, is not provisional, is not in doubt (fewer than ``SUSPECT_REJECTIONS`` of
   the last ``SUSPECT_OF`` windows rejected) and rests on at least ``min_windows`` windows.
"""
from __future__ import annotations

import collections
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..windows import MAX_WINDOW_STD_G, Window, WindowSet, validate_windows, window_std_g
from .lotters import LottersBatch, resolve_parameterization
from .observability import ORDER_LADDER
from .remount import RemountDetector

log = logging.getLogger(__name__)


SUSPECT_REJECTIONS, SUSPECT_OF = 3, 10  # rejected among the last SUSPECT_OF: acceptance withdrawn until they agree
# A jump of one offset is invisible to windows with that axis horizontal, so rejections alternate with
# acceptances (and the accepted ones drag the other parameters along): GIVE_UP_REJECTIONS of the last GIVE_UP_OF
# rejected means a changed sensor; a working recursion rejects ~none with a 5 sigma gate.
GIVE_UP_REJECTIONS, GIVE_UP_OF = 10, 20
MAX_SEED_WINDOWS = 300  # windows kept for the batch fit that seeds the recursion
SEED_OUTLIER_GATE_SIGMA = 5.0  # the seed fit's outlier gate (LottersBatch), as the recursion's gate
SEED_RETRY_EVERY = 10  # windows between seed fits when no new orientation arrived
# With as many windows as parameters a batch fit matches them exactly and can pass its own observability check
# while 30 % off (6 windows of the six-position scenario); twice as many leave residual degrees of freedom.
SEED_WINDOWS_PER_PARAM = 2
MAX_REMOUNT_EVENTS = 20  # re-mount events kept (and saved)


def online_candidates(model: str, extended_terms: str | tuple[str, ...]) -> tuple[str, ...]:
    """The orders (ORDER_LADDER) and extended models ("<order>+<term>", orders >= 6) for a configured order
    and a comma-separated list (or tuple) of extended terms."""
    if model not in ORDER_LADDER:
        raise ValueError(f"unknown model order {model!r}; choose one of {', '.join(ORDER_LADDER)}")
    base = ORDER_LADDER[model]
    terms = [t.strip() for t in extended_terms.split(",")] if isinstance(extended_terms, str) else list(extended_terms)
    return base + tuple(f"{b}+{t}" for t in terms if t for b in base if b != "offsets")


class SeedPool:
    """The windows kept for the batch fit that seeds (or re-seeds) the recursion.

    At most ``capacity`` windows. When full, the oldest window of the most crowded direction cell goes,
    so the rare orientations that make the parameters observable (a lie-down in a day of sitting and
    standing) stay in the pool instead of ageing out. Directions are taken under ``to_g`` (the start
    calibration: rough, but good enough to tell postures apart) and binned in cells of about 20°.
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


@dataclass
class PolicySettings:
    """What the policy needs beyond the recursion: the configured order (the seed fit's), the windows
    before an acceptance, the sample rate [Hz] (a window's duration when its times are missing), whether
    the start is trusted (a resumed state: no bootstrap), the windows that state already rests on, and
    its saved re-mount events."""

    model: str = "6"
    min_windows: int = 6
    fs: float = 100.0
    seeded: bool = False
    windows_base: int = 0
    remount_events: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class OnlineStep:
    """What one window did. ``calibration``: a new revision to publish (None: nothing changed), with
    ``accepted`` its verdict; ``screened`` / ``rejected``: the window was not used / gated out;
    ``remount``: a re-mount event detected at this window (JSON dict)."""

    calibration: Calibration | None = None
    accepted: bool = False
    screened: bool = False
    rejected: bool = False
    remount: dict[str, Any] | None = None


class OnlinePolicy:
    """The decisions of the module docstring for one OnlineCalibrator (``oc``), state explicit."""

    def __init__(self, oc: Any, settings: PolicySettings, start: Calibration, lab: Calibration | None = None):
        self.oc = oc
        self.s = settings
        self.lab = lab
        self.start = start  # the batch fit's starting point
        self.applied = start  # the accepted calibration: directions for the screen, the pool and re-mounts
        self.accepted = False  # the verdict of the last published revision
        self.pool = SeedPool(MAX_SEED_WINDOWS, start)
        self.seeded = settings.seeded  # the recursion runs from a batch fit (or a resumed state), not the raw start
        self.refitting = False  # the recursion gave up: a new pool of post-change windows is being fitted
        self.recent_rejections: collections.deque[bool] = collections.deque(maxlen=GIVE_UP_OF)
        self.windows_base = settings.windows_base
        self.windows_seen = self.windows_screened = self.windows_rejected = 0
        self._since_try = 0
        self.remount = RemountDetector()
        self.remount_events: list[dict[str, Any]] = list(settings.remount_events)

    # -- per window ------------------------------------------------------------------------
    def feed(self, w: Window) -> OnlineStep:
        self.windows_seen += 1
        try:
            one = WindowSet.from_windows([w])
            validate_windows(one)
        except ValueError as exc:
            self.windows_screened += 1
            log.warning("window at sample %d screened out: %s", w.start, exc)
            return OnlineStep(screened=True)
        if float(window_std_g(one, self.applied)[0]) > MAX_WINDOW_STD_G:
            self.windows_screened += 1
            return OnlineStep(screened=True)
        self.pool.add(w)
        self._since_try += 1
        step = OnlineStep(remount=self._remount(w))
        oc = self.oc
        rec = oc.recursive
        before = rec.n_rejected if rec is not None else 0
        try:
            cal = oc.update(w)
        except ValueError as exc:  # a window the estimator cannot use (non-finite): skip it, never crash
            log.warning("window skipped by the estimator: %s", exc)
            return step
        rejected = oc.recursive is not None and oc.recursive is rec and rec.n_rejected > before
        if oc.recursive is not rec:
            self.recent_rejections.clear()  # a new recursion (re-seed): its own record
        self.recent_rejections.append(rejected)
        step.rejected = rejected
        if rejected:
            self.windows_rejected += 1
        if not self.seeded and not (oc.model != "none" and not oc.provisional):
            seed = self._seed_fit()
            if seed is None:
                if oc.model != "none":  # provisional offsets: published (not accepted), as information
                    self._publish(step, cal)
                return step
            self.seeded = True
            self.windows_base = 0
            oc.adopt(seed, windows=self.pool.window_set())
            cal = oc.calibration
        elif self.refitting or (rejected and (not cal.converged or sum(self.recent_rejections) >= GIVE_UP_REJECTIONS)):
            if not self.refitting:
                log.warning("the recursive estimator rejected %d of the last %d windows (%d in a row); fitting the "
                            "windows from now on afresh", sum(self.recent_rejections), len(self.recent_rejections),
                            oc.recursive.consecutive_rejected)
                self.refitting = True
                self.pool = SeedPool(MAX_SEED_WINDOWS, self.applied)
                self.pool.add(w)
            refit = self._seed_fit()
            if refit is None or not (refit.converged and refit.observable):
                self._publish(step, cal, suspect=True)
                return step
            log.warning("re-fitted after the recursion gave up: %d windows, order %s", refit.n_windows, refit.model)
            oc.adopt(refit, clear_store=True, windows=self.pool.window_set())
            self.refitting = False
            self.recent_rejections.clear()
            cal = oc.calibration
        elif rejected:
            if self.suspect() and self.accepted:
                self._publish(step, cal)  # several recent rejections: in doubt, acceptance withdrawn
            return step  # an isolated outlier window: nothing changed
        self._publish(step, cal)
        return step

    def suspect(self) -> bool:
        return sum(list(self.recent_rejections)[-SUSPECT_OF:]) >= SUSPECT_REJECTIONS

    def _publish(self, step: OnlineStep, cal: Calibration, *, suspect: bool = False) -> None:
        cal.n_windows = self.windows_base + self.oc.n_windows
        suspect = suspect or self.suspect()
        if suspect and cal.converged:
            n = sum(list(self.recent_rejections)[-SUSPECT_OF:])
            cal.message = "; ".join(m for m in (cal.message, f"{n} of the last {SUSPECT_OF} windows contradict "
                                                "this calibration (sensor changed?): not accepted until they agree "
                                                "again or a re-fit replaces it") if m)
        accepted = bool(cal.converged and cal.observable and not self.oc.provisional and not suspect
                        and cal.n_windows >= self.s.min_windows and (self.seeded or self.oc.model != "none"))
        self.accepted = accepted
        if accepted:
            self.applied = cal
        step.calibration, step.accepted = cal, accepted

    def _remount(self, w: Window) -> dict[str, Any] | None:
        """Posture statistics for the re-mount detector: the gravity direction of the window under the
        accepted calibration. A re-mount leaves the calibration valid (the norm does not see the housing's
        rotation on the body); it is reported, not corrected."""
        if not self.applied.converged:
            return None
        a = self.applied.apply_reference(np.asarray(w.mean, dtype=float)[None, :])[0]
        dur = float(w.t_end - w.t_start) if w.t_end > w.t_start else max(w.n, 1) / self.s.fs
        ev = self.remount.update(float(w.t_mid), a, dur)
        if ev is None:
            return None
        d = ev.to_json_dict()
        self.remount_events = (self.remount_events + [d])[-MAX_REMOUNT_EVENTS:]
        log.warning("sensor re-mount detected at sensor time %.0f s: the upright gravity direction turned by "
                    "%.0f° (%s rule); the calibration stays valid, posture/body-frame interpretations do not",
                    ev.t, ev.angle_deg, ev.rule)
        return d

    # -- the bootstrap / re-fit batch fit ---------------------------------------------------
    def seed_windows_needed(self) -> int:
        """Windows before the seed fit is tried: SEED_WINDOWS_PER_PARAM per parameter, and ``min_windows``."""
        n = resolve_parameterization(self.s.model, self.start).n_params
        return max(self.s.min_windows, SEED_WINDOWS_PER_PARAM * n, 1)

    def _seed_fit(self) -> Calibration | None:
        """Batch fit (eq. 11a, outlier-gated) over the pooled windows; returned when converged and
        observable at one of the candidate orders, None otherwise."""
        if len(self.pool) < self.seed_windows_needed():
            return None
        if not (self.pool.new_cell or self._since_try >= SEED_RETRY_EVERY or self.refitting):
            return None  # the same postures again: the fit would not change its verdict
        self._since_try = 0
        model = self.s.model
        if model == "12" and self.lab is None and self.start.model != "12":
            model = "9"  # no frame to hold: the online estimator's full order is 9
        try:  # from the start values; LottersBatch retries from an ellipsoid fit when they are far off
            cal = LottersBatch(model, outlier_gate_sigma=SEED_OUTLIER_GATE_SIGMA).fit(self.pool.window_set(),
                                                                                      start=self.start)
        except ValueError as exc:  # e.g. too few distinct orientations yet
            log.debug("seed batch fit not possible yet: %s", exc)
            return None
        if not (cal.converged and cal.observable) or cal.model not in self.oc.candidates:
            return None
        return cal

    def stats(self) -> dict[str, Any]:
        return {"seeded": self.seeded, "refitting": self.refitting, "windows_seen": self.windows_seen,
                "windows_screened": self.windows_screened, "windows_rejected": self.windows_rejected}
