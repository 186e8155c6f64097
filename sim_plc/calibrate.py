"""``cdpr-gateway calibrate --config SIM.yaml [--seconds N] [--runs R] --out DIR``: the
real-robot loop, closed on the soft PLC.

The soft PLC (a ``sim-plc`` subprocess, as the demo starts it) runs SIM.yaml's plant with
its concealed effects (``sim_plc.effects``, ``sim_plc.distribution``); the gateway sees
only what a real robot gives it. Four steps, one progress line each (and one per second
while the gateway runs):

1. **noise floor**: the same plant without its concealed effects, the gateway with the
   nominal model, N s: the corrected-tension RMSE the nominal machinery reaches when the
   model is right (sensor noise through the chain, the loop's timing).
2. **before**: the plant with its effects, the gateway with the nominal model, N s,
   recording what it saw (``DIR/before.csv.gz``, as ``run --record`` does).
3. **diagnose** the recording as a real robot would need it: the wrench reference (any
   ``tension_platform_i`` columns dropped; the gateway's own columns only; rows the
   gateway flagged or that repeat a PLC sample left out, :func:`gateway_rows`), report
   ``DIR/diagnosis.json``, fitted model ``DIR/fitted.yaml`` (:mod:`gateway.diagnose.writemodel`).
4. **after**: the plant with its effects, the gateway with ``DIR/fitted.yaml``, N s
   (``DIR/after.csv.gz``).

Each run is scored by the demo's observer of the loop (:class:`sim_plc.demo.TruthScorer`
on the soft PLC's side channel, never seen by the gateway): the RMSE of the corrected
tension against the plant's true platform tension over good channels (status 0), all
cables pooled. ``DIR/calibration.json`` holds ``before``, ``after``, ``noise_floor_n``,
``findings`` and ``reference``; a table goes to stdout. The gateway's side of the config
(``DIR/nominal.yaml``: SIM.yaml without ``sim_plc:``) is the nominal model; the plant of
step 1 is ``DIR/plant-clean.yaml``.

``--runs R`` (R > 1): step 2 records R runs, each another motion and noise draw of the same
plant -- run 1 SIM.yaml itself, run k ``DIR/plant-run-K.yaml``, SIM.yaml with
``sim_plc.seed`` and ``sim_plc.trajectory.random.seed`` raised by k - 1 (as ``record
--seed`` draws another recording of a machine; the motion differs with a ``random``
trajectory, the other kinds repeat theirs and only the noise differs) -- into
``DIR/before-K.csv.gz``; step 3 diagnoses them **jointly**, one set of findings for the
machine (:func:`gateway.diagnose.fromfiles.diagnose_file`, the path of
``diagnose REC REC ...`` for recordings without platform tensions): the first 75 % of every
run fitted, the last quarters of all runs joined as the validation; the report lists the
runs in ``recordings``. ``before`` in ``calibration.json`` is run 1 (the motion ``after``
repeats), ``before_runs`` every run's score. R = 1 is the four steps above, unchanged.
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
import yaml

from gateway.core.config import Config, load_config
from gateway.core.configtypes import read_yaml
from gateway.errors import GatewayError
from gateway.recordings.reader import Recording
from gateway.runtime.loop import CyclicService
from gateway.service.daemon import build_driver, start_recorder
from sim_plc import demo

BUS = "modbus_tcp"  # the truth side channel is a Modbus register block
MAX_RUNS = 20  # --runs: each is a gateway run of --seconds, one after another


@dataclasses.dataclass(frozen=True)
class RunScore:
    """One gateway run scored against the plant's truth (N)."""

    rmse_n: float
    raw_rmse_n: float
    per_cable_rmse_n: list[float]
    samples: int
    cycles: int
    overruns: int

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _check(cfg: Config, path: str) -> None:
    if cfg.bus.driver != BUS:
        raise GatewayError(f"{path}: bus.driver: calibrate needs modbus_tcp (the truth channel)")
    if cfg.bus.modbus_tcp.registers.platform_mass is None:
        raise GatewayError(
            f"{path}: bus.modbus_tcp.registers.platform_mass: not mapped; the wrench "
            "reference needs the platform mass in the recording"
        )


def _absolute_paths(sim: dict[str, Any], base: Path) -> dict[str, Any]:
    """``sim_plc`` with a trajectory file path made absolute (the copies live in DIR)."""
    traj = sim.get("trajectory")
    if isinstance(traj, dict) and isinstance(traj.get("file"), dict):
        p = traj["file"].get("path")
        if isinstance(p, str) and p and not Path(p).is_absolute():
            traj = {**traj, "file": {**traj["file"], "path": str((base / p).resolve())}}
            return {**sim, "trajectory": traj}
    return sim


def _write_yaml(path: Path, data: dict[str, Any], comment: str) -> None:
    try:
        path.write_text(f"# {comment}\n" + yaml.safe_dump(data, sort_keys=False), "utf-8")
    except OSError as exc:
        raise GatewayError(f"{path}: cannot write: {exc.strerror or exc}") from exc


def prepare_dir(config: str, out: Path) -> tuple[Path, Path]:
    """DIR/nominal.yaml (the gateway's side) and DIR/plant-clean.yaml (no hidden effects)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GatewayError(f"--out {out}: cannot create: {exc.strerror or exc}") from exc
    data = read_yaml(config)
    sim = _absolute_paths(dict(data.get("sim_plc") or {}), Path(config).resolve().parent)
    nominal, clean = out / "nominal.yaml", out / "plant-clean.yaml"
    gateway_side = {k: v for k, v in data.items() if k != "sim_plc"}
    _write_yaml(nominal, gateway_side, f"{config} without sim_plc: the gateway's nominal model")
    _write_yaml(
        clean,
        {**data, "sim_plc": {**sim, "effects": {}}},
        f"{config} with no concealed effects: the noise floor's plant",
    )
    return nominal, clean


def run_plants(config: str, runs: int, out: Path) -> list[str]:
    """The plant of each 'before' run (module docstring, ``--runs``): SIM.yaml, then
    ``DIR/plant-run-K.yaml`` with the seeds raised by K - 1."""
    from sim_plc.config import RandomConfig, SimPlcRaw

    if runs == 1:
        return [config]
    data = read_yaml(config)
    sim = _absolute_paths(dict(data.get("sim_plc") or {}), Path(config).resolve().parent)
    traj = dict(sim.get("trajectory") or {})
    motion = dict(traj.get("random") or {})
    seed, motion_seed = (
        int(sim.get("seed", SimPlcRaw.seed) or 0),
        int(motion.get("seed", RandomConfig.seed) or 0),
    )
    plants = [config]
    for k in range(1, runs):
        drawn = {**traj, "random": {**motion, "seed": motion_seed + k}}
        path = out / f"plant-run-{k + 1}.yaml"
        _write_yaml(
            path,
            {**data, "sim_plc": {**sim, "seed": seed + k, "trajectory": drawn}},
            f"{config} with sim_plc.seed and trajectory.random.seed + {k}: calibrate run {k + 1}",
        )
        plants.append(str(path))
    return plants


def run_scored(
    plant: Path | str, cfg: Config, seconds: float, label: str, record: Path | None = None
) -> RunScore:
    """The soft PLC on ``plant``, the gateway on ``cfg`` for ``seconds``, scored."""
    plc = demo.SoftPlc(str(plant), BUS)
    channel = recorder = None
    try:
        live = demo.with_port(cfg, BUS, plc.host, plc.port)
        service = CyclicService(live, build_driver(live))
        if record is not None:
            recorder = start_recorder(live, str(record))
            service.recorder = recorder
        mb = live.bus.modbus_tcp
        channel = demo.TruthChannel(mb.host, mb.port, mb.unit_id, cfg.cables)
        scorer = demo.TruthScorer(
            cfg.cables, channel, demo.TRUTH_EVERY_CYCLES, demo.ChainWarmup(cfg)
        )
        service.add_observer(scorer)
        demo.run_timed(service, seconds, label, sys.stderr)
    finally:
        if recorder is not None:
            recorder.close()
        if channel is not None:
            channel.close()
        plc.close()
    if recorder is not None and (recorder.failed or recorder.rows_written == 0):
        raise GatewayError(f"{record}: recording failed: {recorder.failed or 'no rows'}")
    score = scorer.score
    n = int(score.samples.sum())
    if n == 0:
        raise GatewayError(f"{label}: no true tensions received from the soft PLC")
    corrected = score.rmse()[1]
    return RunScore(
        rmse_n=math.sqrt(float(score.corrected_sq.sum()) / n),
        raw_rmse_n=math.sqrt(float(score.raw_sq.sum()) / n),
        per_cable_rmse_n=[float(x) for x in corrected],
        samples=n,
        cycles=service.stats.cycles,
        overruns=service.stats.overruns,
    )


def gateway_rows(rec: Recording) -> Recording:
    """The rows of a gateway recording that carry a new, good PLC sample: every
    ``status_i`` 0 (the gateway's own verdict; substituted and invalid rows repeat an old
    reading) and readings that changed since the previous row (a cycle that read the same
    PLC sample again adds nothing but a jittered time stamp)."""
    keep = np.ones(rec.samples, bool)
    for i in range(1, rec.cables + 1):
        status = rec.extra.get(f"status_{i}")
        if status is not None:
            keep &= status == 0
    keep[1:] &= np.any(np.diff(rec.tension_sensor, axis=0) != 0, axis=1)
    if keep.sum() < 10:
        raise GatewayError(f"{rec.source}: fewer than 10 rows with new, good readings")
    kept = rec.take(keep)
    return dataclasses.replace(
        kept,
        tension_platform=None,  # what a real robot has: no platform tensions
        skipped_rows=rec.skipped_rows + int(rec.samples - keep.sum()),
    )


VALIDATION_SHARE = 0.25  # the recording's last quarter: never fitted, scores the model


def split_validation(rec: Recording) -> tuple[Recording, Recording]:
    """(the first 75 % of the rows to fit, the last 25 % to validate on): the model is
    judged on motion it was not fitted on (:mod:`gateway.diagnose.heldout`)."""
    cut = round(rec.samples * (1.0 - VALIDATION_SHARE))
    return rec.take(np.arange(cut)), rec.take(np.arange(cut, rec.samples))


def diagnose_runs(recordings: list[Path], model: Path, report: Path, fitted: Path, say) -> dict:
    """Diagnose the runs of one plant against the wrench balance, jointly when several
    (:func:`gateway.diagnose.fromfiles.diagnose_file`): each run's rows with new, good
    readings (:func:`gateway_rows`), the first 75 % of every run fitted and the last
    quarters the validation (:func:`split_validation`); write the report, then the fitted
    model unless the held-out check refuses it (no 'after' run with a model that fits the
    noise); returns the report."""
    from gateway.diagnose.fromfiles import diagnose_file

    if len(recordings) > 1:
        say(f"fit on the first 75 % of {len(recordings)} runs, validate on their last quarters")
    run = diagnose_file(recordings, model, rows=gateway_rows, split=split_validation, progress=say)
    rep = run.report
    try:
        report.write_text(json.dumps(rep, indent=1), encoding="utf-8")
    except OSError as exc:
        raise GatewayError(f"{report}: cannot write: {exc.strerror or exc}") from exc
    where = "the recording's last quarter" if len(recordings) == 1 else "the runs' last quarters"
    run.write_model(fitted, where=f"{where}, not fitted")
    return rep


def _finding_text(f: dict) -> str:
    parts = []
    for name, values in f["parameters"].items():
        v = np.asarray(values, dtype=float)
        parts.append(
            f"{name} {np.median(v):.4g}" + (f" (median of {v.size})" if v.size > 1 else "")
        )
    return f"{f['effect']}: " + ", ".join(parts)


def table(result: dict[str, Any], config: str, seconds: float) -> str:
    floor = result["noise_floor_n"]
    rows = [
        f"calibrate: {config}, {seconds:g} s per run, reference {result['reference']}",
        "  findings: " + ("; ".join(result["finding_details"]) or "none"),
        "",
        "  run                        corrected RMSE N   raw RMSE N   x floor",
    ]
    runs = (
        ("noise_floor", "noise floor (no effects)"),
        ("before", "before (nominal model)"),
        ("after", "after (fitted model)"),
    )
    scored = [(result[key], title) for key, title in runs]
    if "before_runs" in result:  # --runs: every before run, diagnosed jointly
        scored[1:2] = [
            (r, f"before run {k + 1} (nominal)") for k, r in enumerate(result["before_runs"])
        ]
    for r, title in scored:
        rows.append(
            f"  {title:<26} {r['rmse_n']:16.3f}   {r['raw_rmse_n']:10.3f}   "
            f"{r['rmse_n'] / floor:7.2f}"
        )
    return "\n".join(rows)


def calibrate(config: str, seconds: float, out: Path, say, runs: int = 1) -> dict[str, Any]:
    """The four steps of the module docstring (``runs`` 'before' runs, diagnosed jointly);
    returns what calibration.json holds."""
    sim_cfg = load_config(config)
    _check(sim_cfg, config)
    nominal_path, clean_path = prepare_dir(config, out)
    plants = run_plants(config, runs, out)
    nominal = load_config(nominal_path)
    say(f"1/4 noise floor: plant without concealed effects, nominal model, {seconds:g} s")
    floor = run_scored(clean_path, nominal, seconds, "calibrate floor")
    befores, recorded = [], []
    for k, plant in enumerate(plants):
        name = "before.csv.gz" if runs == 1 else f"before-{k + 1}.csv.gz"
        which = "" if runs == 1 else f" run {k + 1}/{runs}"
        say(f"2/4 before{which}: plant {plant}, nominal model, recording {seconds:g} s")
        label = "calibrate before" + ("" if runs == 1 else f" {k + 1}/{runs}")
        befores.append(run_scored(plant, nominal, seconds, label, out / name))
        recorded.append(out / name)
    before = befores[0]
    what = "before.csv.gz" if runs == 1 else f"the {runs} runs jointly"
    say(f"3/4 diagnose {what} against the wrench balance")
    report = diagnose_runs(recorded, nominal_path, out / "diagnosis.json", out / "fitted.yaml", say)
    say(f"4/4 after: plant {config}, fitted model {out / 'fitted.yaml'}, {seconds:g} s")
    fitted = load_config(out / "fitted.yaml")
    after = run_scored(config, fitted, seconds, "calibrate after", out / "after.csv.gz")
    result = {
        "before": before.as_dict(),
        "after": after.as_dict(),
        "noise_floor_n": floor.rmse_n,
        "noise_floor": floor.as_dict(),
        "findings": [f["effect"] for f in report["findings"]],
        "finding_details": [_finding_text(f) for f in report["findings"]],
        "reference": report["reference"],
        "seconds": seconds,
        "config": config,
    }
    if runs > 1:
        result["runs"] = runs
        result["before_runs"] = [b.as_dict() for b in befores]
    try:
        (out / "calibration.json").write_text(json.dumps(result, indent=1), encoding="utf-8")
    except OSError as exc:
        raise GatewayError(f"{out / 'calibration.json'}: cannot write: {exc}") from exc
    return result


def run_command(command: str, args: argparse.Namespace) -> int:
    if not args.seconds > 0:
        raise GatewayError("--seconds: must be > 0")
    if not 1 <= args.runs <= MAX_RUNS:
        raise GatewayError(f"--runs: must be in 1..{MAX_RUNS}")
    start = time.perf_counter()

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    result = calibrate(args.config, args.seconds, args.out, say, args.runs)
    print(table(result, args.config, args.seconds))
    return 0
