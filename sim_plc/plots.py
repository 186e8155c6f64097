"""PNG plots of ``replicate`` (matplotlib, Agg backend: no screen needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _smooth(y: np.ndarray, n: int) -> np.ndarray:
    """Moving average over ``n`` samples (same length)."""
    if n <= 1 or y.size < n:
        return y
    return np.convolve(y, np.ones(n) / n, mode="same")


def tension_profile(path: Path, run: Any) -> None:
    """Paper Fig. 7: per cable, platform tension (truth), reading and compensated."""
    plt = _pyplot()
    sp, m = run.sp, run.reading.shape[1]
    step = max(sp.t.size // 4000, 1)
    t = sp.t[::step]
    fig, axes = plt.subplots(m // 2 + m % 2, 2, figsize=(12, 2.2 * (m // 2 + m % 2)), sharex=True)
    for i, ax in enumerate(np.atleast_1d(axes).ravel()[:m]):
        ax.plot(t, run.reading[::step, i], lw=0.6, color="0.6", label="sensor reading")
        ax.plot(t, run.estimates["coulomb"][::step, i], lw=0.6, color="tab:orange", label="Coulomb")
        ax.plot(t, run.estimates["dahl"][::step, i], lw=0.6, color="tab:blue", label="Dahl")
        ax.plot(t, sp.tension_true[::step, i], lw=0.8, color="k", ls="--", label="platform (truth)")
        ax.set_ylabel(f"cable {i + 1} [N]")
    axes.ravel()[0].legend(fontsize=7, loc="upper right")
    for ax in axes.ravel()[-2:]:
        ax.set_xlabel("t [s]")
    fig.suptitle("Cable tensions on the eq. 20 path (two layers, extrusion)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def error_over_path(path: Path, run: Any) -> None:
    """Mean absolute platform-tension error over the cables along the path (0.5 s mean)."""
    plt = _pyplot()
    sp = run.sp
    n = max(int(0.5 / max(sp.t[1] - sp.t[0], 1e-9)), 1)
    fig, ax = plt.subplots(figsize=(10, 4))
    for name, color in (("uncompensated", "0.5"), ("coulomb", "tab:orange"), ("dahl", "tab:blue")):
        err = np.nanmean(np.abs(run.estimates[name] - sp.tension_true), axis=1)
        ax.plot(sp.t, _smooth(err, n), lw=0.9, color=color, label=name)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("mean |error| over cables [N]")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title("Platform-tension error along the path")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def hysteresis_loops(path: Path, loops: dict[str, np.ndarray]) -> None:
    """Paper Fig. 9: estimated wrench along z against z on the cyclic 6-DOF motion."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    z = loops["z"]
    for name, color in (("before", "0.5"), ("coulomb", "tab:orange"), ("after", "tab:blue")):
        ax.plot(z, loops[name], lw=0.5, color=color, label=f"{name}")
    ax.plot(z, loops["truth"], lw=0.8, color="k", ls="--", label="truth")
    ax.set_xlabel("z [m]")
    ax.set_ylabel("estimated wrench w_z [N]")
    ax.legend()
    ax.set_title("Wrench hysteresis along z: measured vs compensated")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_plots(out_dir: Path, path_run: Any, loops: dict[str, np.ndarray]) -> list[str]:
    """Write the three PNGs; return their file names."""
    names = ["tension_profile.png", "error_over_path.png", "hysteresis.png"]
    tension_profile(out_dir / names[0], path_run)
    error_over_path(out_dir / names[1], path_run)
    hysteresis_loops(out_dir / names[2], loops)
    return names
