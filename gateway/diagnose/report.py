"""Assemble the JSON report of recording.md from the per-cable selections.

Beyond the schema's keys the report carries ``skipped_rows`` (rows without a required
value) and ``regime_shares`` (per regime: share of the nominal residual energy and of the
samples); ``final`` also carries ``noise_n`` (white noise of the final residual, estimated
from sample-to-sample differences) and ``unexplained_n`` (the held-out RMSE beyond that
noise, ``sqrt(holdout^2 - noise^2)``: what no finding explains; large when the recording
holds physics outside the candidate list, or noise that is not white). ``rmse_*`` are over
every cable and sample, ``holdout_*`` over the held-out blocks, ``validation_*`` over the
``--validate`` recording; each finding's before/after are cumulative in the findings'
order. A standard error that could not be computed (singular Jacobian, parameter at a
bound) is written as -1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.diagnose import locate
from gateway.diagnose.evidence import evidence
from gateway.diagnose.forward import Forward, Nominal, report_stderr, to_report
from gateway.diagnose.prepare import cable_data, clipped_mask, finite_rows
from gateway.diagnose.select import CableOutcome
from gateway.recordings.reader import Recording


@dataclass
class Diagnosis:
    """Everything the report and the pictures are made of. The predictions are not held
    (16 bytes per sample and cable as float64): :meth:`predictions` recomputes a cable's."""

    report: dict
    t: np.ndarray
    measured: np.ndarray
    regime: np.ndarray
    regions: list[locate.Region]
    outcomes: list[CableOutcome]
    findings_order: list[str]
    forwards: list[Forward] = field(default_factory=list)

    def final_theta(self, i: int) -> dict[str, np.ndarray]:
        """Cable ``i``'s (0-based) fitted parameters of the findings (the final model)."""
        return _subset([self.outcomes[i]], self.findings_order)[0]

    def predictions(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Cable ``i``'s (0-based) sensor reading (N,) as the nominal and the final model
        predict it (the same array when the cable kept nothing); chain caches freed."""
        fw, theta = self.forwards[i], self.final_theta(i)
        nominal = fw.predict({})
        final = fw.predict(theta) if theta else nominal
        fw.clear_cache()
        return nominal, final


def _rmse(res: np.ndarray, mask: np.ndarray | None = None) -> float:
    r = res if mask is None else res[mask]
    return float(math.sqrt(np.mean(r**2))) if r.size else 0.0


def _subset(outcomes: list[CableOutcome], effects: list[str]) -> list[dict]:
    """Per cable, the fitted parameters of those of ``effects`` the cable kept."""
    return [{e: o.theta[e] for e in effects if e in o.theta} for o in outcomes]


def _sse(forwards: list[Forward], thetas: list[dict], masks: list[np.ndarray]):
    """Per mask (N, m) bool: sum of squared residuals and sample count over every cable,
    computed cable by cable (no (N, m) temporaries)."""
    sse, count = np.zeros(len(masks)), np.zeros(len(masks))
    for i, (fw, th) in enumerate(zip(forwards, thetas, strict=True)):
        r = fw.data.ts - fw.predict(th)
        fw.clear_cache()
        for j, mask in enumerate(masks):
            rr = r[mask[:, i]]
            sse[j] += float(rr @ rr)
            count[j] += rr.size
    return sse, count


def _rmses(forwards, thetas, masks) -> list[float]:
    sse, count = _sse(forwards, thetas, masks)
    return [math.sqrt(s / c) if c else 0.0 for s, c in zip(sse, count, strict=True)]


def _order(forwards, outcomes, valid) -> list[str]:
    """Effects ordered by the residual energy they explain in the final model (drop-one)."""
    effects = sorted({e for o in outcomes for e in o.kept})
    base = _sse(forwards, _subset(outcomes, effects), [valid])[0][0]
    worth = {}
    for e in effects:
        others = [x for x in effects if x != e]
        worth[e] = _sse(forwards, _subset(outcomes, others), [valid])[0][0] - base
    return sorted(effects, key=lambda e: worth[e], reverse=True)


def validation_forwards(validation, nom: Nominal, cables: int):
    """The validation recording's forwards and its valid (unclipped) samples, or None."""
    if validation is None:
        return None
    vrec, vtp, vdm = finite_rows(*validation)
    if vrec.cables != cables:
        from gateway.errors import RecordingError

        raise RecordingError(
            f"{vrec.source}: has {vrec.cables} cables, the diagnosed recording {cables}"
        )
    fws = [Forward(d, nom) for d in cable_data(vrec, vtp, vdm)]
    return fws, np.column_stack([~clipped_mask(fw.data.ts)[0] for fw in fws])


def _finding(effect, outcomes, rmse_pairs, ev) -> dict:
    cables = [i + 1 for i, o in enumerate(outcomes) if effect in o.theta]
    params: dict[str, list[float]] = {}
    errs: dict[str, list[float]] = {}
    for i in cables:
        o = outcomes[i - 1]
        for k, v in to_report(effect, o.theta[effect]).items():
            params.setdefault(k, []).append(_num(v))
        for k, v in report_stderr(effect, o.theta[effect], o.stderr[effect]).items():
            errs.setdefault(k, []).append(_num(v))
    out = {"effect": effect, "cables": cables, "parameters": params, "stderr": errs, "evidence": ev}
    out.update(rmse_pairs)
    return out


def rmse_pairs(before: Sequence, after: Sequence, validation: bool) -> dict[str, float]:
    """A finding's RMSE fields from the (fit, held-out, validation) scores before and after
    it is added; the validation pair only when there is a validation recording."""
    pairs = {
        "rmse_before_n": before[0],
        "rmse_after_n": after[0],
        "holdout_rmse_before_n": before[1],
        "holdout_rmse_after_n": after[1],
    }
    if validation:
        pairs["validation_rmse_before_n"] = float(before[2] or 0.0)
        pairs["validation_rmse_after_n"] = float(after[2] or 0.0)
    return pairs


def _noise_std(r: np.ndarray) -> float:
    """White-noise std of one residual column: median absolute first difference / sqrt 2."""
    return float(np.median(np.abs(np.diff(r)))) / (0.6745 * math.sqrt(2.0))


def noise_estimate(resid: np.ndarray) -> float:
    """White-noise std (N) of a residual (N, m): median absolute first difference / sqrt 2,
    robust to the slow part of the residual and to outliers; RMS over the cables."""
    if resid.shape[0] < 3:
        return 0.0
    per = np.array([_noise_std(resid[:, i]) for i in range(resid.shape[1])])
    return float(math.sqrt(np.mean(per**2)))


def _num(v: float) -> float:
    """JSON-safe float (NaN/inf -> a large sentinel is worse than 0 for a stderr: use -1)."""
    return float(v) if math.isfinite(v) else -1.0


def _regimes(forwards: list[Forward]) -> np.ndarray:
    """(N, m) int8 regimes; each cable's computed acceleration is freed after use."""
    out = np.empty((forwards[0].data.t.size, len(forwards)), np.int8)
    for i, fw in enumerate(forwards):
        out[:, i] = locate.regimes(fw.data.v, fw.data.a)
        fw.data.release()
    return out


def _baseline(t, forwards, valid, test, regime):
    """The report's ``baseline`` and the located regions with their
    :class:`locate.EnergyMap`, computed cable by cable: no (N, m) residual is held."""
    sse, count = np.zeros(2), np.zeros(2)
    per_cable = []
    emap = locate.EnergyMap(t)
    for i, fw in enumerate(forwards):
        r = fw.data.ts - fw.predict({})
        fw.clear_cache()
        r[~valid[:, i]] = 0.0
        for j, mask in enumerate((valid[:, i], test[:, i])):
            rr = r[mask]
            sse[j] += float(rr @ rr)
            count[j] += rr.size
            if j == 0:
                per_cable.append(_rmse(rr))
        emap.add(i + 1, r, regime[:, i])
    rms, hold = (math.sqrt(s / c) if c else 0.0 for s, c in zip(sse, count, strict=True))
    base = {"rmse_n": rms, "per_cable_rmse_n": per_cable, "holdout_rmse_n": hold}
    return base, emap.regions(), emap


def _final_noise(forwards, thetas, valid) -> float:
    """The white noise of the final model's residual (:func:`noise_estimate`), cable by
    cable."""
    per = np.zeros(len(forwards))
    for i, (fw, th) in enumerate(zip(forwards, thetas, strict=True)):
        r = fw.data.ts - fw.predict(th)
        fw.clear_cache()
        r[~valid[:, i]] = 0.0
        if r.size >= 3:
            per[i] = _noise_std(r)
    return float(math.sqrt(np.mean(per**2))) if valid.shape[0] >= 3 else 0.0


def build_report(
    rec: Recording,
    forwards: list[Forward],
    outcomes: list[CableOutcome],
    blocks: np.ndarray,
    validation,
    nom: Nominal,
    valid: np.ndarray | None = None,
    clipped: dict | None = None,
) -> Diagnosis:
    """The report dict and the arrays behind it; ``validation``: the validation recording's
    forwards and valid samples (:func:`validation_forwards`) or None; ``valid`` (N, m):
    samples scored (False: a clipped reading), ``clipped``: their counts and levels.
    Memory: besides the recording, (N, m) bool masks and int8 regimes; predictions and
    residuals exist one cable at a time (:meth:`Diagnosis.predictions` for the plots)."""
    measured = rec.tension_sensor
    valid = np.ones(measured.shape, bool) if valid is None else valid
    test = (blocks % 2 == 1)[:, None] & valid
    regime = _regimes(forwards)
    baseline, regions, emap = _baseline(rec.t, forwards, valid, test, regime)
    vfw, vvalid = validation or (None, None)
    order = _order(forwards, outcomes, valid)

    def scores(effects: list[str]) -> tuple[float, float, float | None]:
        thetas = _subset(outcomes, effects)
        rms, hold = _rmses(forwards, thetas, [valid, test])
        v = None if vfw is None else _rmses(vfw, thetas, [vvalid])[0]
        return rms, hold, v

    before = scores([])
    findings = []
    for k, effect in enumerate(order):
        after = scores(order[: k + 1])
        pairs = rmse_pairs(before, after, vfw is not None)
        ev = evidence(effect, outcomes, regime, before[1], after[1])
        findings.append(_finding(effect, outcomes, pairs, ev))
        before = after
    noise = _final_noise(forwards, _subset(outcomes, order), valid)
    final = {
        "rmse_n": before[0],
        "holdout_rmse_n": before[1],
        "noise_n": noise,
        "unexplained_n": math.sqrt(max(before[1] ** 2 - noise**2, 0.0)),
    }
    if vfw is not None:
        final["validation_rmse_before_n"] = _rmses(vfw, [{} for _ in vfw], [vvalid])[0]
        final["validation_rmse_after_n"] = float(before[2] or 0.0)
    report = {
        "cables": rec.cables,
        "samples": rec.samples,
        "skipped_rows": rec.skipped_rows,
        "baseline": baseline,
        **emap.report_fields(regions),
        "findings": findings,
        "final": final,
        "clipped": clipped or {"per_cable": [0] * rec.cables, "levels_n": [[]] * rec.cables},
    }
    return Diagnosis(report, rec.t, measured, regime, regions, outcomes, order, forwards)
