"""``diagnose --report DIR``: PNG pictures (matplotlib, Agg) and a markdown summary.

* ``residual.png``: residual of the nominal model and of the final one over time per
  cable, the regions where the final residual concentrates shaded;
* ``signature_<effect>.png``: per finding, the residual the final model leaves without
  that effect against the effect's own contribution (binned means; on the 1:1 line
  when the effect explains it);
* ``overlay.png``: measured, nominal and fitted sensor reading around the largest region;
* ``unexplained.png``: when the final residual holds structure beyond the catalogue, its
  binned mean against the signal that explains it;
* ``summary.md``: the verdict, the findings table with their tests, ambiguities, what lies
  beyond the catalogue, where the final residual lives.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gateway.core.heap import trim_heap
from gateway.diagnose import signals
from gateway.diagnose.report import Diagnosis
from gateway.model import effects as fx

MAX_POINTS = 20000
SIGNATURE_POINTS = 200_000
"""Samples (all cables) a signature plot bins: every k-th beyond that (memory; 40 bins)."""


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend, imported on first use: the series a report
    shows are computed before it is loaded (it holds ~35 MiB), so the peak of a 10-min
    8-cable report is the diagnosis', not the diagnosis' plus matplotlib's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def thin(n: int) -> slice:
    return slice(None, None, max(1, n // MAX_POINTS))


def save(fig: Any, path: Path) -> None:
    """Lay out, write at 90 dpi and close ``fig``."""
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    pyplot().close(fig)
    trim_heap()  # a figure's many small blocks, freed, would stay resident


def binned_means(x: np.ndarray, y: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``x`` and ``y`` over ``bins`` equal-count bins of ``x`` (empty bins dropped)."""
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(edges.size - 2, 0))
    count = np.bincount(which, minlength=edges.size)
    keep = count > 0
    mx = np.bincount(which, x, minlength=edges.size)[keep] / count[keep]
    my = np.bincount(which, y, minlength=edges.size)[keep] / count[keep]
    return mx, my


def around_largest_region(t: np.ndarray, regions: Sequence[Any]) -> tuple[int, np.ndarray]:
    """The cable index (0-based, 0 when there is no region) and the sample mask of the
    window around the largest located region (or 1 s either side of the middle)."""
    if regions:
        reg = regions[0]
        i, mid = max(reg.cable - 1, 0), 0.5 * (reg.start_s + reg.end_s)
        half = max(1.0, reg.end_s - reg.start_s)
    else:
        i, mid, half = 0, float(t[t.size // 2]), 1.0
    return i, (t >= mid - half) & (t <= mid + half)


Series = tuple[np.ndarray, np.ndarray]
"""Nominal and final predictions (n, m) (thinned) or (n,) (one cable's window)."""


def residual_series(diag: Diagnosis) -> Series:
    """The predictions of every cable at the residual plot's thinned samples, computed
    one cable at a time (before any figure exists: memory)."""
    sl = thin(diag.t.size)
    pairs = [tuple(p[sl] for p in diag.predictions(i)) for i in range(diag.measured.shape[1])]
    return np.column_stack([n for n, _ in pairs]), np.column_stack([f for _, f in pairs])


def overlay_series(diag: Diagnosis) -> Series:
    """The predictions of the overlay plot's cable in its window."""
    i, sel = around_largest_region(diag.t, diag.regions_nominal or diag.regions)
    nominal, final = diag.predictions(i)
    return nominal[sel], final[sel]


def residual_plot(diag: Diagnosis, path: Path, series: Series | None = None) -> None:
    """Residual over time per cable, regions shaded (``series``: :func:`residual_series`)."""
    m = diag.measured.shape[1]
    nominal, final = residual_series(diag) if series is None else series
    fig, axes = pyplot().subplots(m, 1, figsize=(10, 1.8 * m + 1), sharex=True, squeeze=False)
    sl = thin(diag.t.size)
    for i, ax in enumerate(axes[:, 0]):
        y = diag.measured[sl, i]
        ax.plot(diag.t[sl], y - nominal[:, i], lw=0.5, label="nominal")
        ax.plot(diag.t[sl], y - final[:, i], lw=0.5, label="fitted")
        for reg in diag.regions:
            if reg.cable == i + 1:
                ax.axvspan(reg.start_s, reg.end_s, color="tab:red", alpha=0.2)
        ax.set_ylabel(f"cable {i + 1}\nresidual (N)")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[0, 0].set_title(
        "measured - simulated sensor reading "
        + (
            "(shaded: where the residual left after the findings concentrates)"
            if diag.regions
            else "(no concentrated region: the residual is spread evenly)"
        )
    )
    axes[-1, 0].set_xlabel("t (s)")
    save(fig, path)


class SignatureSeries(NamedTuple):
    """What a signature plot shows: the effect's contribution ``x``, the residual without it
    ``y`` and the module's plot signal ``s``, thinned to :data:`MAX_POINTS` (the scatter),
    and their binned means over every sample kept (:data:`SIGNATURE_POINTS`)."""

    x: np.ndarray
    y: np.ndarray
    s: np.ndarray
    lim: tuple[float, float]
    by_x: tuple[np.ndarray, np.ndarray]
    by_s: tuple[np.ndarray, np.ndarray]
    fitted_by_s: np.ndarray


def signature_series(diag: Diagnosis, effect: str) -> SignatureSeries:
    """The signature of ``effect`` over all its cables, computed one cable at a time."""
    xs, ys, ss = [], [], []
    cables = [i for i, o in enumerate(diag.outcomes) if effect in o.theta]
    step = max(1, diag.t.size * len(cables) // SIGNATURE_POINTS)
    name = fx.REGISTRY[effect].plot
    for i in cables:
        fw, final = diag.forwards[i], diag.final_theta(i)
        rest = {k: v for k, v in final.items() if k != effect}
        without = fw.predict(rest)[::step].copy()
        xs.append(fw.predict(final)[::step] - without)
        fw.clear_cache()
        ys.append(diag.measured[::step, i] - without)
        ss.append(np.array(signals.SIGNALS[name](fw.data)[::step]))
        fw.data.release()
        trim_heap()
    x, y, s = np.concatenate(xs), np.concatenate(ys), np.concatenate(ss)
    sl = thin(x.size)
    sx, sy = binned_means(s, y, 40)
    return SignatureSeries(
        x=x[sl].copy(),
        y=y[sl].copy(),
        s=s[sl].copy(),
        lim=(float(x.min()), float(x.max())),
        by_x=binned_means(x, y, 40),
        by_s=(sx, sy),
        fitted_by_s=binned_means(s, x, 40)[1],
    )


def signature_plot(
    diag: Diagnosis, effect: str, path: Path, series: SignatureSeries | None = None
) -> None:
    """Left: the residual without ``effect`` against its contribution, binned, all its
    cables (on the 1:1 line when the effect explains it). Right: the same residual against
    the signal the effect's module names (:attr:`~gateway.model.effects.Effect.plot`,
    :data:`gateway.diagnose.signals.SIGNALS`), with the effect's contribution over it
    (``series``: :func:`signature_series`)."""
    sig = signature_series(diag, effect) if series is None else series
    name = fx.REGISTRY[effect].plot
    fig, (ax, ax2) = pyplot().subplots(1, 2, figsize=(11, 4.5))
    ax.plot(sig.x, sig.y, ".", ms=1, alpha=0.2, color="grey")
    ax.plot(*sig.by_x, "o-", color="tab:blue", label="binned mean")
    ax.plot(sig.lim, sig.lim, "k--", lw=1, label="1:1")
    ax.set_xlabel(f"{effect} contribution (N)")
    ax.set_ylabel(f"residual without {effect} (N)")
    ax.set_title(f"signature of {effect}")
    ax.legend(fontsize=8)
    ax2.plot(sig.s, sig.y, ".", ms=1, alpha=0.2, color="grey")
    ax2.plot(*sig.by_s, "o-", color="tab:blue", label="residual without it, binned")
    ax2.plot(sig.by_s[0], sig.fitted_by_s, "-", color="tab:red", lw=2, label=f"{effect}, fitted")
    ax2.set_xlabel(f"{name} ({signals.UNITS.get(name, '')})")
    ax2.set_ylabel("N")
    ax2.set_title(f"against {name}")
    ax2.legend(fontsize=8)
    save(fig, path)


def unexplained_plot(diag: Diagnosis, path: Path) -> None:
    """The final residual's structure beyond the catalogue: its binned mean against the
    signal that explains most of it on held-out data, with standard errors."""
    st = diag.structure
    if st is None:
        return
    fig, ax = pyplot().subplots(figsize=(6.5, 4.5))
    ax.errorbar(
        st.centre,
        st.mean,
        yerr=2 * st.se,
        fmt="o-",
        capsize=3,
        color="tab:purple",
        label="final residual, binned mean +- 2 se",
    )
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel(f"{st.signal} ({signals.UNITS.get(st.signal, '')})")
    ax.set_ylabel("residual after the findings (N)")
    ax.set_title(f"beyond the catalogue: {100 * st.share:.0f} % of the held-out residual")
    ax.legend(fontsize=8)
    save(fig, path)


def overlay_plot(diag: Diagnosis, path: Path, series: Series | None = None) -> None:
    """Measured, nominal and fitted reading around the largest located region
    (``series``: :func:`overlay_series`)."""
    i, sel = around_largest_region(diag.t, diag.regions_nominal or diag.regions)
    nominal, final = overlay_series(diag) if series is None else series
    fig, ax = pyplot().subplots(figsize=(10, 4))
    ax.plot(diag.t[sel], diag.measured[sel, i], lw=0.8, label="measured", color="grey")
    ax.plot(diag.t[sel], nominal, lw=1.0, label="nominal model")
    ax.plot(diag.t[sel], final, lw=1.0, label="fitted model")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"cable {i + 1} sensor reading (N)")
    ax.set_title("before / after around the largest mismatch region")
    ax.legend(fontsize=8)
    save(fig, path)


def _fmt(values: list[float]) -> str:
    return ", ".join(f"{v:.4g}" for v in values)


def summary(diag: Diagnosis, source: str) -> str:
    """The markdown summary for an engineer."""
    rep = diag.report
    lines = [f"# Diagnosis of `{source}`", ""]
    lines.append(
        f"{rep['cables']} cable(s), {rep['samples']} samples. Nominal model residual "
        f"RMSE {rep['baseline']['rmse_n']:.3f} N; after the findings "
        f"{rep['final']['rmse_n']:.3f} N (held out: {rep['final']['holdout_rmse_n']:.3f} N)."
    )
    if "validation_rmse_after_n" in rep["final"]:
        f = rep["final"]
        lines.append(
            f"On the validation recording: {f['validation_rmse_before_n']:.3f} N -> "
            f"{f['validation_rmse_after_n']:.3f} N."
        )
    lsq = rep["baseline"].get("least_squares")
    if lsq:
        lines.append(lsq["sentence"])
    fin = rep["final"]
    for ex in rep.get("unexplained_excluded", []):
        lines.append(f"Column `{ex['column']}` is not searched as an explanation: {ex['reason']}.")
    unexpl = rep.get("unexplained")
    if unexpl:
        lines.append(
            f"Beyond the catalogue: {100 * unexpl['share']:.0f} % of the held-out residual "
            f"left after the findings is explained by a smooth function of "
            f"`{unexpl['signal']}` (q = {unexpl['q']:.2g}): {unexpl['reading']} "
            "(![unexplained](unexplained.png))."
        )
    elif fin.get("unexplained_n", 0.0) > 2.0 * fin.get("noise_n", 0.0):
        lines.append(
            f"The held-out residual ({fin['holdout_rmse_n']:.3f} N) is still well above the "
            f"sensor noise estimated from sample-to-sample differences ({fin['noise_n']:.3f} N): "
            "the recording holds a mismatch that none of the candidate effects explains (see "
            "where the residual lives, below), or noise that is not white."
        )
    for f in rep["findings"]:
        if f.get("alternatives"):
            alts = ", ".join(a["effect"] for a in f["alternatives"])
            lines.append(
                f"**Ambiguous:** {f['effect']} or {alts} explain the residual about equally "
                f"well on held-out data; a recording with {f.get('separate_by', 'other motion')} "
                "would tell them apart."
            )
    clip = rep.get("clipped", {})
    for i, (count, levels) in enumerate(
        zip(clip.get("per_cable", []), clip.get("levels_n", []), strict=False), 1
    ):
        if count:
            lines.append(
                f"Cable {i}: {count} readings ({count / rep['samples']:.1%}) sit at the sensor's "
                f"saturation level ({', '.join(f'{x:.4g} N' for x in levels)}): clipped, "
                "excluded from the fit and from every RMSE."
            )
    lines.append("")
    if not rep["findings"]:
        lines += [
            "**Verdict: none** - nothing significant is missing from the nominal model "
            "(no candidate effect improved the held-out fit beyond the noise).",
            "",
        ]
    else:
        lines += [
            "| # | effect | cables | parameters | held-out RMSE before -> after (N) | "
            "held-out z | q |",
            "|---|---|---|---|---|---|---|",
        ]
        for k, f in enumerate(rep["findings"], 1):
            par = "; ".join(f"{n} = {_fmt(v)}" for n, v in f["parameters"].items())
            z = f.get("statistic", [])
            q = f.get("q", [])
            lines.append(
                f"| {k} | {f['effect']} | {_fmt(f['cables'])} | {par} | "
                f"{f['holdout_rmse_before_n']:.3f} -> {f['holdout_rmse_after_n']:.3f} | "
                f"{_fmt(z)} | {', '.join(f'{x:.2g}' for x in q)} |"
            )
        lines.append("")
        for k, f in enumerate(rep["findings"], 1):
            lines += [
                f"{k}. **{f['effect']}**: {f['evidence']} "
                f"![signature](signature_{f['effect']}.png)",
                "",
            ]
    base = rep.get("baseline", {})
    lines += [
        "## Where the residual lives (after the findings; the nominal model's beside it)",
        "",
        "| regime | share of residual energy | nominal model | share of samples |",
        "|---|---|---|---|",
    ]
    for name, s in rep["regime_shares"].items():
        nominal = base.get("regime_shares", {}).get(name, {}).get("energy")
        nom = f"{nominal:.1%}" if nominal is not None else "-"
        lines.append(f"| {name} | {s['energy']:.1%} | {nom} | {s['samples']:.1%} |")
    if rep["mismatch"]:
        lines += ["", "Largest regions (shaded in the residual plot):", ""]
    else:
        lines += [
            "",
            "No region concentrates the residual (no stretch holds more than twice the mean "
            "residual energy): the mismatch is spread over the whole recording, as a "
            "constant, slowly varying or speed-proportional one is; nothing is shaded.",
        ]
    lines += [region_line(r) for r in rep["mismatch"][:8]]
    warm = rep.get("warmup") or {}
    if warm.get("samples"):
        lines += [
            "",
            f"The first {warm['seconds']:.2f} s (to {warm['until_s']:.2f} s) are the "
            "diagnosis' warm-up: "
            f"{warm['treatment']}; {len(warm['regions'])} region(s) inside it are not "
            "listed above.",
        ]
    lines += ["", "![residual](residual.png)", "", "![overlay](overlay.png)", ""]
    return "\n".join(lines)


def region_line(r: dict[str, Any]) -> str:
    """One mismatch region for summary.md; cable 0 is the platform (the wrench reference
    locates regions in the platform's force balance, not on one cable)."""
    who = "the platform (wrench balance, all cables)" if r["cable"] == 0 else f"cable {r['cable']}"
    return (
        f"- {who}, {r['start_s']:.2f}-{r['end_s']:.2f} s, {r['regime']}: "
        f"{r['share']:.1%} of the residual energy"
    )


def write_files(
    diag: Any,
    directory: Path,
    text: str,
    residual: Callable[[Any, Path], None],
    overlay: Callable[[Any, Path], None],
    signature: Callable[[Any, str, Path], None],
) -> None:
    """``residual.png``, ``overlay.png``, a ``signature_<effect>.png`` per finding (drawn by
    the given plot functions) and ``text`` as ``summary.md`` into ``directory`` (created)."""
    directory.mkdir(parents=True, exist_ok=True)
    residual(diag, directory / "residual.png")
    overlay(diag, directory / "overlay.png")
    for f in diag.report["findings"]:
        signature(diag, f["effect"], directory / f"signature_{f['effect']}.png")
    if getattr(diag, "structure", None) is not None:
        unexplained_plot(diag, directory / "unexplained.png")
    (directory / "summary.md").write_text(text, encoding="utf-8")


def write_report(diag: Diagnosis, directory: Path, source: str) -> None:
    """Write the pictures and ``summary.md`` into ``directory`` (created if needed). The
    series every plot shows are computed first (one cable at a time), so that no chain
    simulation runs while a figure exists or matplotlib is loaded."""
    text = summary(diag, source)
    res, ovl = residual_series(diag), overlay_series(diag)
    sigs = {f["effect"]: signature_series(diag, f["effect"]) for f in diag.report["findings"]}
    write_files(
        diag,
        directory,
        text,
        lambda d, path: residual_plot(d, path, res),
        lambda d, path: overlay_plot(d, path, ovl),
        lambda d, effect, path: signature_plot(d, effect, path, sigs[effect]),
    )
