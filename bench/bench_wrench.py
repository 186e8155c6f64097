"""Diagnosis against the wrench balance (no platform tensions): CPU seconds and peak RSS.

Two soft-PLC recordings, 1 kHz, 8 cables, pose and mass kept, ``tension_platform_i``
dropped (config/calibrate/viscous.yaml's plant: Pott's closed-form distribution, random
6-DOF motion, 0.5 N sensor noise): a clean one (no hidden effect) and one hiding viscous
15 N s/m on every cable. Each is written to Parquet and diagnosed by
``cdpr-gateway diagnose FILE --model config/default.yaml --json r.json`` under
``/usr/bin/time -v`` (CPU = user + system, peak RSS), one run at a time. Goal (issue 32
item 1): <= 60 s CPU and <= 300 MiB each on 10 min.

``WRENCH_SECONDS`` (default 600) the length; ``WRENCH_DIR`` keeps the recordings and the
reports there (made once, reused when present); ``WRENCH_CASES=clean`` or ``viscous``
runs one; ``WRENCH_AGAINST=/path/to/tree`` diagnoses each recording with that tree too,
alternating, ``WRENCH_REPEATS`` (default 1) times each, and prints both side by side with
their ratios and whether the two reports' findings agree (effects, cables, and each
parameter within the two runs' combined standard error).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
PLANT = HERE / "config" / "calibrate" / "viscous.yaml"
CASES = {"clean": {}, "viscous": {"viscous": {"c_ns_m": 15.0}}}


def make(path: Path, case: str, seconds: float) -> None:
    """The recording of ``case`` (:data:`CASES`) without platform tensions, at ``path``."""
    from gateway.core.config import config_from_mapping
    from gateway.core.configtypes import read_yaml
    from gateway.recordings.reader import write_recording
    from sim_plc.plant import make_recording

    data = read_yaml(PLANT)
    data["sim_plc"]["effects"] = CASES[case]
    cfg = config_from_mapping(data, str(PLANT))
    rec = make_recording(cfg, None, seconds)
    write_recording(path, replace(rec, tension_platform=None, source=str(path)))


def timed(tree: Path, path: Path, out: Path) -> tuple[float, float]:
    """CPU seconds (user + system) and peak RSS (MiB) of ``diagnose path`` run from
    ``tree``, its JSON report at ``out``."""
    import re

    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "gateway", "diagnose", str(path)]
    cmd += ["--model", "config/default.yaml", "--json", str(out), "--quiet"]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    cpu = re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)", done.stderr)
    if done.returncode not in (0, 1) or rss is None or len(cpu) != 2:
        raise RuntimeError(f"{tree}: diagnose {path} failed: {done.stderr[-800:]}")
    return float(cpu[0]) + float(cpu[1]), int(rss.group(1)) / 1024


def findings(report: dict) -> dict[str, dict]:
    """effect -> {cables, params: name -> (values per cable, stderr per cable)}."""
    out = {}
    for f in report["findings"]:
        params = {}
        for name, vals in f.get("parameters", {}).items():
            se = f.get("stderr", {}).get(name)
            params[name] = (vals, se)
        out[f["effect"]] = {"cables": f["cables"], "params": params}
    return out


def agree(a: dict, b: dict) -> list[str]:
    """What differs between two reports' findings (empty: the same effects on the same
    cables, each parameter within 2 combined standard errors)."""
    fa, fb = findings(a), findings(b)
    diffs = []
    if set(fa) != set(fb):
        return [f"effects {sorted(fa)} vs {sorted(fb)}"]
    for eff, x in fa.items():
        y = fb[eff]
        if x["cables"] != y["cables"]:
            diffs.append(f"{eff}: cables {x['cables']} vs {y['cables']}")
            continue
        for name, (va, sa) in x["params"].items():
            vb, sb = y["params"].get(name, (None, None))
            for i, (p, q) in enumerate(zip(_list(va), _list(vb), strict=False)):
                s = math.hypot(_at(sa, i), _at(sb, i))
                if not (abs(p - q) <= 2 * s or abs(p - q) <= 1e-9 * max(abs(p), 1.0)):
                    diffs.append(f"{eff}.{name}[{i}]: {p:.4g} vs {q:.4g} (2 se {2 * s:.2g})")
    return diffs


def _list(v) -> list[float]:
    return [float(x) for x in v] if isinstance(v, list) else [float(v)]


def _at(se, i: int) -> float:
    if se is None:
        return 0.0
    return float(se[i]) if isinstance(se, list) else float(se)


def summary(report: dict) -> str:
    parts = []
    for eff, f in findings(report).items():
        vals = "; ".join(
            f"{n} " + ", ".join(f"{x:.3g}" for x in _list(v)) for n, (v, _) in f["params"].items()
        )
        parts.append(f"{eff} on {f['cables']} ({vals})")
    return ", ".join(parts) or "none"


def run() -> None:
    seconds = float(os.environ.get("WRENCH_SECONDS", "600"))
    cases = os.environ.get("WRENCH_CASES", ",".join(CASES)).split(",")
    against = os.environ.get("WRENCH_AGAINST")
    repeats = int(os.environ.get("WRENCH_REPEATS", "1"))
    keep = os.environ.get("WRENCH_DIR")
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(keep or tmp)
        where.mkdir(parents=True, exist_ok=True)
        for case in cases:
            path = where / f"{case}-{seconds:g}s.parquet"
            if not path.exists():
                make(path, case, seconds)
            trees = [HERE] if not against else [Path(against).resolve(), HERE]
            reports: dict[Path, dict] = {}
            figures: dict[Path, list[tuple[float, float]]] = {t: [] for t in trees}
            for _ in range(repeats):
                for k, tree in enumerate(trees):
                    out = (
                        where
                        / f"{case}-{seconds:g}s.{'before' if k < len(trees) - 1 else 'after'}.json"
                    )
                    figures[tree].append(timed(tree, path, out))
                    reports[tree] = json.loads(out.read_text())
                    cpu, rss = figures[tree][-1]
                    print(
                        f"   {case} {seconds:g} s, {tree}: CPU {cpu:.1f} s, peak RSS {rss:.0f} MiB",
                        flush=True,
                    )
            for tree in trees:
                cpu = min(c for c, _ in figures[tree])
                rss = max(m for _, m in figures[tree])
                print(
                    f"   {case} ({seconds:g} s x 1 kHz x 8 cables) {tree}: CPU {cpu:.1f} s "
                    f"(goal <= 60), peak RSS {rss:.0f} MiB (goal <= 300); found "
                    f"{summary(reports[tree])}"
                )
            if against:
                old, new = trees
                ratio_cpu = min(c for c, _ in figures[new]) / min(c for c, _ in figures[old])
                ratio_rss = max(m for _, m in figures[new]) / max(m for _, m in figures[old])
                diffs = agree(reports[old], reports[new])
                print(
                    f"   {case}: CPU ratio {ratio_cpu:.2f}, RSS ratio {ratio_rss:.2f} "
                    f"(this tree / {old}); findings "
                    + ("agree" if not diffs else "DIFFER: " + "; ".join(diffs))
                )


if __name__ == "__main__":
    run()
