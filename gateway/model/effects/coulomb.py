"""``coulomb``: the pulleys' bearing coefficient and a load-independent level (docs/physics.md
sec. 4).

``mu``: the bearing coefficient of *every* pulley of the cable, absolute: it replaces the
nominal per-pulley ``mu`` in both directions (NaN or absent: keep the nominal).
``f0_n``: the chain's load-independent Coulomb level (seals, brushes, preload), split evenly
over the pulleys and added to each pulley's level ``F_R = lambda T + f0 / n``, so under
Dahl it shares the pre-sliding dynamics. Friction only ever adds: both are >= 0.
"""

from __future__ import annotations

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects.base import (
    INF,
    Compose,
    Effect,
    FitData,
    ModelFile,
    NominalChain,
    Online,
    Param,
    Spec,
    Values,
    nominal_mu_mean,
)


def move_from_nominal(old: np.ndarray, new: np.ndarray, nominal: float) -> np.ndarray:
    """An absolute coefficient corrected on top of a model: the model's value (its nominal
    where NaN) moved by the change the correction fitted from the nominal; NaN in ``new``
    keeps the model's value."""
    base = np.where(np.isfinite(old), old, nominal)
    return np.where(np.isfinite(new), base + (new - nominal), old)


def fit_spec(nom: NominalChain, n_mu: int) -> Spec:
    """``n_mu`` bearing coefficients (neutral: the nominal mean) and ``f0``.

    Without wrap anywhere (a rig without pulleys) only ``f0`` acts: ``mu`` is held at 0."""
    mu0 = nominal_mu_mean(nom)
    wrapped = bool(np.any(np.asarray(nom.wrap_rad, dtype=float) > 0))
    mu_hi = 0.5 if wrapped else 1e-6
    lin = tuple(range(n_mu + 1)) if wrapped else (n_mu,)
    neutral = np.array([mu0] * n_mu + [0.0])
    return Spec(
        neutral,
        np.zeros(n_mu + 1),
        np.array([mu_hi] * n_mu + [INF]),
        lin,
        np.array([1e-3] * n_mu + [0.1]),
        (neutral,),
    )


def fold_negative_f0(
    effect: str, values: Values, mu_names: tuple[str, ...], ctx: ModelFile
) -> None:
    """A negative ``f0_n`` (``mu`` and ``f0`` trade off on a cable whose tension varies
    little: the fit pins their sum ``lambda(mu) T + f0``) is folded into the coefficients
    at the cable's mean reading ``T``: ``mu' = mu + f0 / (T sum_j 2 sin(wrap_j / 2))``,
    ``f0' = 0`` (the same Coulomb level there), in place; named in ``ctx.notes``."""
    if ctx.mean_reading is None:
        return
    f0 = values["f0_n"]
    k = float(np.sum(2.0 * np.sin(0.5 * np.asarray(ctx.friction.wrap_rad, dtype=float))))
    tension = ctx.mean_reading
    fold = (f0 < 0) & (tension > 0) & (k > 0)
    for name in mu_names:
        fold &= np.isfinite(values[name])
    if not np.any(fold):
        return
    for i in np.flatnonzero(fold):
        old = ", ".join(f"{n} {values[n][i]:.4g}" for n in mu_names)
        new = [max(values[n][i] + f0[i] / (tension[i] * k), 0.0) for n in mu_names]
        for n, v in zip(mu_names, new, strict=True):
            values[n][i] = v
        written = ", ".join(f"{n} {v:.4g}" for n, v in zip(mu_names, new, strict=True))
        ctx.notes.append(
            f"folded: {effect} on cable {i + 1}: fitted {old}, f0_n {f0[i]:.4g}; written as "
            f"{written}, f0_n 0 (the same level at its mean {tension[i]:.0f} N)"
        )
        f0[i] = 0.0


class Coulomb(Effect):
    name = "coulomb"
    stage = "chain"
    params = (
        Param(
            "mu",
            "1",
            float("nan"),
            low=0.0,
            high=0.5,
            step=1e-3,
            nominal="mu_mean",
            doc="bearing coefficient of every pulley (absolute)",
        ),
        Param("f0_n", "N", 0.0, low=0.0, step=0.1, doc="load-independent level of the chain"),
    )
    physics = "- sgn(v) (lambda T + f0): per-pulley mu (absolute), load-independent f0"
    online = Online(True, "the chain's Coulomb level")
    needs_motion = True
    wrench = True
    group = "scale"
    look = (
        "the residual flips sign with the direction of motion and scales with the load "
        "(plot residual against sgn(v) T)"
    )
    plot = "sgn(v)*T"
    separate = "standstill at several loads (a gain acts at rest, friction does not)"
    example = {"mu": 0.025}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        mu = p["mu"]
        given = np.isfinite(mu)
        draft.mu[given] = np.maximum(mu[given], 0.0)[:, None]
        draft.mu_in[given] = np.maximum(mu[given], 0.0)[:, None]
        draft.f0_n = draft.f0_n + p["f0_n"]
        draft.needs_friction()

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        return fit_spec(nom, 1)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {
            "mu": move_from_nominal(old["mu"], new["mu"], ctx.nominal_mu),
            "f0_n": old["f0_n"] + new["f0_n"],
        }

    def to_model(self, values: Values, ctx: ModelFile) -> None:
        fold_negative_f0(self.name, values, ("mu",), ctx)


EFFECT = Coulomb()
