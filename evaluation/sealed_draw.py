"""Drawing the sealed scenarios (``evaluation/scenarios_sealed.yaml``) once, from a seed.

The tuning suite (``scenarios.yaml``) fixes one motion (the oscillation), 1 kHz, 0.4 N of
noise and mostly two cables. The sealed draw gives each tuning scenario a twin with every
generator setting the suite has changed: point-to-point moves (two in three), rates of
250-2000 Hz, noise of 0.25-0.6 N, one to four cables (a rig stays a rig), uneven sampling
(one in five), other seeds; and its effects at other sizes: each parameter's change from
its absent value (the registry's ``neutral``) times 0.7-1.5, or the value itself where that
would leave it under half or over twice its tuning size (a speed scale, not a correction),
or where the absent value is infinite (a stiffness); a phase drawn anew; a position (a
length with an absolute tolerance) moved by up to twice its tolerance either way. A twin on
the soft PLC's plant keeps the plant and draws its sizes and seed. Code that serves every
effect: no effect is named here.

``python -m evaluation.scenarios_table --seal SEED`` writes the file; a new draw is a reseal
(:mod:`evaluation.sealing`): the doc records the new hash and why. A scenario that joins the
tuning suite later gets its twin alone (``--twin NAME --seal SEED``, :func:`append`): drawn
by the same code from its own seed and appended, the other twins (and their published
results) untouched; the reseal records it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evaluation.scenarios import SUITE_FILE, Scenario, suite, tolerance
from evaluation.sealing import append_case, case_line
from gateway.diagnose.prepare import nominal_from
from gateway.model import effects as fx

Draw = dict[str, Any]
APPENDED: tuple[tuple[str, int], ...] = (("coulomb_load", 2026112901),)
"""The twins appended to the sealed file after its draw, in order: (tuning scenario, seed
of :func:`twin`)."""


def _value(
    param: fx.Param, tuning: float, neutral: float, f: float, rng, tol: tuple[str, float] | None
) -> float:
    if param.unit == "rad":
        return float(rng.uniform(0.0, 2.0 * math.pi))
    if tuning == neutral:  # absent on this cable: stays absent
        return tuning
    if param.unit == "m" and tol is not None and tol[0] == "abs":
        # a position (a length checked to within an absolute tolerance), not a size
        return tuning + float(rng.uniform(-2.0, 2.0)) * tol[1]
    if not math.isfinite(neutral):  # absent at infinity (a stiffness): the size itself
        return tuning * f
    value = neutral + (tuning - neutral) * f
    if tuning > 0 and not 0.5 * tuning <= value <= 2.0 * tuning:
        value = tuning * f
    return value


def effects_draw(sc: Scenario, cables: int, rng: np.random.Generator) -> Draw:
    """``sc``'s effects at other sizes (module docstring), per-cable lists over ``cables``."""
    nom = nominal_from(sc.nominal())
    out: Draw = {}
    for name, params in sc.effects.items():
        eff = fx.REGISTRY[name]
        neutral = eff.neutral(nom)
        drawn: Draw = {}
        for p in eff.params:
            if p.name not in params:
                continue
            given = params[p.name]
            f = float(rng.uniform(0.7, 1.5))
            tol = tolerance(name, p.name)
            if isinstance(given, tuple):
                per = [
                    _value(p, float(given[i % len(given)]), neutral[p.name], f, rng, tol)
                    for i in range(cables)
                ]
                drawn[p.name] = [round(x, 6) for x in per]
            else:
                drawn[p.name] = round(_value(p, float(given), neutral[p.name], f, rng, tol), 6)
        out[name] = drawn
    return out


def _settings(sc: Scenario, rng: np.random.Generator, seed: int) -> Draw:
    """Generator settings other than the tuning suite's (``sc``'s rig or plant kept)."""
    if sc.plant:
        return {
            "plant": True,
            "cables": sc.cables,
            "seconds": sc.seconds,
            "slow": sc.slow,
            "seed": seed,
        }
    out: Draw = {
        "seed": seed,
        "motion": "moves" if rng.uniform() < 2 / 3 else "oscillation",
        "rate_hz": float(rng.choice([250.0, 500.0, 1000.0, 2000.0])),
        "noise_n": round(float(rng.uniform(0.25, 0.6)), 3),
    }
    if sc.rig:
        out["rig"] = True
    else:
        out["cables"] = int(rng.choice([1, 2, 3, 4]))
    if rng.uniform() < 0.2:
        out["uneven"] = True
    if sc.nominal_model != Scenario.nominal_model:
        out["nominal_model"] = sc.nominal_model
    if not sc.edges:
        out["edges"] = False
    return out


def _twin(sc: Scenario, rng: np.random.Generator, seed: int) -> Draw:
    """``sc``'s sealed twin with recording seed ``seed`` (module docstring)."""
    settings = _settings(sc, rng, seed)
    cables = 1 if settings.get("rig") else int(settings.get("cables", sc.cables))
    case: Draw = {"name": f"sealed_{sc.name}"}
    if sc.effects:
        case["effects"] = effects_draw(sc, cables, rng)
    return {**case, **settings}


def _base(seed: int) -> int:
    return seed % 997 * 10 + 1000  # far from the tuning seeds (and their +500, +1000)


def draw(seed: int) -> list[Draw]:
    """The sealed twins of the tuning scenarios for ``seed`` (module docstring)."""
    rng = np.random.default_rng(seed)
    return [_twin(sc, rng, _base(seed) + k) for k, sc in enumerate(suite())]


def twin(name: str, seed: int) -> Draw:
    """The twin of the tuning scenario ``name`` drawn alone from ``seed`` (:func:`draw`'s
    code; its recording seed is the one :func:`draw` of ``seed`` would give it)."""
    for k, sc in enumerate(suite()):
        if sc.name == name:
            return _twin(sc, np.random.default_rng(seed), _base(seed) + k)
    raise KeyError(f"{SUITE_FILE.name}: no scenario {name!r}")


def write(path: Path, seed: int) -> None:
    """Write the sealed file of ``seed`` (one flow-style line per case)."""
    header = (
        f"# The sealed diagnosis scenarios: drawn once from {SUITE_FILE.name} by `python -m "
        f"evaluation.scenarios_table --seal {seed}`\n# (evaluation/sealed_draw.py); scored like "
        "the "
        "tuning suite (its tolerances), never tuned on.\n# Not to be edited or redrawn "
        "quietly: docs/diagnose-suite.md records this file's SHA-256 (## Seals).\n"
        "scenarios:\n"
    )
    body = "".join(case_line(case) for case in draw(seed))
    path.write_text(header + body, encoding="utf-8")


def append(path: Path, name: str, seed: int) -> Draw:
    """Append the twin of the tuning scenario ``name`` drawn alone from ``seed``
    (:func:`twin`) to the sealed file, the twins before it untouched; refused if the file
    has it already."""
    case = twin(name, seed)
    with open(path, encoding="utf-8") as fh:
        names = {c["name"] for c in yaml.safe_load(fh)["scenarios"]}
    cmd = f"python -m evaluation.scenarios_table --twin {name} --seal {seed}"
    how = f"the twin of {name} by `{cmd}`"
    append_case(path, case, names, how)
    return case
