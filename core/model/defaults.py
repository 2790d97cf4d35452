"""The default model drawn from the datasheet spreads, and the calibration-level truth of a model.

Which terms exist, their priors and their ``gravcal simulate`` groups come from the registry
(``core/model/terms``); the datasheet values they draw from are in ``datasheet.py``.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..calibration import Calibration
from ..samples import TRIAD
from .base import Context, Term
from .datasheet import V_NOMINAL
from .sensor_model import SensorModel
from .terms import BASE_TERMS, CATALOGUE, GROUPS, REGISTRY, Axes, projection_matrix, term_spec


def catalogue_term(name: str, rng: Any = None, *, nominal: bool = False) -> Term:
    """The term for a catalogue or term name, drawn from the datasheet spreads (or nominal)."""
    r = None if nominal else np.random.default_rng(rng)
    return term_spec(name).prior(r)


def default_model(rng: Any = None, *, nominal: bool = False, **switches: Any) -> SensorModel:
    """The ADXL210 pair + ENC-03J model with parameters drawn from datasheet spreads.

    rng: a Generator or seed (None: fresh entropy). nominal=True: datasheet typical values, no
    draws ("+-typ" effects get +typ/-typ alternating over channels so they still act).
    ``switches``: a group name of ``GROUPS`` (the registry's ``group`` of each term)
    switches on its terms (a Term or dict value for a group named like its one term overrides it);
    a term or catalogue name: False drops the term, True adds it, a dict replaces some of its
    params, a Term replaces it. Each term draws from its own seeded stream (registry order), so
    switching one term on or off does not change the draws of the others.
    """
    gen = np.random.default_rng(rng)
    seeds = dict(zip(REGISTRY, gen.integers(0, 2**63 - 1, len(REGISTRY))))

    def build(name: str) -> Term:
        return REGISTRY[name].prior(None if nominal else np.random.default_rng(int(seeds[name])))

    groups: dict[str, bool] = {}
    overrides: dict[str, Any] = {}
    for key, value in switches.items():
        if key in GROUPS:
            if isinstance(value, (Term, dict)) and GROUPS[key] == (key,):
                overrides[key], value = value, True
            groups[key] = bool(value)
        else:
            overrides[key] = value
    names = list(BASE_TERMS)
    for group, on in groups.items():
        if on:
            names += GROUPS[group]
    if any(n != "axes" and issubclass(REGISTRY[n].forward, Axes) for n in names):
        names.remove("axes")  # a physical projection replaces the ideal one
    terms: dict[str, Term] = {n: build(n) for n in names}
    for group, on in groups.items():  # groups that change base terms (the temperature group: the oscillator)
        varied = [n for n in terms if group in REGISTRY[n].variants]
        if on and varied:
            r = None if nominal else np.random.default_rng(int(seeds[GROUPS[group][-1]]) + 1)
            for n in varied:
                terms[n] = REGISTRY[n].variants[group](terms[n], r)

    for key, value in overrides.items():
        name = CATALOGUE.get(key, key)
        if name not in REGISTRY:
            raise ValueError(f"default_model: unknown override {key!r}, neither a registered term ({', '.join(REGISTRY)}) "
                             f"nor a group ({', '.join(GROUPS)})")
        if value is False or value is None:
            terms.pop(name, None)
        elif value is True:
            terms[name] = terms.get(name) or build(name)
        elif isinstance(value, Term):
            if value.name != name:
                raise ValueError(f"default_model: override {key!r} is a {value.name!r} term")
            terms[name] = value
        elif isinstance(value, dict):
            base = terms.get(name) or build(name)
            params = {k: v.tolist() for k, v in base.params.items()}
            unknown = set(value) - set(params)
            if unknown:
                raise ValueError(f"default_model: term {name!r} has no parameter(s) {sorted(unknown)}; "
                                 f"it has {sorted(params)}")
            params.update(value)
            terms[name] = type(base)(**params)
        else:
            raise ValueError(f"default_model: override {key!r} must be True, False, a dict of params or a Term")
        if name in terms and isinstance(terms[name], Axes):  # one projection of the board frame at a time
            for other in [n for n, t in terms.items() if n != name and isinstance(t, Axes)]:
                terms.pop(other)
    return SensorModel(list(terms.values()))


def linear_channels(model: SensorModel, temp_c: float = 25.0, vsupply: float = V_NOMINAL,
                    t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Effective duty = S a + d of all four channels: S (4, 3) [duty/g], d (4,) [duty].

    Composes ``linear_part`` of every channel- and duty-stage term (deterministic parts:
    random walks and noise have zero mean; nonlinearity has no linear part).
    """
    ctx = Context(t=np.array([float(t)]), temp=np.array([float(temp_c)]), vsupply=np.array([float(vsupply)]),
                  fs=100.0, rng=np.random.default_rng(0))
    gain = np.ones(4)
    offset = np.zeros(4)
    for term in model.stage_terms("channel") + model.stage_terms("duty"):
        if not hasattr(term, "linear_part"):
            raise ValueError(f"term {term.name!r} has no calibration-level view (linear_part); "
                             "triad_truth cannot include it")
        g, o = term.linear_part(ctx)
        g = np.broadcast_to(np.asarray(g, float).reshape(-1), (4,))
        o = np.broadcast_to(np.asarray(o, float).reshape(-1), (4,))
        gain, offset = g * gain, g * offset + o
    return gain[:, None] * projection_matrix(model), offset


def triad_truth(model: SensorModel, temp_c: float = 25.0, vsupply: float = V_NOMINAL, t: float = 0.0) -> Calibration:
    """The effective raw = K a + o of the triad (duty cycles of ax, ay, az) at given conditions.

    This is what an ideal estimator should find: K (3x3) [duty/g] includes the axis geometry
    (off-diagonal), temperature and supply at (temp_c [°C], vsupply [V]) and deterministic
    drift at time t [s]; o [duty]. Exact for the linear part of the model.
    """
    s, d = linear_channels(model, temp_c, vsupply, t)
    tri = list(TRIAD)
    return Calibration(
        model="truth", offset=d[tri], sensitivity=s[tri], n_windows=0,
        message="true effective linear model of the simulated sensor",
        metadata={"temp_c": float(temp_c), "vsupply": float(vsupply), "t": float(t),
                  "ax2_sensitivity": s[3].tolist(), "ax2_offset": float(d[3])},
    )
