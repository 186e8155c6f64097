"""Cables that share a design share evidence: an effect is tested across the cables
jointly, accepted for the machine when the pooled evidence is significant, and a cable
keeps or drops it on its own evidence only when its data says it differs.

**The pooled statistic** (:func:`pooled_tests`). Every cable's test of an effect (a kept
one against the model refitted without it, one not kept screened on top of the cable's
final model: :func:`.significance.candidate_tests`) has a one-sided p-value from its
held-out blocks (Student t). Each is turned into a normal score ``z_i = Phi^-1(1 - p_i)``
and combined by Stouffer, ``Z = sum z_i / sqrt(k)`` over the ``k`` cables that tested the
effect (the cables' residuals are independent readings: one load cell each); its p-values
go through Benjamini-Hochberg over the effects. An effect is **common** when
``q <= Thresholds.fdr``, ``Z >= Thresholds.z_holdout`` (the strict test the selection asks
of a kept effect), the smallest Z with one cable left out is at least
``Thresholds.z_screen`` (the evidence does not rest on one cable: Stouffer alone lets one
cable's strong fault carry seven clean ones) and at least one cable kept it on its own
evidence (the per-cable tests of its parameters guard against a stand-in for a model-form
error), or, where none did, it passes the joint test below. Of two common effects one of
which nests the other (a ``spring`` kept on two cables of eight, an ``offset`` on the other
six), the simpler one is common at first: the nesting one was tested, on the cables that
kept it, against nothing (its nested part included), never its extra freedom across the
cables. Whether its extra freedom is the machine's is then asked of all the cables at once
(below, "Of two nesting effects"); where it is not, it stays a cable-specific rival, judged
on each cable against the common effects.

**Of two nesting effects** (:func:`richer`): per cable the richer effect must beat the
simpler one by ``Thresholds.z_holdout`` on its own (``Selector._prefer_nested``), which a
direction-dependent loss 2-3 N apart under 15-18 % noise does not on most cables (a
``coulomb_directional`` kept on one cable of seven, ``coulomb`` on six), although the
cables share the drive train. For each common effect and each richer effect that nests it
and states its extra freedom (``Effect.beyond``: ``mu_out - mu_in``, a spring's ``k``),
every cable that kept either is fitted with both in turn (the richer one in place of the
simpler one, or the reverse) and the richer is tested against the simpler one on the
cable's held-out blocks and, with several recordings, on the recordings left out in turn
(the smaller z). The richer one is common in place of the simpler one when those tests pass
the joint test's rule: Stouffer ``Z >= z_holdout``, with one cable left out
``>= z_screen``, its q (BH with the other pooled tests) ``<= fdr``, and the random-effects
mean of the cables' departures (``Effect.beyond`` of their fits, the parameters' errors
combined as if independent) ``Thresholds.z_min`` standard errors from none; else the
simpler one stays common. Its common value is the median of the cables' fits; a cable that
kept the simpler one then takes the richer one as a common effect it lacks (below).

**The joint test** (:func:`jointly`): an effect no cable kept on its own can still be the
machine's: a 3 N offset under 15 % noise that each cable's forward step finds by a z of
1-3. Where the cables' quick screens of such an effect on top of their models pool to
``Z >= Thresholds.z_screen`` (the forward step's screen, over the cables), it is fitted on
every cable jointly with the cable's model and tested there as a kept effect is (the held-out
blocks, and with several recordings the recordings left out in turn: the smaller z); the
effect is common when those tests pool (Stouffer) to ``Z >= z_holdout`` with one cable left
out ``>= z_screen``, its q (BH with the other pooled tests) ``<= fdr``, and the cables'
departures of its parameters from the neutral value, pooled by :func:`shrink` (the
random-effects mean and its standard error), lie ``Thresholds.z_min`` standard errors from
none (the per-cable parameter test, over the cables). An effect that nests another (a
``spring``, an ``offset``) is tested on the held-out blocks against the simpler one fitted
in its place (its extra freedom), and is not common where the simpler one is. Its common
value is the median of the cables' joint fits.

**The common effects on every cable** (:func:`extend`, :func:`on_cable`). A common effect is
the default hypothesis on every cable of the machine: a cable that did not keep it gets it,
unless its own data say otherwise. Per cable, the common effects it lacks are taken
together (of two that nest each other, the one of the larger pooled Z):

* a cable-specific effect the cable kept that nests or is nested by one of them (a
  ``spring``, whose ``k l0`` holds an offset, for a common ``offset``) gives way to it: the
  cable's model without it is the base;
* the common effects at the common value (the median of the internal parameters of the
  cables that kept them, on top of the base, not refitted) must not make the cable's
  held-out blocks worse by ``Thresholds.z_screen`` standard errors, jointly (a gain and an
  offset fitted together on the other cables are judged together); where they do, each
  is judged alone, and then fitted with the cable's other effects (:func:`agrees`: it
  lowers the cable's held-out error by ``z_screen`` standard errors, or its fitted
  parameters lie within ``z_screen`` standard errors of the common value); one the
  cable's data refuse both ways stays off it (a fault on one cable among eight: the
  clean cables' data refuse the faulty cable's value);
* the rest are fitted on the cable jointly with its other effects (its own parameters);
  where a cable-specific effect gave way, the cable keeps its own model only if that
  beats the common one on the cable's held-out blocks by ``Thresholds.z_holdout`` (the
  strict test a kept effect passes): the rival is compared against the common effect on
  this cable, not against nothing, so a stand-in that won the cable's own forward
  selection by a little no longer decides. Both sides hold the common effects that do
  not conflict with the rival (:func:`rival`: the cable's own model with them fitted): a
  spring that stood in for an offset and part of a common gain is judged against the
  offset with the gain on both sides, not against a model that lacks the gain. Where the
  cable's own model wins, it keeps it with those common effects.

Cables whose data refused a common effect, or kept their own effects against it, are its
``differs``. A cable that kept a common effect drops it only when its own held-out z is
below ``-z_screen`` (not for a q-value or a parameter test that a weak share of a common
effect fails alone).

**Partial pooling of the parameters** (:func:`shrink`): per reported parameter, the
cables' estimates ``y_i`` with standard errors ``s_i`` are shrunk toward the common value
by empirical Bayes: the between-cable variance ``tau^2`` from DerSimonian-Laird's moment
estimator (``Q = sum w_i (y_i - ybar)^2``, ``w_i = 1 / s_i^2``,
``tau^2 = max(0, (Q - (k - 1)) / (sum w - sum w^2 / sum w))``), the common value
``mu = sum y_i / (s_i^2 + tau^2) / sum 1 / (s_i^2 + tau^2)``, and each cable's
``y_i + B_i (mu - y_i)`` with ``B_i = s_i^2 / (s_i^2 + tau^2)``: a cable whose estimate is
precise keeps it, a noisy one borrows from the others, and where the cables truly differ
(``tau`` large against the ``s_i``) little is borrowed. The fitted model keeps each cable's
own estimates (the report's ``parameters``); ``pooling.parameters`` gives the shrunk ones.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from gateway.diagnose.selection import Model, Selector, Thresholds, overlaps
from gateway.diagnose.significance import Tested, left_out_tests, retire, score, stricter
from gateway.diagnose.stats import bh_qvalues
from gateway.model import effects as fx


@dataclass
class Pooled:
    """One effect's pooled test over the cables that tested it."""

    effect: str
    statistic: float
    p: float
    cables: list[int]
    """0-based cables whose test went into ``statistic``."""
    q: float = 1.0
    loo: float = 0.0
    """The smallest Stouffer Z with one cable left out: evidence that rests on one cable
    alone (a fault on one cable among eight) is not common."""
    common: bool = False
    differs: list[int] = field(default_factory=list)
    """0-based cables whose own held-out data refused the common value."""


def normal_score(p: float) -> float:
    """``Phi^-1(1 - p)``, bounded to +-8 (a p of 0 or 1 from an exact fit or no change)."""
    p = min(max(float(p), 1e-15), 1.0 - 1e-15)
    return float(np.clip(-special.ndtri(p), -8.0, 8.0))


def stouffer(ps: list[float]) -> tuple[float, float]:
    """Stouffer's combination of one-sided p-values: (Z, its one-sided p)."""
    if not ps:
        return 0.0, 1.0
    z = sum(normal_score(p) for p in ps) / math.sqrt(len(ps))
    return z, float(special.ndtr(-z))


def pooled_tests(units: list[Tested], th: Thresholds) -> dict[str, Pooled]:
    """Per effect tested on two or more cables: the Stouffer statistic over the cables'
    held-out p-values, BH over the effects, and whether it is common (module
    docstring)."""
    by: dict[str, list[tuple[int, float]]] = {}
    for k, u in enumerate(units):
        for e, t in u.outcome.tests.items():
            if "p" in t:
                by.setdefault(e, []).append((k, float(t["p"])))
    out = {}
    for e, rows in by.items():
        if len(rows) < 2:
            continue
        ps = [p for _, p in rows]
        z, p = stouffer(ps)
        loo = min(stouffer(ps[:j] + ps[j + 1 :])[0] for j in range(len(ps)))
        out[e] = Pooled(e, z, p, [k for k, _ in rows], loo=loo)
    q = bh_qvalues([r.p for r in out.values()])
    for r, qv in zip(out.values(), q, strict=True):
        r.q = float(qv)
        owners = [u for u in units if r.effect in u.model.kept]
        r.common = (
            r.q <= th.fdr and r.statistic >= th.z_holdout and r.loo >= th.z_screen and bool(owners)
        )
    for r in out.values():
        if r.common and any(out[s].common for s in nested_in(r.effect) if s in out):
            r.common = False  # the simpler one is the machine's default (module docstring)
    return out


def nested_in(effect: str) -> list[str]:
    """The simpler effects ``effect`` nests (``Effect.nests``: a ``spring`` nests the
    ``offset``)."""
    return [s.name for s in fx.REGISTRY[effect].nests]


def common_value(units: list[Tested], effect: str) -> np.ndarray:
    """The common internal parameters of ``effect``: the median over the cables that kept
    it (robust to one cable's outlying fit)."""
    return np.median(np.stack([u.model.kept[effect] for u in units if effect in u.model.kept]), 0)


def extend(
    units: list[Tested],
    th: Thresholds,
    rebuild: Callable[[Tested], tuple[Selector, Model]],
    say=lambda _m: None,
) -> dict[str, Pooled]:
    """The pooled tests (:func:`pooled_tests`), and the common effects made the default
    hypothesis on every cable (module docstring, "The common effects on every cable"), in
    place; the cables that changed are scored again. Returns the pooled tests (their
    ``differs`` filled)."""
    pooled = pooled_tests(units, th)
    values = jointly(units, pooled, th, rebuild, say)
    values.update(richer(units, pooled, th, rebuild, say))
    order = sorted(pooled.items(), key=lambda kv: -kv[1].statistic)
    common = [e for e, r in order if r.common]
    if not common:
        return pooled
    values = {e: values[e] if e in values else common_value(units, e) for e in common}
    for k, u in enumerate(units):
        kept = u.model.kept
        missing: list[str] = []
        for e in common:  # the strongest first; of two that overlap, the stronger
            if e in kept or overlaps(e, [c for c in kept if c in pooled and pooled[c].common]):
                continue
            if not overlaps(e, missing):
                missing.append(e)
        if not missing:
            continue
        sel, model = rebuild(u) if u.selector is None else (u.selector, u.model)
        missing = [e for e in missing if e in sel.candidates]
        if not missing:
            continue
        adopted = on_cable(sel, model, missing, values, common, th)
        for e in missing:
            if adopted is None or e not in adopted.kept:
                pooled[e].differs.append(k)
        if adopted is None or adopted is model:
            continue
        gone = [e for e in kept if e not in adopted.kept]
        added = [e for e in adopted.kept if e not in kept]
        say(
            f"cable {k + 1}: {', '.join(added)} common to the cables"
            + (f" in place of {', '.join(gone)}" if gone else "")
            + " (pooled z "
            + ", ".join(f"{pooled[e].statistic:.1f}" for e in added)
            + ")"
        )
        u.selector, u.model = sel, adopted
        u.outcome.kept = [e for e in u.outcome.kept if e in adopted.kept] + added
        score(u)
        retire(u)
    return pooled


@dataclass
class Joint:
    """One effect no cable kept, fitted on one cable jointly with its model and tested
    there like a kept effect (:func:`jointly`)."""

    p: float
    z: float
    theta: np.ndarray
    stderr: np.ndarray
    neutral: np.ndarray


def jointly(
    units: list[Tested],
    pooled: dict[str, Pooled],
    th: Thresholds,
    rebuild: Callable[[Tested], tuple[Selector, Model]],
    say=lambda _m: None,
) -> dict[str, np.ndarray]:
    """The joint test of the effects no cable kept on its own (module docstring, "The
    joint test"), in place on ``pooled``: returns the common values of those it made
    common."""
    common = [e for e, r in pooled.items() if r.common]
    todo = [
        e
        for e, r in sorted(pooled.items(), key=lambda kv: -kv[1].statistic)
        if not r.common
        and r.statistic >= th.z_screen
        and not any(e in u.model.kept for u in units)
        and not overlaps(e, common)
    ]
    if not todo:
        return {}
    # the simpler of two nesting candidates first: the nesting one is tested against it
    todo = sorted(todo, key=lambda e: -sum(e in nested_in(o) for o in todo))
    per: dict[str, list[Joint]] = {e: [] for e in todo}
    for u in units:
        sel, model = rebuild(u) if u.selector is None else (u.selector, u.model)
        fits: dict[str, Model] = {}
        for e in todo:
            if e not in sel.candidates or overlaps(e, model.kept):
                continue
            s = sel.unit.screen(model, e)
            fits[e] = fitted = sel.fit(s.kept, s.specs)
            simpler = [n for n in nested_in(e) if n in fits]
            against = fits[simpler[0]] if simpler else model
            t = sel.test(against, fitted)
            z, p = t["z"], t["p"]
            lo = None if simpler else left_out_tests(sel, fitted).get(e)
            if lo is not None:
                z, p = stricter(t, lo)
            neutral = getattr(fitted.specs[e], "neutral", None)  # None: zero
            neutral = np.zeros(fitted.kept[e].size) if neutral is None else np.asarray(neutral)
            per[e].append(Joint(p, z, fitted.kept[e], fitted.stderr[e], neutral))
        release = getattr(sel.unit, "release", None)
        if release is not None:
            release()
    values = {}
    for e in todo:
        rows = per[e]
        if len(rows) < 2:
            continue
        ps = [j.p for j in rows]
        z, p = stouffer(ps)
        loo = min(stouffer(ps[:j] + ps[j + 1 :])[0] for j in range(len(ps)))
        q = float(bh_qvalues([p, *(r.p for f, r in pooled.items() if f != e)])[0])
        value, present = pooled_value(e, rows)
        if not (q <= th.fdr and z >= th.z_holdout and loo >= th.z_screen and present >= th.z_min):
            continue
        if any(n in values for n in nested_in(e)):
            continue  # its extra freedom over a common simpler one: not common
        r = pooled[e]
        r.statistic, r.p, r.q, r.loo, r.common = z, p, q, loo, True
        values[e] = value
        say(
            f"{e} tested on the cables jointly: pooled z {z:.1f} (one cable left out: "
            f"{loo:.1f}), the common value {present:.1f} standard errors from none"
        )
    return values


def nesting(effect: str) -> list[str]:
    """The richer effects that nest ``effect`` and say how far a fit lies from it
    (``Effect.beyond``: a ``coulomb_directional`` over ``coulomb``, a ``spring`` over the
    ``offset``)."""
    me = fx.REGISTRY[effect]
    return [n for n, e in fx.REGISTRY.items() if me in e.nests and e.beyond]


@dataclass
class Against:
    """One cable's test of a richer effect against the simpler one it nests, fitted in
    its place (:func:`richer`)."""

    cable: int
    p: float
    z: float
    theta: np.ndarray
    d: float
    """The fit's departure from the simpler effect (``Effect.beyond``) ..."""
    d_se: float
    """... and its standard error (the parameters' errors combined as if independent)."""
    blocks: dict[str, float]
    """The test on the cable's held-out blocks alone."""
    models: tuple = ()
    """The simpler and the richer fit's ``(kept, specs)``."""


def _release(sel: Selector) -> None:
    release = getattr(sel.unit, "release", None)
    if release is not None:
        release()


def richer(
    units: list[Tested],
    pooled: dict[str, Pooled],
    th: Thresholds,
    rebuild: Callable[[Tested], tuple[Selector, Model]],
    say=lambda _m: None,
) -> dict[str, np.ndarray]:
    """The richer of two nesting effects made common in place of the simpler common one
    where its joint held-out improvement over it passes the joint test (module docstring,
    "Of two nesting effects"), in place on ``pooled``: returns the common values of those
    it made common."""
    pairs = [
        (r, s)
        for s, ps in sorted(pooled.items(), key=lambda kv: -kv[1].statistic)
        if ps.common
        for r in nesting(s)
        if not (r in pooled and pooled[r].common)
    ]
    if not pairs:
        return {}
    per: dict[tuple[str, str], list[Against]] = {pair: [] for pair in pairs}
    for k, u in enumerate(units):
        todo = [(r, s) for r, s in pairs if r in u.model.kept or s in u.model.kept]
        if not todo:
            continue
        sel, model = rebuild(u) if u.selector is None else (u.selector, u.model)
        for r, s in todo:
            if r not in sel.candidates or s not in sel.candidates:
                continue
            own, other = (s, r) if s in model.kept else (r, s)
            theta, specs = model.without(own)
            if overlaps(other, theta):
                continue
            sc = sel.unit.screen(sel.unit.evaluate(theta, specs), other)
            fitted = sel.fit(sc.kept, sc.specs)
            simple, rich = (model, fitted) if own == s else (fitted, model)
            t = sel.test(simple, rich)
            w = np.asarray(fx.REGISTRY[r].beyond, float)
            se = np.asarray(rich.stderr.get(r, np.full(w.size, np.nan)), float)
            d = float(w @ rich.kept[r])
            d_se = float(np.sqrt(np.sum((w * se)[w != 0] ** 2)))
            row = Against(k, t["p"], t["z"], rich.kept[r], d, d_se, t)
            row.models = ((simple.kept, simple.specs), (rich.kept, rich.specs))
            per[(r, s)].append(row)
        _release(sel)
    # the recordings left out in turn (several recordings) only where the held-out blocks
    # pool to z_holdout: each cable's z is the smaller of the two, so Stouffer's Z can only
    # fall (the decision is the same, the refits are saved)
    again = {
        pair: rows
        for pair, rows in per.items()
        if len(rows) >= 2 and stouffer([j.p for j in rows])[0] >= th.z_holdout
    }
    for k, u in enumerate(units):
        mine = [(r, j) for (r, _), rows in again.items() for j in rows if j.cable == k]
        if not mine:
            continue
        sel, _ = rebuild(u) if u.selector is None else (u.selector, u.model)
        for r, j in mine:
            (s_kept, s_specs), (r_kept, r_specs) = j.models
            simple, rich = sel.unit.evaluate(s_kept, s_specs), sel.unit.evaluate(r_kept, r_specs)
            lo = left_out_tests(sel, rich, {r: simple}).get(r)
            if lo is not None:
                j.z, j.p = stricter(j.blocks, lo)
        _release(sel)
    values: dict[str, np.ndarray] = {}
    for (r, s), rows in per.items():
        if len(rows) < 2 or not pooled[s].common or r in values:
            continue
        ps = [j.p for j in rows]
        z, p = stouffer(ps)
        loo = min(stouffer(ps[:j] + ps[j + 1 :])[0] for j in range(len(ps)))
        q = float(bh_qvalues([p, *(o.p for f, o in pooled.items() if f != r)])[0])
        present = departure([j.d for j in rows], [j.d_se for j in rows])
        passed = q <= th.fdr and z >= th.z_holdout and loo >= th.z_screen and present >= th.z_min
        say(
            f"{r} in place of {s} tested on the cables jointly: pooled z {z:.1f} (one cable "
            f"left out: {loo:.1f}, q {q:.2g}), its departure from {s} {present:.1f} standard "
            f"errors from none: {r if passed else s} is common"
        )
        if not passed:
            continue
        pooled[s].common = False
        pooled[r] = Pooled(r, z, p, [j.cable for j in rows], q=q, loo=loo, common=True)
        values[r] = np.median(np.stack([j.theta for j in rows]), 0)
    return values


def departure(d: list[float], se: list[float]) -> float:
    """How many pooled standard errors the random-effects mean (:func:`shrink`) of the
    cables' departures ``d`` (standard errors ``se``) lies from none; 0 with fewer than two
    usable ones."""
    y, s = np.asarray(d, float), np.asarray(se, float)
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    if ok.sum() < 2:
        return 0.0
    mu, tau, _ = shrink(y[ok], s[ok])
    tau = tau if math.isfinite(tau) else 0.0
    return abs(mu) * math.sqrt(float(np.sum(1.0 / (s[ok] ** 2 + tau**2))))


def pooled_value(effect: str, rows: list[Joint]) -> tuple[np.ndarray, float]:
    """The common internal parameters of ``effect`` from the cables' joint fits (the
    median, as :func:`common_value`), and how many pooled standard errors the
    random-effects mean of the cables' departures from the neutral value (:func:`shrink`)
    lies from none (the effect's own measure, ``Effect.significance``): the per-cable
    parameter test, over the cables jointly."""
    if len({j.theta.shape for j in rows}) != 1 or len({j.neutral.shape for j in rows}) != 1:
        return np.median(np.stack([rows[0].theta]), 0), 0.0
    y = np.stack([j.theta - j.neutral for j in rows])
    s = np.stack([np.asarray(j.stderr, float) for j in rows])
    mu, se = np.zeros(y.shape[1]), np.full(y.shape[1], np.nan)
    for i in range(y.shape[1]):
        ok = np.isfinite(y[:, i]) & np.isfinite(s[:, i]) & (s[:, i] > 0)
        if ok.sum() < 2:
            continue
        mu[i], tau, _ = shrink(y[ok, i], s[ok, i])
        tau = tau if math.isfinite(tau) else 0.0
        se[i] = 1.0 / math.sqrt(float(np.sum(1.0 / (s[ok, i] ** 2 + tau**2))))
    z = fx.REGISTRY[effect].significance(mu, se, np.zeros_like(mu))
    return np.median(np.stack([j.theta for j in rows]), 0), z


def on_cable(
    sel: Selector,
    model: Model,
    missing: list[str],
    values: dict[str, np.ndarray],
    common: list[str],
    th: Thresholds,
) -> Model | None:
    """The cable's model with the common effects it lacks (``missing``) as its default
    (module docstring): the cable's kept effects that nest or are nested by one of them
    (a ``spring`` for an ``offset``) give way; the effects its data refuse at the common
    ``values`` (worse by ``z_screen`` on its held-out blocks) are left out; the rest are
    fitted jointly with the kept effects. The cable's own model, with the missing
    effects that do not conflict with its own fitted in it (:func:`rival`), stays only if
    it beats that one on its held-out blocks by ``Thresholds.z_holdout`` (significant
    evidence of its own, against the common effects on this cable, not against nothing).
    Returns the model adopted (``model`` itself when the cable keeps its own and no
    common effect is added to it), None when every missing effect was refused."""
    kept = model.kept
    gone = [x for x in kept if x not in common and overlaps(x, missing)]
    if len(kept) - len(gone) + len(missing) > th.max_effects:
        return None
    base = model
    if gone:
        rest = {x: v for x, v in kept.items() if x not in gone}
        base = sel.fit(rest, {x: model.specs[x] for x in rest})
    # the common values jointly on top of the cable's other effects (not refitted); where
    # the cable's data refuse them together, each on its own
    screened = [sel.unit.screen(base, e) for e in missing]
    specs = {e: s.specs[e] for e, s in zip(missing, screened, strict=True)}
    at = sel.unit.evaluate(
        {**base.kept, **{e: values[e] for e in missing}}, {**base.specs, **specs}
    )
    if sel.z(base, at) <= -th.z_screen:
        keep = []
        for e, s in zip(missing, screened, strict=True):
            one = sel.unit.evaluate({**base.kept, e: values[e]}, {**base.specs, e: specs[e]})
            if sel.z(base, one) > -th.z_screen or agrees(sel, base, s, e, values[e], th):
                keep.append(e)
        missing = keep
    if not missing:
        return None if not gone else model
    theta = {**base.kept}
    for e, s in zip(specs, screened, strict=True):
        if e in missing:
            theta[e] = s.kept[e]
    fitted = sel.fit(theta, {**base.specs, **{e: specs[e] for e in missing}})
    if not gone:
        return fitted
    own = rival(sel, model, [e for e in missing if not overlaps(e, gone)])
    if sel.z(fitted, own) >= th.z_holdout:
        return own  # the cable's own effects beat the common ones on its data
    return fitted


def rival(sel: Selector, model: Model, others: list[str]) -> Model:
    """The cable's own model with the common effects that do not conflict with its own
    (``others``) fitted jointly: what the common effects in place of its own are compared
    against, so that both sides hold the effects they share (a spring that stood in for
    part of a common gain is not judged against a model that lacks the gain)."""
    if not others:
        return model
    theta, specs = dict(model.kept), dict(model.specs)
    for e in others:
        s = sel.unit.screen(model, e)
        theta[e], specs[e] = s.kept[e], s.specs[e]
    return sel.fit(theta, specs)


def agrees(
    sel: Selector, base: Model, screened: Model, effect: str, value: np.ndarray, th: Thresholds
) -> bool:
    """Whether the cable's data take ``effect`` once it is fitted on the cable jointly with
    its other effects (from ``screened``'s start): it lowers the cable's held-out error by
    ``Thresholds.z_screen`` standard errors, or its parameters lie within ``z_screen``
    standard errors of the common ``value``. The common value on top of the cable's
    model, not refitted, can be refused for reasons that are not the cable's: the cables
    that kept the effect fitted it beside a stand-in (an offset beside a plain Coulomb
    where the machine's friction is directional: 5.7 N for 3 N), or the cable's other
    effects hold part of it and the common value on top counts that part twice. A clean
    cable among faulty ones fits the effect near its neutral value: no held-out gain,
    many standard errors from the faulty cables' value, refused."""
    fitted = sel.fit({**base.kept, effect: screened.kept[effect]}, screened.specs)
    if sel.z(base, fitted) >= th.z_screen:
        return True
    got, se = fitted.kept[effect], fitted.stderr[effect]
    if got.shape != np.shape(value) or not np.all(np.isfinite(se) & (se > 0)):
        return False
    return bool(np.max(np.abs(got - value) / se) <= th.z_screen)


def against(tests: dict[str, float], th: Thresholds) -> bool:
    """A cable's own held-out evidence is significantly against an effect."""
    return float(tests.get("z", 0.0)) <= -th.z_screen


def shrink(y: np.ndarray, s: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Empirical-Bayes partial pooling (module docstring): ``(mu, tau, shrunk)`` from
    estimates ``y`` (k,) and their standard errors ``s`` (k,). Estimates without a usable
    error (not finite or <= 0) are left as they are and do not inform ``mu`` or ``tau``;
    with fewer than two usable ones, ``mu`` is their mean and ``tau`` NaN."""
    y, s = np.asarray(y, float), np.asarray(s, float)
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    out = y.copy()
    if ok.sum() < 2:
        mean = float(np.mean(y[np.isfinite(y)])) if np.isfinite(y).any() else math.nan
        return mean, math.nan, out
    yy, v = y[ok], s[ok] ** 2
    w = 1.0 / v
    ybar = float(np.sum(w * yy) / np.sum(w))
    q = float(np.sum(w * (yy - ybar) ** 2))
    denom = float(np.sum(w) - np.sum(w**2) / np.sum(w))
    tau2 = max(0.0, (q - (yy.size - 1)) / denom) if denom > 0 else 0.0
    ws = 1.0 / (v + tau2)
    mu = float(np.sum(ws * yy) / np.sum(ws))
    b = v / (v + tau2)
    out[ok] = yy + b * (mu - yy)
    return mu, math.sqrt(tau2), out


def final_pooled(
    units: list[Tested], th: Thresholds, first: dict[str, Pooled]
) -> dict[str, Pooled]:
    """The pooled tests over the final tests (the report's numbers), with the decision of
    :func:`extend` (``common``, ``differs``) carried over: what was decided is reported."""
    out = pooled_tests(units, th)
    for e, r in out.items():
        was = first.get(e)
        r.common = bool(was and was.common)
        r.differs = list(was.differs) if was else []
    return out


def report_field(finding: dict, pooled: Pooled | None) -> dict | None:
    """A finding's ``pooling`` block (docs/diagnose-report.schema.json), from its reported
    parameters and standard errors (-1: not known) and its pooled test; None where the
    effect was not tested on two or more cables."""
    if pooled is None:
        return None
    stderr = finding.get("stderr", {})
    common_params, sd, shrunk = {}, {}, {}
    for name, values in finding["parameters"].items():
        se = np.array(stderr.get(name, [-1.0] * len(values)), float)
        se[se <= 0] = np.nan
        mu, tau, out = shrink(np.array(values, float), se)
        common_params[name] = _num(mu)
        sd[name] = _num(tau)
        shrunk[name] = [_num(v) for v in out]
    return {
        "scope": "common" if pooled.common and not pooled.differs else "cable_specific",
        "statistic": _num(pooled.statistic),
        "p": _num(pooled.p),
        "q": _num(pooled.q),
        "cables_tested": [k + 1 for k in pooled.cables],
        "differs": [k + 1 for k in pooled.differs],
        "common_parameters": common_params,
        "between_cable_sd": sd,
        "parameters": shrunk,
    }


def _num(v: float) -> float:
    return float(v) if math.isfinite(v) else -1.0
