"""One checkable sentence per finding: what to look for on the plot, and confusions."""

from __future__ import annotations

import numpy as np

from gateway.diagnose.forward import report_stderr, to_report
from gateway.diagnose.selection import Outcome as CableOutcome
from gateway.model import effects as fx


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
        how = fx.REGISTRY[effect].separate
        return (
            f"; the held-out data cannot tell it from {names} (listed as alternatives: both "
            f"fit about as well), a recording with {how} would"
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
        f"On cable{'s' if len(cables) > 1 else ''} {', '.join(cables)} {fx.REGISTRY[effect].look}; "
        f"fitted {_summary(effect, outcomes)}{pooled(effect, outcomes)}, "
        f"it lowers the held-out RMSE from "
        f"{holdout_before:.3g} N to {holdout_after:.3g} N ({pct:.1f} %)"
        f"{_confusion(effect, outcomes)}."
    )
