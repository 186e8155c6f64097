"""Is a fitted model better on data it was not fitted on? And if not, how much more motion
would the recording need? (``diagnose --write-model`` and ``calibrate`` ask before they
write a model; from the report's own fields, nothing is refitted.)

The score on unseen data, best first: the ``--validate`` recording (``final``'s
``validation_rmse_before_n`` / ``validation_rmse_after_n``: never fitted), else the
held-out time blocks of the recording itself (the first finding's
``holdout_rmse_before_n``, i.e. the nominal model, against ``final.holdout_rmse_n``). A
model whose findings do not lower that error is refused: on too little motion an effect's
parameters fit the noise (``calibrate --seconds 1`` on a plant with nothing hidden wrote
``inertia m_eff_kg 27.45`` and was worse after than before).

How much more motion: :func:`motion` measures what the recording had (seconds, velocity
reversals per cable, the speed range); the guide is what ``calibrate`` needs for every
effect of its examples (README table: 30 s of the examples' random 6-DOF motion), scaled
by the recording's own rate of reversals. A rule of thumb from those runs, not a bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

REFERENCE_S = 30.0  # calibrate's examples: every catalogue effect found, after <= 1.05x floor


@dataclass(frozen=True)
class Motion:
    seconds: float
    reversals: int  # velocity sign changes per cable (median over the cables)
    speed_min_m_s: float  # |setpoint velocity| over all cables and samples
    speed_max_m_s: float

    def text(self) -> str:
        return (
            f"{self.seconds:.1f} s, {self.reversals} velocity reversals per cable, speeds "
            f"{self.speed_min_m_s:.3f}-{self.speed_max_m_s:.3f} m/s"
        )


def motion(t: np.ndarray, velocity: np.ndarray) -> Motion:
    """What a recording's motion offers the fit: ``t`` (N,), ``velocity`` (N, m) m/s."""
    v = np.asarray(velocity, dtype=float)
    moving = np.where(np.abs(v) > 1e-4, np.sign(v), 0.0)
    reversals = [int(np.sum(np.diff(c[c != 0]) != 0)) for c in moving.T]
    speed = np.abs(v[np.isfinite(v)])
    return Motion(
        seconds=float(t[-1] - t[0]) if t.size > 1 else 0.0,
        reversals=int(np.median(reversals)) if reversals else 0,
        speed_min_m_s=float(speed.min()) if speed.size else 0.0,
        speed_max_m_s=float(speed.max()) if speed.size else 0.0,
    )


def unseen_score(
    report: dict[str, Any], validation: str = "the --validate recording"
) -> tuple[str, float, float] | None:
    """(what, RMSE before, RMSE after) on data the findings were not fitted on; None
    without findings (nothing fitted). ``validation`` names the validation recording."""
    findings = report.get("findings") or []
    if not findings:
        return None
    final = report["final"]
    if "validation_rmse_after_n" in final:
        return (
            validation,
            float(final["validation_rmse_before_n"]),
            float(final["validation_rmse_after_n"]),
        )
    return (
        "the held-out time blocks",
        float(findings[0]["holdout_rmse_before_n"]),
        float(final["holdout_rmse_n"]),
    )


def refusal(
    report: dict[str, Any], moved: Motion, validation: str = "the --validate recording"
) -> str | None:
    """Why the fitted model must not be written (one line), or None when it may."""
    score = unseen_score(report, validation)
    if score is None:
        return None
    what, before, after = score
    if math.isfinite(after) and after < before:
        return None
    effects = ", ".join(f["effect"] for f in report["findings"])
    factor = REFERENCE_S / max(moved.seconds, 1e-9)
    need = ""
    if factor > 1:
        reversals = moved.reversals / max(moved.seconds, 1e-9) * REFERENCE_S
        rate = (
            f"about {reversals:.0f} reversals per cable at this motion's rate"
            if reversals >= 1
            else "with reversals of every cable"
        )
        need = (
            f"; record about {REFERENCE_S:.0f} s ({factor:.0f}x more: {rate}), over "
            "the speed range the machine uses"
        )
    else:
        need = (
            "; the motion is long enough by the calibrate examples' measure: widen the "
            "speed range or add reversals"
        )
    return (
        f"not written: the fitted model ({effects}) does not lower the error on data it "
        f"was not fitted on ({what}: {before:.3f} N before, {after:.3f} N after); the "
        f"recording has {moved.text()}{need}"
    )
