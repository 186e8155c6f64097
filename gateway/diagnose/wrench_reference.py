"""The wrench reference: the platform's wrench balance (:mod:`.wrench`) as the reference of
the one pipeline (:func:`gateway.diagnose.engine.diagnose`), one unit for every cable at
once (:class:`.wrench_unit.WrenchUnit`).

Where its stages differ from the platform-tension reference's, the difference is here:

1. **prepare**: the balance's series (:func:`wrench.prepare`); on a long recording a
   thinned copy for the selection (:func:`screening_step`);
2. **locate**: with the report (:mod:`.wrench_report`), from the force residuals of the
   nominal and the final model, which the report computes anyway;
3. **select**: the one selector (:class:`gateway.diagnose.selection.Selector`) over the
   unit, the significance stage (:mod:`gateway.diagnose.significance`: BH over every
   candidate, parameters against their spread across time blocks) and the confirmation on
   the nonlinear residual; where an anchor was away from the nominal model, once more with
   the kept effects linearised at their refit (:data:`PASSES`);
4. **fit**: on a thinned selection, the kept effects refitted on every sample (the
   selection's own refit otherwise);
5. **report**: :func:`.wrench_report.build` (and its least-squares block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gateway.core.config import Config, FrictionConfig
from gateway.core.heap import trim_heap
from gateway.diagnose import wrench, wrench_report
from gateway.diagnose.selection import Outcome, Selector, Thresholds
from gateway.diagnose.sessions import Sessions
from gateway.diagnose.significance import Tested, decide
from gateway.diagnose.wrench import WRENCH_EFFECTS, Prepared, prepare
from gateway.diagnose.wrench_unit import WrenchUnit
from gateway.recordings.reader import Recording

PASSES = 2
"""Selections: where the first kept an effect linearised away from the nominal model, a
second with the kept effects linearised at their refit and every other candidate's anchor
chosen on top of it (a candidate anchored on the nominal residual alone may have taken
what a kept effect explains, a linearisation far from where it is then screened)."""
SCREEN_HZ = 40.0
"""The lowest rate the selection runs at on a long recording (:func:`screening_step`);
the kept effects are refitted and every score computed on every sample. The thinned
copy's derived series are the full rate's (:meth:`wrench.WrenchData.thinned`); only the
chain runs at the lower rate. On a 2-min 1 kHz soft-PLC recording (0.5 N sensor noise,
force residual 0.8 N RMS) the nominal model's platform tensions at the fit rows run at
42 Hz differ from those at 1 kHz by 0.011 N RMS (0.06 N at most), the force residual
by 0.018 N RMS; at 250 Hz by 0.003 and 0.005 N."""


def screening_step(rec: Recording) -> int:
    """Every how many samples the wrench reference selects on (1: every sample): the
    largest divisor of the fit rows' stride (:data:`wrench.FIT_BUDGET`) that leaves at
    least :data:`SCREEN_HZ`. The thinned copy holds the same fit rows (the selection fits
    and tests the same samples); only the chain and the derivatives run at the lower rate
    (the chain over a 10-min 1 kHz recording was most of the diagnosis' CPU)."""
    n = rec.samples
    stride = math.ceil(n / wrench.FIT_BUDGET) if n > 0 else 1
    if stride < 2:
        return 1
    dt = float(np.median(np.diff(rec.t)))
    if not dt > 0.0:
        return 1
    fits = [d for d in range(2, stride + 1) if stride % d == 0 and d * dt * SCREEN_HZ <= 1 + 1e-9]
    return max(fits, default=1)


@dataclass
class WrenchPrepared:
    """The recording, the balance's series the selection runs on (``prep``: a thinned copy
    when ``step`` > 1, replaced by every sample's in :meth:`WrenchReference.fit`) and the
    validation recording (scored by the report, never fitted)."""

    rec: Recording
    friction: FrictionConfig
    step: int
    prep: Prepared | None
    validation: Recording | None


@dataclass
class WrenchSelected:
    """The unit, the selector's outcome, the kept effects, their fit and standard errors."""

    unit: WrenchUnit | None
    outcome: Outcome
    kept: list[str]
    theta: dict[str, np.ndarray]
    se: dict[str, np.ndarray]


class WrenchReference:
    """The strategy of the wrench reference (no platform tensions: pose, mass and a model
    file with a geometry). ``sessions`` (``validation_sessions``): the recording (the
    validation recording) is several recordings of one machine joined
    (:func:`.sessions.join_wrench`), diagnosed for one set of findings: time blocks within
    each recording, the pose differentiated within each, the report's ``recordings``."""

    name = "wrench"

    def __init__(
        self,
        cfg: Config | None,
        sessions: Sessions | None = None,
        validation_sessions: Sessions | None = None,
    ) -> None:
        self.cfg, self.sessions, self.validation_sessions = cfg, sessions, validation_sessions

    def prepare(
        self, rec: Recording, friction: FrictionConfig, validation: Recording | None, say
    ) -> WrenchPrepared:
        step = screening_step(rec) if self.sessions is None else 1
        if step > 1:  # the selection on a thinned copy, the kept effects refitted on all
            prep = prepare(rec, self.cfg, friction, step=step)
            trim_heap()
            say(
                f"{rec.source}: wrench reference, selection on every {step}th sample "
                f"({prep.model.data.t.size} samples), sensitivities of "
                f"{len(WRENCH_EFFECTS)} candidate effects"
            )
        else:
            prep = prepare(rec, self.cfg, friction, self.sessions)
            trim_heap()  # the preparation's temporaries and LLVM's pages leave the process
            say(
                f"{rec.source}: wrench reference, {prep.model.data.t.size} samples, "
                f"sensitivities of {len(WRENCH_EFFECTS)} candidate effects"
            )
        return WrenchPrepared(rec, friction, step, prep, validation)

    def locate(self, prepared: WrenchPrepared) -> None:
        """Nothing before the selection: the report locates the nominal and the final force
        residuals (:func:`.wrench_report.build`), which it computes for its scores."""
        return None

    def select(self, prepared: WrenchPrepared, th: Thresholds, say) -> WrenchSelected:
        """Selection, significance and confirmation (:data:`PASSES` times at most)."""
        assert prepared.prep is not None
        at: dict[str, np.ndarray] = {}
        for k in range(PASSES):
            unit = WrenchUnit(prepared.prep, WRENCH_EFFECTS, at)
            selector = Selector(unit, th)
            outcome = selector.run()
            say(f"wrench reference: selected {', '.join(outcome.kept) or 'nothing'}")
            tested = Tested(selector, selector.final, outcome)  # significance, refit
            decide([tested], th, lambda msg: say(f"significance: {msg}"))
            kept, theta, se = unit.confirm(selector, outcome.kept, say)
            say(f"wrench reference: kept {', '.join(kept) or 'nothing'}")
            if at or not any(e in unit.shift for e in kept):
                break  # every kept effect linearised at the nominal model, or already at the fit
            at = theta  # again, every candidate linearised on top of this fit
            say(f"wrench reference: again, linearised at the fit of {', '.join(kept)}")
            if k + 1 < PASSES:  # this pass's designs go before the next's are made (peak memory)
                del unit, selector, tested, outcome
                trim_heap()
        return WrenchSelected(unit, outcome, kept, theta, se)

    def fit(
        self, prepared: WrenchPrepared, selected: WrenchSelected, th: Thresholds, say
    ) -> WrenchSelected:
        """On a thinned selection, the kept effects refitted on every sample: the thinned
        copy and its unit go first (taken out of ``prepared`` and ``selected``, which the
        caller still holds), then every sample's series and a unit of the kept effects
        only, linearised at the selection's fit. The designs go before the report."""
        if prepared.step > 1:
            assert selected.unit is not None
            ident = selected.unit.ident
            selected.unit = prepared.prep = None
            trim_heap()
            prep = prepare(prepared.rec, self.cfg, prepared.friction)
            trim_heap()  # as after the selection's preparation: LLVM's pages go again
            prepared.prep = prep
            kept, theta, se = selected.kept, selected.theta, selected.se
            sel = WrenchUnit(prep, tuple(kept), {e: theta[e] for e in kept})
            kept = [e for e in kept if e in sel.cols]  # none unidentifiable here so far
            theta, se = {e: theta[e] for e in kept}, {e: se[e] for e in kept}
            if kept:
                theta, se = sel.refit(kept)
                say(f"wrench reference: {', '.join(kept)} refitted on every sample")
            sel.ident = {**ident, **sel.ident}
            selected = WrenchSelected(sel, selected.outcome, kept, theta, se)
        assert selected.unit is not None
        selected.unit.drop_designs()  # the report reads the columns and the identifiability
        return selected

    def report(
        self, prepared: WrenchPrepared, located: None, fitted: WrenchSelected, th: Thresholds
    ) -> wrench_report.WrenchDiagnosis:
        assert prepared.prep is not None and fitted.unit is not None
        return wrench_report.build(
            prepared.rec,
            prepared.prep,
            fitted.unit,
            fitted.outcome,
            fitted.theta,
            fitted.se,
            self.cfg,
            prepared.validation,
            self.sessions,
            self.validation_sessions,
        )
