"""Which findings are real: every candidate x unit tested on held-out data, the false
discovery rate controlled over all of them, parameters judged by their spread across time
blocks (:mod:`.stats` explains each test).

For every unit (a cable, or the platform's wrench balance) and every candidate effect:

* a kept effect against the model refitted without it,
* a candidate not kept screened on top of the final model,

each gives a held-out ``z`` and a one-sided p-value; Benjamini-Hochberg over the p-values of
all units and candidates gives each a q-value. A finding stays only where

1. ``q <= Thresholds.fdr`` (it lowers the error on data it was not fitted on by more than
   chance allows, with the false discoveries among everything tried under control), and
2. it differs from "absent" by ``Thresholds.z_min`` times its uncertainty: its parameters
   from the nominal model's values in the Jacobian's standard errors, and its contribution
   to the prediction in the spread of refits with one group of training blocks left out
   (the delete-a-group jackknife, :func:`block_refits`): a stand-in that holds a
   model-form error, or a coefficient at the nominal value, varies between stretches of
   the recording and fails here. The parameters' own standard errors from refits (with
   whole trials left out where the recording has several) are reported beside the
   Jacobian's.

Findings that fail are dropped, the unit refitted without them and the tests repeated
(at most ``ROUNDS`` times).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gateway.diagnose.selection import Model, Outcome, Rival, Selector, overlaps
from gateway.diagnose.stats import bh_qvalues, block_groups, jackknife_se

ROUNDS = 3
GROUPS = 8
"""Groups of training blocks for the jackknife (each refit leaves one out)."""


@dataclass
class Tested:
    """One unit in the significance stage: its selector (None once retired: only its
    numbers are kept), final model and outcome (its tests)."""

    selector: Selector | None
    model: Model
    outcome: Outcome
    dropped: list[str] = field(default_factory=list)
    index: int = 0


def candidate_tests(sel: Selector, model: Model) -> dict[str, dict[str, float]]:
    """Per candidate: held-out ``z``, ``p`` and the relative held-out ``gain`` of the model
    with it over the model without it (module docstring)."""
    out: dict[str, dict[str, float]] = {}
    for effect in model.kept:
        reduced = sel.fit(*model.without(effect), nfev=30)
        out[effect] = sel.test(reduced, model)
    on, screened = sel.screened  # the last forward step screened on this very model: reuse
    for cand in sel.candidates:
        if cand in model.kept or overlaps(cand, model.kept):
            continue
        if on is model and cand in screened:
            out[cand] = screened[cand]
        else:
            out[cand] = sel.test(model, sel.unit.screen(model, cand))
    release = getattr(sel.unit, "release", None)
    if release is not None:
        release()
    return out


def block_refits(sel: Selector, model: Model) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """From refits with one group of training blocks left out each: the standard errors of
    the kept effects' internal parameters (:func:`.stats.jackknife_se`), and per effect how
    many such standard errors its contribution to the prediction lies from none.

    The contribution ``c_g`` of an effect in refit ``g`` (the prediction with it minus
    without it, on the training samples) is projected on the full fit's ``c``:
    ``a_g = <c_g, c> / <c, c>``; the full fit has ``a = 1``, so ``1 / se(a)`` measures the
    effect's presence however its parameters trade off among themselves (a Stribeck level
    against its speed) and is near 0 for a contribution that is nothing but noise (a
    coefficient at the nominal value).

    The presence comes from interleaved groups of blocks (every refit sees every part of
    the recording). The standard errors of a recording of several trials come from refits
    that leave out whole trials (:func:`.stats.block_groups`): the spread a second
    recording shows. The presence does not: a few trials are too few groups to judge
    presence by (with 4, a Student-t threshold dropped even an offset of 80 % held-out
    gain on a real recording)."""
    if not model.kept:
        return {}, {}
    unit = sel.unit
    masks = block_groups(unit.blocks, unit.train, GROUPS)
    if len(masks) < 2:
        return {e: np.full(v.size, np.nan) for e, v in model.kept.items()}, {}
    fits = [unit.refit_on(model, m) for m in masks]  # type: ignore[attr-defined]
    segments = getattr(unit, "segments", None)
    by_trial = (
        masks if segments is None else block_groups(unit.blocks, unit.train, GROUPS, segments)
    )
    trial_fits = (
        fits
        if by_trial is masks
        or (len(by_trial) == len(masks) and all(map(np.array_equal, by_trial, masks)))
        else [unit.refit_on(model, m) for m in by_trial]  # type: ignore[attr-defined]
    )
    se = {e: jackknife_se(np.stack([f[e] for f in trial_fits])) for e in model.kept}
    presence = {}
    for e in model.kept:
        c = unit.contribution(model.kept, e)  # type: ignore[attr-defined]
        norm = float(c @ c)
        if norm <= 0.0:
            presence[e] = 0.0
            continue
        a = np.array([float(unit.contribution(f, e) @ c) / norm for f in fits])  # type: ignore[attr-defined]
        spread = float(jackknife_se(a[:, None])[0])
        presence[e] = float(np.inf) if spread == 0.0 else 1.0 / spread
    release = getattr(unit, "release", None)
    if release is not None:
        release()
    return se, presence


def combined_stderr(jacobian: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """The larger of the two standard errors, element by element (NaN where neither)."""
    j = np.where(np.isfinite(jacobian), jacobian, -np.inf)
    b = np.where(np.isfinite(blocks), blocks, -np.inf)
    out = np.maximum(j, b)
    return np.where(np.isfinite(out), out, np.nan)


def param_z(sel: Selector, model: Model, effect: str, presence: float | None) -> float:
    """How far ``effect`` lies from absent: the smaller of its parameters' distance from
    the nominal in (Jacobian) standard errors and its contribution's presence across
    time blocks (:func:`block_refits`)."""
    z = float(sel.unit.significance(model, effect))
    return z if presence is None else min(z, presence)


def left_out_tests(
    sel: Selector, model: Model, reduced: dict[str, Model] | None = None
) -> dict[str, dict[str, float]]:
    """Each kept effect's test with the recordings left out in turn (several recordings
    joined: :meth:`.reference.CableUnit.recordings_left_out`), or {} (one recording). With
    ``reduced``, only its effects, each against the model given there in place of the model
    without it (a richer effect against the simpler one it nests)."""
    left_out = getattr(sel.unit, "recordings_left_out", None)
    if left_out is None:
        return {}
    return left_out(model) if reduced is None else left_out(model, reduced)


def stricter(test: dict[str, float], left_out: dict[str, float]) -> tuple[float, float]:
    """(z, p) of an effect that must beat chance on the held-out blocks and on the
    recordings left out in turn: the smaller z, the larger p."""
    return min(test["z"], left_out["z"]), max(test["p"], left_out["p"])


def score(u: Tested) -> None:
    """One unit's tests (every candidate), block refits and parameter tests, in place;
    the q-values come with :func:`decide`, over every unit."""
    sel, model = u.selector, u.model
    assert sel is not None
    tests = candidate_tests(sel, model)
    for e, t in left_out_tests(sel, model).items():  # several recordings
        b = tests[e]
        b["blocks_z"], b["recordings_z"] = b["z"], t["z"]
        b["z"], b["p"] = stricter(b, t)
    se_blocks, presence = block_refits(sel, model)
    for e in model.kept:
        tests[e]["param_z"] = param_z(sel, model, e, presence.get(e))
    u.outcome.tests, u.outcome.stderr_blocks = tests, se_blocks


def retire(u: Tested) -> None:
    """Free what a scored unit holds beyond its numbers (its data, its residual); a later
    round rebuilds it (:func:`decide`'s ``rebuild``)."""
    u.selector = None
    u.model = Model(u.model.kept, u.model.specs, u.model.stderr, np.zeros(0))


def _fails(units: list[Tested], th, common: frozenset[str] = frozenset()) -> list[list[str]]:
    """q-values over every unit and candidate (stored in each outcome's tests); the kept
    effects of each unit that fail (module docstring). An effect ``common`` to the cables
    (:mod:`.pooling`: its pooled evidence is significant) fails on a unit only where the
    unit's own held-out z is below ``-z_screen`` (its data says it differs)."""
    flat = [(k, e) for k, u in enumerate(units) for e in u.outcome.tests]
    q = bh_qvalues([units[k].outcome.tests[e]["p"] for k, e in flat])
    for (k, e), qv in zip(flat, q, strict=True):
        units[k].outcome.tests[e]["q"] = float(qv)
    out = []
    for u in units:
        t = u.outcome.tests
        out.append(
            [
                e
                for e in u.model.kept
                if (
                    t[e]["z"] <= -th.z_screen
                    if e in common
                    else t[e]["q"] > th.fdr
                    or t[e]["gain"] < th.rel_min
                    or t[e]["param_z"] < th.z_min
                )
            ]
        )
    return out


def decide(
    units: list[Tested],
    th,
    say=lambda _m: None,
    rebuild=None,
    common: frozenset[str] = frozenset(),
) -> None:
    """The significance stage over every unit, in place (module docstring): q-values over
    every unit's tests (each unit scored by :func:`score` when it is not yet), failing
    findings dropped and the unit refitted and scored again, until none fails.
    ``rebuild(u)``: a retired unit's selector again (its model re-evaluated at its
    values); ``common``: effects the cables share (:func:`_fails`)."""
    for u in units:
        if u.outcome.tests == {} and u.selector is not None:
            score(u)
    for _ in range(ROUNDS):
        fails = _fails(units, th, common)
        if not any(fails):
            break
        for u, fail in zip(units, fails, strict=True):
            if not fail:
                continue
            say(f"{', '.join(fail)} not significant ({_why(u.outcome.tests, fail)})")
            if u.selector is None:
                u.selector, u.model = rebuild(u)
            u.dropped += fail
            keep = {e: v for e, v in u.model.kept.items() if e not in fail}
            specs = {e: u.model.specs[e] for e in keep}
            u.model = u.selector.fit(keep, specs) if keep else u.selector.unit.empty()
            score(u)
            if rebuild is not None:
                retire(u)
    else:
        _fails(units, th, common)
    for u in units:
        o = u.outcome
        o.kept = [e for e in o.kept if e in u.model.kept] + [
            e for e in u.model.kept if e not in o.kept
        ]
        o.theta, o.stderr, o.specs = u.model.kept, u.model.stderr, u.model.specs
        o.rivals = {e: r for e, r in o.rivals.items() if e in u.model.kept}
        o.stderr_blocks = {e: s for e, s in o.stderr_blocks.items() if e in u.model.kept}


def _why(tests: dict[str, dict[str, float]], fail: list[str]) -> str:
    parts = []
    for e in fail:
        t = tests[e]
        parts.append(
            f"{e}: q {t['q']:.2g}, held-out gain {100 * t['gain']:.2f} %, "
            f"parameters {t['param_z']:.1f} standard errors from the nominal"
        )
    return "; ".join(parts)


def harmonize(units: list[Tested]) -> None:
    """One name for an ambiguity, in place: where a unit kept ``a`` and the held-out data
    cannot tell it from ``b`` (an unseparable rival), while more units kept ``b`` (as many:
    with a larger sum of held-out z), this unit takes ``b`` (its fit as the rival:
    parameters, errors) and lists ``a`` as the rival, so the report gives one finding with
    ``a`` among its alternatives, not ``a`` on some cables and ``b`` on others."""
    counts: dict[str, tuple[int, float]] = {}
    for u in units:
        for e in u.outcome.kept:
            n, z = counts.get(e, (0, 0.0))
            counts[e] = (n + 1, z + float(u.outcome.tests.get(e, {}).get("z", 0.0)))
    for u in units:
        o = u.outcome
        for e in list(o.kept):
            for rv in o.rivals.get(e, []):
                if rv.separable or counts.get(rv.effect, (0, 0.0)) <= counts.get(e, (0, 0.0)):
                    continue
                if rv.effect in o.theta:
                    continue
                mine = Rival(e, rv.holdout_sse, False, o.theta[e], o.stderr[e], -rv.z)
                o.kept = [rv.effect if k == e else k for k in o.kept]
                o.theta = {(rv.effect if k == e else k): v for k, v in o.theta.items()}
                o.theta[rv.effect] = rv.theta
                o.stderr = {(rv.effect if k == e else k): v for k, v in o.stderr.items()}
                o.stderr[rv.effect] = rv.stderr
                o.specs = {(rv.effect if k == e else k): v for k, v in o.specs.items()}
                others = [r for r in o.rivals.pop(e) if r.effect != rv.effect]
                o.rivals[rv.effect] = [mine, *others]
                if e in o.tests:
                    o.tests[rv.effect] = {**o.tests[e], "swapped_from": e}  # type: ignore[dict-item]
                o.stderr_blocks.pop(e, None)
                break
