"""The Cx/Cy output filter of each channel."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context
from ..datasheet import CX_TOL, CX_UF
from ..filters import filter_sections, first_order_section, state_at
from ..spec import TermSpec
from ..stateful import StatefulTerm


class AnalogLowpass(StatefulTerm):
    """The Cx/Cy filter: one pole at f_3dB = 5 µF / C per channel (RFILT = 32 kohm on chip).

    params: ``c_uf`` (4,) filter capacitors [µF]. Discretised at the simulation rate with a
    matched pole exp(-2 pi f_3dB / fs). State: the filter state per channel; the first block
    starts settled on its first sample (the sensor was on before the session started).
    """

    name = "analog_lowpass"
    stage = "channel"

    def __init__(self, c_uf: Any = np.full(4, CX_UF), **params: Any):
        super().__init__(c_uf=c_uf, **params)

    @property
    def f3db_hz(self) -> np.ndarray:
        return 5.0 / self.params["c_uf"]

    def _sections(self, fs: float) -> list[np.ndarray]:
        pole = np.exp(-2.0 * np.pi * self.f3db_hz / fs)
        return [first_order_section([1.0 - p], [1.0, -p]) for p in pole]

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        x0 = np.asarray(x, float)[0] if len(x) else np.zeros(4)
        sections = self._sections(ctx.fs)
        return {"sections": sections, "zi": [state_at(sos, x0[c]) for c, sos in enumerate(sections)]}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        out = np.empty_like(np.asarray(x, float))
        for c, sos in enumerate(st["sections"]):  # 4 channels, each its own pole
            out[:, c] = filter_sections(sos, x[:, c], st["zi"][c])
        return out

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)  # unit DC gain


SPEC = TermSpec(name="analog_lowpass", forward=AnalogLowpass, prior=lambda rng: AnalogLowpass(
    c_uf=np.full(4, CX_UF) if rng is None else CX_UF * (1 + rng.uniform(-CX_TOL, CX_TOL, 4))))
