"""One selector for both references: stepwise selection of effects, judged on held-out
time blocks, over a :class:`Unit` the reference gives it.

A unit is what is selected on as one: a cable against its platform tension
(:class:`gateway.diagnose.reference.CableUnit`), or every cable at once against the
platform's wrench balance (:class:`gateway.diagnose.wrench_unit.WrenchUnit`). The unit knows its
candidates, how to fit effects (a quick screen on top of a model, a joint refit) and its
residual (per sample, or per wrench component); the selector knows only residuals, held-out
blocks and the tests of :mod:`.stats`.

Each forward step screens every remaining candidate on top of the kept effects, ranks them
by held-out sum of squares and keeps the best one if it passes the forward test (lowers the
held-out SSE by ``rel_min`` and ``abs_min_n2`` per sample and by ``z_screen`` standard
errors, :func:`.stats.holdout_z`), also after a joint refit. Where no single one passes,
the best pair of the most promising ones (effects that cancel alone, e.g. an offset and a
drift of opposite sign). Then swaps (a near-collinear stand-in replaced) and the strict
backward check (each kept effect against the model refitted without it: ``z_holdout``
and its parameters ``z_min`` standard errors from the nominal). While the held-out residual
still holds more than white noise (a test over the held-out blocks, :meth:`Selector.left`,
not a fixed multiple of the noise), a best-subset search over a short list can undo an
early greedy choice. A kept effect that nests a simpler one (``Effect.nests``) must beat
it by the strict test. Finally each kept effect of a group (``Effect.group``) is swapped
for its rivals: the evidence and the report's alternatives say whether held-out data tells
them apart.

Whether a finding is reported is decided after every unit is selected, by significance
over every candidate x unit tried (:mod:`gateway.diagnose.significance`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from gateway.diagnose.stats import holdout_z, p_value, sign_test_p, white_noise
from gateway.model import effects as fx

ROUNDS = 3
PAIR_POOL = 4
"""Singles (best held-out SSE first) whose pairs are screened when no single passes."""
SUBSET_EXTRA = 3
"""Effects besides the kept ones on the best-subset search's short list."""
LEFT_P = 0.05
"""The held-out residual holds more than white noise when its excess over the noise is
significant at this level (:meth:`Selector.left`: it only decides whether the selection
looks further; what it finds must pass every test)."""


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
    """Acceptance thresholds (module docstring; :mod:`.significance` for ``fdr``)."""

    rel_min: float = 0.003
    abs_min_n2: float = 1e-6
    z_holdout: float = 4.0
    z_screen: float = 2.0
    z_separate: float = 3.0
    z_min: float = 4.0
    max_effects: int = 6
    fdr: float = 0.01


@dataclass
class Model:
    """A selection state of a unit: fitted effects (internal parameters), their recipes
    and standard errors, and the unit's residual (what the unit compares)."""

    kept: dict[str, np.ndarray]
    specs: dict[str, Any]
    stderr: dict[str, np.ndarray]
    resid: np.ndarray

    def without(self, effect: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        rest = {k: v for k, v in self.kept.items() if k != effect}
        return rest, {k: self.specs[k] for k in rest}


class Unit(Protocol):
    """What a reference gives the selector for one unit of selection."""

    candidates: list[str]
    blocks: np.ndarray
    """(n,) block index of every residual element."""
    train: np.ndarray
    test: np.ndarray
    n_blocks: int

    def empty(self) -> Model: ...
    def evaluate(self, theta: dict[str, np.ndarray], specs: dict[str, Any]) -> Model:
        """The model at the values ``theta`` (no fit; standard errors as not known)."""
        ...

    def screen(self, model: Model, effect: str) -> Model:
        """``effect`` fitted quickly on top of ``model`` (its linear parameters solved, the
        kept ones' linear parameters re-solved with it); ``kept`` holds the kept effects'
        values of ``model`` and the new effect's, ``resid`` the screened fit's."""
        ...

    def fit(self, theta: dict[str, np.ndarray], specs: dict[str, Any], nfev: int = 60) -> Model:
        """Every effect of ``theta`` refitted jointly on the training samples."""
        ...

    def significance(self, model: Model, effect: str) -> float:
        """How many standard errors ``effect``'s parameters lie from the nominal model."""
        ...


@dataclass
class Rival:
    """A confusable alternative fitted in place of a kept effect."""

    effect: str
    holdout_sse: float
    separable: bool
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stderr: np.ndarray = field(default_factory=lambda: np.zeros(0))
    z: float = 0.0


@dataclass
class Outcome:
    """What the selection kept on one unit, in the order it was kept."""

    kept: list[str]
    theta: dict[str, np.ndarray]
    stderr: dict[str, np.ndarray]
    specs: dict[str, Any]
    rivals: dict[str, list[Rival]] = field(default_factory=dict)
    tried: list[str] = field(default_factory=list)
    tests: dict[str, dict[str, float]] = field(default_factory=dict)
    """Per candidate: ``z``, ``p`` (and, once the significance stage ran, ``q``)."""
    stderr_blocks: dict[str, np.ndarray] = field(default_factory=dict)


CableOutcome = Outcome  # the name the platform-tension reference has used


class Selector:
    """Forward selection, swaps, backward check, subsets, nested and rival checks on one
    :class:`Unit` (module docstring)."""

    def __init__(self, unit: Unit, th: Thresholds) -> None:
        self.unit, self.th = unit, th
        self.candidates = unit.candidates
        self.screened: tuple[Model | None, dict[str, dict[str, float]]] = (None, {})
        """The last forward step's add-one tests (:meth:`test`) and the model they were
        screened on top of (their numbers only: no residual is kept)."""

    # ---- held-out scores ----
    def test_sse(self, resid: np.ndarray) -> np.ndarray:
        u = self.unit
        sse = np.bincount(u.blocks[u.test], weights=resid[u.test] ** 2, minlength=u.n_blocks)
        return sse[1::2]

    def z(self, a: Model | np.ndarray, b: Model | np.ndarray) -> float:
        """Held-out z of model B over model A (models or their residuals)."""
        ra = a.resid if isinstance(a, Model) else a
        rb = b.resid if isinstance(b, Model) else b
        u = self.unit
        cross = np.bincount(
            u.blocks[u.test], weights=(rb * (ra - rb))[u.test], minlength=u.n_blocks
        )
        return holdout_z(self.test_sse(ra), self.test_sse(rb), cross)

    def p(self, a: Model, b: Model) -> float:
        """One-sided p-value of B over A (:func:`.stats.p_value`)."""
        return p_value(self.z(a, b), self.held_out_blocks())

    def held_out_blocks(self) -> int:
        u = self.unit
        return int(np.unique(u.blocks[u.test]).size)

    def test(self, a: Model, b: Model) -> dict[str, float]:
        """The held-out test of B over A: ``z``, ``p`` and the relative held-out ``gain``."""
        z = self.z(a, b)
        before = float(self.test_sse(a.resid).sum())
        gain = (before - float(self.test_sse(b.resid).sum())) / before if before > 0 else 0.0
        return {"z": float(z), "p": p_value(z, self.held_out_blocks()), "gain": gain}

    def accept(self, a: Model, b: Model, z_min: float) -> bool:
        before, after = self.test_sse(a.resid), self.test_sse(b.resid)
        gain = float(before.sum() - after.sum())
        n_test = int(self.unit.test.sum())
        return (
            gain >= self.th.rel_min * float(before.sum())
            and gain >= self.th.abs_min_n2 * n_test
            and self.z(a, b) >= z_min
        )

    def significant(self, model: Model, effect: str) -> bool:
        return self.unit.significance(model, effect) >= self.th.z_min

    def left(self, model: Model) -> bool:
        """The held-out residual holds more than white noise: in more of the held-out
        blocks than chance allows (a sign test at :data:`LEFT_P`: robust to one block of a
        load step, and to the few blocks of a short recording) its mean square exceeds the
        block's own white noise (:func:`.stats.white_noise`, from sample-to-sample
        differences, which slow structure does not raise), on average by at least what a
        finding must remove (``rel_min`` of the held-out error)."""
        u = self.unit
        r = model.resid
        ratios = []
        for b in np.unique(u.blocks[u.test]):
            rb = r[u.test & (u.blocks == b)]
            noise = white_noise(rb)
            if rb.size >= 10 and noise > 0.0:
                ratios.append(float(np.mean(rb**2)) / noise**2)
        if len(ratios) < 2:
            return False
        ratio = np.asarray(ratios)
        # an excess below rel_min of the held-out error is one no finding could remove
        # (the forward test asks that much of every finding): nothing to look for
        if float(np.mean(ratio)) - 1.0 < self.th.rel_min:
            return False
        return sign_test_p(int(np.sum(ratio > 1.0)), ratio.size) < LEFT_P

    # ---- the selection ----
    def run(self) -> Outcome:
        """Rounds of forward steps (pairs where no single passes), swaps and the strict
        backward check (until a forward pass adds nothing, at most ``ROUNDS``); then,
        while the held-out residual holds more than noise, a best-subset search over a
        short list; then the nested and the rival checks."""
        model = self.unit.empty()
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
        out = Outcome(order, model.kept, model.stderr, model.specs)
        out.rivals = self._rivals(model)
        self.final = model
        return out

    def fit(self, theta: dict[str, np.ndarray], specs: dict[str, Any], nfev: int = 60) -> Model:
        if not theta:
            return self.unit.empty()
        return self.unit.fit(theta, specs, nfev)

    def _forward(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """Add the best candidate while one passes the forward test; where no single one
        does, the best pair of the most promising singles."""
        order = list(order)
        while len(model.kept) < self.th.max_effects:
            ranked = []
            for effect in self.candidates:
                if effect in model.kept or overlaps(effect, model.kept):
                    continue
                screened = self.unit.screen(model, effect)
                ranked.append((float(self.test_sse(screened.resid).sum()), effect, screened))
            ranked.sort(key=lambda row: row[0])
            self.screened = (model, {e: self.test(model, s) for _, e, s in ranked})
            added = self._add_single(model, ranked)
            if added is None and len(model.kept) + 2 <= self.th.max_effects and self.left(model):
                added = self._add_pair(model, ranked)
            if added is None:
                break
            model, new = added
            order += new
        return model, order

    def _add_single(self, model: Model, ranked) -> tuple[Model, list[str]] | None:
        for _, effect, screened in ranked:
            if not self.accept(model, screened, self.th.z_screen):
                continue
            joint = self.fit(screened.kept, screened.specs)
            if self.accept(model, joint, self.th.z_screen):
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
                (_, ea, sa), (_, eb, sb) = pool[a], pool[b]
                if overlaps(ea, [eb]):
                    continue
                theta = {**model.kept, ea: sa.kept[ea], eb: sb.kept[eb]}
                specs = {**model.specs, ea: sa.specs[ea], eb: sb.specs[eb]}
                joint = self.fit(theta, specs, nfev=30)
                if not self.accept(model, joint, self.th.z_holdout):
                    continue
                if not (self.significant(joint, ea) and self.significant(joint, eb)):
                    continue
                sse = float(self.test_sse(joint.resid).sum())
                if best is None or sse < best[0]:
                    best = (sse, joint, [ea, eb])
        return None if best is None else (best[1], best[2])

    def _look_further(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """While the held-out residual holds more than white noise (at most ``ROUNDS``
        times): best subset of a short list, then forward steps on top of it and the strict
        check; stops when that changes nothing."""
        for _ in range(ROUNDS):
            if not self.left(model):
                break
            before = set(model.kept)
            model = self._subsets(model)
            model, order = self._forward(model, order)
            model = self._backward(model)
            if set(model.kept) == before:
                break
        return model, order

    def _subsets(self, model: Model) -> Model:
        """Best subset, by held-out SSE, of a short list: the kept effects and the
        ``SUBSET_EXTRA`` best-screened others, every subset of up to ``len(kept) + 2``
        effects fitted jointly from the screened starting values. Undoes an early greedy
        choice that a stand-in made look right (e.g. Coulomb taking the viscous force at
        the typical speed). Kept only if it beats the current model on the forward test."""
        starts: dict[str, np.ndarray] = dict(model.kept)
        specs: dict[str, Any] = dict(model.specs)
        screened = []
        empty = self.unit.empty()
        for effect in (c for c in self.candidates if c not in model.kept):
            s = self.unit.screen(empty, effect)
            screened.append((float(self.test_sse(s.resid).sum()), effect))
            starts[effect], specs[effect] = s.kept[effect], s.specs[effect]
        screened.sort()
        short = list(model.kept) + [e for _, e in screened[:SUBSET_EXTRA]]
        best, best_sse = model, float(self.test_sse(model.resid).sum())
        top = min(len(short), len(model.kept) + 2, self.th.max_effects)
        for size in range(1, top + 1):
            for combo in itertools.combinations(short, size):
                if set(combo) == set(model.kept) or any(overlaps(e, combo) for e in combo):
                    continue
                trial = self.fit({e: starts[e] for e in combo}, {e: specs[e] for e in combo}, 30)
                sse = float(self.test_sse(trial.resid).sum())
                if sse < best_sse:
                    best, best_sse = trial, sse
        if best is model or not self.accept(model, best, self.th.z_screen):
            return model
        return self.fit(best.kept, best.specs)

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
                reduced = self.fit(*model.without(effect), nfev=30)
                ok = self.accept(reduced, model, self.th.z_holdout) and self.significant(
                    model, effect
                )
                score = self.z(reduced, model)
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
            rest, rest_specs = model.without(effect)
            base = self.unit.evaluate(rest, rest_specs)
            screened = []
            for cand in self.candidates:
                if cand in model.kept or overlaps(cand, rest):
                    continue
                s = self.unit.screen(base, cand)
                screened.append((float(self.test_sse(s.resid).sum()), cand, s))
            screened.sort(key=lambda row: row[0])
            for _, cand, s in screened[:2]:  # the two best, each refitted jointly
                joint = self.fit(s.kept, s.specs)
                if self.accept(model, joint, self.th.z_screen) and self.significant(joint, cand):
                    model = joint
                    break
        return model

    def _prefer_nested(self, model: Model, order: list[str]) -> tuple[Model, list[str]]:
        """A kept effect that reduces to a simpler one (``Effect.nests``) stays only if it
        passes the strict test against the model with the simpler one in its place: its
        extra parameters must lower the held-out error beyond chance.

        Every such test is decided on the selected model, so the outcome does not depend
        on the order the effects were kept in. (Decided one after the other, a replacement
        changed the model the next test ran on: on the da Vinci's L_2 series, Maxwell-slip
        gave way to presliding (z 0.48), whose larger held-out residual then let an offset
        replace the spring, which beats the offset by z 5.06 on the selected model:
        held-out RMSE 0.809 -> 1.041 N.) The selected model is where the held-out test is
        most trustworthy: with every kept effect in it, the residual is closest to the
        noise (as in :meth:`_backward`). The effects that fail are then replaced, the
        weakest (lowest z) first, each only while the model with all replacements so far
        is not beaten by the selected one by the strict test: simplifications that each
        lose little can together lose much (on L_2 presliding and lowpass in place of
        Maxwell-slip and sensor creep: z 11 worse, held-out 1.021 N)."""
        failing: list[tuple[float, str, str]] = []
        for effect in model.kept:
            for simpler in fx.REGISTRY[effect].nests:
                name = simpler.name
                if name in model.kept or name not in self.candidates:
                    continue
                trial = self._in_place(model, effect, name)
                if not self.accept(trial, model, self.th.z_holdout):
                    failing.append((self.z(trial, model), effect, name))
                    break
        selected, replaced = model, dict[str, str]()
        for _, effect, name in sorted(failing):
            if name in replaced.values():
                continue  # two effects nesting one: the weaker one's place
            trial = self._in_place(model, effect, name)
            if self.accept(trial, selected, self.th.z_holdout):
                break  # together the replacements lose beyond chance: stop here
            model, replaced[effect] = trial, name
        return model, [replaced.get(e, e) for e in order]

    def _in_place(self, model: Model, effect: str, other: str, **fit: Any) -> Model:
        """``model`` with ``other`` fitted jointly in ``effect``'s place (screened on the
        model without ``effect``, then refitted with the rest)."""
        rest, rest_specs = model.without(effect)
        s = self.unit.screen(self.unit.evaluate(rest, rest_specs), other)
        return self.fit(s.kept, s.specs, **fit)

    def _rivals(self, model: Model) -> dict[str, list[Rival]]:
        """Swap each kept effect of a group for each rival; compare on held-out blocks."""
        result: dict[str, list[Rival]] = {}
        for effect in model.kept:
            rows = []
            rest, _ = model.without(effect)
            for rival in rivals(effect):
                if rival in model.kept or rival not in self.candidates or overlaps(rival, rest):
                    continue
                fit = self._in_place(model, effect, rival, nfev=30)
                z = self.z(fit, model)
                rows.append(
                    Rival(
                        rival,
                        float(self.test_sse(fit.resid).sum()),
                        z >= self.th.z_separate,
                        fit.kept[rival],
                        fit.stderr.get(rival, np.full(fit.kept[rival].size, np.nan)),
                        z,
                    )
                )
            if rows:
                result[effect] = rows
        return result
