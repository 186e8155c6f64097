"""``cdpr-gateway replicate --out DIR``: the paper's experiment (sec. IV) end to end.

Three runs of the plant (batch mode, :mod:`sim_plc.plant`) with the config's friction as
the truth and the same friction as the gateway's model (a matched model):

1. the eq. 20 path in two layers at 0.04 m/s with extrusion (changing load): the error of
   the platform tension estimated from the digitised sensor reading, uncompensated,
   Coulomb-compensated and Dahl-compensated (``chain_runs.run`` compensating, driven by the setpoint
   velocity), as MAE, std of the absolute error and RMSE, per cable and overall;
2. the same path at constant mass (no extrusion);
3. the cyclic 6-DOF motion through one point (paper Fig. 9): the wrench ``w = -A tau``
   from measured and from compensated tensions, and the width of its hysteresis loop
   along z.

The noise floor is the RMS difference between the digitised reading and the noiseless
analog sensor tension (noise + quantisation). Improvements are ``1 - MAE_x / MAE_unc``.
Writes ``replication.json``, ``replication.md`` and PNG plots into DIR.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from gateway.core.cliopts import output_dir
from gateway.core.config import Config, load_config
from gateway.core.resources import data_file
from gateway.errors import ConfigError
from gateway.model import chain_runs
from gateway.model.chain_schema import ChainParams
from sim_plc.config import SimPlcConfig, load_sim_config
from sim_plc.plant import PlantModel, Setpoints, sensor_batch

DEFAULT_REPLICATE_CONFIG = data_file("replicate.yaml")  # config/ or the wheel's package data
PAPER = {
    "coulomb_mae_n": 10.58,
    "coulomb_std_n": 3.37,
    "dahl_mae_n": 7.26,
    "dahl_std_n": 1.56,
    "improvement_dahl_vs_uncompensated": 0.65,
    "changing_load_improvement": 0.40,
    "hysteresis_width_after_n": 5.0,
}
CYCLIC_PERIODS = 6  # periods of the cyclic motion; the first is the run-in, not scored


def _log(msg: str) -> None:
    print(f"replicate: {msg}", file=sys.stderr, flush=True)


@dataclasses.dataclass
class Run:
    """One plant run: setpoints, the reading (N, m) in N, the noise floor and estimates."""

    sp: Setpoints
    reading: np.ndarray
    noise_floor_n: float
    estimates: dict[str, np.ndarray]


def run_plant(cfg: Config, sim: SimPlcConfig, seconds: float, label: str) -> Run:
    """Simulate ``seconds`` and compensate the reading with the config's friction model."""
    model = PlantModel(cfg, sim)
    n = max(round(seconds / sim.period_s), 2)
    t = np.arange(n) * sim.period_s
    last = [-10]

    def progress(f: float) -> None:
        if int(f * 10) != last[0]:
            last[0] = int(f * 10)
            _log(f"{label}: statics {int(f * 100):3d} %")

    sp = model.setpoints(t, progress)
    noise = np.random.default_rng(sim.seed).standard_normal((n, model.cables))
    clean = sensor_batch(model, sp, np.zeros_like(noise))
    reading = model.reading(model.adc(sensor_batch(model, sp, noise)))
    floor = float(np.sqrt(np.nanmean((reading - clean) ** 2)))
    nominal = ChainParams.from_friction(cfg.friction, cfg.cables)
    est = {"uncompensated": reading}
    for name in ("coulomb", "dahl"):
        est[name] = chain_runs.run(
            nominal.with_model(name), "compensate", reading, sp.velocity, sp.t
        )
    return Run(sp, reading, floor, est)


def error_stats(estimate: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """MAE, std of the absolute error and RMSE (N), overall and per cable."""
    err = estimate - truth
    ab = np.abs(err)

    def stats(axis: int | None) -> dict[str, Any]:
        vals = {
            "mae_n": np.nanmean(ab, axis=axis),
            "std_n": np.nanstd(ab, axis=axis),
            "rmse_n": np.sqrt(np.nanmean(err**2, axis=axis)),
        }
        return {k: (float(v) if axis is None else [float(x) for x in v]) for k, v in vals.items()}

    return {**stats(None), "per_cable": stats(0)}


def path_metrics(run: Run) -> dict[str, Any]:
    truth = run.sp.tension_true
    out: dict[str, Any] = {k: error_stats(v, truth) for k, v in run.estimates.items()}
    unc = out["uncompensated"]
    for name in ("coulomb", "dahl"):
        out[f"improvement_{name}_vs_uncompensated"] = 1 - out[name]["mae_n"] / unc["mae_n"]
        out[f"improvement_rmse_{name}_vs_uncompensated"] = 1 - out[name]["rmse_n"] / unc["rmse_n"]
    return out


def hysteresis_width(z: np.ndarray, fz: np.ndarray, dz: np.ndarray, bins: int = 40) -> float:
    """Largest gap (N) between the rising and falling branch of ``fz`` over ``z``.

    Bins over the middle 80 % of the z range; each branch averaged per bin, bins where a
    branch has fewer than 5 samples are left out.
    """
    lo, hi = np.quantile(z, [0.0, 1.0])
    span = hi - lo
    edges = np.linspace(lo + 0.1 * span, hi - 0.1 * span, bins + 1)
    idx = np.digitize(z, edges) - 1
    gaps = []
    for b in range(bins):
        sel = idx == b
        up, down = fz[sel & (dz > 0)], fz[sel & (dz < 0)]
        if up.size >= 5 and down.size >= 5:
            gaps.append(abs(float(np.mean(up) - np.mean(down))))
    return max(gaps) if gaps else math.nan


def cyclic_metrics(run: Run, sim: SimPlcConfig) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Wrench hysteresis along z: before (measured), after (Dahl), Coulomb, truth."""
    sp = run.sp
    freq = max(sim.trajectory.cyclic.frequency_hz)
    period = 1.0 / freq if freq > 0 else 0.0
    keep = sp.t >= min(period, 0.5 * sp.t[-1])
    z = sp.pose[:, 2]
    dz = np.gradient(z, sp.t)
    wz = {
        "truth": -np.einsum("nm,nm->n", sp.a_mat[:, 2, :], sp.tension_true),
        "before": -np.einsum("nm,nm->n", sp.a_mat[:, 2, :], run.estimates["uncompensated"]),
        "coulomb": -np.einsum("nm,nm->n", sp.a_mat[:, 2, :], run.estimates["coulomb"]),
        "after": -np.einsum("nm,nm->n", sp.a_mat[:, 2, :], run.estimates["dahl"]),
    }
    widths = {k: hysteresis_width(z[keep], v[keep], dz[keep]) for k, v in wz.items()}
    return widths, {"z": z[keep], **{k: v[keep] for k, v in wz.items()}}


def _variant(sim: SimPlcConfig, kind: str, extrusion: float | None = None) -> SimPlcConfig:
    traj = dataclasses.replace(sim.trajectory, kind=kind, repeat=False)  # type: ignore[arg-type]
    ext = sim.extrusion_kg_s if extrusion is None else extrusion
    return dataclasses.replace(sim, trajectory=traj, extrusion_kg_s=ext)


def _goals(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
    d, c = res["dahl"], res["coulomb"]
    ratio = d["rmse_n"] / res["noise_floor_n"]
    after = res["hysteresis_width_n"]["after"]
    return {
        "dahl_rmse_within_1.2x_noise_floor": {
            "value": ratio,
            "target": "<= 1.2",
            "met": ratio <= 1.2,
        },
        "improvement_at_least_85pct": {
            "value": res["improvement_dahl_vs_uncompensated"],
            "target": ">= 0.85",
            "met": res["improvement_dahl_vs_uncompensated"] >= 0.85,
        },
        "dahl_better_than_coulomb": {
            "value": [d["mae_n"], c["mae_n"], d["std_n"], c["std_n"]],
            "target": "dahl mae and std < coulomb's",
            "met": d["mae_n"] < c["mae_n"] and d["std_n"] < c["std_n"],
        },
        "hysteresis_after_at_most_2n": _hysteresis_goal(after),
    }


def _hysteresis_goal(after: float) -> dict[str, Any]:
    """The hysteresis goal, or why it could not be measured: the cyclic run must travel a
    stretch of z both up and down (5 samples each way per bin) after its first period."""
    if math.isnan(after):
        why = (
            "not measured: the cyclic run travelled no stretch of z both up and down after "
            "its first period (run longer: --seconds)"
        )
        return {"value": None, "target": "<= 2 N", "met": False, "why": why}
    return {"value": after, "target": "<= 2 N", "met": after <= 2.0}


def replicate(
    cfg: Config, out_dir: Path, seconds_limit: float | None = None, plots: bool = True
) -> dict[str, Any]:
    """Run the experiment, write JSON, markdown and plots into ``out_dir``; return the JSON."""
    t_start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    sim = load_sim_config(cfg)
    path_sim = _variant(sim, "paper")
    path_s = PlantModel(cfg, path_sim).trajectory.duration_s
    cyc = sim.trajectory.cyclic
    cyc_s = CYCLIC_PERIODS / max(max(cyc.frequency_hz), 1e-3)
    if seconds_limit is not None:
        path_s, cyc_s = min(path_s, seconds_limit), min(cyc_s, seconds_limit)
    _log(f"eq. 20 path with extrusion, {path_s:.1f} s")
    changing = run_plant(cfg, path_sim, path_s, "changing load")
    _log(f"eq. 20 path at constant mass, {path_s:.1f} s")
    constant = run_plant(cfg, _variant(sim, "paper", 0.0), path_s, "constant load")
    _log(f"cyclic 6-DOF motion, {cyc_s:.1f} s")
    cyclic = run_plant(cfg, _variant(sim, "cyclic"), cyc_s, "cyclic")
    main = path_metrics(changing)
    const = path_metrics(constant)
    widths, loops = cyclic_metrics(cyclic, sim)
    res: dict[str, Any] = {
        "config": _relative(cfg.source),
        "seconds": {"path": path_s, "cyclic": cyc_s},
        "noise_floor_n": changing.noise_floor_n,
        "uncompensated": main["uncompensated"],
        "coulomb": main["coulomb"],
        "dahl": main["dahl"],
        "improvement_dahl_vs_uncompensated": main["improvement_dahl_vs_uncompensated"],
        "improvement_coulomb_vs_uncompensated": main["improvement_coulomb_vs_uncompensated"],
        "improvement_rmse_dahl_vs_uncompensated": main["improvement_rmse_dahl_vs_uncompensated"],
        "changing_load_improvement": main["improvement_dahl_vs_uncompensated"],
        "constant_load_improvement": const["improvement_dahl_vs_uncompensated"],
        "constant_load": const,
        "mass_kg": {"start": float(changing.sp.mass[0]), "end": float(changing.sp.mass[-1])},
        "tension_range_n": [
            float(changing.sp.tension_true[:, :4].min()),
            float(changing.sp.tension_true[:, :4].max()),
        ],
        "hysteresis_width_n": widths,
        "dahl_rmse_over_noise_floor": main["dahl"]["rmse_n"] / changing.noise_floor_n,
        "paper": PAPER,
        "parameters": _parameters(cfg, sim),
    }
    res["goals"] = _goals(res)
    res["plots"] = []
    if plots:
        from sim_plc.plots import write_plots

        res["plots"] = write_plots(out_dir, changing, loops)
    res["runtime_s"] = time.perf_counter() - t_start
    (out_dir / "replication.json").write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    (out_dir / "replication.md").write_text(markdown(res), encoding="utf-8")
    _log(f"wrote {out_dir / 'replication.json'} and replication.md ({res['runtime_s']:.1f} s)")
    return res


def _relative(path: str) -> str:
    """``path`` relative to the project root when it lies inside it."""
    try:
        return str(Path(path).resolve().relative_to(DEFAULT_REPLICATE_CONFIG.parent.parent))
    except ValueError:
        return path


def _parameters(cfg: Config, sim: SimPlcConfig) -> dict[str, Any]:
    return {
        "friction": dataclasses.asdict(sim.friction),
        "model_friction": dataclasses.asdict(cfg.friction),
        "noise_std_n": sim.noise_std_n,
        "sensor_range_n": cfg.sensor.range_n,
        "adc_full_scale": cfg.sensor.adc_full_scale,
        "tension_limits_n": [sim.tension.min_n, sim.tension.max_n],
        "initial_mass_kg": sim.initial_mass_kg,
        "extrusion_kg_s": sim.extrusion_kg_s,
        "paper_path": dataclasses.asdict(sim.trajectory.paper),
        "cyclic": dataclasses.asdict(sim.trajectory.cyclic),
        "frame_anchors_m": [list(a) for a in cfg.geometry.frame_anchors_m],
        "platform_anchors_m": [list(b) for b in cfg.geometry.platform_anchors_m],
        "seed": sim.seed,
        "period_s": sim.period_s,
    }


def _row(name: str, st: dict[str, Any], paper: str) -> str:
    return f"| {name} | {st['mae_n']:.2f} | {st['std_n']:.2f} | {st['rmse_n']:.2f} | {paper} |"


def markdown(res: dict[str, Any]) -> str:
    """The human-readable report: parameters, why they are plausible, results vs paper."""
    p, w = res["parameters"], res["hysteresis_width_n"]
    fr = p["friction"]
    wraps = ", ".join(f"{q['wrap_deg']:g} deg (mu {q['mu']:g})" for q in fr["pulleys"])
    lines = [
        "# Replication of the paper's experiment (sec. IV)",
        "",
        f"Generated by `cdpr-gateway replicate` from `{res['config']}`; simulated "
        f"{res['seconds']['path']:.1f} s of the eq. 20 path (twice: with extrusion and at "
        f"constant mass) and {res['seconds']['cyclic']:.1f} s of cyclic 6-DOF motion.",
        "",
        "## Parameters and why they are plausible",
        "",
        f"- Sensors: {p['sensor_range_n']:g} N range, S7 analog format 0..{p['adc_full_scale']}"
        f" (resolution {p['sensor_range_n'] / p['adc_full_scale']:.4f} N), Gaussian noise "
        f"std {p['noise_std_n']} N = 0.1 % of range: what a strain-gauge amplifier with a "
        "15-bit converter achieves at 1 kHz bandwidth.",
        f"- Friction (truth and model, matched): {fr['model']}, pulleys {wraps}, "
        f"sigma {fr['sigma_n_m']:g} N/m (the paper's), beta {fr['beta']:g}. mu 0.015 is a "
        "ball-bearing pulley; with three pulleys the Coulomb gain is about 4.5 %, i.e. "
        f"up to {0.045 * res['tension_range_n'][1]:.0f} N at the "
        f"{res['tension_range_n'][0]:.0f}-{res['tension_range_n'][1]:.0f} N the upper "
        "cables carry (paper: 500 N sensors, tensions well inside).",
        f"- Load: {p['initial_mass_kg']:g} kg at the start (platform and concrete), extruder "
        f"{p['extrusion_kg_s']:g} kg/s while printing (mass {res['mass_kg']['start']:.1f} -> "
        f"{res['mass_kg']['end']:.1f} kg).",
        f"- Geometry: 4 x 3 x 3 m frame, 0.4 x 0.3 x 0.2 m platform (physics.md sec. 4), "
        "cables crossed (uncrossed, this aspect ratio gives a singular structure matrix); tension"
        f" distribution limits {p['tension_limits_n'][0]:g}..{p['tension_limits_n'][1]:g} N "
        "(mid-range objective eq. 18/19) so that readings stay inside the 500 N range.",
        f"- Path: eq. 20 with u in [{p['paper_path']['u_start']:g}, "
        f"{p['paper_path']['u_end']:g}] (y = 15 (15 - u) ends at 0), centred on the home "
        f"pose, {p['paper_path']['layers']} layers, {p['paper_path']['speed_m_s']:g} m/s.",
        "",
        "## Results (platform-tension error, N; |error| mean, its std, RMSE)",
        "",
        f"Noise floor (reading minus noiseless sensor tension, RMS): {res['noise_floor_n']:.3f} N.",
        "",
        "| estimate | MAE | std | RMSE | paper |",
        "|---|---|---|---|---|",
        _row("uncompensated", res["uncompensated"], "-"),
        _row("Coulomb", res["coulomb"], "10.58 +/- 3.37"),
        _row("Dahl", res["dahl"], "7.26 +/- 1.56"),
        "",
        f"- Dahl vs uncompensated (MAE): {100 * res['improvement_dahl_vs_uncompensated']:.1f} %"
        " better (paper: 65 %); under changing load "
        f"{100 * res['changing_load_improvement']:.1f} %, at constant mass "
        f"{100 * res['constant_load_improvement']:.1f} % (paper: ~40 % under changing loads).",
        f"- Coulomb vs uncompensated: "
        f"{100 * res['improvement_coulomb_vs_uncompensated']:.1f} % better.",
        f"- Wrench hysteresis width along z (cyclic motion): before {w['before']:.2f} N, "
        f"Coulomb {w['coulomb']:.2f} N, after (Dahl) {w['after']:.2f} N, truth "
        f"{w['truth']:.2f} N (paper: down to 5 N).",
        "",
        "## Goals",
        "",
        "| goal | value | target | met |",
        "|---|---|---|---|",
    ]
    for name, g in res["goals"].items():
        val = g["value"]
        if val is None:
            text = g["why"]
        else:
            text = ", ".join(f"{v:.3f}" for v in val) if isinstance(val, list) else f"{val:.3f}"
        lines.append(f"| {name} | {text} | {g['target']} | {'yes' if g['met'] else 'NO'} |")
    lines += [
        "",
        "## Why it beats the paper, and what that does and does not show",
        "",
        "The model here is matched: the plant's truth friction is the model the gateway "
        "compensates with, and the setpoint velocity equals the actual one. What remains is "
        "sensor noise and quantisation: the Dahl states move with cable travel, not with the "
        "noise, so the noise passes through the compensation unchanged (Dahl RMSE / noise "
        f"floor = {res['dahl_rmse_over_noise_floor']:.3f}). The paper's "
        "real pulleys differ from any model (unmodelled stiction, rope bending, temperature), "
        "which is what its 7.26 N residual measures. Use `cdpr-gateway diagnose` on a "
        "recording with a concealed effect to see how a mismatch shows.",
        "",
        f"Coulomb compensation leaves a hysteresis of {w['coulomb']:.1f} N: it flips its "
        "correction the instant a cable reverses, while the true friction passes through "
        "pre-sliding over about 2 F_R / sigma (~1-3 cm) of cable travel, so near the turning "
        "points it over-corrects with the opposite sign (visible in `hysteresis.png`). Its "
        "mean error is small because most of the path is steady sliding; its spread is large "
        "for the same reason.",
        "",
        "Plots: " + ", ".join(f"`{n}`" for n in res["plots"]),
        "",
    ]
    return "\n".join(lines)


def run_command(command: str, args: argparse.Namespace) -> int:
    if args.seconds is not None and not args.seconds > 0:
        raise ConfigError("--seconds: must be > 0")
    out = output_dir(args.out, "--out")  # before the work
    cfg = load_config(args.config)
    res = replicate(cfg, out, args.seconds, plots=not args.no_plots)
    for name, goal in res["goals"].items():
        verdict = "met" if goal["met"] else "MISSED"
        _log(f"goal {name}: {verdict} ({goal.get('why', goal['value'])})")
    missed = [name for name, goal in res["goals"].items() if not goal["met"]]
    if missed:
        _log(f"error: goal missed: {', '.join(missed)} (exit status 1)")
        return 1
    return 0
