"""The fitted model file: what ``diagnose --write-model`` writes, and how a model file's
fitted effects take part when it is read back as ``diagnose --model``.

**Writing** (:func:`write_model`): the nominal model plus every effect of the report's
findings, in the ``friction.effects`` form of docs/physics.md sec. 5 (report names; a
scalar where every cable has the same value, else one value per cable). A cable a finding
does not name gets the effect's neutral value (a parameter whose absent value is the
nominal's, e.g. a bearing coefficient, gets the nominal pulleys' mean where some cables
have a fitted value; it is left out when none has). The file is the ``--model`` file byte
for byte except its ``friction.effects`` entry (:mod:`gateway.diagnose.modelfile`:
comments, layout and every other key kept). Effects the model already carried are
composed with the new findings (each effect's ``compose``): the diagnosis ran relative to
them (below), so a finding is a correction on top. What an effect needs done to a fitted
value before it goes into a file (a phase fitted against the travel converted to the cable
length, a negative level folded into its coefficient) is its ``to_model``; values outside
what a file admits are clamped; both are named in comments above that entry.

**Reading back** (:func:`relative_to_model`): the diagnosis fits candidates on a nominal
chain. A model file with ``friction.effects`` is honoured by diagnosing an equivalent
recording: its readings are carried to the platform by the model *with* its effects (every
path and sensor effect undone in reverse order by its batch inverse, with the forms the
diagnosis fits, then the chain) and back to the sensor by the nominal chain alone; a hidden
platform mass is added to the ``mass`` column (and through the statics to the platform
tensions).
A model that explains the recording therefore leaves nothing to find (verdict ``none``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from gateway.core.config import Config, FrictionConfig
from gateway.core.configtypes import read_yaml
from gateway.diagnose.modelfile import with_effects
from gateway.diagnose.pose_statics import mass_sensitivity
from gateway.errors import ConfigError, GatewayError
from gateway.model import chain_runs
from gateway.model import effects as fx
from gateway.model.effects.base import Compose, ModelFile, NominalChain
from gateway.recordings.reader import Recording


def fitted_effects(
    report: dict[str, Any], cables: int, nominal: NominalChain | None = None
) -> fx.Effects:
    """The findings of a diagnosis report as per-cable arrays (registry names); a cable a
    finding does not name gets the effect's neutral value (the ``nominal`` model's where
    the parameter's absent value is the nominal's; NaN, "the nominal", without one)."""
    out: fx.Effects = {}
    for finding in report.get("findings", []):
        name = finding["effect"]
        eff = fx.REGISTRY[name]
        neutral = eff.neutral(nominal) if nominal is not None else {}
        idx = [int(c) - 1 for c in finding["cables"]]
        values: dict[str, np.ndarray] = {}
        for prm in eff.params:
            given = np.asarray(finding["parameters"].get(prm.name, []), dtype=float)
            absent = neutral.get(prm.name, prm.default)
            if not eff.per_cable:
                default = absent if given.size == 0 else float(np.median(given))
                values[prm.name] = np.array([default])
                continue
            arr = np.full(cables, absent)
            if given.size == len(idx):
                arr[idx] = given
            values[prm.name] = arr
        out[name] = values
    return out


def compose(old: fx.Effects, new: fx.Effects, nominal_mu: float) -> fx.Effects:
    """Effects of a model (``old``) with the corrections a diagnosis relative to it found
    (``new``), each by its effect's ``compose``. A correction found inside the model's own
    sensor effects is scaled by them (``outer_gain``: e.g. an offset found on top of a
    gain)."""
    out = {k: {p: v.copy() for p, v in params.items()} for k, params in old.items()}
    outer = np.ones(1)
    for e in fx.ordered(old, "sensor"):
        factor = e.gain_factor(old[e.name])
        if factor is not None:
            outer = outer * factor
    ctx = Compose(nominal_mu, outer)
    for name, params in new.items():
        if name not in out:
            out[name] = {p: v.copy() for p, v in params.items()}
        else:
            out[name] = fx.REGISTRY[name].compose(out[name], params, ctx)
    return out


def _fill_nominal(eff: fx.Effects, friction: FrictionConfig) -> None:
    """A parameter that is the nominal where NaN gets the nominal's value on the cables
    without a fitted one when some cable has one (a file holds no NaN), in place."""
    for name, values in eff.items():
        for prm in fx.REGISTRY[name].params:
            v = values[prm.name]
            if prm.nominal and np.any(np.isnan(v)) and not np.all(np.isnan(v)):
                v[np.isnan(v)] = fx.REGISTRY[name].neutral(friction)[prm.name]


def fitted_friction(
    friction: FrictionConfig,
    report: dict[str, Any],
    cables: int,
    rec: Recording | None = None,
    notes: list[str] | None = None,
) -> FrictionConfig:
    """``friction`` with the report's findings (each effect's ``from_fit``) composed onto
    its effects, made admissible (each effect's ``to_model`` where the recording is known;
    values outside the admissible range clamped; both named in ``notes``)."""
    try:
        old = friction.effect_values(cables)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    nominal_mu = float(np.mean(friction.mu)) if friction.pulleys else 0.0
    new = fitted_effects(report, cables, friction)
    ctx = ModelFile(
        friction,
        None if rec is None or rec.length is None else np.asarray(rec.length[0], dtype=float),
        None if rec is None else np.nanmean(np.asarray(rec.tension_sensor, dtype=float), axis=0),
    )
    for name, values in new.items():
        fx.REGISTRY[name].from_fit(values, ctx)
    total = compose(old, new, nominal_mu)
    _fill_nominal(total, friction)
    if rec is not None:
        for name, values in total.items():
            fx.REGISTRY[name].to_model(values, ctx)
    clamp_to_admissible(total, ctx.notes)
    if notes is not None:
        notes.extend(ctx.notes)
    return dataclasses.replace(friction, effects=FrictionConfig.effects_mapping(total))


def clamp_to_admissible(eff: fx.Effects, notes: list[str] | None = None) -> None:
    """Fitted values outside what the model file admits (a negative level, a gain
    <= -1, ...: a fit on a cable whose parameters trade off) are set to the nearest
    admissible value, in place; each is named in ``notes``."""
    for name, values in eff.items():
        for prm in fx.REGISTRY[name].params:
            v = values[prm.name]
            fixed = np.array([prm.admissible(x) if math.isfinite(x) else x for x in v])
            bad = np.isfinite(v) & (fixed != v)
            if np.any(bad):
                cables = ", ".join(str(i + 1) for i in np.flatnonzero(bad))
                if notes is not None:
                    notes.append(
                        f"clamped: {name}.{prm.name} on cable {cables}: fitted "
                        f"{', '.join(f'{x:.4g}' for x in v[bad])}, written as "
                        f"{', '.join(f'{x:g}' for x in fixed[bad])} (the nearest admissible)"
                    )
                v[bad] = fixed[bad]


def write_model(
    path: Path,
    model_path: Path,
    friction: FrictionConfig,
    report: dict[str, Any],
    rec: Recording | None = None,
) -> FrictionConfig:
    """Write the fitted model file ``path`` (module docstring); returns its friction.
    What was done to fitted values (each effect's ``to_model``, :func:`clamp_to_admissible`)
    is named in comments above the ``effects`` entry."""
    notes: list[str] = []
    fitted = fitted_friction(friction, report, int(report["cables"]), rec, notes)
    read_yaml(model_path)  # the loader's checks and limits, before the text is taken apart
    effects = _plain(fitted.to_mapping()).get("effects", {})
    notes.insert(
        0,
        f"{model_path} plus the findings of a diagnosis of "
        f"{rec.source if rec is not None else 'a recording'}",
    )
    try:
        text = with_effects(Path(model_path).read_text(encoding="utf-8"), effects, notes)
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise GatewayError(f"{path}: cannot write the model: {exc.strerror or exc}") from exc
    return fitted


def _plain(value: Any) -> Any:
    """YAML-safe plain types (tuples -> lists, numpy scalars -> float; NaN stays NaN)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def relative_to_model(
    rec: Recording, friction: FrictionConfig, cfg: Config | None = None
) -> tuple[Recording, FrictionConfig]:
    """(the recording as the nominal chain sees it, the nominal friction) for a model with
    ``friction.effects`` (module docstring); unchanged without effects. A platform mass
    the model hides changes the ``mass`` column and, through ``dT_p/dm`` (pose, mass and
    the geometry of ``cfg``), the ``tension_platform_i`` columns."""
    if not friction.effects:
        return rec, friction
    m = rec.cables
    try:
        eff = friction.effect_values(m)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    nominal = dataclasses.replace(friction, effects={})
    t, v = rec.t, rec.velocity
    length = rec.length if rec.length is not None else fx.displacement(t, v)
    y = np.asarray(rec.tension_sensor, dtype=float)
    # the model's own inverse (the forms the diagnosis fitted, acceleration with look-ahead),
    # not the gateway's causal one: a backward difference lags by half a sample, which on
    # a fitted inertia reads as a negative viscous force (m dt / 2 w^2 v)
    series = fx.SeriesData(t, v, length, lambda: fx.acceleration(t, v), float(t[0]))
    y = fx.inverse(series, y, eff)
    tp = chain_runs.run(fx.chain_params(friction, eff, m), "compensate", y, v, t)
    ts = chain_runs.run(fx.chain_params(nominal, {}, m), "simulate", tp, v, t)
    if not np.all(np.isfinite(ts)):
        raise GatewayError(f"{rec.source}: the model's effects give non-finite tensions")
    mass, tp_rec = rec.mass, rec.tension_platform
    delta = fx.mass_delta(eff, t, float(t[0]))
    if delta is not None:
        if tp_rec is not None:
            sens = mass_sensitivity(rec, cfg)
            if sens is None:
                raise ConfigError(
                    f"{rec.source}: the model's {', '.join(fx.stage_of('statics'))} needs pose "
                    "and mass columns and the robot's geometry (--model a full config)"
                )
            tp_rec = tp_rec + delta[:, None] * sens.full(t)
        if mass is not None:
            mass = mass + delta
    out = dataclasses.replace(rec, tension_sensor=ts, mass=mass, tension_platform=tp_rec)
    return out, nominal
