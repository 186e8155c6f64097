"""Stage 5 of the platform-tension reference: the JSON report of docs/recording-format.md
from the fitted, tested units.

Beyond the schema's keys the report carries ``skipped_rows`` (rows without a required
value). ``baseline`` describes the nominal model's residual (its RMSE, ``mismatch`` regions
and ``regime_shares``); the top-level ``mismatch`` and ``regime_shares`` describe the
**final** model's residual: where what is left lives. ``final`` carries ``noise_n`` (white
noise of the final residual, :func:`.stats.white_noise`) and ``unexplained_n`` (the
held-out RMSE beyond that noise). ``unexplained`` (present only when the final residual
holds structure that a smooth function of some signal explains on held-out blocks beyond
chance, :mod:`.signals`) names the signal, its share of the residual variance and the
closest physical reading; ``unexplained_excluded`` lists the extra columns left out of
that search because they are a cable's reading in disguise (a scaled or offset copy:
:func:`.signals.disguised_readings`). ``baseline.least_squares`` holds the engineer's
least-squares fits (:mod:`.lsq`), scored on the same held-out blocks and validation
recording as the final model, and one sentence on whether the catalogue's model beats them.

Each finding carries, per cable in ``cables``: ``statistic`` (the held-out z of the model
with it against the model without it), ``p`` and ``q`` (Benjamini-Hochberg over every
candidate x cable tried, :mod:`.significance`), ``stderr`` (the larger of the Jacobian's
and the spread of refits across time blocks, whole trials left out where the recording
joins several), ``stderr_jacobian`` and ``stderr_blocks``; with several recordings
(:mod:`.sessions`) ``recordings_statistic``, the z on recordings left out in turn, and
``statistic`` the smaller of the two (``p`` the larger);
``alternatives`` lists the effects of its group the held-out data cannot tell from it (each
with its parameters and held-out RMSE) and ``separate_by`` the motion that would. ``rmse_*``
are over every cable and sample, ``holdout_*`` over the held-out blocks, ``validation_*``
over the ``--validate`` recording (scored, never deciding: ``validation_statistic`` per
cable is the validation recording's z of the model with the finding against it without,
:func:`.reference.validation_scores`); each finding's before/after are cumulative in the
findings' order. A standard error that could not be computed is written as -1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.core.heap import trim_heap
from gateway.diagnose import locate, lsq, pooling, sessions, signals
from gateway.diagnose.evidence import evidence
from gateway.diagnose.forward import CableData, Forward, report_stderr, to_report
from gateway.diagnose.selection import Outcome, Thresholds
from gateway.diagnose.significance import Tested, combined_stderr
from gateway.diagnose.stats import white_noise
from gateway.model import effects as fx


@dataclass
class Diagnosis:
    """Everything the report and the pictures are made of. The predictions are not held
    (16 bytes per sample and cable as float64): :meth:`predictions` recomputes a cable's.
    ``regions`` are the final residual's, ``regions_nominal`` the nominal one's."""

    report: dict
    t: np.ndarray
    measured: np.ndarray
    regime: np.ndarray
    regions: list[locate.Region]
    outcomes: list[Outcome]
    findings_order: list[str]
    forwards: list[Forward] = field(default_factory=list)
    regions_nominal: list[locate.Region] = field(default_factory=list)
    structure: signals.Structure | None = None

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


def _subset(outcomes: list[Outcome], effects: list[str]) -> list[dict]:
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


def _num(v: float) -> float:
    """JSON-safe float (NaN/inf -> -1, the schema's "could not be computed")."""
    return float(v) if math.isfinite(v) else -1.0


def _finding(effect: str, tested: list[Tested], pairs: dict, ev: str, n_test: int) -> dict:
    cables = [i + 1 for i, u in enumerate(tested) if effect in u.outcome.theta]
    params: dict[str, list[float]] = {}
    errs: dict[str, list[float]] = {}
    errs_jac: dict[str, list[float]] = {}
    errs_blk: dict[str, list[float]] = {}
    stat, ps, qs, vstat, rstat = [], [], [], [], []
    for i in cables:
        o = tested[i - 1].outcome
        theta, se = o.theta[effect], o.stderr[effect]
        se_blk = o.stderr_blocks.get(effect, np.full(theta.size, np.nan))
        for k, v in to_report(effect, theta).items():
            params.setdefault(k, []).append(_num(v))
        for name, values, target in (
            ("combined", combined_stderr(se, se_blk), errs),
            ("jacobian", se, errs_jac),
            ("blocks", se_blk, errs_blk),
        ):
            del name
            for k, v in report_stderr(effect, theta, values).items():
                target.setdefault(k, []).append(_num(v))
        t = o.tests.get(effect, {})
        stat.append(_num(t.get("z", math.nan)))
        ps.append(_num(t.get("p", math.nan)))
        qs.append(_num(t.get("q", math.nan)))
        if "validation_z" in t:
            vstat.append(_num(t["validation_z"]))
        if "recordings_z" in t:
            rstat.append(_num(t["recordings_z"]))
    out = {
        "effect": effect,
        "cables": cables,
        "parameters": params,
        "stderr": errs,
        "stderr_jacobian": errs_jac,
        "stderr_blocks": errs_blk,
        "statistic": stat,
        "p": ps,
        "q": qs,
        "evidence": ev,
    }
    if vstat and len(vstat) == len(cables):
        out["validation_statistic"] = vstat
    if rstat and len(rstat) == len(cables):
        out["recordings_statistic"] = rstat
    per = per_recording_field(effect, [tested[i - 1].outcome.theta[effect] for i in cables])
    if per is not None:
        out["per_recording"] = per
    alts = alternatives(effect, tested, n_test)
    if alts:
        out["alternatives"] = alts
        out["separate_by"] = fx.REGISTRY[effect].separate
    out.update(pairs)
    return out


def per_recording_field(effect: str, thetas: list[np.ndarray]) -> list[dict] | None:
    """An effect fitted per recording (:mod:`.sessions`): per recording (in the order of
    the report's ``recordings``), its reported parameters per cable of the finding (the
    finding's ``parameters`` are their mean); None for an effect shared by the recordings."""
    if not thetas or sessions.per_recording(effect, thetas[0].size) == 1:
        return None
    per = [sessions.rows(effect, th) for th in thetas]
    out = []
    for r in range(per[0].shape[0]):
        params: dict[str, list[float]] = {}
        for rows in per:
            for k, v in to_report(effect, rows[r]).items():
                params.setdefault(k, []).append(_num(v))
        out.append({"parameters": params})
    return out


def alternatives(effect: str, tested: list[Tested], n_test: int) -> list[dict]:
    """The rivals the held-out data cannot tell from ``effect`` on some of its cables,
    each with its parameters there and its held-out RMSE (N)."""
    rows: dict[str, dict] = {}
    for i, u in enumerate(tested):
        for rv in u.outcome.rivals.get(effect, []):
            if rv.separable:
                continue
            row = rows.setdefault(
                rv.effect,
                {"effect": rv.effect, "cables": [], "parameters": {}, "holdout_rmse_n": []},
            )
            row["cables"].append(i + 1)
            for k, v in to_report(rv.effect, rv.theta).items():
                row["parameters"].setdefault(k, []).append(_num(v))
            row["holdout_rmse_n"].append(math.sqrt(rv.holdout_sse / max(n_test, 1)))
    return list(rows.values())


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


def noise_estimate(resid: np.ndarray) -> float:
    """White-noise std (N) of a residual (N, m), RMS over the cables
    (:func:`.stats.white_noise` per cable)."""
    if resid.shape[0] < 3:
        return 0.0
    per = np.array([white_noise(resid[:, i]) for i in range(resid.shape[1])])
    return float(math.sqrt(np.mean(per**2)))


EXPLAIN_SAMPLES = 150_000


def final_residual(prep, forwards, thetas, located, th: Thresholds):
    """The final model's residual, cable by cable (no (N, m) residual is held): its white
    noise (RMS over cables), where it lives (:class:`locate.EnergyMap`) and the strongest
    significant structure a signal explains (:mod:`.signals`: the report's ``unexplained``
    and the :class:`signals.Structure`, or Nones), and the extra columns left out of that
    search as a cable's reading in disguise (:func:`signals.disguised_readings`)."""
    per = np.zeros(len(forwards))
    emap = locate.EnergyMap(prep.rec.t)
    # the structure search on at most EXPLAIN_SAMPLES samples a cable (evenly thinned: a
    # smooth function of a signal needs no more; memory and time of a long recording)
    n = prep.rec.samples
    idx = np.arange(0, n, max(1, -(-n // EXPLAIN_SAMPLES)))
    blk = prep.blocks[idx]
    extra = {k: np.asarray(v, dtype=float)[idx] for k, v in (prep.rec.extra or {}).items()}
    excluded = signals.disguised_readings(
        extra, [d.ts[idx] for d in prep.datas], [prep.valid[idx, i] for i in range(len(forwards))]
    )
    for e in excluded:
        del extra[e["column"]]
    explainer = signals.Explainer(blk, prep.n_blocks, extra)
    for i, (fw, th_i) in enumerate(zip(forwards, thetas, strict=True)):
        r = fw.data.ts - fw.predict(th_i)
        fw.clear_cache()
        r[~prep.valid[:, i]] = 0.0
        per[i] = white_noise(r[prep.valid[:, i]])
        emap.add(i + 1, r, located.regime[:, i])
        use = prep.usable[idx, i]
        d = fw.data  # thinned: its x and a from the thinned series (not the whole's)
        length = None if d.length is None else d.length[idx]
        thin = CableData(
            d.t[idx],
            d.v[idx],
            d.tp[idx],
            d.ts[idx],
            d.t0_at(idx),
            x0=d.x0,
            length=length,
            session=None if d.session is None else d.session[idx],
        )
        explainer.add(thin, r[idx], (blk % 2 == 0) & use, (blk % 2 == 1) & use)
        del thin, r
        d.release()
        trim_heap()
    noise = float(math.sqrt(np.mean(per**2))) if per.size else 0.0
    found = explainer.result()
    st = signals.significant(found, th.fdr)
    if st is None:
        return noise, emap, None, None, excluded
    field_ = {
        "signal": st.signal,
        "share": st.share,
        "reading": signals.reading(st),
        "statistic": _num(st.z),
        "q": _num(st.q),
        "plot": "unexplained.png",
        "curve": {
            "x": [float(x) for x in st.centre],
            "y": [float(y) for y in st.mean],
            "stderr": [float(s) for s in st.se],
        },
        "ranking": [{"signal": f.signal, "share": f.share, "q": _num(f.q)} for f in found[:6]],
    }
    return noise, emap, field_, st, excluded


def _predict(forwards: list[Forward], thetas: list[dict]):
    """Cable ``i``'s final-model prediction (N,), chain cache freed."""

    def one(i: int) -> np.ndarray:
        p = forwards[i].predict(thetas[i])
        forwards[i].clear_cache()
        return p

    return one


def least_squares(prep, forwards, thetas, test, vfw, vvalid) -> dict:
    """``baseline.least_squares``: the engineer's fits (:mod:`.lsq`) on the diagnosis'
    training blocks (its fitted samples: past the warm-up, not clipped), scored on its
    held-out blocks and the validation recording beside the final model."""
    train = (prep.blocks % 2 == 0)[:, None] & prep.usable
    validation = None
    if vfw is not None:
        validation = ([fw.data for fw in vfw], vvalid, _predict(vfw, thetas))
    return lsq.block(
        [fw.data for fw in forwards], train, test, _predict(forwards, thetas), validation
    )


def build_report(prep, located, fitted: list[Tested], th: Thresholds) -> Diagnosis:
    """The report dict and the arrays behind it (module docstring). Memory: besides the
    recording, (N, m) bool masks and int8 regimes; predictions and residuals exist one cable
    at a time (:meth:`Diagnosis.predictions` for the plots)."""
    rec = prep.rec
    outcomes = [u.outcome for u in fitted]
    forwards = [Forward(d, prep.nom) for d in prep.datas]
    valid = prep.valid
    test = (prep.blocks % 2 == 1)[:, None] & valid
    vfw, vvalid = prep.validation or (None, None)
    order = _order(forwards, outcomes, valid)
    n_test = int(np.mean(test.sum(axis=0))) if test.size else 0

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
        ev = evidence(effect, outcomes, located.regime, before[1], after[1])
        findings.append(_finding(effect, fitted, pairs, ev, n_test))
        before = after
    for f in findings:  # the cables' pooled evidence and shrunk parameters (:mod:`.pooling`)
        block = pooling.report_field(f, getattr(prep, "pooled", {}).get(f["effect"]))
        if block is not None:
            f["pooling"] = block
    thetas = _subset(outcomes, order)
    noise, final_loc, unexplained, structure, excluded = final_residual(
        prep, forwards, thetas, located, th
    )
    final = {
        "rmse_n": before[0],
        "holdout_rmse_n": before[1],
        "noise_n": noise,
        "unexplained_n": math.sqrt(max(before[1] ** 2 - noise**2, 0.0)),
    }
    if vfw is not None:
        final["validation_rmse_before_n"] = _rmses(vfw, [{} for _ in vfw], [vvalid])[0]
        final["validation_rmse_after_n"] = float(before[2] or 0.0)
    baseline = {**located.baseline, **located.fields}
    baseline["least_squares"] = least_squares(prep, forwards, thetas, test, vfw, vvalid)
    report = {
        "reference": "platform_tension",
        "cables": rec.cables,
        "samples": rec.samples,
        "skipped_rows": rec.skipped_rows,
        **({} if prep.sessions is None else {"recordings": prep.sessions.report()}),
        "baseline": baseline,
        **final_loc.report_fields(final_loc.regions()),
        "findings": findings,
        "final": final,
        "clipped": prep.clipped,
        "significance": {
            "fdr": th.fdr,
            "tests": sum(len(o.tests) for o in outcomes),
            "test": "held-out block z, Student t (blocks - 1), Benjamini-Hochberg",
        },
    }
    if unexplained is not None:
        report["unexplained"] = unexplained
    if excluded:
        report["unexplained_excluded"] = excluded
    return Diagnosis(
        report,
        rec.t,
        rec.tension_sensor,
        located.regime,
        final_loc.regions(),
        outcomes,
        order,
        forwards,
        located.regions,
        structure,
    )
