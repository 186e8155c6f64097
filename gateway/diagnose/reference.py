"""The platform-tension reference as the selector's strategy: one :class:`CableUnit` per
cable, the cable's sensor reading against the nominal chain run from its platform tension
(:class:`gateway.diagnose.forward.Forward`), fitted by :mod:`gateway.diagnose.fit`.

(The other reference, the platform's wrench balance, is :class:`gateway.diagnose.
wrench_reference.WrenchReference`, with one unit: every cable at once.)
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gateway.core.heap import trim_heap
from gateway.diagnose import locate, sessions
from gateway.diagnose.fit import best_start, joint_fit, linear_refit, spec_for
from gateway.diagnose.forward import CableData, Forward, Nominal
from gateway.diagnose.pooling import Pooled, extend, final_pooled
from gateway.diagnose.prepare import (
    SELECTION_BUDGET,
    Sensitivity,
    cable_candidates,
    cable_data,
    candidates_for,
    clipped_mask,
    finite_rows,
    nominal_from,
    selection_subset,
    validation_forwards,
    warmup_mask,
)
from gateway.diagnose.report import Diagnosis, build_report
from gateway.diagnose.selection import Model, Selector, Thresholds
from gateway.diagnose.sessions import Sessions
from gateway.diagnose.sessions import time_blocks as session_blocks
from gateway.diagnose.significance import Tested, decide, harmonize, retire, score
from gateway.diagnose.stats import holdout_z, p_value
from gateway.diagnose.timebase import gap_segments, time_blocks
from gateway.errors import RecordingError
from gateway.model import effects as fx
from gateway.recordings.reader import Recording


class CableUnit:
    """One cable for the selector (:class:`gateway.diagnose.selection.Unit`): residual =
    measured reading - the model's prediction, per sample."""

    def __init__(
        self,
        fw: Forward,
        blocks: np.ndarray,
        n_blocks: int,
        candidates: list[str],
        usable: np.ndarray | None = None,
        stride: int = 1,
        segments: np.ndarray | None = None,
    ) -> None:
        """``usable`` (N,) bool: samples that may be fitted and scored (None: all; False:
        warm-up and clipped readings); ``segments`` (N,): the piece of the recording (a
        trial between gaps) of each sample, for the refits across trials
        (:func:`.stats.block_groups`)."""
        self.fw, self.blocks, self.n_blocks = fw, blocks, n_blocks
        self.segments = segments
        use = np.ones(blocks.shape, bool) if usable is None else usable
        self.train = (blocks % 2 == 0) & use
        self.test = (blocks % 2 == 1) & use
        self.candidates = candidates
        self.stride = stride

    def _resid(self, theta: dict[str, np.ndarray]) -> np.ndarray:
        return self.fw.data.ts - self.fw.predict(theta)

    def empty(self) -> Model:
        return Model({}, {}, {}, self._resid({}))

    def evaluate(self, theta: dict[str, np.ndarray], specs: dict[str, Any]) -> Model:
        nan = {e: np.full(v.size, np.nan) for e, v in theta.items()}
        return Model(dict(theta), dict(specs), nan, self._resid(theta))

    def screen(self, model: Model, effect: str) -> Model:
        """The best of the effect's starting points (grids, periodogram) with its linear
        parameters solved by one Gauss-Newton step, then one joint step on the linear
        parameters of the kept effects and the new one (:func:`fit.linear_refit`), which
        keeps a step cheap: only what is taken is refined by least squares."""
        fw = self.fw
        spec = spec_for(effect, fw.data, fw.nom, model.resid, self.train)
        start = best_start(fw, model.kept, effect, spec, self.train)
        theta = {**model.kept, effect: start}
        specs = {**model.specs, effect: spec}
        if model.kept:
            theta = linear_refit(fw, theta, specs, self.train)
        stderr = {**model.stderr, effect: np.full(start.size, np.nan)}
        return Model({**model.kept, effect: theta[effect]}, specs, stderr, self._resid(theta))

    def fit(self, theta: dict[str, np.ndarray], specs: dict[str, Any], nfev: int = 60) -> Model:
        """Joint refit of ``theta`` (linear parts first re-solved together)."""
        theta = linear_refit(self.fw, theta, specs, self.train)
        f = joint_fit(self.fw, theta, specs, self.train, max_nfev=nfev, stride=self.stride)
        return Model(f.theta, dict(specs), f.stderr, self.fw.data.ts - f.pred)

    def refit_on(self, model: Model, mask: np.ndarray, nfev: int = 20) -> dict[str, np.ndarray]:
        """The kept effects refitted on the samples ``mask`` only (from the model's values):
        a refit for the standard errors across time blocks."""
        stride = max(1, int(mask.sum()) // 150_000)
        f = joint_fit(self.fw, model.kept, model.specs, mask, max_nfev=nfev, stride=stride)
        return f.theta

    def recordings_left_out(
        self, model: Model, reduced: Mapping[str, Model] | None = None
    ) -> dict[str, dict[str, float]]:
        """Several recordings joined (:mod:`.sessions`): per kept effect, the test of the
        model with it against the model without it on recordings left out in turn (with
        ``reduced``: only its effects, each against the model given there, e.g. a simpler
        nested effect in its place: :func:`.pooling.richer`). Each
        fold refits both (from the model's values) on the training samples of the other
        recordings, gives a per-recording effect (an offset) on the left-out recording the
        mean of the others' values (that session's zero is not known to the fold), and
        scores every usable sample of the left-out recording, block by block; the blocks
        of all folds make one held-out z (``z``, ``p``: :func:`.stats.holdout_z`,
        :func:`.stats.p_value`). Empty for one recording."""
        fw = self.fw
        session = fw.data.session
        if session is None or not model.kept:
            return {}
        ts = fw.data.ts
        usable = self.train | self.test
        against = (
            {e: model.without(e) for e in model.kept}
            if reduced is None
            else {e: (m.kept, m.specs) for e, m in reduced.items()}
        )
        parts: dict[str, list[list[np.ndarray]]] = {e: [[], [], []] for e in against}
        for r in range(int(session.max()) + 1):
            fit, scored = self.train & (session != r), usable & (session == r)
            if not fit.any() or not scored.any():
                continue
            stride = max(1, int(fit.sum()) // SELECTION_BUDGET)
            blk = self.blocks[scored]
            present = np.unique(blk)

            def per_block(w: np.ndarray, blk=blk, present=present) -> np.ndarray:
                return np.bincount(blk, weights=w, minlength=self.n_blocks)[present]

            def refit(theta, specs, r=r, fit=fit, stride=stride) -> dict[str, np.ndarray]:
                if not theta:
                    return {}
                f = joint_fit(fw, theta, specs, fit, max_nfev=20, stride=stride)
                return {e: _unknown_session(e, v, r) for e, v in f.theta.items()}

            r_full = (ts - fw.predict(refit(model.kept, model.specs)))[scored]
            sse_full = per_block(r_full**2)
            for e, (theta, specs) in against.items():
                r_red = (ts - fw.predict(refit(theta, specs)))[scored]
                row = parts[e]
                row[0].append(per_block(r_red**2))
                row[1].append(sse_full)
                row[2].append(per_block(r_full * (r_red - r_full)))
        out = {}
        for e, (red, full, cross) in parts.items():
            if not red:
                continue
            z = holdout_z(np.concatenate(red), np.concatenate(full), np.concatenate(cross))
            out[e] = {"z": float(z), "p": p_value(z, int(sum(a.size for a in red)))}
        return out

    def contribution(self, theta: dict[str, np.ndarray], effect: str) -> np.ndarray:
        """What ``effect`` adds to the prediction of ``theta`` on the training samples."""
        rest = {k: v for k, v in theta.items() if k != effect}
        fw = self.fw
        return (fw.predict(theta) - fw.predict(rest))[self.train]

    def release(self) -> None:
        self.fw.clear_cache()

    def significance(self, model: Model, effect: str) -> float:
        return fx.REGISTRY[effect].significance(
            model.kept[effect], model.stderr[effect], model.specs[effect].neutral
        )


def _unknown_session(effect: str, theta: np.ndarray, r: int) -> np.ndarray:
    """``theta`` with recording ``r``'s part of a per-recording effect set to the mean of
    the other recordings' (a fold that left ``r`` out cannot know it)."""
    rows = sessions.rows(effect, theta)
    if rows.shape[0] == 1:
        return theta
    rows = rows.copy()
    rows[r] = np.delete(rows, r, axis=0).mean(axis=0)
    return rows.ravel()


# ---- the platform-tension reference: stages -------------------------------------------------
@dataclass
class PlatformPrepared:
    """A recording ready for the per-cable selection: the nominal chain, one
    :class:`CableData` per cable, blocks, the samples each cable may fit and score
    (``usable``: past its warm-up, not clipped), its candidates, a subset for long
    recordings, the validation recording's forwards."""

    rec: Recording
    nom: Nominal
    datas: list[CableData]
    blocks: np.ndarray
    n_blocks: int
    valid: np.ndarray
    usable: np.ndarray
    candidates: list[list[str]]
    subset: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    validation: tuple[list[Forward], np.ndarray] | None
    clipped: dict
    segments: np.ndarray | None = None
    """(N,) the piece of the recording (trial) of each sample (:func:`.timebase.gap_segments`)."""
    pooled: dict[str, Pooled] = field(default_factory=dict)
    """Per effect, its test pooled over the cables (:mod:`.pooling`), once fitted."""
    sessions: Sessions | None = None
    """The recordings of a joined series (:mod:`.sessions`); None: one recording."""


class PlatformReference:
    """The strategy of the platform-tension reference (``tension_platform_i`` columns, or
    platform tensions from pose and mass): one unit per cable."""

    name = "platform_tension"

    def __init__(
        self, tp: np.ndarray | None = None, dtp_dm: Sensitivity = None, sessions=None
    ) -> None:
        self.tp, self.dtp_dm, self.sessions = tp, dtp_dm, sessions

    def prepare(self, rec: Recording, friction, validation, say) -> PlatformPrepared:
        tp = rec.tension_platform if self.tp is None else self.tp
        if tp is None:
            raise RecordingError(f"{rec.source}: no platform tensions")
        nom = nominal_from(friction)
        rec, tp, dtp_dm = finite_rows(rec, tp, self.dtp_dm)
        sessions = self.sessions
        if sessions is not None and sessions.index.size != rec.samples:
            raise RecordingError(f"{rec.source}: rows without values in a joined series")
        datas = cable_data(rec, tp, dtp_dm, sessions=sessions)
        blocks, nb = session_blocks(rec.t, sessions)
        valid = np.empty((rec.samples, rec.cables), bool)
        usable = np.empty((rec.samples, rec.cables), bool)
        levels, cands = [], []
        all_cands = candidates_for(dtp_dm is not None)
        for i, d in enumerate(datas):
            mask, at = clipped_mask(d.ts)
            valid[:, i] = ~mask
            levels.append(at)
            if at:
                say(f"cable {i + 1}: {int(mask.sum())} clipped readings excluded")
            usable[:, i] = warmup_mask(d, nom) & valid[:, i]
            cands.append(cable_candidates(all_cands, d, nom))
            d.release()
        clipped = {
            "per_cable": [int((~valid[:, i]).sum()) for i in range(rec.cables)],
            "levels_n": levels,
        }
        return PlatformPrepared(
            rec,
            nom,
            datas,
            blocks,
            nb,
            valid,
            usable,
            cands,
            selection_subset(rec.t, blocks),
            validation_forwards(
                validation, nom, rec.cables, None if rec.length is None else rec.length[0]
            ),
            clipped,
            gap_segments(rec.t),
            sessions=sessions if sessions is not None and sessions.count > 1 else None,
        )

    def units(self, prep: PlatformPrepared, say) -> Iterator[tuple[int, CableUnit]]:
        """One selection unit per cable (on the subset of a long recording); the cable's
        cached simulations and computed series are freed when the caller moves on."""
        for i, d in enumerate(prep.datas):
            where = "" if prep.subset is None else f" on {prep.subset[0].size} of {d.t.size}"
            say(
                f"cable {i + 1}/{len(prep.datas)}: {len(prep.candidates[i])} candidate "
                f"effects{where}"
            )
            unit = self.unit(prep, i)
            yield i, unit
            unit.release()
            d.release()
            trim_heap()  # the cable's many freed temporaries leave the process

    def unit(self, prep: PlatformPrepared, i: int) -> CableUnit:
        """Cable ``i``'s selection unit: every sample, or the subset of a long recording
        (whose pieces join across gaps: the friction state warms up after each join as
        after the start, by travel)."""
        d, cands = prep.datas[i], prep.candidates[i]
        if prep.subset is None:
            return CableUnit(
                Forward(d, prep.nom),
                prep.blocks,
                prep.n_blocks,
                cands,
                prep.usable[:, i],
                segments=prep.segments,
            )
        idx, sub_blocks, use = prep.subset
        sub = d.subset(idx)
        d.release()
        use = use & prep.usable[idx, i] & warmup_mask(sub, prep.nom)
        segs = None if prep.segments is None else prep.segments[idx]
        return CableUnit(
            Forward(sub, prep.nom),
            sub_blocks,
            int(sub_blocks.max()) + 1,
            cands,
            use,
            segments=segs,
        )

    def full_unit(self, prep: PlatformPrepared, i: int) -> CableUnit:
        """Cable ``i`` on every sample (thinned scoring in the fit of a long recording)."""
        fw = Forward(prep.datas[i], prep.nom)
        train = (prep.blocks % 2 == 0) & prep.usable[:, i]
        stride = max(1, int(train.sum()) // SELECTION_BUDGET)
        return CableUnit(
            fw,
            prep.blocks,
            prep.n_blocks,
            prep.candidates[i],
            prep.usable[:, i],
            stride,
            segments=prep.segments,
        )

    def locate(self, prep: PlatformPrepared) -> Located:
        """Regimes and where the nominal model's residual lives (cable by cable)."""
        return locate_residual(prep, [{} for _ in prep.datas])

    def release(self, unit: CableUnit) -> None:
        unit.fw.clear_cache()

    def select(self, prep: PlatformPrepared, th: Thresholds, say) -> list[Tested]:
        """:func:`select_units`."""
        return select_units(self, prep, th, say)

    def fit(
        self, prep: PlatformPrepared, tested: list[Tested], th: Thresholds, say
    ) -> list[Tested]:
        """:func:`fit_units`."""
        return fit_units(self, prep, tested, th, say)

    def report(
        self, prep: PlatformPrepared, located: Located, fitted: list[Tested], th: Thresholds
    ) -> Diagnosis:
        """:func:`gateway.diagnose.report.build_report`."""
        return build_report(prep, located, fitted, th)


@dataclass
class Located:
    """Regimes (N, m) and where a model's residual lives: the regions of concentrated
    energy, their share, and the regime shares (:class:`locate.EnergyMap`)."""

    regime: np.ndarray
    regions: list[locate.Region]
    fields: dict
    baseline: dict


def locate_residual(prep: PlatformPrepared, thetas: list[dict[str, np.ndarray]]) -> Located:
    """Where the residual of the model ``thetas`` (per cable) lives, cable by cable (no
    (N, m) residual is held); with the RMSE on every valid and every held-out sample."""
    n, m = prep.rec.samples, prep.rec.cables
    regime = np.empty((n, m), np.int8)
    emap = locate.EnergyMap(prep.rec.t)
    sse, count = np.zeros(2), np.zeros(2)
    per_cable = []
    test = (prep.blocks % 2 == 1)[:, None] & prep.valid
    for i, d in enumerate(prep.datas):
        regime[:, i] = locate.regimes(d.v, d.a)
        fw = Forward(d, prep.nom)
        r = d.ts - fw.predict(thetas[i])
        fw.clear_cache()
        r[~prep.valid[:, i]] = 0.0
        for j, mask in enumerate((prep.valid[:, i], test[:, i])):
            rr = r[mask]
            sse[j] += float(rr @ rr)
            count[j] += rr.size
            if j == 0:
                per_cable.append(float(np.sqrt(np.mean(rr**2))) if rr.size else 0.0)
        emap.add(i + 1, r, regime[:, i])
        del r
        trim_heap()  # and LLVM's pages that loading the first kernel touched
    rms, hold = (float(np.sqrt(s / c)) if c else 0.0 for s, c in zip(sse, count, strict=True))
    regions = emap.regions()
    baseline = {"rmse_n": rms, "per_cable_rmse_n": per_cable, "holdout_rmse_n": hold}
    return Located(regime, regions, emap.report_fields(regions), baseline)


# ---- select and fit, unit by unit ----------------------------------------------------------
def select_units(
    ref: PlatformReference, prep: PlatformPrepared, th: Thresholds, say
) -> list[Tested]:
    """Stage 3, with the per-unit half of stage 4: the selector over each cable (on the
    subset of a long recording), then scored
    (every candidate tested, block refits) while its data is at hand; then only its
    numbers are kept (memory: one cable's series at a time)."""
    out = []
    for i, unit in ref.units(prep, say):
        sel = Selector(unit, th)
        outcome = sel.run()
        say(f"cable {i + 1}/{len(prep.datas)}: selected {', '.join(outcome.kept) or 'nothing'}")
        model = sel.final
        u = Tested(sel, model, outcome, index=i)
        score(u)
        retire(u)
        out.append(u)
    return out


def fit_units(
    ref: PlatformReference, prep: PlatformPrepared, tested: list[Tested], th: Thresholds, say
) -> list[Tested]:
    """Stage 4: the significance stage over every cable and candidate (q-values over all
    of them; a cable whose finding fails is rebuilt, refitted and scored again), then the
    survivors refitted on all training samples. A long recording was selected on a subset
    of its training blocks (each split in halves that train and test): the significance
    stage tests there too, on samples the fits never saw, and the recording's own
    held-out blocks stay unseen for the report's scores. Before it, an effect whose
    evidence pooled over the cables is significant is fitted on the cables whose data do
    not refuse it, and only its own evidence against it drops it from a cable
    (:mod:`.pooling`)."""

    def rebuild(u: Tested) -> tuple[Selector, Model]:
        unit = ref.unit(prep, u.index)
        return Selector(unit, th), unit.evaluate(u.model.kept, u.model.specs)

    pooled = extend(tested, th, rebuild, lambda msg: say(f"pooled: {msg}"))
    common = frozenset(e for e, r in pooled.items() if r.common)
    decide(tested, th, lambda msg: say(f"significance: {msg}"), rebuild, common)
    harmonize(tested)
    prep.pooled = final_pooled(tested, th, pooled)
    if prep.subset is not None:
        for i, u in enumerate(tested):
            o = u.outcome
            if o.kept:
                unit = ref.full_unit(prep, i)
                full = unit.fit(o.theta, o.specs, nfev=20)
                o.theta, o.stderr = full.kept, full.stderr
                unit.release()
                trim_heap()
    if prep.validation is not None:
        vfws, vvalid = prep.validation
        for i, u in enumerate(tested):
            for e, t in validation_scores(u.outcome.theta, vfws[i], vvalid[:, i]).items():
                u.outcome.tests.setdefault(e, {}).update(t)
    for i, u in enumerate(tested):
        say(f"cable {i + 1}/{len(tested)}: kept {', '.join(u.outcome.kept) or 'nothing'}")
    return tested


def validation_scores(
    kept: dict[str, np.ndarray], vfw: Forward, ok: np.ndarray
) -> dict[str, dict[str, float]]:
    """How each kept effect scores on the validation recording (never fitted, and never
    deciding: the findings are the same whichever recording is handed in). Per effect,
    with the parameters fitted here: ``validation_z``, how many standard errors the
    validation SSE of the model with it lies below the model without it
    (:func:`.stats.holdout_z` over the validation's time blocks), and ``validation_gain``,
    that decrease relative to the SSE without it. ``vfw``: the same cable of the
    validation recording, ``ok`` its valid samples. The guard against an effect that does
    not generalise is the fitted recording's own held-out blocks (the selection's strict
    test and the significance stage: q over every candidate x cable, presence across
    refits with whole trials left out)."""
    out: dict[str, dict[str, float]] = {}
    if not kept:
        return out
    vblocks, nvb = time_blocks(vfw.data.t)
    ts = vfw.data.ts
    full = vfw.predict(kept)
    r_full = np.where(ok, ts - full, 0.0)
    sse_full = np.bincount(vblocks, weights=r_full**2, minlength=nvb)
    for effect in kept:
        rest = {k: v for k, v in kept.items() if k != effect}
        red = vfw.predict(rest)
        r_red = np.where(ok, ts - red, 0.0)
        sse_red = np.bincount(vblocks, weights=r_red**2, minlength=nvb)
        cross = np.bincount(
            vblocks, weights=np.where(ok, r_full * (full - red), 0.0), minlength=nvb
        )
        before = float(sse_red.sum())
        gain = (before - float(sse_full.sum())) / before if before > 0 else 0.0
        z = holdout_z(sse_red, sse_full, cross)
        out[effect] = {"validation_z": float(z), "validation_gain": float(gain)}
    vfw.clear_cache()
    return out
