"""Stepwise forward selection of effects on one cable, judged on held-out time blocks.

The recording is cut into ``n_blocks`` time blocks; even blocks train, odd blocks are held
out, so both halves see every regime of a repeated motion. Each step fits every remaining
candidate on top of the effects already kept (their nonlinear parameters held, their
linear ones re-solved with the candidate's), scores it on the held-out blocks, and keeps
the best one only if

* it lowers the held-out sum of squares by at least ``rel_min`` of it (relative) and by
  ``abs_min_n2`` per held-out sample in N^2 (absolute),
* the lowering is significant against the noise: >= ``z_holdout`` standard errors
  (:func:`holdout_z`; the error estimated from block sums, so that residuals correlated
  in time do not inflate it),
* after a joint refit of every kept effect with it, its parameters differ from the
  nominal (neutral) values by at least ``z_min`` standard errors.

Confusable effects (delay / lowpass / inertia, gain / coulomb, drift / offset) are then
each swapped for their rivals and refitted jointly; the held-out comparison says whether
the data can tell them apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gateway.diagnose.fit import (
    FitResult,
    Spec,
    best_start,
    block_sse,
    joint_fit,
    linear_refit,
    spec_for,
)
from gateway.diagnose.forward import Forward

ROUNDS = 3
RIVALS: dict[str, tuple[str, ...]] = {
    "delay": ("lowpass", "inertia"),
    "lowpass": ("delay", "inertia"),
    "inertia": ("delay", "lowpass"),
    "gain": ("coulomb",),
    "coulomb": ("gain",),
    "drift": ("offset",),
    "offset": ("drift",),
}


@dataclass(frozen=True)
class Thresholds:
    """Acceptance thresholds (see the module docstring)."""

    rel_min: float = 0.003
    abs_min_n2: float = 1e-6
    z_holdout: float = 4.0
    z_screen: float = 2.0
    z_separate: float = 3.0
    z_min: float = 4.0
    max_effects: int = 6


@dataclass
class Rival:
    """A confusable alternative fitted in place of a kept effect."""

    effect: str
    holdout_sse: float
    separable: bool


@dataclass
class CableOutcome:
    """What the selection kept on one cable, in the order it was kept."""

    kept: list[str]
    theta: dict[str, np.ndarray]
    stderr: dict[str, np.ndarray]
    specs: dict[str, Spec]
    rivals: dict[str, list[Rival]] = field(default_factory=dict)
    tried: list[str] = field(default_factory=list)


def holdout_z(sse_a: np.ndarray, sse_b: np.ndarray, cross: np.ndarray) -> float:
    """How many standard errors model B's held-out SSE lies below model A's.

    ``sse_a``, ``sse_b``: per held-out block; ``cross``: per block ``sum r_b (p_b - p_a)``
    (residual of B times the difference of the predictions). If B adds nothing real, the
    decrease ``sum(sse_a - sse_b) = sum(2 r_b d + d^2)`` has its noise in ``2 sum r_b d``,
    whose variance is estimated from the block sums (robust to residuals correlated within
    a block).
    """
    gain = float(sse_a.sum() - sse_b.sum())
    noise = 2.0 * math.sqrt(float(np.sum(cross**2)))
    if noise == 0.0:
        return math.inf if gain > 0 else 0.0
    return gain / noise


def significance(spec: Spec, theta: np.ndarray, se: np.ndarray, effect: str) -> float:
    """Largest |parameter - neutral| / stderr of an effect (amplitude for eccentricity)."""
    if effect == "eccentricity":
        amp = math.hypot(theta[0], theta[1])
        se_amp = math.hypot(theta[0] * se[0], theta[1] * se[1]) / max(amp, 1e-300)
        return amp / se_amp if se_amp > 0 else 0.0
    dev = np.abs(theta - spec.neutral)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(se > 0, dev / se, 0.0)
    return float(np.nanmax(z)) if z.size else 0.0


class CableSelector:
    """Forward selection for one cable (``fw``) over ``candidates``."""

    def __init__(
        self,
        fw: Forward,
        blocks: np.ndarray,
        n_blocks: int,
        candidates: list[str],
        th: Thresholds,
        stride: int = 1,
        usable: np.ndarray | None = None,
    ) -> None:
        """``usable`` (N,) bool: samples that may be scored (None: all; warm-up excluded)."""
        self.fw, self.blocks, self.nb = fw, blocks, n_blocks
        use = np.ones(blocks.shape, bool) if usable is None else usable
        self.train = (blocks % 2 == 0) & use
        self.test = (blocks % 2 == 1) & use
        self.candidates = candidates
        self.th = th
        self.stride = stride

    def _test_sse(self, pred: np.ndarray) -> np.ndarray:
        sse = block_sse(self.fw.data.ts - pred, self.blocks, self.nb, self.test)
        return sse[1::2]

    def _z(self, pred_a: np.ndarray, pred_b: np.ndarray) -> float:
        """Held-out z of model B (``pred_b``) over model A."""
        r_b = self.fw.data.ts - pred_b
        cross = np.bincount(
            self.blocks[self.test], weights=(r_b * (pred_b - pred_a))[self.test], minlength=self.nb
        )
        return holdout_z(self._test_sse(pred_a), self._test_sse(pred_b), cross)

    def _accept(self, pred_a: np.ndarray, pred_b: np.ndarray, z_min: float) -> bool:
        before, after = self._test_sse(pred_a), self._test_sse(pred_b)
        gain = float(before.sum() - after.sum())
        n_test = int(self.test.sum())
        return (
            gain >= self.th.rel_min * float(before.sum())
            and gain >= self.th.abs_min_n2 * n_test
            and self._z(pred_a, pred_b) >= z_min
        )

    def _screen(
        self, kept: dict[str, np.ndarray], effect: str, pred: np.ndarray, specs: dict[str, Spec]
    ):
        """Fit ``effect`` on top of ``kept`` for ranking.

        The best of the effect's starting points (grids, periodogram) with its linear
        parameters solved by one Gauss-Newton step, then one joint step on the linear
        parameters of the kept effects and the new one (:func:`linear_refit`); only the
        effect that is taken is refined by least squares (jointly with the kept ones),
        which keeps a step cheap.
        """
        spec = spec_for(effect, self.fw.data, self.fw.nom, self.fw.data.ts - pred, self.train)
        start = best_start(self.fw, kept, effect, spec, self.train)
        theta = {**kept, effect: start}
        if kept:
            theta = linear_refit(self.fw, theta, {**specs, effect: spec}, self.train)
        nan = {effect: np.full(start.size, np.nan)}
        return spec, FitResult({effect: theta[effect]}, nan, self.fw.predict(theta), True)

    def run(self) -> CableOutcome:
        """Rounds of forward steps, swaps and the strict backward check (until a forward
        pass adds nothing, at most ``ROUNDS``), then the confusable rivals."""
        state: tuple = ({}, {}, {}, self.fw.predict({}))
        order: list[str] = []
        for _ in range(ROUNDS):
            before = set(state[0])
            state, order = self._forward(state, order)
            if set(state[0]) == before:
                break  # nothing new: the swaps and the check of the last round stand
            state = self._swap(*state)
            state = self._backward(*state)
        kept, specs, stderr, pred = state
        order = [e for e in order if e in kept] + [e for e in kept if e not in order]
        out = CableOutcome(order, kept, stderr, specs)
        out.rivals = self._rivals(kept, specs, pred)
        return out

    def _forward(self, state: tuple, order: list[str]) -> tuple[tuple, list[str]]:
        """Add the best candidate while one passes the (lenient) forward test."""
        kept, specs, stderr, pred = state
        order = list(order)
        while len(kept) < self.th.max_effects:
            best = None
            for effect in (c for c in self.candidates if c not in kept):
                spec, fit = self._screen(kept, effect, pred, specs)
                after = self._test_sse(fit.pred)
                ok = self._accept(pred, fit.pred, self.th.z_screen)
                if ok and (best is None or after.sum() < best[2]):
                    best = (effect, spec, float(after.sum()), fit)
            if best is None:
                break
            effect, spec, _, fit = best
            trial_specs = {**specs, effect: spec}
            joint = joint_fit(
                self.fw,
                {**kept, effect: fit.theta[effect]},
                trial_specs,
                self.train,
                stride=self.stride,
            )
            if not self._accept(pred, joint.pred, self.th.z_screen):
                break
            kept, specs, stderr, pred = joint.theta, trial_specs, joint.stderr, joint.pred
            order.append(effect)
        return (kept, specs, stderr, pred), order

    def _backward(self, kept, specs, stderr, pred):
        """Drop, one at a time, the weakest kept effect that fails the strict test.

        With every kept effect in the model the residual is close to the noise, so the
        held-out z and the parameter standard errors are trustworthy here (during the
        forward steps the residual still holds the effects not yet found).
        """
        while kept:
            weakest, worst = None, math.inf
            for effect in kept:
                rest = {k: v for k, v in kept.items() if k != effect}
                fit = (
                    joint_fit(
                        self.fw,
                        rest,
                        {k: specs[k] for k in rest},
                        self.train,
                        max_nfev=30,
                        stride=self.stride,
                    )
                    if rest
                    else None
                )
                reduced = fit.pred if fit else self.fw.predict({})
                z_par = significance(specs[effect], kept[effect], stderr[effect], effect)
                ok = self._accept(reduced, pred, self.th.z_holdout) and z_par >= self.th.z_min
                score = self._z(reduced, pred)
                if not ok and score < worst:
                    weakest, worst = (effect, fit), score
            if weakest is None:
                break
            effect, fit = weakest
            kept = {k: v for k, v in kept.items() if k != effect}
            specs = {k: specs[k] for k in kept}
            if fit is None:
                return {}, {}, {}, self.fw.predict({})
            kept, stderr, pred = fit.theta, fit.stderr, fit.pred
        return kept, specs, stderr, pred

    def _swap(self, kept, specs, stderr, pred):
        """One pass of swaps: replace a kept effect by another candidate if that fits the
        held-out data significantly better (greedy selection can take a near-collinear
        stand-in first, e.g. an offset for a gain on a load that varies little)."""
        for effect in list(kept):
            if effect not in kept:
                continue
            rest = {k: v for k, v in kept.items() if k != effect}
            screened = []
            for cand in (c for c in self.candidates if c not in kept):
                spec, fit = self._screen(
                    rest, cand, self.fw.predict(rest), {k: specs[k] for k in rest}
                )
                screened.append((float(self._test_sse(fit.pred).sum()), cand, spec, fit))
            screened.sort(key=lambda row: row[0])
            for _, cand, spec, fit in screened[:2]:  # the two best, each refitted jointly
                trial_specs = {**{k: specs[k] for k in rest}, cand: spec}
                joint = joint_fit(
                    self.fw,
                    {**rest, cand: fit.theta[cand]},
                    trial_specs,
                    self.train,
                    stride=self.stride,
                )
                z_par = significance(spec, joint.theta[cand], joint.stderr[cand], cand)
                if self._accept(pred, joint.pred, self.th.z_screen) and z_par >= self.th.z_min:
                    kept, specs, stderr, pred = joint.theta, trial_specs, joint.stderr, joint.pred
                    break
        return kept, specs, stderr, pred

    def _rivals(self, kept, specs, pred) -> dict[str, list[Rival]]:
        """Swap each confusable kept effect for each rival; compare on held-out blocks."""
        result: dict[str, list[Rival]] = {}
        for effect in kept:
            rows = []
            for rival in RIVALS.get(effect, ()):
                if rival in kept or rival not in self.candidates:
                    continue
                rest = {k: v for k, v in kept.items() if k != effect}
                base_pred = self.fw.predict(rest)
                spec = spec_for(
                    rival, self.fw.data, self.fw.nom, self.fw.data.ts - base_pred, self.train
                )
                start = best_start(self.fw, rest, rival, spec, self.train)
                rest_specs = {k: specs[k] for k in rest}
                fit = joint_fit(
                    self.fw,
                    {**rest, rival: start},
                    {**rest_specs, rival: spec},
                    self.train,
                    max_nfev=30,
                    stride=self.stride,
                )
                separable = self._z(fit.pred, pred) >= self.th.z_separate
                rows.append(Rival(rival, float(self._test_sse(fit.pred).sum()), separable))
            if rows:
                result[effect] = rows
        return result
