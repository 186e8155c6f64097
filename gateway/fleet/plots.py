"""The fleet's pictures and ``fleet.md``.

Per robot one PNG: one panel per fitted parameter (``effect.parameter``) with its value
over the recordings' start times, one line per cable, error bars of one standard error;
every recording of the robot is marked on each panel's time axis -- grey ticks for those
with no finding of that effect, red crosses for those that failed -- so a parameter that
appears, drifts or goes away can be read off against the recordings that were made.
"""

from __future__ import annotations

import datetime
import math
import re
from collections import defaultdict
from pathlib import Path
from typing import Any

MAX_PANELS = 12  # parameters per robot shown; the table holds them all


def _when(start: str) -> datetime.datetime:
    try:
        when = datetime.datetime.fromisoformat(start)
    except ValueError:
        return datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)
    return when if when.tzinfo else when.replace(tzinfo=datetime.UTC)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:64] or "robot"


def _parameters(rows: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """(effect, parameter) pairs fitted in ``rows``, in order of first appearance."""
    found: dict[tuple[str, str], None] = {}
    for r in rows:
        if r.get("effect") not in ("", "none", None):
            for k, v in r.items():
                if k.endswith("_stderr") or k not in _param_names(r):
                    continue
                if isinstance(v, float) and not math.isnan(v):
                    found[(r["effect"], k)] = None
    return list(found)


def _param_names(row: dict[str, Any]) -> set[str]:
    from gateway.fleet.table import FIXED, RECORDING, RMSE

    return set(row) - set(FIXED) - set(RMSE) - set(RECORDING)


def write_plots(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """One PNG per robot under ``out``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_robot: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_robot[r["robot"]].append(r)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for robot, rs in sorted(by_robot.items()):
        params = _parameters(rs)[:MAX_PANELS] or [("none", "")]
        fig, axes = plt.subplots(
            len(params), 1, figsize=(8, 2.2 * len(params) + 0.6), squeeze=False, sharex=True
        )
        recordings: dict[str, tuple[datetime.datetime, str]] = {}
        for r in rs:
            recordings[r["recording"]] = (_when(r["start"]), r["status"])
        for ax, (effect, name) in zip(axes[:, 0], params, strict=True):
            _panel(ax, rs, recordings, effect, name)
        axes[-1, 0].set_xlabel("recording start (UTC)")
        axes[-1, 0].set_xlim(*time_span([w for w, _ in recordings.values()]))
        joined = sum(rec.count(" + ") for rec in recordings)  # --per-robot: recordings joined
        count = plural(len(recordings) + joined, "recording")
        if joined:
            count += " diagnosed jointly"
        fig.suptitle(f"robot {robot}: fitted parameters over time ({count})")
        fig.autofmt_xdate()
        fig.tight_layout()
        path = out / f"robot-{_safe(robot)}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def plural(n: int, word: str) -> str:
    """``1 recording``, ``2 recordings``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def time_span(times: list[datetime.datetime]) -> tuple[datetime.datetime, datetime.datetime]:
    """The x axis: the recordings' starts with 5 % to spare, at least an hour either side of
    one start (matplotlib's own limits for one date spanned 2025-2029)."""
    lo, hi = min(times), max(times)
    pad = max((hi - lo) * 0.05, datetime.timedelta(hours=1))
    return lo - pad, hi + pad


def axis_label(effect: str, name: str) -> str:
    """``offset`` / ``c_n (N)``: the report parameter's unit, from its suffix."""
    from gateway.core.configdoc import unit_of

    unit = unit_of(name)
    return f"{effect}\n{name} ({unit})" if unit else f"{effect}\n{name}"


def _panel(ax, rs, recordings, effect: str, name: str) -> None:
    series: dict[int, list[tuple[datetime.datetime, float, float]]] = defaultdict(list)
    with_effect = set()
    for r in rs:
        if r.get("effect") == effect and name and not math.isnan(r.get(name, math.nan)):
            err = r.get(f"{name}_stderr", math.nan)
            err = err if err >= 0 else math.nan  # the report's -1: not estimable
            series[int(r["cable"])].append((_when(r["start"]), r[name], err))
            with_effect.add(r["recording"])
    for cable, pts in sorted(series.items()):
        pts.sort()
        x, y, e = zip(*pts, strict=True)
        ax.errorbar(
            x,
            y,
            yerr=e,
            marker="o",
            ms=3,
            capsize=2,
            lw=0.8,
            label="platform" if cable == 0 else f"cable {cable}",
        )
    without = [
        w for rec, (w, status) in recordings.items() if rec not in with_effect and status == "ok"
    ]
    failed = [w for w, status in recordings.values() if status == "failed"]
    trans = ax.get_xaxis_transform()  # x in data, y in axes fractions: marks at the bottom
    if without:
        ax.plot(
            without,
            [0.03] * len(without),
            "|",
            color="grey",
            ms=10,
            transform=trans,
            label=f"no {effect if name else 'finding'} ({plural(len(without), 'recording')})",
        )
    if failed:
        ax.plot(
            failed,
            [0.03] * len(failed),
            "x",
            color="red",
            transform=trans,
            label=f"failed ({plural(len(failed), 'recording')})",
        )
    ax.set_ylabel(axis_label(effect, name) if name else "no finding")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=5, loc="upper left")


def write_summary(
    path: Path, results: list[dict[str, Any]], plots: list[Path], info: dict[str, str]
) -> None:
    """``fleet.md``: what ran where, per recording (``info["recordings"]`` given: per robot,
    its recordings diagnosed jointly) the verdict, the failures, the files."""
    ok = [r for r in results if not r["error"]]
    failed = [r for r in results if r["error"]]
    lines = [
        "# Fleet diagnosis",
        "",
        f"{plural(len(results), 'recording')}, {len(ok)} diagnosed, {len(failed)} failed; "
        f"{info.get('cluster', '')}; wall time {info.get('wall', '')}.",
        "",
        f"Model: `{info.get('model', '')}`. Table: `fleet.parquet`, `fleet.csv` (one row per "
        "recording x finding x cable); each recording's report under `reports/` is what "
        "`cdpr-gateway diagnose` writes for it alone.",
        "",
        "| robot | start | recording | verdict | RMSE before -> after (N) | report |",
        "|---|---|---|---|---|---|",
    ]
    if "recordings" in info:  # --per-robot: one task per robot, its recordings joined
        lines[2] = (
            f"{plural(len(results), 'robot')} ({info['recordings']} recordings), "
            f"{len(ok)} diagnosed, {len(failed)} failed; "
            f"{info.get('cluster', '')}; wall time {info.get('wall', '')}."
        )
        lines[4] = (
            f"Model: `{info.get('model', '')}`. Each robot's recordings diagnosed jointly "
            "(`--per-robot`). Table: `fleet.parquet`, `fleet.csv` (one row per robot x "
            "finding x cable); each robot's report under `reports/` is what "
            "`cdpr-gateway diagnose REC REC ...` writes for its recordings together."
        )
        lines[6] = (
            "| robot | first start | recordings | verdict | RMSE before -> after (N) | report |"
        )
    for r in results:
        lines.append(
            f"| {r['robot']} | {r['start']} | `{r['recording']}` | {r['verdict']} | "
            f"{r['rmse']} | {r['report']} |"
        )
    if failed:
        lines += ["", "## Failed", ""]
        lines += [f"- `{r['recording']}`: {r['error']}" for r in failed]
    lines += ["", "## Plots", ""]
    lines += [f"![{p.stem}](plots/{p.name})" for p in plots]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
