"""The diagnosis, one way through: prepare -> locate -> select -> fit -> report.

:func:`diagnose` is the whole pipeline for the platform-tension reference (one unit of
selection per cable); :func:`gateway.diagnose.wrench_select.diagnose_wrench` is the same
pipeline with the wrench balance as the reference (one unit: every cable at once). Each
stage takes the previous stage's output:

1. **prepare** (the reference's ``prepare``): finite rows, per-cable series, time blocks,
   warm-up, clipped readings, candidates, a subset of a long recording;
2. **locate**: where the nominal model's residual lives (regimes, regions);
3. **select** (:class:`gateway.diagnose.selection.Selector` over the reference's units);
4. **fit**: the selected effects refitted on every training sample, kept only by
   significance over every candidate x unit tried (:mod:`gateway.diagnose.significance`),
   then scored on the validation recording (which never decides what is kept);
5. **report**: findings with their tests, standard errors and alternatives, the final
   residual (where it lives, and what it depends on beyond the catalogue).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.core.heap import return_large_frees, trim_heap
from gateway.diagnose.forward import CableData, Forward
from gateway.diagnose.prepare import (  # noqa: F401 - the stages' helpers, re-exported
    Sensitivity,
    cable_candidates,
    cable_data,
    candidates_for,
    clipped_mask,
    deadband,
    finite_rows,
    nominal_from,
    selection_subset,
    time_blocks,
    velocity_noise,
    warmup_mask,
)
from gateway.diagnose.reference import PlatformReference, fit_units, select_units
from gateway.diagnose.report import Diagnosis, build_report
from gateway.diagnose.selection import Thresholds
from gateway.diagnose.sessions import Sessions
from gateway.model.effects.forms import lowpass
from gateway.recordings.reader import Recording

Progress = Callable[[str], None]


def diagnose(
    rec: Recording,
    friction: FrictionConfig,
    tp=None,
    dtp_dm: Sensitivity = None,
    validation: tuple[Recording, object, Sensitivity] | None = None,
    thresholds: Thresholds | None = None,
    progress: Progress | None = None,
    sessions: Sessions | None = None,
) -> Diagnosis:
    """Diagnose ``rec`` against the nominal ``friction`` model with the platform-tension
    reference (module docstring).

    ``tp`` (N, m): platform tensions (default: the recording's); ``dtp_dm``: platform tension
    per kg of platform mass (enables a platform mass effect); ``validation``: a second
    recording of the same machine, its platform tensions and dtp_dm (never fitted);
    ``sessions``: ``rec`` is several recordings of one machine joined
    (:func:`.sessions.join`), diagnosed for one set of findings.
    """
    say = progress or (lambda _msg: None)
    th = thresholds or Thresholds()
    return_large_frees()  # many (N,) temporaries: freed ones must not stay resident
    ref = PlatformReference(tp, dtp_dm, sessions)
    prepared = ref.prepare(rec, friction, validation, say)
    located = ref.locate(prepared)  # gives back LLVM's pages and the heap after each cable
    selected = select_units(ref, prepared, th, say)
    fitted = fit_units(ref, prepared, selected, th, say)
    return build_report(prepared, located, fitted, th)


def load_kernels(friction: FrictionConfig) -> None:
    """Load the chain simulation's and the filter's compiled kernels (numba's cache) on
    three samples, then give back the LLVM pages that loading touched (:func:`trim_heap`).
    Called before a recording is read: LLVM's one-off work (numba's runtime module is
    compiled in the process, ~45 MiB of LLVM code touched) then happens while the process
    is small, not on top of the recording and the first cable. Results are unchanged (the
    kernels keep no state)."""
    t = np.arange(3) * 1e-3
    data = CableData(t, np.array([0.0, 0.1, 0.0]), np.full(3, 100.0), np.full(3, 100.0), 0.0)
    Forward(data, nominal_from(friction)).predict({})
    lowpass(t, data.ts, 0.01)  # the filter of sensor_creep, lowpass, maxwell_slip
    trim_heap()


def reference_mode(rec: Recording) -> str:
    """``platform_tension`` when the recording has ``tension_platform_i`` columns, else
    ``wrench``: the platform's wrench balance from pose, mass and a model file with a
    geometry (:mod:`gateway.diagnose.wrench`; no tension distribution is assumed)."""
    return "platform_tension" if rec.tension_platform is not None else "wrench"
