"""The catalogue (docs/physics.md sec. 4): every effect module collected, and the forms that
serve all of them by looping over it.

* :data:`REGISTRY`: effect name -> its :class:`~.base.Effect` (one module each), in the
  catalogue's order; :func:`ordered` gives the effects of a set in the order they act.
* :func:`effect_values` validates ``{effect: {parameter: scalar | per-cable list}}`` into
  per-cable arrays, naming the offending key; :func:`to_mapping` writes them back.
* :func:`chain_params`: the nominal chain with the chain-side effects applied (the plant,
  the scenarios, the diagnosis, the wrench reference and the gateway all call it, so a
  parameter means the same everywhere).
* :func:`forward` / :func:`inverse`: the path and sensor effects in batch form, in their
  order (and reversed); :class:`ForwardStepper`: per sample (the plant);
  :class:`OnlineInverse`: the gateway's per-cycle inverse of the online ones;
  :func:`compensate_online`: its batch form.
* :func:`mass_delta`: the platform mass the statics effects hide.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from gateway.fastcall import entry_point
from gateway.model.chain_runs import run
from gateway.model.chain_schema import ChainDraft, ChainParams
from gateway.model.effects import (
    backlash,
    cable_stretch,
    coulomb,
    coulomb_directional,
    coulomb_load,
    delay,
    drift,
    eccentricity,
    gain,
    inertia,
    lowpass,
    mass_change,
    maxwell_slip,
    offset,
    presliding,
    sensor_creep,
    spring,
    stribeck,
    viscous,
)
from gateway.model.effects.base import (
    STAGES,
    Effect,
    Effects,
    NominalChain,
    Sample,
    Series,
    SeriesData,
    Values,
)
from gateway.model.effects.forms import causal_acceleration

MODULES = (
    coulomb,
    coulomb_directional,
    coulomb_load,
    presliding,
    viscous,
    stribeck,
    inertia,
    delay,
    lowpass,
    gain,
    offset,
    drift,
    eccentricity,
    mass_change,
    maxwell_slip,
    cable_stretch,
    backlash,
    sensor_creep,
    spring,
)
"""The catalogue's order (reports and the model file list effects in it)."""
REGISTRY: dict[str, Effect] = {mod.EFFECT.name: mod.EFFECT for mod in MODULES}
EFFECT_NAMES: tuple[str, ...] = tuple(REGISTRY)
ONLINE_EFFECTS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.online.compensable)
"""Effects the gateway's per-cycle compensation applies."""


def _rank(e: Effect) -> tuple[int, int]:
    return STAGES.index(e.stage), e.order


ACTING = sorted(REGISTRY.values(), key=_rank)
"""Every effect in the order it acts from the platform to the reading."""


def ordered(names: Iterable[str], *stages: str) -> list[Effect]:
    """The effects of ``names`` (of the given stages; all if none given) in acting order."""
    wanted = set(names)
    return [e for e in ACTING if e.name in wanted and (not stages or e.stage in stages)]


def stage_of(stage: str) -> tuple[str, ...]:
    """The names of the effects acting at ``stage``."""
    return tuple(e.name for e in ACTING if e.stage == stage)


# ---- values -------------------------------------------------------------------------------
def _values(raw: Any, size: int, key: str) -> np.ndarray:
    if isinstance(raw, bool):
        raise ValueError(f"{key}: expected a number or a list of numbers, got {raw!r}")
    try:
        arr = np.asarray(raw, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: expected a number or a list of numbers, got {raw!r}") from None
    if arr.ndim == 0:
        return np.full(size, float(arr))
    if arr.shape != (size,):
        raise ValueError(f"{key}: expected a scalar or {size} values, got {arr.size}")
    return arr.copy()


def effect_values(
    raw: Mapping[str, Any] | None,
    cables: int,
    pulley_radius_m: float = 0.05,
    where: str = "effects",
) -> Effects:
    """Validate ``{effect: {param: scalar | per-cable list}}``; missing params get defaults.

    Errors are ``ValueError`` whose message starts with the dotted key (``where.effect.p``).
    A parameter whose absent value is its nominal (:attr:`~.base.Param.nominal`) takes
    the nominal ``pulley_radius_m`` when it names it, else stays NaN (the nominal, e.g.
    ``coulomb.mu``: the pulleys keep theirs); only such a parameter may be NaN, and only a
    parameter whose absent value is infinite (a stiffness) may be infinite. A platform
    effect has one value (shape (1,)).
    """
    nominals = {"pulley_radius_m": float(pulley_radius_m)}
    out: Effects = {}
    for name, params in (raw or {}).items():
        key = f"{where}.{name}"
        eff = REGISTRY.get(str(name))
        if eff is None:
            raise ValueError(f"{key}: unknown effect (known: {', '.join(EFFECT_NAMES)})")
        params = {} if params is None else params
        if not isinstance(params, Mapping):
            raise ValueError(f"{key}: expected a mapping of parameters")
        for p in params:
            if p not in eff.param_names:
                known = ", ".join(eff.param_names)
                raise ValueError(f"{key}.{p}: unknown parameter (known: {known})")
        size = cables if eff.per_cable else 1
        vals = {}
        for prm in eff.params:
            default = prm.default
            substituted = math.isnan(default) and prm.nominal in nominals
            if substituted:
                default = nominals[str(prm.nominal)]
            given = params.get(prm.name)  # absent or null: the default
            v = _values(default if given is None else given, size, f"{key}.{prm.name}")
            nan_means_nominal = math.isnan(prm.default) and not substituted
            finite_or_absent = np.isfinite(v) | (v == prm.default)  # an absent k = inf
            if not nan_means_nominal and not np.all(finite_or_absent):
                raise ValueError(f"{key}.{prm.name}: values must be finite")
            reason = prm.check(v)
            if reason:
                raise ValueError(f"{key}.{prm.name}: {reason}")
            vals[prm.name] = v
        out[eff.name] = vals
    return out


def to_mapping(eff: Effects) -> dict[str, dict[str, float | list[float]]]:
    """Plain YAML-ready form of validated values: a scalar where all cables agree; a
    parameter that is NaN everywhere (the nominal) is left out."""
    out: dict[str, dict[str, float | list[float]]] = {}
    for name in EFFECT_NAMES:
        if name not in eff:
            continue
        params: dict[str, float | list[float]] = {}
        for p, v in eff[name].items():
            if np.all(np.isnan(v)):
                continue
            same = v.size == 1 or bool(np.all(v == v[0]))
            params[p] = float(v[0]) if same else [float(x) for x in v]
        out[name] = params
    return out


# ---- the chain ----------------------------------------------------------------------------
def chain_params(
    nominal: NominalChain, eff: Effects, cables: int, online_only: bool = False
) -> ChainParams:
    """The nominal chain with the chain-side effects of ``eff`` applied, ``cables`` wide
    (only the ones the gateway compensates online with ``online_only``: the gateway's
    chain).

    ``nominal.mu``: per pulley (n,) or (m, n); each chain-side effect edits the chain's
    draft (:class:`gateway.model.chain_schema.ChainDraft`) in the catalogue's order
    (:meth:`~.base.Effect.apply_chain`).
    """
    draft = ChainDraft.nominal(nominal, cables)
    for e in ordered(eff, "chain"):
        if online_only and not e.online.compensable:
            continue
        e.apply_chain(draft, eff[e.name])
    return draft.params()


def mass_delta(eff: Effects, t: np.ndarray, t0: float) -> np.ndarray | None:
    """The platform mass (kg, (N,)) the statics effects of ``eff`` add to the recorded one,
    or None when there are none."""
    out = None
    for e in ordered(eff, "statics"):
        d = e.mass_delta(t, t0, eff[e.name])
        out = d if out is None else out + d
    return out


# ---- path and sensor forms ----------------------------------------------------------------
def forward(s: Series, y: np.ndarray, eff: Effects) -> np.ndarray:
    """The reading with the path and sensor effects of ``eff``, in acting order (batch)."""
    for e in ordered(eff, "path", "sensor"):
        y = e.forward(s, y, eff[e.name])
    return y


def inverse(s: Series, y: np.ndarray, eff: Effects, online_only: bool = False) -> np.ndarray:
    """:func:`forward` undone, effect by effect in reverse order (only the ones the gateway
    removes online with ``online_only``)."""
    for e in reversed(ordered(eff, "path", "sensor")):
        if online_only and not e.online.compensable:
            continue
        y = e.inverse(s, y, eff[e.name])
    return y


class ForwardStepper:
    """Per-sample form of :func:`forward` (the soft PLC's plant runs it cycle by cycle):
    each effect's :meth:`~.base.Effect.stepper` in acting order. Not causal (the truth
    may look one sample ahead); the gateway's causal form is :class:`OnlineInverse`."""

    def __init__(self, eff: Effects, cables: int, period_s: float) -> None:
        self.steppers = [
            e.stepper(eff[e.name], cables, period_s) for e in ordered(eff, "path", "sensor")
        ]

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        for st in self.steppers:
            y = st.step(s, y)
        return y


def online_params(e: Effect, values: Values, cables: int) -> np.ndarray:
    """An online kernel's parameters: (k, m), one row per parameter of ``e``, then its
    :attr:`~.base.Effect.online_state` rows (zeros)."""
    rows = [np.broadcast_to(np.asarray(values[n], dtype=float), (cables,)) for n in e.param_names]
    rows += [np.zeros(cables)] * e.online_state
    return np.ascontiguousarray(np.stack(rows))


class OnlineInverse:
    """The gateway's per-cycle inverse of the online path and sensor effects of ``eff``:
    each effect's compiled :attr:`~.base.Effect.online_kernel`, in reverse acting order,
    called on the caller's own buffers (compiled entries, no type dispatch, no allocation).

    ``y_in``, ``out`` (m,): the validated reading and the chain's sensor-side input;
    ``v``, ``v_prev`` (m,): this and the previous PLC sample's setpoint velocity; ``length``
    (m,): the setpoint cable length; ``dt``: the time between the two samples (s; <= 0 on
    the first); ``new``: False when the cycle reads the same PLC sample again (an effect
    with state, :attr:`~.base.Effect.online_state`, then starts again from its state before
    that sample, so a repeated sample does not advance it twice).
    """

    def __init__(
        self,
        eff: Effects,
        cables: int,
        out: np.ndarray,
        v: np.ndarray,
        v_prev: np.ndarray,
        length: np.ndarray,
    ) -> None:
        self.steps = []
        self.stateful: list[tuple[np.ndarray, np.ndarray]] = []  # (rows, their saved copy)
        for e in reversed(ordered(eff, "path", "sensor")):
            if not e.online.compensable or e.online_kernel is None:
                continue
            p = online_params(e, eff[e.name], cables)
            entry = entry_point(e.online_kernel, p, out, v, v_prev, 0.0, length)
            self.steps.append((entry, p))
            if e.online_state:
                self.stateful.append((p, p.copy()))
        self.names = tuple(
            e.name
            for e in reversed(ordered(eff, "path", "sensor"))
            if e.online.compensable and e.online_kernel is not None
        )

    def __call__(
        self,
        y_in: np.ndarray,
        out: np.ndarray,
        v: np.ndarray,
        v_prev: np.ndarray,
        dt: float,
        length: np.ndarray,
        new: bool = True,
    ) -> None:
        for p, saved in self.stateful:
            if new:
                saved[:] = p
            else:
                p[:] = saved
        out[:] = y_in
        for entry, p in self.steps:
            entry(p, out, v, v_prev, dt, length)


def compensate_online(
    params: ChainParams,
    eff: Effects,
    t: np.ndarray,
    reading: np.ndarray,
    velocity: np.ndarray,
    length: np.ndarray,
) -> np.ndarray:
    """Batch form of the gateway's compensation: reading (N, m) -> platform tension (N, m).

    The online path and sensor effects undone in reverse order (the acceleration the
    backward difference of the setpoint velocity, ``x`` the setpoint ``length``), then the
    chain (sensor -> platform) with ``dt`` from ``t``.
    """
    t = np.asarray(t, dtype=float)
    s = SeriesData(
        t,
        velocity,
        np.asarray(length, dtype=float),
        causal_acceleration(t, velocity),
        float(t[0]) if t.size else 0.0,
    )
    ts = inverse(s, np.asarray(reading, dtype=float), eff, online_only=True)
    return run(params, "compensate", ts, velocity, t)
