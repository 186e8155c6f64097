"""The wrench reference's report (:class:`gateway.diagnose.wrench_reference.WrenchReference`):
findings in the order of the force residual energy each explains, their values and
standard errors on the cables the motion identifies, the evidence sentences, where the
residual lives, the signatures for the pictures and the least-squares block.

Every ``*_rmse_n`` is the RMS of the force part of the unweighted wrench residual (N, over
the three components and the samples); moments in ``wrench``. The balance is one unit: a
finding's ``statistic``, ``p`` and ``q`` are one joint test, repeated for each of its
cables. ``baseline.least_squares``: the engineer's Coulomb + viscous + offset per cable
fitted on the same balance (:mod:`.wrench_lsq`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gateway.core.config import Config
from gateway.diagnose import locate, wrench_lsq
from gateway.diagnose.report import Diagnosis, rmse_pairs
from gateway.diagnose.selection import Outcome
from gateway.diagnose.sessions import Sessions
from gateway.diagnose.significance import combined_stderr
from gateway.diagnose.stats import white_noise_columns
from gateway.diagnose.wrench import (
    PER_CABLE,
    SUBPARAMS,
    VIF_MAX,
    WRENCH_EFFECTS,
    Prepared,
    WrenchModel,
    identifiable_cables,
    report_columns,
    wrench_data,
)
from gateway.diagnose.wrench_unit import WrenchUnit, force_rms
from gateway.model import effects as fx
from gateway.recordings.reader import Recording

NOT_CANDIDATES = tuple(n for n in fx.EFFECT_NAMES if n not in WRENCH_EFFECTS)
SIGNATURE_POINTS = 20000


@dataclass
class WrenchDiagnosis(Diagnosis):
    """A :class:`Diagnosis` of the wrench reference. ``measured`` is zero (the balance),
    ``nominal_pred`` and ``final_pred`` minus the force residuals (N, 3) of the nominal and
    the final model (held: the balance is not per cable); ``signatures``: per finding,
    its contribution to the force residual and the residual the final model leaves
    without it (both flattened, thinned), for :mod:`.wrench_plots`."""

    signatures: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    nominal_pred: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    final_pred: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def _per_cable(effect: str) -> bool:
    return fx.REGISTRY[effect].per_cable


def _report_values(effect: str, theta: np.ndarray, cables: list[int]) -> dict[str, list[float]]:
    """Internal parameters (k, m) -> report values on ``cables``."""
    values = report_columns(effect, theta)
    return {
        name: [float(v[i if _per_cable(effect) else 0]) for i in cables]
        for name, v in values.items()
    }


def _fitted_cables(sel: WrenchUnit, effect: str) -> list[int]:
    if not _per_cable(effect):
        return list(range(sel.model.data.cables))
    return sorted({i for _, i in sel.cols[effect]})


def _stderr_values(
    sel: WrenchUnit, effect: str, theta: np.ndarray, se: np.ndarray, cables: list[int]
) -> dict:
    """Standard errors of the internal columns -> of the report values
    (:meth:`Effect.report_stderr`); -1 for a parameter not fitted on the cable."""
    e = fx.REGISTRY[effect]
    table = {(j, i): float(s) for (j, i), s in zip(sel.cols[effect], se, strict=True)}
    out: dict[str, list[float]] = {name: [] for name in SUBPARAMS[effect]}
    for i in cables:
        col = i if _per_cable(effect) else 0
        internal = np.array([table.get((j, col), np.nan) for j in range(len(SUBPARAMS[effect]))])
        known = np.array([(j, col) in table for j in range(internal.size)])
        rep = e.report_stderr(theta[:, col], np.where(known, internal, 0.0))
        for j, name in enumerate(SUBPARAMS[effect]):
            out[name].append(float(rep[name]) if known[j] else -1.0)
    return out


def _identifiability(sel: WrenchUnit) -> dict:
    """Per candidate: the cables the motion identifies (variance inflation <= VIF_MAX for
    every sub-parameter), the others, the inflations and the block's condition number."""
    out: dict[str, dict] = {}
    for e, blocks in sel.ident.items():
        if not _per_cable(e):
            out[e] = {"identifiable": bool(blocks[0]["live"][0]), "platform": True}
            continue
        ok = sorted(set.intersection(*(set(identifiable_cables(b)) for b in blocks)))
        vif = np.max(np.column_stack([b["vif"] for b in blocks]), axis=1)
        out[e] = {
            "identifiable_cables": [i + 1 for i in ok],
            "unidentifiable_cables": [i + 1 for i in range(vif.size) if i not in ok],
            "max_variance_inflation": [float(v) if math.isfinite(v) else -1.0 for v in vif],
            "condition": max(
                float(b["condition"]) if math.isfinite(b["condition"]) else -1.0 for b in blocks
            ),
        }
    return out


def _order(model: WrenchModel, theta: dict, mask: np.ndarray) -> list[str]:
    """Kept effects by the force residual energy each explains in the final model."""
    full = force_rms(model.force_residual(theta)[0], mask) ** 2
    worth = {
        e: force_rms(model.force_residual({k: v for k, v in theta.items() if k != e})[0], mask) ** 2
        - full
        for e in theta
    }
    return sorted(theta, key=lambda e: worth[e], reverse=True)


def _missing(cables: list[int]) -> str:
    if not cables:
        return ""
    return f" Not identifiable from this motion on cables {cables} (not fitted there)."


def _evidence(effect: str, cables: list[int], values: dict, before: float, after: float) -> str:
    pct = 100.0 * (1.0 - after / before) if before > 0 else 0.0
    vals = ", ".join(
        f"{k} = {min(v):.4g}..{max(v):.4g}" if len(set(v)) > 1 else f"{k} = {v[0]:.4g}"
        for k, v in values.items()
    )
    where = (
        "the platform (one value for the whole recording)"
        if not _per_cable(effect)
        else f"cable{'s' if len(cables) > 1 else ''} {', '.join(str(c + 1) for c in cables)}"
    )
    return (
        f"Wrench balance (no platform tensions): {effect} on {where}, identified jointly "
        f"across cables through the varying structure matrix; fitted {vals}; it lowers the "
        f"held-out RMS of the force residual from {before:.3g} N to {after:.3g} N ({pct:.1f} %)."
    )


def build(
    rec: Recording,
    prep: Prepared,
    sel: WrenchUnit,
    outcome: Outcome,
    theta: dict[str, np.ndarray],
    se: dict[str, np.ndarray],
    cfg: Config | None,
    validation: Recording | None = None,
    sessions: Sessions | None = None,
    validation_sessions: Sessions | None = None,
) -> WrenchDiagnosis:
    """The diagnosis of ``rec`` from the fitted unit ``sel`` (on every sample of ``prep``),
    the selector's ``outcome`` and the kept effects' refit ``theta`` and standard errors
    ``se``; the ``validation`` recording scored, never fitted (module docstring)."""
    data, model = prep.model.data, prep.model
    test = (prep.blocks % 2 == 1) & prep.warm  # held-out samples, all of them
    order = _order(model, theta, test) if len(theta) > 1 else list(theta)
    vmodel = None
    if validation is not None:
        vsession = None if validation_sessions is None else validation_sessions.index
        vmodel = WrenchModel(wrench_data(validation, cfg, vsession), model.nom)

    def scores(effects: list[str]) -> tuple[float, float, float | None, np.ndarray, float]:
        """RMS of the force residual (all, held out, validation), the force residual
        (N, 3) and the moment's RMS: the residual (N, 6) itself is not kept."""
        th = {e: theta[e] for e in effects}
        force, moment_ms = model.force_residual(th)
        v = None if vmodel is None else force_rms(vmodel.force_residual(th)[0])
        return force_rms(force), force_rms(force, test), v, force, math.sqrt(moment_ms)

    before = scores([])
    nominal = before  # the nominal model's scores (before moves on with each finding)
    findings = []
    for k, e in enumerate(order):
        after = scores(order[: k + 1])
        cables = _fitted_cables(sel, e)
        values = _report_values(e, theta[e], cables)
        missing = [i + 1 for i in range(data.cables) if i not in cables]
        test_e = outcome.tests.get(e, {})
        se_blk = outcome.stderr_blocks.get(e, np.full(se[e].size, np.nan))
        f = {
            "effect": e,
            "cables": [c + 1 for c in cables],
            "parameters": values,
            "stderr": _stderr_values(sel, e, theta[e], combined_stderr(se[e], se_blk), cables),
            "stderr_jacobian": _stderr_values(sel, e, theta[e], se[e], cables),
            "stderr_blocks": _stderr_values(sel, e, theta[e], se_blk, cables),
            # one joint test over every cable (the balance is one unit)
            "statistic": [float(test_e.get("z", -1.0))] * len(cables),
            "p": [float(test_e.get("p", -1.0))] * len(cables),
            "q": [float(test_e.get("q", -1.0))] * len(cables),
            "evidence": _evidence(e, cables, values, before[1], after[1]) + _missing(missing),
            **rmse_pairs(before, after, vmodel is not None),
        }
        findings.append(f)
        before = after
    # the signatures before the diagnosis, which takes the force residuals over (negated
    # in place); thinned copies, not views of two (N, 3) series each (27 MiB for 10 min)
    step = max(1, data.t.size * 3 // SIGNATURE_POINTS)
    signatures = {}
    for e in order:
        if len(order) == 1:  # without it, the nominal model: its scores' force residual
            without = nominal[3]
        else:
            without = model.force_residual({k: v for k, v in theta.items() if k != e})[0]
        contrib = (without - before[3]).reshape(-1)[::step].copy()
        signatures[e] = (contrib, without.reshape(-1)[::step].copy())
        del without, contrib
    least_squares = wrench_lsq.block(
        prep,
        sel.r0,
        sel.train_samples,
        test,
        nominal[3],
        before[3],
        None if vmodel is None else (vmodel, float(before[2] or 0.0)),
    )
    diag = _build(rec, prep, sel, findings, order, nominal, before, vmodel)
    diag.report["baseline"]["least_squares"] = least_squares
    diag.signatures.update(signatures)
    if sessions is not None:  # after samples and skipped_rows, as the platform report
        rep = diag.report
        where = list(rep).index("skipped_rows") + 1
        items = list(rep.items())
        rep.clear()
        rep.update([*items[:where], ("recordings", sessions.report()), *items[where:]])
    return diag


def _build(rec, prep, sel, findings, order, nominal, final, vmodel) -> WrenchDiagnosis:
    """The diagnosis from the nominal and the final :func:`build` scores (each
    with the force residual (N, 3) and the moment's RMS). The force residuals are taken
    over: negated in place into ``nominal_pred`` and ``final_pred`` (not copied: 14 MiB
    each for 10 min), the scores' caller reads them no more."""
    data = prep.model.data
    r_nominal, r_final = nominal[3], final[3]
    fs = white_noise_columns(r_final)
    noise = float(math.sqrt(np.mean(fs**2)))
    fin = {
        "rmse_n": final[0],
        "holdout_rmse_n": final[1],
        "noise_n": noise,
        "unexplained_n": math.sqrt(max(final[1] ** 2 - noise**2, 0.0)),
        "moment_rmse_nm": final[4],
    }
    if vmodel is not None:
        fin["validation_rmse_before_n"] = force_rms(vmodel.force_residual({})[0])
        fin["validation_rmse_after_n"] = float(final[2] or 0.0)
    norm0 = np.linalg.norm(r_nominal, axis=1)[:, None]
    norm1 = np.linalg.norm(r_final, axis=1)[:, None]
    regime = locate.regimes(data.speed, np.gradient(data.speed, data.t))[:, None]

    def located(norm: np.ndarray) -> list[locate.Region]:
        return [
            locate.Region(0, r.start_s, r.end_s, r.regime, r.share)
            for r in locate.regions(data.t, norm, regime)
        ]

    regions, regions_final = located(norm0), located(norm1)
    report = {
        "reference": "wrench",
        "cables": rec.cables,
        "samples": int(data.t.size),
        "skipped_rows": rec.skipped_rows + (rec.samples - int(data.t.size)),
        "baseline": {
            "rmse_n": nominal[0],
            "per_cable_rmse_n": [],
            **locate.report_fields(regions, norm0, regime),
        },
        **locate.report_fields(regions_final, norm1, regime),
        "findings": findings,
        "final": fin,
        "identifiability": _identifiability(sel),
        "wrench": {
            "candidates": list(WRENCH_EFFECTS),
            "not_candidates": list(NOT_CANDIDATES),
            "variance_inflation_max": VIF_MAX,
            "baseline_moment_rmse_nm": nominal[4],
            "per_cable_effects": list(PER_CABLE),
        },
    }
    return WrenchDiagnosis(
        report,
        data.t,
        np.broadcast_to(0.0, (data.t.size, 3)),  # views, read only: 14 MiB each for 10 min
        np.broadcast_to(regime, (data.t.size, 3)),
        regions_final,
        [],
        order,
        [],
        regions_nominal=regions,
        nominal_pred=np.negative(r_nominal, out=r_nominal),
        final_pred=r_nominal if r_final is r_nominal else np.negative(r_final, out=r_final),
    )
