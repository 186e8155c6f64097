"""The diagnosis on real recordings, blind, and the least-squares baseline beside it.

``python -m evaluation.realsuite DATA [--table docs/diagnose-suite.md]`` (``DATA``: the
directory holding ``emps/`` and ``davinci/``, :mod:`evaluation.realdata`; ``python -m bench
real`` runs it on the shared data and prints the same) diagnoses:

* **EMPS** against a blank model (no friction law, no pulleys), ``--validate`` with the
  pulses recording; the fitted inertia, viscous and Coulomb level against the published
  identification (targets 5/10/10 %, :data:`evaluation.realdata.EMPS_TARGETS`).
* **da Vinci** against a blank model (:data:`evaluation.realdata.DAVINCI_MODEL`): fitted on
  the first 9 trials of ``Tool_4_Maryland_L_4``, ``--validate`` with its other 6; the
  fitted model then predicts those 6 and the 4 trials of ``Tool_4_Maryland_L_2`` (never
  seen), scored by :func:`evaluation.realdata.rmse` like the baseline (:mod:`evaluation.baseline`,
  fitted on the same 9). Whether the diagnosis names the same effects when fitted on
  either validation set instead is reported too, and the parameters of the effects all
  three fits found, with both standard errors, against the spread between the fits
  (:func:`spread`).

Each run writes its section "## Real recordings" of the table file (the rest is kept).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from evaluation import baseline, realdata
from evaluation.suitedoc import replace_section
from gateway.core.config import FrictionConfig
from gateway.diagnose.engine import diagnose
from gateway.diagnose.writemodel import fitted_friction
from gateway.recordings.reader import Recording

HEADING = "## Real recordings (blind)"


def _diagnose(fit: Recording, model: FrictionConfig, validation: Recording | None) -> dict:
    start = time.perf_counter()
    val = None if validation is None else (validation, validation.tension_platform, None)
    report = diagnose(fit, model, validation=val).report
    fitted = fitted_friction(model, report, fit.cables, fit, [])
    return {"report": report, "fitted": fitted, "seconds": time.perf_counter() - start}


def _parameters(report: dict) -> dict[str, dict[str, float]]:
    return {
        f["effect"]: {k: float(v[0]) for k, v in f["parameters"].items()}
        for f in report["findings"]
    }


def _estimates(report: dict) -> dict[str, dict[str, tuple[float, float, float]]]:
    """Per finding and parameter: (value, the Jacobian's standard error, the standard
    error from the refits across time blocks or trials)."""
    return {
        f["effect"]: {
            k: (
                float(v[0]),
                float(f["stderr_jacobian"][k][0]),
                float(f["stderr_blocks"][k][0]),
            )
            for k, v in f["parameters"].items()
        }
        for f in report["findings"]
    }


def run_emps(root: Path) -> dict[str, Any]:
    """EMPS blind (module docstring): parameters, their errors against the published ones,
    RMSE before -> after on the fit (held-out blocks) and the validation recording."""
    sets = realdata.emps_sets(root)
    res = _diagnose(sets.fit, realdata.EMPS_MODEL, sets.validation)
    params = _parameters(res["report"])
    got = {
        "m_eff_kg": params.get("inertia", {}).get("m_eff_kg"),
        "c_ns_m": params.get("viscous", {}).get("c_ns_m"),
        "f0_n": params.get("coulomb", {}).get("f0_n"),
        # the sensor reads minus the motor force: its offset is minus the motor's
        "offset_n": None if "offset" not in params else -params["offset"]["c_n"],
    }
    errors = {
        k: (None if got[k] is None else abs(got[k] - ref) / abs(ref))  # type: ignore[operator]
        for k, ref in realdata.EMPS_PUBLISHED.items()
    }
    met = all(
        errors[k] is not None and errors[k] <= tol  # type: ignore[operator]
        for k, tol in realdata.EMPS_TARGETS.items()
    )
    fin = res["report"]["final"]
    return {
        "found": [f["effect"] for f in res["report"]["findings"]],
        "got": got,
        "errors": errors,
        "met": met,
        "holdout": (res["report"]["baseline"]["holdout_rmse_n"], fin["holdout_rmse_n"]),
        "validation": (fin["validation_rmse_before_n"], fin["validation_rmse_after_n"]),
        "validation_predicted": realdata.rmse(
            sets.validation, realdata.predict(sets.validation, res["fitted"])
        ),
        "unexplained": res["report"].get("unexplained"),
        "seconds": res["seconds"],
    }


def run_davinci(root: Path, refits: bool = True) -> dict[str, Any]:
    """da Vinci blind and the baseline (module docstring)."""
    sets = realdata.davinci_sets(root)
    model = realdata.DAVINCI_MODEL
    res = _diagnose(sets.fit, model, sets.validation)
    assert sets.other is not None
    scored = {
        name: {
            "before": realdata.rmse(rec, realdata.predict(rec, model)),
            "tool": realdata.rmse(rec, realdata.predict(rec, res["fitted"])),
        }
        for name, rec in (
            ("fit", sets.fit),
            ("validation", sets.validation),
            ("other_series", sets.other),
        )
    }
    start = time.perf_counter()
    base = baseline.fit(sets.fit)
    base_s = time.perf_counter() - start
    for name, rec in (
        ("fit", sets.fit),
        ("validation", sets.validation),
        ("other_series", sets.other),
    ):
        scored[name]["baseline"] = realdata.rmse(rec, baseline.predict(base.theta, rec)[:, None])
    fin = res["report"]["final"]
    out: dict[str, Any] = {
        "found": [f["effect"] for f in res["report"]["findings"]],
        "parameters": _parameters(res["report"]),
        "validation_report": (fin["validation_rmse_before_n"], fin["validation_rmse_after_n"]),
        "scored": scored,
        "baseline": base.as_dict(),
        "baseline_seconds": base_s,
        "unexplained": res["report"].get("unexplained"),
        "seconds": res["seconds"],
    }
    out["estimates"] = {"fit": _estimates(res["report"])}
    if refits:  # the same effects when fitted on either validation set instead?
        out["refits"] = {}
        for name, rec in (("validation", sets.validation), ("other_series", sets.other)):
            report = _diagnose(rec, model, None)["report"]
            out["refits"][name] = [f["effect"] for f in report["findings"]]
            out["estimates"][name] = _estimates(report)
    return out


def spread(estimates: dict[str, dict]) -> list[dict[str, Any]]:
    """Each parameter of the effects every fit found: its values, the standard deviation
    between the fits, and the root mean square of each kind of standard error (the
    Jacobian's, the refits' across blocks or trials). An error that means something is
    about as large as the spread between recordings of the same machine."""
    import numpy as np

    fits = list(estimates.values())
    common = [e for e in fits[0] if all(e in f for f in fits[1:])] if fits else []
    rows = []
    for e in common:
        for k in fits[0][e]:
            got = np.array([f[e][k] for f in fits], dtype=float)  # (fits, 3)
            bad = got[:, 1:] < 0  # -1: could not be computed (the report's JSON)
            se = np.where(bad, np.nan, got[:, 1:])
            rows.append(
                {
                    "effect": e,
                    "parameter": k,
                    "values": got[:, 0].tolist(),
                    "jacobian": se[:, 0].tolist(),
                    "blocks": se[:, 1].tolist(),
                    "sd": float(np.std(got[:, 0], ddof=1)) if len(fits) > 1 else float("nan"),
                    "rms_jacobian": float(np.sqrt(np.nanmean(se[:, 0] ** 2))),
                    "rms_blocks": float(np.sqrt(np.nanmean(se[:, 1] ** 2))),
                }
            )
    return rows


def _params_text(params: dict[str, dict[str, float]]) -> str:
    return "; ".join(
        f"{e} " + ", ".join(f"{k} {v:.4g}" for k, v in p.items()) for e, p in params.items()
    )


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "none" if x is None else format(x, spec)


def table(emps: dict[str, Any], dv: dict[str, Any]) -> str:
    """The markdown section (HEADING) of both machines."""
    pub, got, err = realdata.EMPS_PUBLISHED, emps["got"], emps["errors"]
    lines = [
        HEADING,
        "",
        "Written by `python -m bench real` (`evaluation/realsuite.py`; the data are read where "
        "they lie and never copied into the project). Converters: `evaluation/realdata.py`; "
        "baseline: `evaluation/baseline.py`. RMSE in N.",
        "",
        '**EMPS** (prismatic axis, one "cable" without pulleys; blank model; fit '
        "`DATA_EMPS.mat`, `--validate` with `DATA_EMPS_PULSES.mat`): found "
        f"{', '.join(emps['found']) or 'none'}; targets "
        f"{'met' if emps['met'] else '**not met**'} (inertia/viscous/Coulomb within "
        "5/10/10 % of the published identification).",
        "",
        "| parameter | published | blind diagnosis | error | target |",
        "|---|---|---|---|---|",
    ]
    names = {
        "m_eff_kg": "inertia (kg)",
        "c_ns_m": "viscous (N s/m)",
        "f0_n": "Coulomb (N)",
        "offset_n": "offset of the motor force (N)",
    }
    for key, label in names.items():
        tol = realdata.EMPS_TARGETS.get(key)
        e = err[key]
        lines.append(
            f"| {label} | {pub[key]:.2f} | {_fmt(got[key], '.2f')} | "
            f"{'none' if e is None else f'{100 * e:.1f} %'} | "
            f"{'-' if tol is None else f'{100 * tol:.0f} %'} |"
        )
    h, v = emps["holdout"], emps["validation"]
    lines += [
        "",
        f"Held-out RMSE {h[0]:.2f} -> {h[1]:.2f}; validation (pulses) {v[0]:.2f} -> "
        f"{v[1]:.2f} (the fitted model's prediction of the whole validation recording: "
        f"{emps['validation_predicted']:.2f}); {emps['seconds']:.0f} s.",
        "",
        "**da Vinci** (cable-and-pulley transmission, one cable over a 5 mm capstan; blank "
        "model: one 180 deg pulley, mu 0, Coulomb law; fit: the first 9 trials of "
        "`Tool_4_Maryland_L_4`, `--validate` with its other 6; `Tool_4_Maryland_L_2` never "
        f"seen): found {', '.join(dv['found']) or 'none'} ({_params_text(dv['parameters'])}), "
        f"{dv['seconds']:.0f} s. The diagnosis' own validation figure: "
        f"{dv['validation_report'][0]:.2f} -> {dv['validation_report'][1]:.2f}.",
        "",
        "| recording | before (T_s = T_p) | blind diagnosis | least-squares baseline | "
        "target (the issue's baseline) |",
        "|---|---|---|---|---|",
    ]
    targets = realdata.DAVINCI_TARGETS_N
    rows = (
        ("fit", "L_4, 9 fit trials"),
        ("validation", "L_4, 6 validation trials"),
        ("other_series", "L_2, 4 trials (another series)"),
    )
    for key, label in rows:
        s = dv["scored"][key]
        tgt = targets.get(key)
        mark = "" if tgt is None else (" (met)" if s["tool"] <= tgt else " (**not met**)")
        lines.append(
            f"| {label} | {s['before']:.2f} | {s['tool']:.2f}{mark} | {s['baseline']:.2f} | "
            f"{'-' if tgt is None else f'<= {tgt:.2f}'} |"
        )
    b = dv["baseline"]
    lines += [
        "",
        "Scored on every sample after the first 0.5 s of each trial, each trial simulated "
        "from a relaxed state (`evaluation.realdata.rmse`), for both models. Baseline "
        "(Dahl with level `mu |T_p| + f0`, gain, viscous, spring in the spindle position, "
        f"constant; `scipy.optimize.least_squares`, {dv['baseline_seconds']:.0f} s): "
        + ", ".join(f"{k} {v:.4g}" for k, v in b.items())
        + ".",
    ]
    if "refits" in dv:
        refit = dv["refits"]
        same = all(sorted(r) == sorted(dv["found"]) for r in refit.values())
        lines += [
            "",
            "Fitted on either validation set instead: "
            + "; ".join(
                f"{k.replace('_', ' ')}: {', '.join(v) or 'none'}" for k, v in refit.items()
            )
            + f" ({'the same effects' if same else '**not the same effects**'}).",
        ]
    if len(dv.get("estimates", {})) > 1:
        lines += ["", *_spread_table(dv["estimates"])]
    for name, res in (("EMPS", emps), ("da Vinci", dv)):
        lines += ["", f"{name}: `unexplained`: {_unexplained_text(res.get('unexplained'))}"]
    return "\n".join(lines) + "\n"


def _spread_table(estimates: dict[str, dict]) -> list[str]:
    """The spread of the common parameters between the three fits against their errors."""
    rows = spread(estimates)
    sets = "; ".join(f"{k.replace('_', ' ')} {', '.join(v)}" for k, v in estimates.items())
    if not rows:
        return [
            "Uncertainty: no effect is common to all three fits, so no parameter is compared "
            f"between them (the fits' effect sets: {sets})."
        ]
    lines = [
        "Uncertainty: each parameter of the effects all three fits found, fitted on each "
        "set (value, the Jacobian's standard error / the standard error from refits leaving "
        "out whole trials), against the standard deviation between the three fits and the "
        "root mean square of each error.",
        "",
        "| parameter | L_4, 9 fit trials | L_4, 6 validation trials | L_2, 4 trials | "
        "sd of the three | rms Jacobian | rms blocks | sd / rms blocks |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        cells = [
            f"{v:.4g} ({j:.2g} / {b:.2g})"
            for v, j, b in zip(r["values"], r["jacobian"], r["blocks"], strict=True)
        ]
        ratio = r["sd"] / r["rms_blocks"] if r["rms_blocks"] > 0 else float("nan")
        lines.append(
            f"| {r['effect']} {r['parameter']} | {' | '.join(cells)} | {r['sd']:.3g} | "
            f"{r['rms_jacobian']:.2g} | {r['rms_blocks']:.2g} | {ratio:.1f} |"
        )
    covered = [f"{r['effect']} {r['parameter']}" for r in rows if r["sd"] <= 2 * r["rms_blocks"]]
    beyond = [f"{r['effect']} {r['parameter']}" for r in rows if r["sd"] > 2 * r["rms_blocks"]]
    ratio_jac = [r["sd"] / r["rms_jacobian"] for r in rows if r["rms_jacobian"] > 0]
    lines += [
        "",
        f"The spread between the fits is {min(ratio_jac, default=math.nan):.0f}-"
        f"{max(ratio_jac, default=math.nan):.0f} times the Jacobian's errors; within twice "
        f"the errors from refits for {', '.join(covered) or 'none'}; beyond for "
        f"{', '.join(beyond) or 'none'} (the fits' effect sets: {sets}).",
    ]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluation.realsuite", description=__doc__)
    ap.add_argument("data", type=Path, help="directory with emps/ and davinci/")
    ap.add_argument("--table", type=Path, help="write the section into this file")
    ap.add_argument("--no-refits", action="store_true", help="skip the two refits (~2 min)")
    args = ap.parse_args(argv)
    emps = run_emps(args.data)
    dv = run_davinci(args.data, refits=not args.no_refits)
    text = table(emps, dv)
    print(text)
    if args.table:
        replace_section(args.table, text)
    return 0


def _unexplained_text(u: dict | None) -> str:
    """The report's ``unexplained`` entry in words: the signal, its share and q, the reading,
    and the next signals of the ranking."""
    if not u:
        return "none reported."
    others = ", ".join(f"`{r['signal']}` {r['share']:.0%}" for r in u.get("ranking", [])[1:4])
    return (
        f"`{u['signal']}` explains {u['share']:.0%} of the final residual's variance on "
        f"held-out blocks (q {u['q']:.1e}): {u['reading']}."
        + (f" Next: {others}." if others else "")
    )


if __name__ == "__main__":
    sys.exit(main())
