"""The fleet table: one row per recording x finding x cable (and one per recording with no
finding, or that failed), written as Parquet and CSV.

Columns: ``recording``, ``report`` (the report's file under ``reports/``), ``robot``,
``start`` (ISO 8601), ``status`` (``ok`` / ``failed``), ``error``, ``worker`` (the Dask
worker that ran it, ``tcp://HOST:PORT``; empty for a recording refused before it was
sent), ``reference``,
``samples``, ``effect`` (``none`` for a recording without finding), ``rank`` (the
finding's place in the report, 1 = most important; 0 without finding), ``cable`` (0: the
platform, or no finding), then per parameter name of any finding the value and
``NAME_stderr`` (empty where the effect has no such parameter), ``rmse_before_n``,
``rmse_after_n``, ``holdout_rmse_before_n``, ``holdout_rmse_after_n`` (the finding's,
cumulative as in the report), ``baseline_rmse_n`` and ``final_rmse_n`` (the recording's),
``final_holdout_rmse_n`` and ``lsq_holdout_rmse_n`` (the held-out RMSE of the final model
and of the better of the engineer's least-squares baselines, ``baseline.least_squares``;
empty where the report has none, e.g. the wrench reference).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from gateway.fleet.task import TaskResult

FIXED = [
    "recording",
    "report",
    "robot",
    "start",
    "status",
    "error",
    "worker",
    "reference",
    "samples",
    "effect",
    "rank",
    "cable",
]
RMSE = ["rmse_before_n", "rmse_after_n", "holdout_rmse_before_n", "holdout_rmse_after_n"]
RECORDING = ["baseline_rmse_n", "final_rmse_n", "final_holdout_rmse_n", "lsq_holdout_rmse_n"]
"""The recording's RMSE columns (the same on each of its rows)."""
TEXT = {"recording", "report", "robot", "start", "status", "error", "worker", "reference", "effect"}
INTEGER = {"samples", "rank", "cable"}


def _per_cable(values: Any, cables: list[int], index: int) -> float:
    """The value of cable ``cables[index]`` in a report's parameter entry (a list per
    cable, or one value for the platform)."""
    if isinstance(values, list):
        if len(values) == len(cables):
            return float(values[index])
        return float(values[0]) if len(values) == 1 else math.nan
    return float(values)


def _finding_rows(base: dict[str, Any], rank: int, finding: dict[str, Any]) -> list[dict]:
    cables = [int(c) for c in finding.get("cables", [])] or [0]
    rows = []
    for i, cable in enumerate(cables):
        row = {**base, "effect": finding["effect"], "rank": rank, "cable": cable}
        for name, values in finding.get("parameters", {}).items():
            row[name] = _per_cable(values, cables, i)
        for name, values in finding.get("stderr", {}).items():
            row[f"{name}_stderr"] = _per_cable(values, cables, i)
        for key in RMSE:
            row[key] = float(finding.get(key, math.nan))
        rows.append(row)
    return rows


def _lsq_holdout(rep: dict[str, Any]) -> float:
    """The better least-squares baseline's held-out RMSE (N), or NaN without the block."""
    fits = rep["baseline"].get("least_squares", {}).get("fits", {})
    return min((float(f["holdout_rmse_n"]) for f in fits.values()), default=math.nan)


def table_rows(results: list[tuple[TaskResult, str]]) -> list[dict[str, Any]]:
    """Rows of the table from (result, report file name) pairs, in the order given."""
    rows: list[dict[str, Any]] = []
    for res, report_name in results:
        base: dict[str, Any] = {
            "recording": res.recording,
            "report": report_name,
            "robot": res.robot,
            "start": res.start,
            "status": "failed" if res.error else "ok",
            "error": res.error or "",
            "worker": res.worker,
        }
        if res.report_json is None:
            rows.append({**base, "effect": "", "rank": 0, "cable": 0})
            continue
        rep = json.loads(res.report_json)
        base.update(
            reference=rep.get("reference", ""),
            samples=int(rep.get("samples", 0)),
            baseline_rmse_n=float(rep["baseline"]["rmse_n"]),
            final_rmse_n=float(rep["final"]["rmse_n"]),
            final_holdout_rmse_n=float(rep["final"].get("holdout_rmse_n", math.nan)),
            lsq_holdout_rmse_n=_lsq_holdout(rep),
        )
        findings = rep.get("findings", [])
        if not findings:
            rows.append({**base, "effect": "none", "rank": 0, "cable": 0})
        for rank, finding in enumerate(findings, start=1):
            rows += _finding_rows(base, rank, finding)
    return rows


def columns_of(rows: list[dict[str, Any]]) -> list[str]:
    params = sorted({k for r in rows for k in r} - set(FIXED) - set(RMSE) - set(RECORDING))
    values = [p for p in params if not p.endswith("_stderr")]
    ordered = [c for p in values for c in (p, f"{p}_stderr") if c in params]
    ordered += [p for p in params if p not in ordered]
    return FIXED + ordered + RMSE + RECORDING


def write_table(rows: list[dict[str, Any]], out: Path) -> tuple[Path, Path]:
    """``out/fleet.parquet`` and ``out/fleet.csv``; returns both paths."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = columns_of(rows)
    arrays = []
    for c in cols:
        if c in TEXT:
            arrays.append(pa.array([str(r.get(c, "")) for r in rows], pa.string()))
        elif c in INTEGER:
            arrays.append(pa.array([int(r.get(c, 0)) for r in rows], pa.int64()))
        else:
            arrays.append(pa.array([float(r.get(c, math.nan)) for r in rows], pa.float64()))
    pq.write_table(
        pa.Table.from_arrays(arrays, names=cols), out / "fleet.parquet", compression="zstd"
    )
    with open(out / "fleet.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(cols)
        for r in rows:
            writer.writerow([_cell(r.get(c), c) for c in cols])
    return out / "fleet.parquet", out / "fleet.csv"


def _cell(value: Any, column: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)
