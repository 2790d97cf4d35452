"""Settings of the Lötters et al. (1998) reproduction (core.reproduce), apart so that the command line
can show the defaults without importing the estimators."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KEYS = ("o1_all", "o1_offsets", "o2_all", "o2_offsets")
# Sect. 4: "larger than 105°", "larger than 30°", "at least 75°" (orientation 2, offsets only: sentence cut)
PAPER_THRESHOLDS_DEG = {"o1_all": 105.0, "o1_offsets": 30.0, "o2_all": 75.0}
PAPER_STRICT = {"o1_all": True, "o1_offsets": True, "o2_all": False}  # "larger than" vs "at least"
DEFAULT_THETA_STEP_DEG = 15.0
CRITERIA = ("mean", "worst")  # over the three axes: their mean (the paper's "average error"), or the worst axis
SPREADS = ("area", "angle")
C_MU_READINGS = ("std", "variance")


def theta_grid(step_deg: float) -> np.ndarray:
    """0, step, 2 step, ... up to 180° (180 included when step divides it)."""
    if not (0 < step_deg <= 180):
        raise ValueError(f"the θ step must be in (0, 180] degrees, got {step_deg:g}")
    return np.arange(0.0, 180.0 + 1e-9, step_deg)


def paper_threshold_on_grid(key: str, theta: np.ndarray) -> float:
    """The paper's threshold as the first grid point it allows ("larger than 105°" -> the first point past 105)."""
    p = PAPER_THRESHOLDS_DEG[key]
    ok = theta > p if PAPER_STRICT[key] else theta >= p
    if not ok.any():
        raise ValueError(f"the θ grid ends before the paper's threshold for {key} ({p:g}°)")
    return float(theta[np.argmax(ok)])


@dataclass
class ReproduceConfig:
    theta_deg: np.ndarray = field(default_factory=lambda: theta_grid(DEFAULT_THETA_STEP_DEG))
    seeds: int = 20
    n_points: int = 100  # quasi-static points per run (not given in the paper; see core.reproduce)
    c_mu: float = 0.05  # the paper's diagonal of C_mu
    c_mu_reading: str = "std"  # "std" [g] (supported by the paper's curves) or "variance" [g²]
    spread: str = "area"  # "area": uniform over the cap; "angle": polar angle uniform
    start_error: float = 0.05  # start within this fraction of 1 g of the truth
    held_sensitivity_error: float = 0.0  # offsets only: sensitivities held off the truth by up to this fraction
    criterion: str = "mean"  # how the three axes' errors combine into the one compared with threshold_pct
    threshold_pct: float = 3.0

    @property
    def sigma_mu_g(self) -> float:
        if self.c_mu_reading == "variance":
            return float(np.sqrt(self.c_mu))
        if self.c_mu_reading == "std":
            return float(self.c_mu)
        raise ValueError(f"c_mu_reading must be one of {', '.join(C_MU_READINGS)}, got {self.c_mu_reading!r}")

    def validate(self) -> None:
        """Raise ValueError naming the first bad setting."""
        self.sigma_mu_g  # noqa: B018 - validates the reading
        theta = np.asarray(self.theta_deg, dtype=float)
        if theta.ndim != 1 or theta.size == 0 or np.any(theta < 0) or np.any(theta > 180) or np.any(np.diff(theta) <= 0):
            raise ValueError("theta_deg must be an increasing grid within [0, 180] degrees")
        if self.seeds < 1 or self.n_points < 6:
            raise ValueError("need seeds >= 1 and n_points >= 6")
        if self.spread not in SPREADS:
            raise ValueError(f"spread must be one of {', '.join(SPREADS)}, got {self.spread!r}")
        if self.criterion not in CRITERIA:
            raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {self.criterion!r}")
        if not (0 <= self.held_sensitivity_error < 1):
            raise ValueError(f"held_sensitivity_error must be in [0, 1), got {self.held_sensitivity_error!r}")
