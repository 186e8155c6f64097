"""``diagnose --report DIR`` in the wrench reference: pictures of the force residual.

* ``residual.png``: the force residual ``A T_p + w`` (x, y, z) of the nominal and of the
  final model over time, the located regions (platform, ``cable 0``) shaded;
* ``signature_<effect>.png``: per finding, the force residual the final model leaves
  without the effect against the effect's own contribution (binned means; on the 1:1
  line when the effect explains it);
* ``overlay.png``: the force residual's magnitude, nominal and fitted, around the largest
  region; ``summary.md``: :func:`gateway.diagnose.plots.summary`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gateway.diagnose.plots import (
    around_largest_region,
    binned_means,
    pyplot,
    save,
    summary,
    thin,
    write_files,
)
from gateway.diagnose.wrench_report import WrenchDiagnosis

AXES = ("x", "y", "z")


def residual_plot(diag: WrenchDiagnosis, path: Path) -> None:
    sl = thin(diag.t.size)
    fig, axes = pyplot().subplots(3, 1, figsize=(10, 6.5), sharex=True)
    for k, ax in enumerate(axes):
        ax.plot(diag.t[sl], -diag.nominal_pred[sl, k], lw=0.5, label="nominal")
        ax.plot(diag.t[sl], -diag.final_pred[sl, k], lw=0.5, label="fitted")
        for reg in diag.regions:
            ax.axvspan(reg.start_s, reg.end_s, color="tab:red", alpha=0.2)
        ax.set_ylabel(f"F{AXES[k]} residual (N)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title("wrench balance A T_p + w, force part (shaded: located regions)")
    axes[-1].set_xlabel("t (s)")
    save(fig, path)


def signature_plot(diag: WrenchDiagnosis, effect: str, path: Path) -> None:
    x, y = diag.signatures[effect]
    mx, my = binned_means(x, y, 30)
    fig, ax = pyplot().subplots(figsize=(5, 4.5))
    ax.plot(mx, my, "o-", ms=3, label="binned means")
    lim = float(np.max(np.abs(np.concatenate([mx, my, [1e-9]]))))
    ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8, label="1:1")
    ax.set_xlabel(f"{effect}: contribution to the force residual (N)")
    ax.set_ylabel("force residual without it (N)")
    ax.legend(fontsize=8)
    save(fig, path)


def overlay_plot(diag: WrenchDiagnosis, path: Path) -> None:
    _, sel = around_largest_region(diag.t, diag.regions)
    fig, ax = pyplot().subplots(figsize=(10, 4))
    ax.plot(diag.t[sel], np.linalg.norm(diag.nominal_pred[sel], axis=1), lw=0.8, label="nominal")
    ax.plot(diag.t[sel], np.linalg.norm(diag.final_pred[sel], axis=1), lw=0.8, label="fitted")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("|force residual| (N)")
    ax.set_title("before / after around the largest mismatch region")
    ax.legend(fontsize=8)
    save(fig, path)


def write_report(diag: WrenchDiagnosis, directory: Path, source: str) -> None:
    """Pictures and ``summary.md`` into ``directory`` (created if needed)."""
    text = summary(diag, source).replace(
        "Nominal model residual RMSE", "Reference: wrench balance (force part). Nominal model RMSE"
    )
    write_files(diag, directory, text, residual_plot, overlay_plot, signature_plot)
