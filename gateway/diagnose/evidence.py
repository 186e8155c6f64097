"""One checkable sentence per finding: what to look for on the plot, and confusions."""

from __future__ import annotations

import numpy as np

from gateway.diagnose.forward import report_stderr, to_report
from gateway.diagnose.select import CableOutcome

LOOK = {
    "coulomb": "the residual flips sign with the direction of motion and scales with the "
    "load (plot residual against sgn(v) T)",
    "presliding": "the residual is concentrated just after each reversal, over a few mm of "
    "travel (plot residual against travel since the last reversal)",
    "viscous": "the residual grows in proportion to the cable speed, opposite to v "
    "(plot residual against v)",
    "stribeck": "the residual is largest at low speed on either side of a reversal and "
    "fades with speed (plot residual against v near zero)",
    "inertia": "the residual follows the cable acceleration without lag (plot residual against a)",
    "delay": "the measurement lags the model by a fixed time, visible at every fast edge "
    "(overlay the two around a reversal)",
    "lowpass": "the measurement rounds off every fast edge of the model exponentially "
    "(overlay the two around a reversal)",
    "gain": "the residual is proportional to the tension whatever the direction "
    "(plot residual against T)",
    "offset": "the residual has a constant non-zero mean over the whole recording",
    "drift": "the mean residual grows linearly with time (plot residual against t)",
    "eccentricity": "the residual is periodic in cable travel (plot residual against x)",
    "mass_change": "the residual grows with time in proportion to the cables' share of "
    "the platform weight",
}


def _summary(effect: str, outcomes: list[CableOutcome]) -> str:
    vals: dict[str, list[float]] = {}
    for o in outcomes:
        if effect in o.theta:
            for k, v in to_report(effect, o.theta[effect]).items():
                vals.setdefault(k, []).append(v)
    parts = []
    for k, series in vals.items():
        arr = np.asarray(series)
        if arr.size == 1:
            parts.append(f"{k} = {arr[0]:.4g}")
        else:
            parts.append(f"{k} = {arr.min():.4g}..{arr.max():.4g}")
    return ", ".join(parts)


def pooled(effect: str, outcomes: list[CableOutcome]) -> str:
    """Whether the first parameter is the same on every cable within its errors.

    Inverse-variance weighted mean and the chi-square of the per-cable values about it;
    ``chi2 / dof < 4`` reads as "the same" (a pooled value would do).
    """
    vals: list[float] = []
    errs: list[float] = []
    name = ""
    for o in outcomes:
        if effect in o.theta:
            name, value = next(iter(to_report(effect, o.theta[effect]).items()))
            vals.append(value)
            errs.append(
                next(iter(report_stderr(effect, o.theta[effect], o.stderr[effect]).values()))
            )
    v = np.asarray(vals, dtype=float)
    e = np.asarray(errs, dtype=float)
    if v.size < 2 or not np.all(np.isfinite(e)) or np.any(e <= 0):
        return ""
    w = 1.0 / e**2
    mean = float(np.sum(w * v) / np.sum(w))
    chi2 = float(np.sum(w * (v - mean) ** 2)) / (v.size - 1)
    if chi2 < 4.0:
        return f" ({name} the same on these cables within its errors: pooled {mean:.4g})"
    return f" ({name} differs between cables beyond its errors)"


def _confusion(effect: str, outcomes: list[CableOutcome]) -> str:
    """Sentence part on confusable rivals: separated, or not."""
    unsep: set[str] = set()
    sep: set[str] = set()
    for o in outcomes:
        for rv in o.rivals.get(effect, []):
            (sep if rv.separable else unsep).add(rv.effect)
    if unsep:
        names = ", ".join(sorted(unsep))
        return (
            f"; the held-out data cannot tell it from {names} (both fit about as well, "
            f"too few fast or two-signed samples to separate them), so the better one is "
            f"reported"
        )
    if sep:
        return f"; held out it fits clearly better than {', '.join(sorted(sep))}"
    return ""


def evidence(
    effect: str,
    outcomes: list[CableOutcome],
    regime: np.ndarray,
    holdout_before: float,
    holdout_after: float,
) -> str:
    """One sentence for the finding ``effect``."""
    cables = [str(i + 1) for i, o in enumerate(outcomes) if effect in o.theta]
    pct = 100.0 * (1.0 - holdout_after / holdout_before) if holdout_before > 0 else 0.0
    return (
        f"On cable{'s' if len(cables) > 1 else ''} {', '.join(cables)} {LOOK[effect]}; "
        f"fitted {_summary(effect, outcomes)}{pooled(effect, outcomes)}, "
        f"it lowers the held-out RMSE from "
        f"{holdout_before:.3g} N to {holdout_after:.3g} N ({pct:.1f} %)"
        f"{_confusion(effect, outcomes)}."
    )
