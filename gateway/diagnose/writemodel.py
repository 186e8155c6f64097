"""The fitted model file: what ``diagnose --write-model`` writes, and how a model file's
fitted effects take part when it is read back as ``diagnose --model``.

**Writing** (:func:`write_model`): the nominal model plus every effect of the report's
findings, in the ``friction.effects`` form of docs/physics.md sec. 5 (the registry's
report names; a scalar where every cable has the same value, else one value per cable).
A cable a finding does not name gets the effect's neutral value (``coulomb.mu``: the
nominal pulleys' mean ``mu``, exact when the pulleys share one ``mu``; left out when no
cable has a fitted ``mu``). When ``--model`` was a full config the file is that config with its
``friction:`` replaced, else it holds the ``friction:`` mapping alone. Effects the model
already carried are composed with the new findings (:func:`compose`): the diagnosis ran
relative to them (below), so a finding is a correction on top.

Conversions: the wrench reference fits ``coulomb.mu`` as one coefficient per cable that
scales the nominal per-pulley profile; the model file's ``mu`` is the same for every pulley
of a cable (absolute), which is that mean. An ``eccentricity`` phase fitted against the
travel since the first sample is converted to the cable length
(:func:`gateway.model.effects.eccentricity_phase_at_length`) where the recording has
lengths. ``mass_change`` is one platform value (the median over the cables that carry it
in the platform-tension reference).

**Reading back** (:func:`relative_to_model`): the diagnosis fits candidates on a nominal
chain. A model file with ``friction.effects`` is honoured by diagnosing an equivalent
recording: its readings are carried to the platform by the model *with* its effects (the
gateway's own compensation, :func:`gateway.model.effects.compensate_online`, after the
offline-only sensor effects ``delay``, ``lowpass``, ``drift`` are undone) and back to the
sensor by the nominal chain alone; a ``mass_change`` adds ``q (t - t_0)`` to the ``mass``
column. A model that explains the recording therefore leaves nothing to find (verdict
``none``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gateway.core.config import FrictionConfig
from gateway.core.configtypes import read_yaml
from gateway.errors import ConfigError, GatewayError
from gateway.model import chain
from gateway.model import effects as fx
from gateway.recordings.reader import Recording

ADDITIVE = ("viscous", "offset", "drift", "inertia", "mass_change")
"""Effects whose correction on top of a model adds to the model's value."""


def fitted_effects(report: dict[str, Any], cables: int, rec: Recording | None = None) -> fx.Effects:
    """The findings of a diagnosis report as per-cable arrays (registry names)."""
    out: fx.Effects = {}
    for finding in report.get("findings", []):
        name = finding["effect"]
        eff = fx.REGISTRY[name]
        idx = [int(c) - 1 for c in finding["cables"]]
        values: dict[str, np.ndarray] = {}
        for prm in eff.params:
            given = np.asarray(finding["parameters"].get(prm.name, []), dtype=float)
            if not eff.per_cable:
                default = prm.default if given.size == 0 else float(np.median(given))
                values[prm.name] = np.array([default])
                continue
            arr = np.full(cables, prm.default)
            if given.size == len(idx):
                arr[idx] = given
            values[prm.name] = arr
        if name == "eccentricity" and rec is not None and rec.length is not None:
            ph, r, l0 = values["phi_rad"], values["r_m"], rec.length[0]
            values["phi_rad"] = np.array(
                [
                    fx.eccentricity_phase_at_length(float(ph[i]), float(r[i]), float(l0[i]))
                    for i in range(cables)
                ]
            )
        out[name] = values
    return out


def compose(old: fx.Effects, new: fx.Effects, nominal_mu: float) -> fx.Effects:
    """Effects of a model (``old``) with the corrections a diagnosis relative to it found
    (``new``): additive ones add, gain multiplies (an offset found on top is scaled by the
    old gain), ``coulomb.mu`` moves by the fitted change from the nominal, ``f0_n`` adds;
    the others (presliding, stribeck, eccentricity, delay, lowpass) are replaced."""
    out = {k: {p: v.copy() for p, v in params.items()} for k, params in old.items()}
    for name, params in new.items():
        if name not in out:
            out[name] = {p: v.copy() for p, v in params.items()}
        elif name in ADDITIVE:
            scale = 1.0 + old["gain"]["g"] if name == "offset" and "gain" in old else 1.0
            for p, v in params.items():
                out[name][p] = out[name][p] + scale * v
        elif name == "gain":
            out[name]["g"] = (1.0 + out[name]["g"]) * (1.0 + params["g"]) - 1.0
        elif name == "coulomb":
            old_mu = np.where(np.isfinite(out[name]["mu"]), out[name]["mu"], nominal_mu)
            moved = old_mu + (params["mu"] - nominal_mu)
            out[name]["mu"] = np.where(np.isfinite(params["mu"]), moved, out[name]["mu"])
            out[name]["f0_n"] = out[name]["f0_n"] + params["f0_n"]
        else:
            out[name] = {p: v.copy() for p, v in params.items()}
    return out


def fitted_friction(
    friction: FrictionConfig,
    report: dict[str, Any],
    cables: int,
    rec: Recording | None = None,
    notes: list[str] | None = None,
) -> FrictionConfig:
    """``friction`` with the report's findings composed onto its effects (values outside
    the admissible range clamped, named in ``notes``)."""
    try:
        old = friction.effect_values(cables)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    nominal_mu = float(np.mean(friction.mu)) if friction.pulleys else 0.0
    total = compose(old, fitted_effects(report, cables, rec), nominal_mu)
    mu = total.get("coulomb", {}).get("mu")
    if mu is not None and np.any(np.isnan(mu)) and not np.all(np.isnan(mu)):
        mu[np.isnan(mu)] = nominal_mu  # a file holds no NaN: the nominal pulleys' mean mu
    if rec is not None and "coulomb" in total:
        fold_negative_f0(total["coulomb"], friction, rec, notes)
    clamp_to_admissible(total, notes)
    return dataclasses.replace(friction, effects=FrictionConfig.effects_mapping(total))


def fold_negative_f0(
    coulomb: dict[str, np.ndarray], friction: FrictionConfig, rec: Recording,
    notes: list[str] | None,
) -> None:  # fmt: skip
    """A negative ``f0_n`` (``mu`` and ``f0`` trade off on a cable whose tension varies
    little: the fit pins their sum ``lambda(mu) T + f0``) is folded into ``mu`` at the
    cable's mean reading ``T``: ``mu' = mu + f0 / (T sum_j 2 sin(wrap_j / 2))``, ``f0' = 0``
    (the same Coulomb level there), in place; named in ``notes``."""
    f0, mu = coulomb["f0_n"], coulomb["mu"]
    k = float(np.sum(2.0 * np.sin(0.5 * np.asarray(friction.wrap_rad, dtype=float))))
    tension = np.nanmean(np.asarray(rec.tension_sensor, dtype=float), axis=0)
    fold = (f0 < 0) & np.isfinite(mu) & (tension > 0) & (k > 0)
    if not np.any(fold):
        return
    new_mu = np.maximum(mu[fold] + f0[fold] / (tension[fold] * k), 0.0)
    if notes is not None:
        for i, m_new in zip(np.flatnonzero(fold), new_mu, strict=True):
            notes.append(
                f"folded: coulomb on cable {i + 1}: fitted mu {mu[i]:.4g}, f0_n {f0[i]:.4g}; "
                f"written as mu {m_new:.4g}, f0_n 0 (the same level at its mean {tension[i]:.0f} N)"
            )
    mu[fold], f0[fold] = new_mu, 0.0


def clamp_to_admissible(eff: fx.Effects, notes: list[str] | None = None) -> None:
    """Fitted values outside what the model file admits (``coulomb.f0_n`` < 0, a gain
    <= -1, ...: a fit on a cable whose parameters trade off) are set to the nearest
    admissible value, in place; each is named in ``notes``."""
    for name, values in eff.items():
        for prm in fx.REGISTRY[name].params:
            v = values[prm.name]
            low = prm.low + (1e-9 if prm.low_open else 0.0)
            bad = np.isfinite(v) & (v < low)
            if prm.low_open:
                bad |= np.isfinite(v) & (v <= prm.low)
            if np.any(bad):
                cables = ", ".join(str(i + 1) for i in np.flatnonzero(bad))
                if notes is not None:
                    notes.append(
                        f"clamped: {name}.{prm.name} on cable {cables}: fitted "
                        f"{', '.join(f'{x:.4g}' for x in v[bad])}, written as {low:g} "
                        "(the smallest admissible)"
                    )
                v[bad] = low


def write_model(
    path: Path,
    model_path: Path,
    friction: FrictionConfig,
    report: dict[str, Any],
    rec: Recording | None = None,
) -> FrictionConfig:
    """Write the fitted model file ``path`` (module docstring); returns its friction.
    Folded and clamped values (:func:`fold_negative_f0`, :func:`clamp_to_admissible`) are
    named in the file's header."""
    notes: list[str] = []
    fitted = fitted_friction(friction, report, int(report["cables"]), rec, notes)
    data = read_yaml(model_path)
    mapping = _plain(fitted.to_mapping())
    out = {**data, "friction": mapping} if "geometry" in data else {"friction": mapping}
    header = (
        f"# fitted model: {model_path} plus the findings of a diagnosis of "
        f"{rec.source if rec is not None else 'a recording'} (cdpr-gateway diagnose "
        "--write-model)\n"
    ) + "".join(f"# {n}\n" for n in notes)
    try:
        path.write_text(header + yaml.safe_dump(out, sort_keys=False), encoding="utf-8")
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


def relative_to_model(rec: Recording, friction: FrictionConfig) -> tuple[Recording, FrictionConfig]:
    """(the recording as the nominal chain sees it, the nominal friction) for a model with
    ``friction.effects`` (module docstring); unchanged without effects."""
    if not friction.effects:
        return rec, friction
    m = rec.cables
    try:
        eff = friction.effect_values(m)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    nominal = dataclasses.replace(friction, effects={})
    t, v = rec.t, rec.velocity
    ps = fx.path_sensor(eff, m, friction.pulley_radius_m)
    y = np.asarray(rec.tension_sensor, dtype=float)
    if "delay" in eff:  # the reading lags by d: advance it
        d = np.broadcast_to(np.asarray(ps.delay_s, dtype=float), (m,))
        y = np.stack([np.interp(t + d[i], t, y[:, i]) for i in range(m)], axis=1)
    if "lowpass" in eff:  # offline inverse of 1 / (tau s + 1)
        y = y + ps.lowpass_tau_s * np.gradient(y, t, axis=0)
    tt = (t - t[0])[:, None]
    if "drift" in eff:
        y = y - ps.drift_n_s * tt
    length = rec.length if rec.length is not None else fx.displacement(t, v)
    online = fx.online_effects(eff, m, friction.pulley_radius_m)
    tp = fx.compensate_online(fx.chain_params(friction, eff, m), online, t, y, v, length)
    ts = chain.simulate(fx.chain_params(nominal, {}, m), tp, v, t)
    mass = rec.mass
    if "mass_change" in eff and mass is not None:
        mass = mass + float(eff["mass_change"]["q_kg_s"][0]) * (t - t[0])
    if not np.all(np.isfinite(ts)):
        raise GatewayError(f"{rec.source}: the model's effects give non-finite tensions")
    return dataclasses.replace(rec, tension_sensor=ts, mass=mass), nominal
