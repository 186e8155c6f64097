"""``cdpr-gateway calibrate`` over every example of ``config/calibrate/``.

Each example (every file of ``config/calibrate/``) hides one effect at 2-5x the 0.5 N
sensor noise (``viscous_60`` and the ``*_large`` ones at 7-12x) in a soft PLC whose
controller distributes tensions by the closed form (not the gateway's statics). Per
example: the finding, the corrected-tension RMSE against the plant's truth before and after
calibration (each cable scored once the gateway's chain has warmed up,
:class:`sim_plc.truth.ChainWarmup`), the noise floor (the same plant without the effect,
nominal model), after / floor (goal <= 1.15) and the gateway's cycles in each run (30 000
in 30 s on an idle machine: fewer means the machine was loaded, and the RMSE of a run then
varies by tens of per cent).

``python -m bench calibrate`` (30 s per run, three runs per example: ~45 min for the 18
examples); ``CALIBRATE_SECONDS`` and ``CALIBRATE_ONLY=viscous,gain`` change that. Results stay in
``$CALIBRATE_OUT`` (default: a temporary directory, removed afterwards).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from gateway.core.configtypes import read_yaml
from sim_plc.calibrate import calibrate

EXAMPLES = Path(__file__).resolve().parent.parent / "config" / "calibrate"
GOAL = 1.15


def examples() -> dict[str, str]:
    """Example name -> the effect it hides (its one ``sim_plc.effects`` entry)."""
    out = {}
    for path in sorted(EXAMPLES.glob("*.yaml")):
        (effect,) = read_yaml(path)["sim_plc"]["effects"]
        out[path.stem] = effect
    return out


def _row(name: str, res: dict) -> str:
    floor = res["noise_floor_n"]
    ratio = res["after"]["rmse_n"] / floor
    want = examples()[name]
    found = ", ".join(res["findings"]) or "none"
    ok = "ok" if want in res["findings"] and ratio <= GOAL else "FAIL"
    cycles = "/".join(str(res[k]["cycles"]) for k in ("noise_floor", "before", "after"))
    return (
        f"| {name:<11} | {found:<18} | {res['before']['rmse_n']:6.3f} | "
        f"{res['after']['rmse_n']:6.3f} | {floor:6.3f} | {ratio:5.2f} | {ok} | {cycles} |"
    )


def run() -> None:
    seconds = float(os.environ.get("CALIBRATE_SECONDS", "30"))
    only = [n for n in os.environ.get("CALIBRATE_ONLY", "").split(",") if n]
    names = [n for n in examples() if not only or n in only]
    keep = os.environ.get("CALIBRATE_OUT")
    tmp = None if keep else tempfile.TemporaryDirectory(prefix="bench-calibrate-")
    base = Path(keep) if keep else Path(tmp.name)  # type: ignore[union-attr]
    rows = []
    try:
        for name in names:
            start = time.perf_counter()

            def say(msg: str, name: str = name, start: float = start) -> None:
                print(f"  [{name} {time.perf_counter() - start:5.0f} s] {msg}", flush=True)

            res = calibrate(str(EXAMPLES / f"{name}.yaml"), seconds, base / name, say)
            rows.append(_row(name, res))
            print(rows[-1], flush=True)
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(
        f"\ncalibrate, {seconds:g} s per run (before/after/floor: corrected-tension RMSE "
        f"vs the plant's truth, N; ratio = after / floor, goal <= {GOAL})"
    )
    print(
        "| effect      | finding            | before |  after |  floor | ratio |    | cycles "
        "floor/before/after |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r)
