"""The foreign-generator cases, strictly scored, and their table.

Each case is a recording of the independent generator (:mod:`tests.diagnose_helpers`,
never :mod:`gateway.model` physics) with its truth. A case passes only with the exact set
of effects (an extra finding fails it), on the right cables, every parameter within its
tolerance, and the held-out (and, with validation, the validation) RMSE lowered.

``python -m tests.foreign_cases --table docs/diagnose-suite.md`` runs every case, the tuning
ones (:data:`CASES`) and the sealed ones (:mod:`tests.foreign_sealed`), and writes their
sections of the file (the rest is kept).
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from evaluation import sealing
from evaluation.scenarios import substitutes
from evaluation.suitedoc import replace_section
from tests import foreign_sealed
from tests.diagnose_helpers import Foreign, run_foreign

P5_MIXED = ((30.0, 0.01), (60.0, 0.02), (90.0, 0.015), (45.0, 0.03), (20.0, 0.01))
RIG_AXIS = {
    "inertia": {"m_eff_kg": 95.0},
    "viscous": {"c_ns_m": 200.0},
    "coulomb": {"f0_n": 20.0},
    "offset": {"c_n": -3.0},
}


@dataclass(frozen=True)
class Case:
    """A foreign recording, the nominal model it is diagnosed against, and the truth.

    ``truth``: effect -> {reported parameter: (value, relative tolerance, absolute
    tolerance)}; ``cables``: effect -> 1-based cables (default: all)."""

    name: str
    fo: Foreign
    truth: dict[str, dict[str, tuple[float, float, float]]]
    nominal: str | None = None
    pulleys: tuple | None = None
    validate: bool = False
    cables: dict[str, list[int]] = field(default_factory=dict)
    note: str = ""


CASES = (
    Case(
        "rig_no_pulleys_f0",
        Foreign(
            rig=True, tension=150.0, pulleys=(), model="coulomb", effects={"coulomb": {"f0_n": 5.0}}
        ),
        {"coulomb": {"f0_n": (5.0, 0.05, 0.0)}},
        nominal="none",
        pulleys=(),
        note="1: nominal `none` without pulleys (crashed)",
    ),
    Case(
        "rig_positioning_axis",
        Foreign(
            rig=True,
            tension=150.0,
            pulleys=(),
            model="coulomb",
            motion="positioning",
            vmax=0.13,
            seconds=40.0,
            rate_hz=500.0,
            effects=RIG_AXIS,
        ),
        {
            "inertia": {"m_eff_kg": (95.0, 0.05, 0.0)},
            "viscous": {"c_ns_m": (200.0, 0.05, 0.0)},
            "coulomb": {"f0_n": (20.0, 0.05, 0.0)},
            "offset": {"c_n": (-3.0, 0.1, 0.3)},
        },
        nominal="none",
        pulleys=(),
        validate=True,
        note="2: greedy dead end",
    ),
    Case(
        "offset_drift_cancel",
        Foreign(model="coulomb", effects={"offset": {"c_n": 0.45}, "drift": {"k_n_s": -0.03}}),
        {"offset": {"c_n": (0.45, 0.2, 0.05)}, "drift": {"k_n_s": (-0.03, 0.2, 0.0)}},
        note="3: offset and drift cancel in the mean",
    ),
    Case(
        "jitter_200hz_viscous",
        Foreign(rate_hz=200.0, jitter_s=8e-4, effects={"viscous": {"c_ns_m": 300.0}}),
        {"viscous": {"c_ns_m": (300.0, 0.05, 0.0)}},
        note="4: 200 Hz, +-0.8 ms jitter",
    ),
    Case(
        "jitter_noise_free_100hz",
        Foreign(rate_hz=100.0, jitter_s=2e-3, noise_n=0.0),
        {},
        note="4: noise-free, 100 Hz +-2 ms",
    ),
    Case(
        "jitter_noise_free_250hz",
        Foreign(rate_hz=250.0, jitter_s=8e-4, noise_n=0.0, seed=5),
        {},
        note="4: noise-free, 250 Hz +-0.8 ms",
    ),
    Case(
        "p5_viscous_validate",
        Foreign(pulleys=P5_MIXED, effects={"viscous": {"c_ns_m": 80.0}}),
        {"viscous": {"c_ns_m": (80.0, 0.1, 0.0)}},
        validate=True,
        note="5: no finding that does not generalise",
    ),
    Case(
        "p5_viscous_no_validate",
        Foreign(pulleys=P5_MIXED, effects={"viscous": {"c_ns_m": 80.0}}, seed=4),
        {"viscous": {"c_ns_m": (80.0, 0.1, 0.0)}},
        note="5: the same without --validate",
    ),
    Case(
        "clipped_cable2",
        Foreign(cables=2, clip_n=480.0, clip_cables=(2,), effects={"viscous": {"c_ns_m": 300.0}}),
        {"viscous": {"c_ns_m": (300.0, 0.05, 0.0)}},
        note="7: cable 2 clipped at 480 N",
    ),
    Case(
        "dahl_f0",
        Foreign(effects={"coulomb": {"f0_n": 3.0}}),
        {"coulomb": {"f0_n": (3.0, 0.1, 0.0), "mu": (0.02, 0.1, 0.0)}},
        note="8: f0 under Dahl",
    ),
)


def sealed_cases() -> tuple[Case, ...]:
    """The sealed cases of ``tests/foreign_sealed.yaml`` (validated with a second seed)."""
    out = []
    for row in foreign_sealed.load():
        fo = dict(row["foreign"])
        fo["pulleys"] = tuple(tuple(p) for p in fo["pulleys"])
        truth = {e: {k: tuple(v) for k, v in ps.items()} for e, ps in row["truth"].items()}
        out.append(Case(row["name"], Foreign(**fo), truth, validate=True, note=_machine_note(fo)))
    return tuple(out)


def _machine_note(fo: dict) -> str:
    jitter = f", +-{1e3 * fo['jitter_s']:.1f} ms" if fo.get("jitter_s") else ""
    return (
        f"{len(fo['pulleys'])} pulley{'s' if len(fo['pulleys']) > 1 else ''} {fo['model']}, "
        f"{fo['rate_hz']:g} Hz{jitter}, {fo['noise']} {fo['noise_n']:g} N, {fo['motion']}, "
        f"{fo['cables']} cable{'s' if fo['cables'] > 1 else ''}"
    )


@dataclass
class Score:
    """How a case came out."""

    case: Case
    found: list[str]
    named: bool
    cables_ok: bool
    param_err: float  # worst |error| / tolerance over the truth's parameters (<= 1 passes)
    holdout: tuple[float, float]
    validation: tuple[float, float] | None
    clipped: int
    seconds: float
    alternative: dict[str, str] | None = None
    """The true effects named as alternatives of these findings (finding -> true effect,
    :func:`evaluation.scenarios.substitutes`), every other strict rule holding; None: not so."""

    @property
    def why(self) -> list[str]:
        """What failed the strict score (empty: passed)."""
        val_up = self.validation is not None and self.validation[1] > self.validation[0] + 1e-12
        return [
            text
            for text, failed in (
                ("effects", not self.named),
                ("cables", not self.cables_ok),
                ("parameters", self.param_err > 1.0),
                ("held-out up", self.holdout[1] > self.holdout[0] + 1e-12),
                ("validation up", val_up),
            )
            if failed
        ]

    @property
    def passed(self) -> bool:
        return not self.why

    @property
    def outcome(self) -> str:
        """The table's ``pass`` cell: yes, named as an alternative, or no with why."""
        if self.passed:
            return "yes"
        if self.alternative:
            pairs = ", ".join(f"{t} of {f}" for f, t in self.alternative.items())
            return f"alternative ({pairs})"
        return "**no** (" + ", ".join(self.why) + ")"


def score(case: Case) -> Score:
    """Run one case and score it strictly."""
    start = time.perf_counter()
    diag = run_foreign(case.fo, case.nominal, case.pulleys, case.validate)
    seconds = time.perf_counter() - start
    rep = diag.report
    found = [f["effect"] for f in rep["findings"]]
    cables_ok, err = True, 0.0
    for f in rep["findings"]:
        if f["effect"] not in case.truth:
            continue
        cables_ok &= f["cables"] == _cables(case, f["effect"])
        err = max(err, _param_err(case, f))
    fin = rep["final"]
    hold = (rep["baseline"]["holdout_rmse_n"], fin["holdout_rmse_n"])
    val = None
    if "validation_rmse_before_n" in fin:
        val = (fin["validation_rmse_before_n"], fin["validation_rmse_after_n"])
    clipped = int(sum(rep.get("clipped", {}).get("per_cable", [])))
    out = Score(
        case, found, set(found) == set(case.truth), cables_ok, err, hold, val, clipped, seconds
    )
    if out.passed:
        return out

    def fits(alt: dict) -> bool:
        return alt["cables"] == _cables(case, alt["effect"]) and _param_err(case, alt) <= 1.0

    swap = substitutes(set(case.truth), rep["findings"], fits)
    rest = [w for w in out.why if w not in ("effects", "parameters")]
    if swap is not None and not rest:
        alt_err = max([err, *(_param_err(case, a) for a in swap.values())])
        if alt_err <= 1.0:
            out.param_err = alt_err
            out.alternative = {f: a["effect"] for f, a in swap.items()}
    return out


def _cables(case: Case, effect: str) -> list[int]:
    """The cables (1-based) ``effect`` is on in ``case`` (default: all)."""
    return case.cables.get(effect, list(range(1, case.fo.cables + 1)))


def _param_err(case: Case, finding: dict) -> float:
    """The worst |error| / tolerance of a finding's (or an alternative's) true parameters."""
    err = 0.0
    for name, (value, rel, absol) in case.truth[finding["effect"]].items():
        tol = max(rel * abs(value), absol)
        for got in finding["parameters"].get(name, [math.inf]):
            err = max(err, abs(got - value) / tol)
    return err


def _rows(scores: list[Score]) -> list[str]:
    lines = []
    for s in scores:
        val = "" if s.validation is None else f"{s.validation[0]:.3f} -> {s.validation[1]:.3f}"
        lines.append(
            f"| {s.case.name} | {s.case.note} | {', '.join(sorted(s.case.truth)) or 'none'} "
            f"| {', '.join(s.found) or 'none'} "
            f"| {s.outcome} "
            f"| {s.param_err:.2f} | {s.holdout[0]:.3f} -> {s.holdout[1]:.3f} | {val} "
            f"| {s.clipped} | {s.seconds:.1f} |"
        )
    return lines


SEALED_HEADING = "## Sealed foreign recordings (never tuned on)"


def sealed_table(scores: list[Score], digest: str) -> str:
    """The markdown section of the sealed foreign cases."""
    clean = [s for s in scores if not s.case.truth]
    return (
        "\n".join(
            [
                SEALED_HEADING,
                "",
                f"`tests/foreign_sealed.yaml` (SHA-256 `{digest[:16]}...`, ## Seals): "
                f"{len(scores)} "
                "cases of the independent generator drawn once by `tests/foreign_sealed.py` with "
                "another seed and settings the tuning cases do not use (1-4 pulleys, Coulomb or "
                "Dahl chains, 200-1000 Hz, jitter, five noise kinds, moves or positioning, 1-3 "
                "cables); each effect at the scenario suite's sizes (0.7-1.5x) and tolerances; "
                "every case validated on a second seed. Same strict score; `alternative (t of f)`: "
                "the true effect `t` listed among the alternatives the test could not separate "
                "from the finding `f`, every other rule holding with `t` in place of `f`; failures "
                "are published, never tuned on.",
                "",
                f"**Passed: {sum(s.passed for s in scores)}/{len(scores)}. Named as an "
                "alternative where the test cannot separate it: "
                f"{sum(bool(s.alternative) for s in scores)}. False findings on "
                f"{len(clean)} clean recordings: {sum(len(s.found) for s in clean)}.**",
                "",
                "| case | machine | truth | found | pass | param err | held-out before -> after "
                "| validation before -> after | clipped | s |",
                "|---|---|---|---|---|---|---|---|---|---|",
                *_rows(scores),
            ]
        )
        + "\n"
    )


def table(scores: list[Score]) -> str:
    """The markdown section of the foreign cases."""
    passed = sum(s.passed for s in scores)
    lines = [
        "## Foreign recordings (independent generator)",
        "",
        "Generated by `python -m tests.foreign_cases --table docs/diagnose-suite.md`. "
        "Recordings of the independent generator `tests/diagnose_helpers.py` (explicit "
        "Euler on a 5 kHz grid, resampled), one per failure class seen on recordings the "
        "project had never seen. Strict score: "
        "the exact set of effects (an extra finding fails), the right cables, every "
        "parameter within tolerance (`param err` <= 1), held-out and validation RMSE down.",
        "",
        f"**Passed: {passed}/{len(scores)}. Named as an alternative where the test cannot "
        f"separate it: {sum(bool(s.alternative) for s in scores)}.**",
        "",
        "Notes. Class 4: the false findings do not reproduce here (the cases stay as "
        "regression cases). The chain now steps the Dahl state over the trapezoid travel "
        "of the actual time stamps, not `v dt` of each sample (docs/physics.md, *Cable "
        "travel*): on the noise-free cases the nominal residual after a 2 s warm-up fell "
        "from 0.25 to 0.029 N RMS (100 Hz +-2 ms) and from 0.041 to 0.009 N (250 Hz "
        "+-0.8 ms), the held-out RMSE from 0.218 to 0.024 N and from 0.052 to 0.012 N; "
        "the generator-vs-model floor is 0.010-0.021 N (1 kHz, no jitter). Class 6 is "
        "covered by the physical bounds (tests in `tests/diagnose/test_foreign_regressions.py`). "
        "`dahl_f0` (and every Dahl case) earlier failed on a generator bug: its Dahl "
        "state was clamped to `|F| <= F_R`, which is not eq. 14 (a falling level was "
        "reached at once, even at standstill); generator and model then differed by 0.30 N "
        "RMS (0.45 N at standstill) and `f0` came out 2.68 N for 3.0 N whatever the noise, "
        "grid or `mu`. Without the clamp they differ by 0.04 N RMS on a 5 kHz grid. Of "
        "the `f0` bias that remained (2.87 N with 0.3 N noise, 2.85 N noise-free, "
        "amplified by the `mu`-`f0` correlation of -0.988 on this +-40 % load) the `v dt` "
        "stepping was the larger part: with the trapezoid travel `f0` is 2.93 N, "
        "noise-free 3.00 N. The rest is model form (the generator's normal force includes "
        "`f0`'s own tension drop, ~1 % of `f0`), which the noise-free recording also shows "
        "as an extra offset of 0.04 N (not a case of the table).",
        "",
        "| case | class | truth | found | pass | param err | held-out before -> after "
        "| validation before -> after | clipped | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *_rows(scores),
    ]
    return "\n".join(lines) + "\n"


def _run(cases: tuple[Case, ...], k: str) -> list[Score]:
    scores = []
    for case in cases:
        if k not in case.name:
            continue
        s = score(case)
        print(
            f"{case.name}: found {s.found or 'none'} pass={s.passed} err={s.param_err:.2f} "
            f"hold {s.holdout[0]:.3f}->{s.holdout[1]:.3f} val {s.validation} "
            f"clipped {s.clipped} {s.seconds:.1f}s",
            flush=True,
        )
        scores.append(s)
    return scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--table", type=Path)
    ap.add_argument("--set", choices=("tuning", "sealed", "both"), default="both")
    ap.add_argument("-k", default="", help="only cases whose name contains this")
    ap.add_argument("--seal", type=int, metavar="SEED", help="draw the sealed file anew")
    ap.add_argument("--reseal", metavar="REASON", help="record the sealed file's hash")
    ap.add_argument(
        "--append",
        metavar="EFFECT",
        help="with --seal SEED: append one case of EFFECT drawn alone from SEED",
    )
    args = ap.parse_args()
    doc = args.table or Path("docs/diagnose-suite.md")
    if args.append:
        if args.seal is None:
            ap.error("--append needs --seal SEED")
        case = foreign_sealed.append(foreign_sealed.SEALED_FILE, args.append, args.seal)
        print(f"{foreign_sealed.SEALED_FILE}: appended {case['name']}; --reseal REASON")
        return
    if args.seal is not None:
        foreign_sealed.write(foreign_sealed.SEALED_FILE, args.seal)
        print(f"{foreign_sealed.SEALED_FILE}: drawn from seed {args.seal}; --reseal REASON")
        return
    if args.reseal:
        sealing.add(doc, foreign_sealed.SEALED_FILE, args.reseal)
        return
    if args.set in ("tuning", "both"):
        scores = _run(CASES, args.k)
        if args.table:
            replace_section(args.table, table(scores))
    if args.set in ("sealed", "both"):
        digest = sealing.check(doc, foreign_sealed.SEALED_FILE)
        scores = _run(sealed_cases(), args.k)
        if args.table:
            replace_section(args.table, sealed_table(scores, digest))


if __name__ == "__main__":
    main()
