"""The Cx/Cy output filter of each channel."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import Context, register
from ..datasheet import CX_TOL, CX_UF
from ..spec import TermSpec
from ..stateful import StatefulTerm


@register
class AnalogLowpass(StatefulTerm):
    """The Cx/Cy filter: one pole at f_3dB = 5 µF / C per channel (RFILT = 32 kohm on chip).

    params: ``c_uf`` (4,) filter capacitors [µF]. Discretised at the simulation rate with a
    matched pole exp(-2 pi f_3dB / fs). State: the lfilter state per channel; the first block
    starts settled on its first sample (the sensor was on before the session started).
    """

    name = "analog_lowpass"
    stage = "channel"
    order = 60

    def __init__(self, c_uf: Any = np.full(4, CX_UF), **params: Any):
        super().__init__(c_uf=c_uf, **params)

    @property
    def f3db_hz(self) -> np.ndarray:
        return 5.0 / self.params["c_uf"]

    def _coeffs(self, fs: float) -> list[tuple[np.ndarray, np.ndarray]]:
        pole = np.exp(-2.0 * np.pi * self.f3db_hz / fs)
        return [(np.array([1.0 - p]), np.array([1.0, -p])) for p in pole]

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        from scipy import signal  # noqa: PLC0415 (scipy.signal is heavy; only the simulator needs it)

        x0 = np.asarray(x, float)[0] if len(x) else np.zeros(4)
        coeffs = self._coeffs(ctx.fs)
        return {"coeffs": coeffs, "zi": [signal.lfilter_zi(b, a) * x0[c] for c, (b, a) in enumerate(coeffs)]}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        from scipy import signal  # noqa: PLC0415 (scipy.signal is heavy; only the simulator needs it)

        st = self.current_state(x, ctx)
        out = np.empty_like(np.asarray(x, float))
        for c, (b, a) in enumerate(st["coeffs"]):  # 4 channels, each its own pole
            out[:, c], st["zi"][c] = signal.lfilter(b, a, x[:, c], zi=st["zi"][c])
        return out

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)  # unit DC gain


SPEC = TermSpec(name="analog_lowpass", forward=AnalogLowpass, prior=lambda rng: AnalogLowpass(
    c_uf=np.full(4, CX_UF) if rng is None else CX_UF * (1 + rng.uniform(-CX_TOL, CX_TOL, 4))))
