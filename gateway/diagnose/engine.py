"""The diagnosis, one way through: prepare -> locate -> select -> fit -> report.

:func:`diagnose` runs the stages of a :class:`Reference`, each taking the previous stage's
output: the platform-tension reference (:class:`gateway.diagnose.reference.
PlatformReference`, one unit of selection per cable) or the wrench balance
(:class:`gateway.diagnose.wrench_reference.WrenchReference`, one unit: every cable at once).
For the platform tensions:

1. **prepare** (the reference's ``prepare``): finite rows, per-cable series, time blocks,
   warm-up, clipped readings, candidates, a subset of a long recording;
2. **locate**: where the nominal model's residual lives (regimes, regions);
3. **select** (:class:`gateway.diagnose.selection.Selector` over the reference's units);
4. **fit**: the selected effects refitted on every training sample, kept only by
   significance over every candidate x unit tried (:mod:`gateway.diagnose.significance`),
   then scored on the validation recording (which never decides what is kept);
5. **report**: findings with their tests, standard errors and alternatives, the final
   residual (where it lives, and what it depends on beyond the catalogue).

The file-level flow (read relative to the model, choose the reference, statics, one or
several recordings): :func:`gateway.diagnose.fromfiles.diagnose_file`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.core.heap import return_large_frees, trim_heap
from gateway.diagnose.forward import CableData, Forward
from gateway.diagnose.prepare import Sensitivity, nominal_from
from gateway.diagnose.reference import PlatformReference
from gateway.diagnose.report import Diagnosis
from gateway.diagnose.selection import Thresholds
from gateway.diagnose.sessions import Sessions
from gateway.model.effects.forms import lowpass
from gateway.recordings.reader import Recording

Progress = Callable[[str], None]


class Reference(Protocol):
    """What a reference gives the pipeline: its five stages (module docstring). Each
    returns what the next takes; what they hold is the reference's own."""

    name: str

    def prepare(self, rec: Recording, friction: FrictionConfig, validation: Any, say) -> Any:
        """The recording ready for the selection (``validation``: a second recording of
        the same machine in the reference's form, scored but never fitted, or None)."""
        ...

    def locate(self, prepared: Any) -> Any:
        """Where the nominal model's residual lives."""
        ...

    def select(self, prepared: Any, th: Thresholds, say) -> Any:
        """The selector over the reference's units."""
        ...

    def fit(self, prepared: Any, selected: Any, th: Thresholds, say) -> Any:
        """The kept effects: significance over every candidate x unit, refitted."""
        ...

    def report(self, prepared: Any, located: Any, fitted: Any, th: Thresholds) -> Diagnosis:
        """The diagnosis and its report."""
        ...


def diagnose(
    rec: Recording,
    friction: FrictionConfig,
    reference: Reference | None = None,
    tp=None,
    dtp_dm: Sensitivity = None,
    validation: Any = None,
    thresholds: Thresholds | None = None,
    progress: Progress | None = None,
    sessions: Sessions | None = None,
) -> Diagnosis:
    """Diagnose ``rec`` against the nominal ``friction`` model with ``reference``'s stages
    (module docstring); ``validation``: a second recording of the same machine in the
    reference's form, never fitted.

    Without a reference, the platform-tension reference of ``tp`` (N, m: platform tensions,
    default the recording's), ``dtp_dm`` (platform tension per kg of platform mass: enables
    a platform mass effect) and ``sessions`` (``rec`` is several recordings of one machine
    joined, :func:`.sessions.join`); ``validation`` then is (recording, its platform
    tensions, its dtp_dm).
    """
    if reference is None:
        reference = PlatformReference(tp, dtp_dm, sessions)
    elif tp is not None or dtp_dm is not None or sessions is not None:
        raise TypeError("diagnose: tp, dtp_dm and sessions are the platform reference's")
    say = progress or (lambda _msg: None)
    th = thresholds or Thresholds()
    return_large_frees()  # many (N,) temporaries: freed ones must not stay resident
    prepared = reference.prepare(rec, friction, validation, say)
    located = reference.locate(prepared)
    selected = reference.select(prepared, th, say)
    fitted = reference.fit(prepared, selected, th, say)
    del selected  # the fit's input (a reference may replace it: memory)
    return reference.report(prepared, located, fitted, th)


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
    geometry (:mod:`gateway.diagnose.wrench_reference`; no tension distribution is
    assumed)."""
    return "platform_tension" if rec.tension_platform is not None else "wrench"
