"""The sealed foreign cases (``tests/foreign_sealed.yaml``): drawn once from a seed with
generator settings the tuning cases (:data:`tests.foreign_cases.CASES`) do not use, scored
by the same strict rules, never tuned on.

The draw varies what the independent generator (:mod:`tests.diagnose_helpers`) offers:
1-4 pulleys of other wraps and coefficients, the Coulomb or the Dahl chain, 200-1000 Hz,
timing jitter, five noise kinds at 0.15-0.5 N, point-to-point or positioning moves, 1-3
cables, loads of 150-400 N; one case per effect at about the scenario suite's sizes
(0.7-1.5x, either sign where the effect has one), four pairs, four clean recordings.
Tolerances: the scenario suite's (``evaluation/scenarios.yaml``), as ``(value, rel, abs)``.
Eccentricity is checked on its amplitude and radius only, a spring on its stiffness only:
the generator's travel starts at its fine grid's origin, not at the recording's first row,
so a phase or a length has another zero. Maxwell-slip, backlash and cable stretch are
drawn on the Dahl chain (they act on its presliding state).

``python -m tests.foreign_cases --seal SEED`` writes the file; a new draw is a reseal
(:mod:`evaluation.sealing`). An effect that joins the catalogue later gets one case of its
own, appended (``--append EFFECT --seal SEED``, :func:`append`) from its own seed by the
same draw code, so the cases drawn before, and their published results, stay as they were:
the file is :func:`draw` of :data:`FIRST_SEED` followed by :data:`APPENDED`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evaluation.scenarios import tolerance
from evaluation.sealing import append_case, case_line

SEALED_FILE = Path(__file__).with_name("foreign_sealed.yaml")
SINGLE = (
    "viscous",
    "coulomb",
    "presliding",
    "stribeck",
    "inertia",
    "delay",
    "lowpass",
    "gain",
    "offset",
    "drift",
    "eccentricity",
    "coulomb_directional",
    "maxwell_slip",
    "backlash",
    "cable_stretch",
    "sensor_creep",
    "spring",
)
TRAVEL_DRIVEN = ("maxwell_slip", "backlash", "cable_stretch")
"""Effects on the presliding state the travel drives: drawn on a Dahl chain (the nominal
a Coulomb chain has no such state for them to act on, docs/physics.md sec. 4)."""
PAIRS = (("viscous", "offset"), ("coulomb", "gain"), ("lowpass", "drift"), ("inertia", "viscous"))
FIRST_SEED = 20261127
"""The seed of :func:`draw` the file's first cases come from."""
APPENDED: tuple[tuple[tuple[str, ...], int], ...] = ((("coulomb_load",), 2026112901),)
"""The cases appended after the first draw, in order: (effects, seed of :func:`draw_case`)."""


def _size(rng: np.random.Generator) -> float:
    return float(rng.uniform(0.7, 1.5))


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.uniform() < 0.5 else -1.0


def _effect(name: str, rng: np.random.Generator, mu_mean: float) -> dict[str, float]:
    r = lambda x: round(float(x), 6)  # noqa: E731
    draws = {
        "viscous": lambda: {"c_ns_m": r(6.0 * _size(rng))},
        "coulomb": lambda: {
            "mu": r(mu_mean * (1 + 0.1 * _sign(rng) * _size(rng))),
            "f0_n": r(rng.uniform(0.3, 1.0)),
        },
        "presliding": lambda: {"sigma_n_m": r(400.0 * _size(rng))},
        "stribeck": lambda: {"k": r(0.5 * _size(rng)), "v_s_m_s": r(0.01 * _size(rng))},
        "inertia": lambda: {"m_eff_kg": r(2.0 * _size(rng))},
        "delay": lambda: {"d_s": r(0.004 * _size(rng))},
        "lowpass": lambda: {"tau_s": r(0.004 * _size(rng))},
        "gain": lambda: {"g": r(0.002 * _sign(rng) * _size(rng))},
        "offset": lambda: {"c_n": r(0.25 * _sign(rng) * _size(rng))},
        "drift": lambda: {"k_n_s": r(0.012 * _sign(rng) * _size(rng))},
        "eccentricity": lambda: {
            "a_n": r(0.4 * _size(rng)),
            "r_m": r(0.03 * _size(rng)),
            "phi_rad": r(rng.uniform(0.0, 2 * math.pi)),
        },
        "coulomb_directional": lambda: _directional(rng, mu_mean),
        "maxwell_slip": lambda: {"sigma_n_m": r(3000.0 * _size(rng)), "w": r(0.5 * _size(rng))},
        "backlash": lambda: {"width_m": r(0.002 * _size(rng))},
        "cable_stretch": lambda: {"k_n_m": r(2000.0 * _size(rng))},
        "sensor_creep": lambda: {
            "c": r(0.04 * _sign(rng) * _size(rng)),
            "tau_s": r(0.4 * _size(rng)),
        },
        "spring": lambda: {"k_n_m": r(4.0 * _size(rng)), "l0_m": r(rng.uniform(-0.3, 0.3))},
        "coulomb_load": lambda: {"mu1_per_n": r(2e-5 * _size(rng))},
    }
    return draws[name]()


def _directional(rng: np.random.Generator, mu_mean: float) -> dict[str, float]:
    """Paying out and hauling in each off the pulleys' mean, in opposite senses (the
    tuning case's +17 % and -10 %, each 0.7-1.5x, either way round)."""
    s = _sign(rng)
    return {
        "mu_out": round(mu_mean * (1 + s * 0.17 * _size(rng)), 6),
        "mu_in": round(mu_mean * (1 - s * 0.1 * _size(rng)), 6),
    }


def _machine(rng: np.random.Generator, seed: int) -> dict[str, Any]:
    n = int(rng.integers(1, 5))
    pulleys = [
        [round(float(rng.uniform(20, 150)), 1), round(float(rng.uniform(0.01, 0.03)), 4)]
        for _ in range(n)
    ]
    out: dict[str, Any] = {
        "seed": seed,
        "pulleys": pulleys,
        "model": str(rng.choice(["dahl", "coulomb"])),
        "rate_hz": float(rng.choice([200.0, 250.0, 500.0, 1000.0])),
        "noise": str(rng.choice(["white", "coloured", "hum", "quant", "mixed"])),
        "noise_n": round(float(rng.uniform(0.15, 0.5)), 3),
        "motion": str(rng.choice(["moves", "positioning"])),
        "cables": int(rng.integers(1, 4)),
        "tension": round(float(rng.uniform(150.0, 400.0)), 1),
    }
    if rng.uniform() < 0.3:
        out["jitter_s"] = round(float(rng.uniform(1e-4, 8e-4)), 6)
    return out


def _truth(effects: dict[str, dict[str, float]], mu_mean: float) -> dict[str, dict[str, list]]:
    """(value, rel, abs) per checked parameter, from the scenario suite's tolerances."""
    out: dict[str, dict[str, list]] = {}
    for name, params in effects.items():
        checked = {}
        for param, value in params.items():
            kind, tol = tolerance(name, param) or ("rel", 0.2)
            if (name, param) in (("eccentricity", "phi_rad"), ("spring", "l0_m")):
                continue  # another zero of the travel (module docstring)
            if kind == "abs":
                checked[param] = [value, 0.0, tol]
            elif kind == "change":
                checked[param] = [value, 0.0, round(tol * abs(value - mu_mean), 8)]
            else:
                checked[param] = [value, tol, 0.0]
        out[name] = checked
    return out


def _case(rng: np.random.Generator, seed: int, combo: tuple[str, ...], name: str) -> dict:
    """One case: a machine of recording seed ``seed`` with ``combo``'s effects."""
    fo = _machine(rng, seed)
    mu_mean = float(np.mean([p[1] for p in fo["pulleys"]]))
    effects = {e: _effect(e, rng, mu_mean) for e in combo}
    if "presliding" in effects:
        fo["model"] = "coulomb"  # the nominal model knows no pre-sliding state
    if any(e in effects for e in TRAVEL_DRIVEN):
        fo["model"] = "dahl"
    if effects:
        fo["effects"] = effects
    return {"name": name, "foreign": fo, "truth": _truth(effects, mu_mean)}


def _seeds(seed: int) -> range:
    return range(seed % 991 * 10 + 3000, seed % 991 * 10 + 4000)


def draw(seed: int) -> list[dict[str, Any]]:
    """The sealed foreign cases of ``seed`` (module docstring)."""
    rng = np.random.default_rng(seed)
    seeds = iter(_seeds(seed))
    combos = [(e,) for e in SINGLE] + list(PAIRS) + [()] * 4
    cases = []
    for k, combo in enumerate(combos):
        name = "sealed_" + (
            "+".join(combo) if combo else f"clean_{k - len(SINGLE) - len(PAIRS) + 1}"
        )
        cases.append(_case(rng, next(seeds), combo, name))
    return cases


def draw_case(combo: tuple[str, ...], seed: int) -> dict[str, Any]:
    """One case of ``combo``'s effects drawn alone from ``seed`` (:func:`draw`'s code: the
    machine, the sizes, the truth), for an effect that joins the catalogue later."""
    rng = np.random.default_rng(seed)
    return _case(rng, _seeds(seed)[0], combo, "sealed_" + "+".join(combo))


def expected(first_seed: int = FIRST_SEED) -> list[dict[str, Any]]:
    """The file's cases as the draw code gives them: the first draw, then the appended."""
    return draw(first_seed) + [draw_case(combo, seed) for combo, seed in APPENDED]


def write(path: Path, seed: int) -> None:
    header = (
        f"# The sealed foreign cases: drawn once by `python -m tests.foreign_cases --seal {seed}`"
        "\n# (tests/foreign_sealed.py), scored like the tuning cases, never tuned on. Not to "
        "be edited or redrawn\n# quietly: docs/diagnose-suite.md records this file's SHA-256 "
        "(## Seals).\ncases:\n"
    )
    body = "".join(case_line(case) for case in draw(seed))
    path.write_text(header + body, encoding="utf-8")


def append(path: Path, effect: str, seed: int) -> dict[str, Any]:
    """Append one case of ``effect`` drawn alone from ``seed`` (:func:`draw_case`), the
    cases before it untouched; refused if the file has a case of that name. List
    ``((effect,), seed)`` in :data:`APPENDED` so that :func:`expected` gives the file."""
    case = draw_case((effect,), seed)
    how = f"one case of {effect} by `python -m tests.foreign_cases --append {effect} --seal {seed}`"
    append_case(path, case, {c["name"] for c in load(path)}, how)
    return case


def load(path: Path = SEALED_FILE) -> list[dict[str, Any]]:
    with open(path, encoding="utf-8") as fh:
        return list(yaml.safe_load(fh)["cases"])
