"""Forward models of the candidate effects (docs/physics.md sec. 4) for one cable.

Every candidate is a set of parameters acting on the nominal model, by its stage: a
statics effect changes the platform tension through the statics (``dTp_dm`` below), a
chain-side one the :class:`gateway.model.chain_schema.ChainParams` that
:func:`gateway.model.chain_runs.run` simulates, the path and sensor ones act on the chain's
output in their order (:func:`gateway.model.effects.forward`).

Internal parameter vectors (what the fit varies) and reported parameters
(docs/recording-format.md) differ only where a transform helps the fit (each effect's
``internal`` / ``report``, e.g. a stiffness fitted as its ``log10``).
Everything is one cable: arrays (N,), parameters scalars.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gateway.diagnose.sessions import mean_stderr, mean_theta, per_recording, session_values
from gateway.model import effects as fx
from gateway.model.chain_runs import run
from gateway.model.chain_schema import ChainParams

CHAIN_EFFECTS = (*fx.stage_of("statics"), *fx.stage_of("chain"))
"""Effects that change the chain simulation (the cache key of :class:`Forward`)."""
ALL_EFFECTS = fx.EFFECT_NAMES


class CableData:
    """One cable's series. ``t``, ``v``, ``tp``, ``ts`` (N,): s, m/s, N, N.

    ``x`` displacement (m, ``x0`` at the first sample) and ``a`` acceleration (m/s^2) from
    ``v``, except that ``x`` is ``length - length[0] + x0`` where the recording's cable
    lengths ``length`` (m) are given: an integrated velocity drifts away from a measured
    length (a filtered derivative's bias, the jumps across a gap between joined trials:
    up to 3 mm on the da Vinci's 5 mm stroke); ``t0`` the recording's first time (drift
    is ``k (t - t0)``; several recordings joined: (N,) each sample's recording start, and
    ``session`` (N,) its recording, :mod:`.sessions`); ``dtp_dm`` (N,) N/kg, the change
    of platform tension per kg of platform mass (None: no pose/mass, no ``mass_change``).
    ``x`` and ``a`` are given (a subset of a longer recording takes them from the whole
    recording) or computed from ``t`` and ``v`` when first read and dropped again by
    :meth:`release` (memory: 16 bytes per sample that only the cable being worked on holds;
    recomputing them gives the same values bit for bit). ``dtp_dm`` may be given as a
    function that computes it (e.g. interpolates knots): then it is computed when first
    read and dropped by :meth:`release` as well.
    """

    def __init__(
        self,
        t: np.ndarray,
        v: np.ndarray,
        tp: np.ndarray,
        ts: np.ndarray,
        t0: float | np.ndarray,
        dtp_dm: np.ndarray | Callable[[], np.ndarray] | None = None,
        x: np.ndarray | None = None,
        a: np.ndarray | None = None,
        x0: float = 0.0,
        length: np.ndarray | None = None,
        session: np.ndarray | None = None,
    ) -> None:
        self.t, self.v, self.tp, self.ts, self.t0, self.x0 = t, v, tp, ts, t0, x0
        self.session = session
        self.length = length
        self._given = x is not None or a is not None
        self._x, self._a = x, a
        self._dm_source = dtp_dm if callable(dtp_dm) else None
        self._dm = None if callable(dtp_dm) else dtp_dm

    @property
    def dtp_dm(self) -> np.ndarray | None:
        if self._dm is None and self._dm_source is not None:
            self._dm = self._dm_source()
        return self._dm

    @property
    def x(self) -> np.ndarray:
        if self._x is None:
            if self.length is not None:
                self._x = np.asarray(self.length, dtype=float) - float(self.length[0])
            else:
                self._x = fx.displacement(self.t, self.v)
            if self.x0:
                self._x += self.x0
        return self._x

    @property
    def a(self) -> np.ndarray:
        if self._a is None:
            self._a = fx.acceleration(self.t, self.v) if self.t.size > 1 else np.zeros_like(self.v)
        return self._a

    def release(self) -> None:
        """Drop ``x``, ``a`` and ``dtp_dm`` when they were computed here (the next read
        recomputes)."""
        if not self._given:
            self._x = self._a = None
        if self._dm_source is not None:
            self._dm = None

    def subset(self, idx: np.ndarray) -> CableData:
        """The samples ``idx`` (sorted), keeping ``x``, ``a`` and ``t0`` of the whole."""
        dm = None if self.dtp_dm is None else self.dtp_dm[idx]
        return CableData(
            self.t[idx],
            self.v[idx],
            self.tp[idx],
            self.ts[idx],
            self.t0_at(idx),
            dm,
            self.x[idx],
            self.a[idx],
            session=None if self.session is None else self.session[idx],
        )

    def t0_at(self, idx: np.ndarray):
        """``t0`` for the samples ``idx`` (a float, or their recordings' starts)."""
        return self.t0[idx] if isinstance(self.t0, np.ndarray) else self.t0


@dataclass(frozen=True)
class Nominal:
    """The nominal chain of one cable: model, per-pulley wrap and mu, sigma, beta, viscous."""

    model: str
    wrap_rad: np.ndarray
    mu: np.ndarray
    sigma_n_m: float
    beta: float
    viscous_ns_m: float
    pulley_radius_m: float

    @property
    def mu_mean(self) -> float:
        return float(np.mean(self.mu)) if self.mu.size else 0.0


def to_report(effect: str, theta: np.ndarray) -> dict[str, float]:
    """Internal parameter vector -> reported parameters (names and units of
    docs/recording-format.md); one fitted per recording: its mean (:mod:`.sessions`)."""
    if per_recording(effect, np.size(theta)) > 1:
        theta = mean_theta(effect, theta)
    return fx.REGISTRY[effect].report(np.asarray(theta, dtype=float))


def report_stderr(effect: str, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
    """Standard errors of the reported parameters (delta method for the transforms)."""
    if per_recording(effect, np.size(theta)) > 1:
        theta, se = mean_theta(effect, theta), mean_stderr(effect, theta, se)
    return fx.REGISTRY[effect].report_stderr(np.asarray(theta, dtype=float), np.asarray(se))


def report_values(
    eff: dict[str, np.ndarray], *stages: str, session: np.ndarray | None = None
) -> fx.Effects:
    """Internal vectors of the effects of ``stages`` -> report values as (1,) arrays; an
    effect fitted per recording (:mod:`.sessions`) as (N,) arrays on a joined series
    (``session``: each sample's recording), as its mean over the recordings on another."""
    return {e.name: session_values(e.name, eff[e.name], session) for e in fx.ordered(eff, *stages)}


def chain_params(nom: Nominal, eff: dict[str, np.ndarray]) -> ChainParams:
    """One cable's ChainParams with the chain-side effects in ``eff`` (internal parameter
    vectors) applied by the registry's :func:`gateway.model.effects.chain_params`."""
    return fx.chain_params(nom, report_values(eff, "chain"), 1)


PRUNE_MARGIN = 1e-6
"""Relative margin of :meth:`Forward.predict_bounded`'s stop (the partial sums and the
caller's sum over every sample round differently)."""

CACHE_BYTES = 10 << 20
"""Memory for one :class:`Forward`'s cached chain simulations (speed only, never results)."""


class Forward:
    """Prediction of one cable's sensor reading for a set of effects, with a chain cache.

    The chain simulation is the expensive part; it is cached on the friction-side
    parameters so that varying a sensor or path parameter costs no new simulation.
    """

    def __init__(self, data: CableData, nom: Nominal, cache_size: int = 6) -> None:
        self.data = data
        self.nom = nom
        self._cache: dict[tuple, np.ndarray] = {}
        # at most CACHE_BYTES of simulations (but 2): 4.8 MB each for a 10-min cable
        fit = CACHE_BYTES // max(8 * data.t.size, 1)
        self._cache_size = max(min(cache_size, fit), min(cache_size, 2))
        self.simulations = 0
        self.starts: dict[bytes, np.ndarray] = {}
        """:func:`gateway.diagnose.fit.best_start`'s results by a digest of everything
        they depend on (a few numbers each: the selection screens the same candidate on the
        same model more than once, e.g. again in the next round when nothing changed)."""
        self.start_hint: dict[str, int] = {}
        """The index of the start that won each effect's last :func:`best_start`."""

    def clear_cache(self) -> None:
        """Free the cached chain simulations, the remembered starts and the data's computed
        ``x`` and ``a``."""
        self._cache.clear()
        self.starts.clear()
        self.start_hint.clear()
        self.data.release()

    @staticmethod
    def _key(eff: dict[str, np.ndarray]) -> tuple:
        return tuple((k, tuple(np.round(eff[k], 14))) for k in CHAIN_EFFECTS if k in eff)

    def keep(self, eff: dict[str, np.ndarray], out: np.ndarray) -> None:
        """Put ``out``, the chain output of ``eff`` (from :meth:`chain`), back into the
        cache as its newest entry (the next :meth:`chain` of ``eff`` then needs no
        simulation)."""
        key = self._key(eff)
        self._cache.pop(key, None)
        self._put(key, out)

    def chain(self, eff: dict[str, np.ndarray]) -> np.ndarray:
        """Sensor-side tension (N,) from the friction chain (and mass change) alone."""
        key = self._key(eff)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        params, tp = self._chain_input(eff)
        d = self.data
        out = run(params, "simulate", tp[:, None], d.v[:, None], d.t)[:, 0]
        self._store(key, out)
        return out

    def _chain_input(self, eff: dict[str, np.ndarray]) -> tuple[ChainParams, np.ndarray]:
        d = self.data
        tp = d.tp
        # t0: per-sample recording starts on a joined series (elementwise, :mod:`.sessions`)
        delta = fx.mass_delta(report_values(eff, "statics"), d.t, d.t0)  # type: ignore[arg-type]
        if delta is not None and d.dtp_dm is not None:
            tp = tp + delta * d.dtp_dm
        return chain_params(self.nom, eff), tp

    def _store(self, key: tuple, out: np.ndarray) -> None:
        """A new simulation into the cache (counted)."""
        self.simulations += 1
        self._put(key, out)

    def _put(self, key: tuple, out: np.ndarray) -> None:
        """``out`` as the cache's newest entry, the oldest evicted when it is full."""
        if len(self._cache) >= self._cache_size:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = out

    def predict_bounded(
        self, eff: dict[str, np.ndarray], mask: np.ndarray, bound: float
    ) -> np.ndarray | None:
        """:meth:`predict`, or None once its squared error on the samples ``mask`` is
        certain to exceed ``bound``: the chain simulated batch by batch
        (:func:`gateway.model.chain_runs.run`'s ``pieces``) and stopped when the error of the rows
        done already does (by a margin far above rounding). Only without path and sensor
        effects (the reading is then the chain's output, row by row); else, or with the
        simulation cached, :meth:`predict`. A prediction returned is :meth:`predict`'s,
        bit for bit."""
        key = self._key(eff)
        if not math.isfinite(bound) or key in self._cache or fx.ordered(eff, "path", "sensor"):
            return self.predict(eff)
        params, tp = self._chain_input(eff)
        d = self.data
        out2 = np.empty((d.t.size, 1))
        limit = bound * (1.0 + PRUNE_MARGIN)
        done, sse = 0, 0.0
        pieces = run(params, "simulate", tp[:, None], d.v[:, None], d.t, out=out2, pieces=True)
        for _, rows, _ in pieces:
            r = (d.ts[done:rows] - out2[done:rows, 0])[mask[done:rows]]
            sse += float(r @ r)
            done = rows
            if sse > limit and rows < d.t.size:
                return None
        out = out2[:, 0]
        self._store(key, out)
        return out

    def predict(self, eff: dict[str, np.ndarray]) -> np.ndarray:
        """The sensor reading (N,) the nominal model plus ``eff`` predicts (N)."""
        values = report_values(eff, "path", "sensor", session=self.data.session)
        return fx.forward(self.data, self.chain(eff), values)  # type: ignore[arg-type]  # t0
