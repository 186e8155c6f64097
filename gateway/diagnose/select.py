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

Confusable effects (the effects of one group, :func:`rivals`: e.g. delay / lowpass /
inertia) are then each swapped for their rivals and refitted jointly; the held-out
comparison says whether the data can tell them apart.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
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
from gateway.model import effects as fx

ROUNDS = 3
PAIR_POOL = 4
"""Singles (best held-out SSE first) whose pairs are screened when no single passes."""
PAIR_ABOVE_NOISE = 1.1
"""Pairs are screened only while the held-out RMSE exceeds the noise by this factor (a
residual at the noise holds nothing for a pair to explain)."""
SUBSET_EXTRA = 3
"""Effects besides the kept ones on the best-subset search's short list."""
FAR_ABOVE_NOISE = 3.0
"""Held-out RMSE over white noise above which the selection looks further (subsets)."""


def overlaps(effect: str, kept: Iterable[str]) -> bool:
    """``effect`` nests a kept effect or is nested by one (``Effect.nests``): together they
    would hold the same parameters twice."""
    mine = fx.REGISTRY[effect]
    return any(
        fx.REGISTRY[k] in mine.nests or mine in fx.REGISTRY[k].nests for k in kept if k != effect
    )


def rivals(effect: str) -> tuple[str, ...]:
    """The effects of ``effect``'s group (:attr:`~gateway.model.effects.Effect.group`):
    they explain much the same residual."""
    group = fx.REGISTRY[effect].group
    if not group:
        return ()
    return tuple(n for n, e in fx.REGISTRY.items() if n != effect and e.group == group)


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
class Model:
    """A selection state on one cable: fitted effects, their recipes and errors, prediction."""

    kept: dict[str, np.ndarray]
    specs: dict[str, Spec]
    stderr: dict[str, np.ndarray]
    pred: np.ndarray


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
    """How many standard errors an effect's parameters lie from the nominal model (the
    effect module's :meth:`~gateway.model.effects.Effect.significance`)."""
    return fx.REGISTRY[effect].significance(theta, se, spec.neutral)


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
        """Rounds of forward steps (pairs where no single passes), swaps and the strict
        backward check (until a forward pass adds nothing, at most ``ROUNDS``); then, while
        the held-out residual stays far above the noise, a best-subset search over a short
        list; then the confusable rivals."""
        model = Model({}, {}, {}, self.fw.predict({}))
        order: list[str] = []
        for _ in range(ROUNDS):
            before = set(model.kept)
            model, order = self._forward(model, order)
            if set(model.kept) == before:
                break  # nothing new: the swaps and the check of the last round stand
            model = self._backward(self._swap(model))
        model, order = self._look_further(model, order)
        model, order = self._prefer_nested(model, order)
        order = [e for e in order if e in model.kept] + [e for e in model.kept if e not in order]
        out = CableOutcome(order, model.kept, model.stderr, model.specs)
        out.rivals = self._rivals(model.kept, model.specs, model.pred)
        return out

    def _fit(self, theta: dict[str, np.ndarray], specs: dict[str, Spec], nfev: int = 60) -> Model:
        """Joint refit of ``theta`` (linear parts first re-solved together)."""
        if not theta:
            return Model({}, {}, {}, self.fw.predict({}))
        theta = linear_refit(self.fw, theta, specs, self.train)
        fit = joint_fit(self.fw, theta, specs, self.train, max_nfev=nfev, stride=self.stride)
        return Model(fit.theta, dict(specs), fit.stderr, fit.pred)

    def _significant(self, model: Model, effect: str) -> bool:
        return (
            significance(model.specs[effect], model.kept[effect], model.stderr[effect], effect)
            >= self.th.z_min
        )

    def _far_above_noise(self, model: Model) -> bool:
        return self._above_noise(model, FAR_ABOVE_NOISE)

    def _above_noise(self, model: Model, factor: float) -> bool:
        """The held-out RMSE is more than ``factor`` times the white noise of the training
        residual (median absolute first difference): something is unexplained."""
        r = (self.fw.data.ts - model.pred)[self.train]
        if r.size < 10:
            return False
        noise = float(np.median(np.abs(np.diff(r)))) / 0.6745 / math.sqrt(2.0)
        test = (self.fw.data.ts - model.pred)[self.test]
        rms = float(np.sqrt(np.mean(test**2))) if test.size else 0.0
        return rms > factor * max(noise, 1e-12)

    def _forward(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """Add the best candidate while one passes the (lenient) forward test; where no
        single one does, the best pair of the most promising singles (effects that cancel
        alone, e.g. an offset and a drift of opposite sign)."""
        order = list(order)
        while len(model.kept) < self.th.max_effects:
            ranked = []
            for effect in (c for c in self.candidates if c not in model.kept
                           and not overlaps(c, model.kept)):  # fmt: skip
                spec, fit = self._screen(model.kept, effect, model.pred, model.specs)
                ranked.append((float(self._test_sse(fit.pred).sum()), effect, spec, fit))
            ranked.sort(key=lambda row: row[0])
            added = self._add_single(model, ranked)
            if (
                added is None
                and len(model.kept) + 2 <= self.th.max_effects
                and self._above_noise(model, PAIR_ABOVE_NOISE)
            ):
                added = self._add_pair(model, ranked)
            if added is None:
                break
            model, new = added
            order += new
        return model, order

    def _add_single(self, model: Model, ranked) -> tuple[Model, list[str]] | None:
        for _, effect, spec, fit in ranked:
            if not self._accept(model.pred, fit.pred, self.th.z_screen):
                continue
            joint = self._fit(
                {**model.kept, effect: fit.theta[effect]}, {**model.specs, effect: spec}
            )
            if self._accept(model.pred, joint.pred, self.th.z_screen):
                return joint, [effect]
            return None  # the best single fails jointly: stop (as the greedy step did)
        return None

    def _add_pair(self, model: Model, ranked) -> tuple[Model, list[str]] | None:
        """The best pair among the ``PAIR_POOL`` best-ranked singles, each fitted jointly
        with the kept effects; it must pass the forward test as a pair and each member its
        parameter test."""
        pool = ranked[:PAIR_POOL]
        best: tuple[float, Model, list[str]] | None = None
        for a in range(len(pool)):
            for b in range(a + 1, len(pool)):
                (_, ea, sa, fa), (_, eb, sb, fb) = pool[a], pool[b]
                theta = {**model.kept, ea: fa.theta[ea], eb: fb.theta[eb]}
                joint = self._fit(theta, {**model.specs, ea: sa, eb: sb}, nfev=30)
                if not self._accept(model.pred, joint.pred, self.th.z_holdout):
                    continue
                if not (self._significant(joint, ea) and self._significant(joint, eb)):
                    continue
                sse = float(self._test_sse(joint.pred).sum())
                if best is None or sse < best[0]:
                    best = (sse, joint, [ea, eb])
        return None if best is None else (best[1], best[2])

    def _look_further(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """While the held-out residual stays far above the noise (at most ``ROUNDS``
        times): best subset of a short list, then forward steps on top of it and the strict
        check; stops when that changes nothing."""
        for _ in range(ROUNDS):
            if not self._far_above_noise(model):
                break
            before = set(model.kept)
            model = self._subsets(model)
            model, order = self._forward(model, order)
            model = self._backward(model)
            if set(model.kept) == before:
                break
        return model, order

    def _prefer_nested(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """A kept effect that reduces to a simpler one (``Effect.nests``) stays only if it
        passes the strict test against the model with the simpler one in its place: its
        extra parameters must lower the held-out error beyond chance."""
        for effect in list(model.kept):
            for simpler in fx.REGISTRY[effect].nests:
                if effect not in model.kept or simpler.name in model.kept:
                    continue
                rest = {k: v for k, v in model.kept.items() if k != effect}
                rest_specs = {k: model.specs[k] for k in rest}
                spec, fit = self._screen(rest, simpler.name, self.fw.predict(rest), rest_specs)
                trial = self._fit({**rest, simpler.name: fit.theta[simpler.name]},
                                  {**rest_specs, simpler.name: spec})  # fmt: skip
                if not self._accept(trial.pred, model.pred, self.th.z_holdout):
                    model = trial
                    order = [simpler.name if e == effect else e for e in order]
        return model, order

    def _subsets(self, model: Model) -> Model:
        """Best subset, by held-out SSE, of a short list: the kept effects and the
        ``SUBSET_EXTRA`` best-screened others, every subset of up to ``len(kept) + 2``
        effects fitted jointly from the screened starting values. Undoes an early greedy
        choice that a stand-in made look right (e.g. Coulomb taking the viscous force at
        the typical speed). Kept only if it beats the current model on the forward test."""
        rest = [c for c in self.candidates if c not in model.kept]
        starts: dict[str, np.ndarray] = dict(model.kept)
        specs: dict[str, Spec] = dict(model.specs)
        screened = []
        base = self.fw.predict({})
        for effect in rest:
            spec, fit = self._screen({}, effect, base, {})
            screened.append((float(self._test_sse(fit.pred).sum()), effect))
            starts[effect], specs[effect] = fit.theta[effect], spec
        screened.sort()
        short = list(model.kept) + [e for _, e in screened[:SUBSET_EXTRA]]
        best, best_sse = model, float(self._test_sse(model.pred).sum())
        top = min(len(short), len(model.kept) + 2, self.th.max_effects)
        for size in range(1, top + 1):
            for combo in itertools.combinations(short, size):
                if set(combo) == set(model.kept) or any(overlaps(e, combo) for e in combo):
                    continue
                trial = self._fit({e: starts[e] for e in combo}, {e: specs[e] for e in combo}, 30)
                sse = float(self._test_sse(trial.pred).sum())
                if sse < best_sse:
                    best, best_sse = trial, sse
        if best is model or not self._accept(model.pred, best.pred, self.th.z_screen):
            return model
        return self._fit(best.kept, best.specs)

    def _backward(self, model: Model) -> Model:
        """Drop, one at a time, the weakest kept effect that fails the strict test.

        With every kept effect in the model the residual is close to the noise, so the
        held-out z and the parameter standard errors are trustworthy here (during the
        forward steps the residual still holds the effects not yet found).
        """
        while model.kept:
            weakest: tuple[str, Model] | None = None
            worst = math.inf
            for effect in model.kept:
                rest = {k: v for k, v in model.kept.items() if k != effect}
                reduced = self._fit(rest, {k: model.specs[k] for k in rest}, nfev=30)
                ok = self._accept(
                    reduced.pred, model.pred, self.th.z_holdout
                ) and self._significant(model, effect)
                score = self._z(reduced.pred, model.pred)
                if not ok and score < worst:
                    weakest, worst = (effect, reduced), score
            if weakest is None:
                break
            model = weakest[1]
        return model

    def _swap(self, model: Model) -> Model:
        """One pass of swaps: replace a kept effect by another candidate if that fits the
        held-out data significantly better (greedy selection can take a near-collinear
        stand-in first, e.g. an offset for a gain on a load that varies little)."""
        for effect in list(model.kept):
            if effect not in model.kept:
                continue
            rest = {k: v for k, v in model.kept.items() if k != effect}
            rest_specs = {k: model.specs[k] for k in rest}
            screened = []
            for cand in (c for c in self.candidates if c not in model.kept
                         and not overlaps(c, rest)):  # fmt: skip
                spec, fit = self._screen(rest, cand, self.fw.predict(rest), rest_specs)
                screened.append((float(self._test_sse(fit.pred).sum()), cand, spec, fit))
            screened.sort(key=lambda row: row[0])
            for _, cand, spec, fit in screened[:2]:  # the two best, each refitted jointly
                joint = self._fit({**rest, cand: fit.theta[cand]}, {**rest_specs, cand: spec})
                if self._accept(model.pred, joint.pred, self.th.z_screen) and self._significant(
                    joint, cand
                ):
                    model = joint
                    break
        return model

    def _rivals(self, kept, specs, pred) -> dict[str, list[Rival]]:
        """Swap each confusable kept effect for each rival; compare on held-out blocks."""
        result: dict[str, list[Rival]] = {}
        for effect in kept:
            rows = []
            for rival in rivals(effect):
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


def drop_unvalidated(
    fw: Forward,
    vfw: Forward,
    vvalid: np.ndarray,
    vblocks: np.ndarray,
    n_vblocks: int,
    outcome: CableOutcome,
    train: np.ndarray,
    th: Thresholds,
) -> tuple[CableOutcome, list[str]]:
    """Drop the kept effects that do not lower the error on the validation recording.

    ``vfw``: the same cable of a second recording of the machine (never fitted).
    Every kept effect, with the parameters fitted here, must lower the validation SSE
    against the model without it by ``rel_min`` and by ``z_holdout`` standard errors
    (:func:`holdout_z` over the validation's time blocks); the weakest failing one is
    dropped, the rest refitted on ``train``, until all pass. Returns the outcome and the
    dropped effects."""
    dropped: list[str] = []
    ts = vfw.data.ts
    while outcome.kept:
        full = vfw.predict(outcome.theta)
        r_full = np.where(vvalid, ts - full, 0.0)
        sse_full = np.bincount(vblocks, weights=r_full**2, minlength=n_vblocks)
        worst, worst_z = None, math.inf
        for effect in outcome.kept:
            rest = {k: v for k, v in outcome.theta.items() if k != effect}
            red = vfw.predict(rest)
            r_red = np.where(vvalid, ts - red, 0.0)
            sse_red = np.bincount(vblocks, weights=r_red**2, minlength=n_vblocks)
            cross = np.bincount(
                vblocks, weights=np.where(vvalid, r_full * (full - red), 0.0), minlength=n_vblocks
            )
            z = holdout_z(sse_red, sse_full, cross)
            gain = float(sse_red.sum() - sse_full.sum())
            ok = z >= th.z_holdout and gain >= th.rel_min * float(sse_red.sum())
            if not ok and z < worst_z:
                worst, worst_z = effect, z
        if worst is None:
            break
        dropped.append(worst)
        keep = [e for e in outcome.kept if e != worst]
        theta = {e: outcome.theta[e] for e in keep}
        specs = {e: outcome.specs[e] for e in keep}
        stderr = {e: outcome.stderr[e] for e in keep}
        if theta:
            stride = max(1, int(train.sum()) // 150_000)
            fit = joint_fit(fw, theta, specs, train, max_nfev=30, stride=stride)
            theta, stderr = fit.theta, fit.stderr
        rivals = {e: r for e, r in outcome.rivals.items() if e in keep}
        outcome = CableOutcome(keep, theta, stderr, specs, rivals, outcome.tried)
    return outcome, dropped
