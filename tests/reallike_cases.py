"""The real-like cases (issue 29 item 6), strictly scored through the command line, and
their table.

Each case is a machine of :mod:`tests.reallike` (its truth: catalogue effect names from
:func:`tests.reallike.truth_effects`) with three recordings of different motions. A split
leaves one recording out: the other two are diagnosed together (``cdpr-gateway diagnose FIT
FIT --validate VAL --model M --json OUT``) and the left-out one validates, so a case is three
splits (a ``diagnose`` whose --help shows one RECORDING only would fit the next recording
alone: :func:`multi_recording`). A case passes only if on every split run:

- the exact set of effects (an extra finding fails), each on every cable (the friction and
  the drive are shared by all winches), every parameter within tolerance;
- the validation RMSE at or below the engineer's least squares (:func:`baseline_rmse`:
  Coulomb + viscous + offset per cable, linear, fitted on the same fit recording(s));
- the same set whichever recording is left out (the splits agree).

``python -m tests.reallike_cases --table docs/diagnose-suite.md [--set tuning|sealed|both]
[-k NAME] [--splits N] [--results FILE] [--load FILE ...]`` runs and writes the section (after
every case, so a run cut short still publishes what was run and names what was not);
``--results`` appends each case's score as a JSON line, ``--load`` takes cases already scored
from such files instead of running them (two processes can score the two sets and one writes
the table); ``--seal SEED`` draws the sealed file, ``--reseal REASON`` records its hash
(docs/diagnose-suite.md, ## Seals).
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from evaluation import sealing
from evaluation.suitedoc import replace_section
from tests import reallike as rl

SEALED_FILE = Path(__file__).with_name("reallike_sealed.yaml")
RECORDINGS = 3
LOSES = "worse than least squares"
TOL = {
    # (relative, absolute) per reported parameter: wide, the noise is 10-20 % of the load
    "f0_n": (0.3, 2.0),
    "mu": (0.0, 0.01),
    "mu_out": (0.0, 0.01),
    "mu_in": (0.0, 0.01),
    "c_ns_m": (0.3, 20.0),
    "sigma_n_m": (0.5, 0.0),
    "g": (0.3, 0.01),
    "c_n": (0.3, 2.0),
}


@dataclass(frozen=True)
class Case:
    """A machine, its recordings' logging, and a note; the truth is the machine's."""

    name: str
    machine: rl.Machine
    rate_hz: float = 10.0
    seconds: float = 400.0
    seed: int = 0
    note: str = ""

    def runs(self) -> list[rl.Run]:
        return [
            rl.Run(seed=self.seed + 101 * k, rate_hz=self.rate_hz, seconds=self.seconds)
            for k in range(RECORDINGS)
        ]

    @property
    def truth(self) -> dict[str, dict[str, float]]:
        return rl.truth_effects(self.machine)


M = rl.Machine
CASES = (
    Case("clean_4", M(cables=4), seed=1, note="nominal machine, 10 Hz"),
    Case(
        "robot4_viscous_offset",
        M(cables=4, c_ns_m=200.0, offset_n=-8.0, noise_frac=0.18),
        seed=2,
        note="issue 29's 4-cable robot: shared viscous 200 N s/m, offset",
    ),
    Case(
        "drive6_coulomb_gain",
        M(cables=6, f0_n=12.0, gain=-0.06, mass_kg=45.0),
        rate_hz=20.0,
        seed=3,
        note="torque constant 6 % off, Coulomb level, 20 Hz",
    ),
    Case(
        "winch_directional_dahl",
        M(cables=4, mu_out=0.02, mu_in=0.05, f0_n=4.0, sigma_n_m=3000.0, offset_n=3.0),
        rate_hz=30.0,
        seed=4,
        note="lifting/lowering losses differ, force held at rest remembers the direction",
    ),
    Case(
        "robot8_all_100hz",
        M(cables=8, f0_n=8.0, c_ns_m=120.0, gain=0.04, offset_n=5.0, mass_kg=60.0),
        rate_hz=100.0,
        seconds=300.0,
        seed=5,
        note="8 winches, 100 Hz, four effects",
    ),
    Case("clean_8_30hz", M(cables=8, mass_kg=60.0), rate_hz=30.0, seed=6, note="nominal, 30 Hz"),
    Case(
        "winch7_directional_offset_15hz",
        M(
            cables=7,
            mass_kg=35.0,
            noise_frac=0.17,
            mu_out=0.022,
            mu_in=0.046,
            f0_n=6.0,
            offset_n=-7.0,
        ),
        rate_hz=15.0,
        seed=8,
        note="directional drive-train loss beside an offset, heavy noise (issue 29: coulomb "
        "vs coulomb_directional)",
    ),
    Case(
        "robot5_directional_gain_viscous_20hz",
        M(
            cables=5,
            mass_kg=30.0,
            noise_frac=0.15,
            mu_out=0.015,
            mu_in=0.04,
            f0_n=4.0,
            c_ns_m=180.0,
            gain=0.05,
        ),
        rate_hz=20.0,
        seed=9,
        note="directional loss beside a gain and viscous friction",
    ),
    Case(
        "robot8_directional_100hz",
        M(
            cables=8,
            mass_kg=45.0,
            noise_frac=0.16,
            mu_out=0.018,
            mu_in=0.042,
            f0_n=5.0,
            c_ns_m=140.0,
            gain=-0.05,
            offset_n=6.0,
        ),
        rate_hz=100.0,
        seconds=300.0,
        seed=7,
        note="8 winches, 100 Hz: directional loss beside gain, offset and viscous",
    ),
)


# ---------------------------------------------------------------- sealed set


def draw(seed: int, n: int = 10) -> list[dict]:
    """``n`` machines drawn from ``seed``: 4-8 cables, 10-30 Hz (one in four at 100 Hz),
    noise 10-20 %, each effect present with probability 1/2 (two clean machines)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        r = lambda x: round(float(x), 4)  # noqa: E731
        kw: dict = {
            "cables": int(rng.integers(4, 9)),
            "mass_kg": r(rng.uniform(20, 60)),
            "noise_frac": r(rng.uniform(0.10, 0.20)),
        }
        if k >= 2:  # the first two are clean
            if rng.uniform() < 0.5:
                kw["f0_n"] = r(rng.uniform(5, 15))
            if rng.uniform() < 0.5:
                kw["c_ns_m"] = r(rng.uniform(80, 250))
            if rng.uniform() < 0.3:
                kw["mu_out"], kw["mu_in"] = r(rng.uniform(0.01, 0.03)), r(rng.uniform(0.03, 0.06))
                kw.setdefault("f0_n", r(rng.uniform(3, 8)))
            if rng.uniform() < 0.3 and "f0_n" in kw:
                kw["sigma_n_m"] = r(rng.uniform(1500, 5000))
            if rng.uniform() < 0.5:
                kw["gain"] = r(rng.choice([-1, 1]) * rng.uniform(0.03, 0.08))
            if rng.uniform() < 0.5:
                kw["offset_n"] = r(rng.choice([-1, 1]) * rng.uniform(3, 12))
        rate = 100.0 if rng.uniform() < 0.25 else float(rng.choice([10.0, 15.0, 20.0, 30.0]))
        out.append(
            {
                "name": f"sealed_{k + 1}",
                "machine": kw,
                "rate_hz": rate,
                "seconds": 300.0 if rate == 100.0 else 400.0,
                "seed": int(seed % 100000 + 1000 * k),
            }
        )
    return out


def write_sealed(path: Path, seed: int) -> None:
    head = (
        f"# The sealed real-like cases: drawn once by"
        f" `python -m tests.reallike_cases --seal {seed}`"
        "\n# (tests/reallike_cases.py: draw), scored like the tuning cases, never tuned on."
        "\n# docs/diagnose-suite.md records this file's SHA-256 (## Seals).\n"
    )
    body = yaml.safe_dump({"cases": draw(seed)}, sort_keys=False, default_flow_style=None)
    path.write_text(head + body, encoding="utf-8")


def sealed_cases() -> tuple[Case, ...]:
    doc = yaml.safe_load(SEALED_FILE.read_text(encoding="utf-8"))
    return tuple(
        Case(c["name"], M(**c["machine"]), c["rate_hz"], c["seconds"], c["seed"])
        for c in doc["cases"]
    )


# ---------------------------------------------------------------- the engineer's baseline


def _cols(path: Path) -> dict[str, np.ndarray]:
    with path.open(encoding="utf-8") as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    names = lines[0].strip().split(",")
    data = np.genfromtxt(lines[1:], delimiter=",", dtype=float)
    return {n: data[:, k] for k, n in enumerate(names)}


def _design(cols: dict[str, np.ndarray], i: int) -> tuple[np.ndarray, np.ndarray]:
    v, tp = cols[f"velocity_{i}"], cols[f"tension_platform_{i}"]
    s = np.sign(v)  # the setpoint speed is exactly 0 at rest
    lo, li = rl.lambdas(rl.Machine())  # the datasheet loss the nominal states
    nominal = tp - np.where(s > 0, lo, li) * s * tp
    y = cols[f"tension_sensor_{i}"] - nominal
    x = np.column_stack([s, v, np.ones_like(v)])
    ok = np.isfinite(y) & np.isfinite(x).all(axis=1)
    return x[ok], y[ok]


def baseline_rmse(fit: list[Path], val: Path) -> float:
    """Coulomb + viscous + offset per cable, linear least squares on the fit recording(s)
    (on top of the datasheet loss), scored on ``val``: the RMSE over all cables."""
    fcols = [_cols(p) for p in fit]
    vcols = _cols(val)
    m = sum(1 for k in vcols if k.startswith("velocity_"))
    sq, n = 0.0, 0
    for i in range(1, m + 1):
        parts = [_design(c, i) for c in fcols]
        x = np.vstack([p[0] for p in parts])
        y = np.concatenate([p[1] for p in parts])
        beta = np.linalg.lstsq(x, y, rcond=None)[0]
        xv, yv = _design(vcols, i)
        sq += float(((yv - xv @ beta) ** 2).sum())
        n += yv.size
    return math.sqrt(sq / n)


# ---------------------------------------------------------------- scoring


def multi_recording() -> bool:
    """Does today's ``diagnose`` take several recordings? (read from its --help)."""
    out = subprocess.run(
        [sys.executable, "-m", "gateway", "diagnose", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    usage = out.split("\n\n")[0]
    return "..." in usage


@dataclass
class Split:
    fit: list[int]
    val: int
    found: dict[str, list[int]]
    errors: list[str]
    validation: tuple[float, float]
    baseline: float
    seconds: float
    detail: list[str] = field(default_factory=list)  # which effect, cable, parameter missed


@dataclass
class Score:
    case: Case
    splits: list[Split] = field(default_factory=list)
    wall: float = 0.0  # the case's wall time (s): recordings, diagnoses, baseline
    cpu: float = 0.0  # its CPU time (s), the diagnoses' processes included

    def to_json(self) -> str:
        d = {"case": self.case.name, "wall": self.wall, "cpu": self.cpu}
        d["splits"] = [vars(s) for s in self.splits]
        return json.dumps(d)

    @classmethod
    def from_json(cls, line: str, cases: dict[str, Case]) -> Score:
        d = json.loads(line)
        splits = [Split(**{**s, "validation": tuple(s["validation"])}) for s in d["splits"]]
        return cls(cases[d["case"]], splits, d["wall"], d["cpu"])

    @property
    def same_set(self) -> bool:
        return len({tuple(sorted(s.found)) for s in self.splits}) <= 1

    @property
    def why(self) -> list[str]:
        out: list[str] = []
        for s in self.splits:
            for w in s.errors:
                if w not in out:
                    out.append(w)
        if not self.same_set:
            out.append("set depends on the split")
        return out

    @property
    def passed(self) -> bool:
        return bool(self.splits) and not self.why


def _param_errors(truth: dict, finding: dict) -> float:
    worst = 0.0
    for name, value in truth.get(finding["effect"], {}).items():
        rel, ab = TOL[name]
        tol = max(rel * abs(value), ab)
        for got in finding["parameters"].get(name, [math.inf]):
            worst = max(worst, abs(got - value) / tol)
    return worst


def _g(x: float) -> str:
    return f"{x:.3g}"


def _param_misses(truth: dict, finding: dict) -> list[str]:
    """The parameters of ``finding`` out of tolerance: 'effect name got (truth +- tol)'."""
    out = []
    for name, value in truth.get(finding["effect"], {}).items():
        rel, ab = TOL[name]
        tol = max(rel * abs(value), ab)
        got = finding["parameters"].get(name)
        if not got:
            out.append(f"{finding['effect']} {name} not reported ({_g(value)})")
        elif max(abs(x - value) for x in got) > tol:
            lo, hi = min(got), max(got)
            span = _g(lo) if lo == hi else f"{_g(lo)}..{_g(hi)}"
            out.append(f"{finding['effect']} {name} {span} ({_g(value)} +- {_g(tol)})")
    return out


def score_split(case: Case, paths: list[Path], model: Path, fit: list[int], val: int) -> Split:
    """One diagnosis through the command line, scored strictly."""
    out = model.with_name(f"{case.name}_{val}.json")
    cmd = [sys.executable, "-m", "gateway", "diagnose", *(str(paths[k]) for k in fit)]
    cmd += ["--validate", str(paths[val]), "--model", str(model), "--json", str(out), "--quiet"]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{case.name}: diagnose exited {proc.returncode}: {proc.stderr[-300:]}")
    rep = json.loads(out.read_text(encoding="utf-8"))
    truth, every = case.truth, list(range(1, case.machine.cables + 1))
    found = {f["effect"]: f["cables"] for f in rep["findings"]}
    errors, detail = [], []
    if set(found) != set(truth):
        errors.append("effects")
        detail += [f"missing {e}" for e in sorted(set(truth) - set(found))]
        detail += [f"extra {e} {found[e]}" for e in found if e not in truth]
    if any(found[e] != every for e in found if e in truth):
        errors.append("cables")
        detail += [f"{e} on {found[e]} only" for e in found if e in truth and found[e] != every]
    if max([0.0, *(_param_errors(truth, f) for f in rep["findings"])]) > 1.0:
        errors.append("parameters")
        for f in rep["findings"]:
            detail += _param_misses(truth, f)
    fin = rep["final"]
    vrmse = (fin["validation_rmse_before_n"], fin["validation_rmse_after_n"])
    base = baseline_rmse([paths[k] for k in fit], paths[val])
    if vrmse[1] > base:
        errors.append(LOSES)
        detail.append(f"{LOSES} by {_g(vrmse[1] - base)} N")
    return Split(fit, val, found, errors, vrmse, base, seconds, detail)


def _cpu() -> float:
    return sum(
        r.ru_utime + r.ru_stime
        for r in (
            resource.getrusage(resource.RUSAGE_SELF),
            resource.getrusage(resource.RUSAGE_CHILDREN),
        )
    )


def score(case: Case, splits: int = RECORDINGS, workdir: Path | None = None) -> Score:
    """Generate the case's recordings and score ``splits`` of its leave-one-out splits."""
    wall, cpu = time.perf_counter(), _cpu()
    with tempfile.TemporaryDirectory() as tmp:
        d = workdir or Path(tmp)
        paths = [
            rl.write(d / f"{case.name}_{k}.csv", rl.generate(case.machine, run), case.name)
            for k, run in enumerate(case.runs())
        ]
        model = d / f"{case.name}_model.yaml"
        model.write_text(rl.model_yaml(), encoding="utf-8")
        multi = multi_recording()
        sc = Score(case)
        for val in range(splits):
            fit = [k for k in range(RECORDINGS) if k != val]
            fit = fit if multi else [(val + 1) % RECORDINGS]
            sc.splits.append(score_split(case, paths, model, fit, val))
        sc.wall, sc.cpu = time.perf_counter() - wall, _cpu() - cpu
        return sc


# ---------------------------------------------------------------- table

HEADING = "## Real-like recordings (issue 29)"


def _machine(c: Case) -> str:
    m = c.machine
    return f"{m.cables} winches, {c.rate_hz:g} Hz, noise {100 * m.noise_frac:.0f} %"


def _found(s: Split) -> str:
    return ", ".join(f"{e} {cab}" for e, cab in s.found.items()) or "none"


def rows(scores: list[Score]) -> list[str]:
    lines = []
    for sc in scores:
        for s in sc.splits:
            outcome = "yes" if not s.errors else "**no** (" + "; ".join(s.detail or s.errors) + ")"
            lines.append(
                f"| {sc.case.name} | {_machine(sc.case)} "
                f"| {', '.join(sorted(sc.case.truth)) or 'none'} "
                f"| {'+'.join(str(k + 1) for k in s.fit)} / {s.val + 1} | {_found(s)}"
                f"{'' if sc.same_set else ' (set differs between splits)'} "
                f"| {outcome} | {s.validation[0]:.2f} -> {s.validation[1]:.2f} "
                f"| {s.baseline:.2f} | {s.seconds:.0f} |"
            )
    return lines


def table(
    tuning: list[Score], sealed: list[Score], digest: str, note: str, missing: list[str]
) -> str:
    def tally(scores: list[Score]) -> str:
        clean = [s for s in scores if not s.case.truth]
        false = sum(len(sp.found) for s in clean for sp in s.splits)
        split = [s for s in scores if len(s.splits) > 1]
        same = (
            f"{sum(s.same_set for s in split)}/{len(split)}"
            if split
            else "not tested (one split per case)"
        )
        return (
            f"{sum(s.passed for s in scores)}/{len(scores)} cases passed; "
            f"false findings on {len(clean)} clean machines: {false}; "
            f"validation <= least squares on "
            f"{sum(LOSES not in sp.errors for s in scores for sp in s.splits)}/"
            f"{sum(len(s.splits) for s in scores)} runs; the same set whichever recording is "
            f"left out: {same}"
        )

    done = [*tuning, *sealed]
    wall, cpu = sum(s.wall for s in done), sum(s.cpu for s in done)
    nsplits = sum(len(s.splits) for s in done)
    fits = sorted({len(sp.fit) for s in done for sp in s.splits})
    head = (
        "| case | machine | truth | fit / validation | found [cables] | pass | validation "
        "before -> after (N) | least squares (N) | s |\n|---|---|---|---|---|---|---|---|---|"
    )
    run = (
        f"Run {time.strftime('%Y-%m-%d', time.gmtime())}: {len(done)} cases, {nsplits} "
        f"diagnoses of {' or '.join(str(f) for f in fits)} fit recording(s) each; "
        f"the cases' wall times add up to {wall / 60:.0f} min, their CPU times (the "
        f"diagnoses' processes included) to {cpu / 60:.0f} min. "
        + (f"Not run: {', '.join(missing)}." if missing else "Every case was run.")
    )
    return (
        "\n".join(
            [
                HEADING,
                "",
                "Generated by `python -m tests.reallike_cases --table docs/diagnose-suite.md`. "
                "Machines of the real-like generator `tests/reallike.py` (its own statics and "
                "friction integration, not `gateway/model`): 4-8 winches sharing one drive "
                "train, the motor current as the reading converted with a datasheet torque "
                "constant that is off (catalogue `gain`) and a current offset (`offset`), "
                "10-100 Hz, noise 10-20 % of the load, gaps, blanks, long standstills under "
                "load. Nominal model: the datasheet loss (one 180-degree pulley, mu 0.01, "
                "Coulomb). Truth in catalogue names: `coulomb` (f0, mu), `coulomb_directional` "
                "(mu_out != mu_in), `viscous`, `presliding` (Dahl state held at rest), `gain`, "
                "`offset`, every one on all cables. Each case has three recordings of different "
                "motions; leave-one-recording-out: a split diagnoses the other two together "
                "(`cdpr-gateway diagnose REC REC --validate VAL`: one set of findings for both) "
                "and validates on the one left out, so a case is three splits (`fit / "
                "validation` numbers the recordings). A split passes only with the exact set "
                "(an extra finding fails), every effect on all cables, every parameter in "
                "tolerance (`tests/reallike_cases.py: TOL`) and the validation RMSE at or "
                "below the engineer's least squares (Coulomb + viscous + offset per cable, "
                "linear, fitted on the same two recordings, scored on the same left-out one); "
                "a case passes only if all its splits pass and find the same set of effects. "
                "`s`: the diagnosis' wall time.",
                "",
                run,
                *(["", note] if note else []),
                "",
                f"**Tuning: {tally(tuning)}.**",
                "",
                f"**Sealed (`tests/reallike_sealed.yaml`, SHA-256 `{digest[:16]}...`, never "
                f"tuned on): {tally(sealed)}.**",
                "",
                head,
                *rows(tuning),
                *rows(sealed),
            ]
        )
        + "\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--table", type=Path)
    ap.add_argument("--set", choices=("tuning", "sealed", "both"), default="both")
    ap.add_argument("-k", default="", help="only these cases (comma-separated names)")
    ap.add_argument("--splits", type=int, default=RECORDINGS, help="leave-one-out splits run")
    ap.add_argument("--note", default="", help="a paragraph for the section (e.g. the failures)")
    ap.add_argument("--results", type=Path, help="append each case's score here (JSON lines)")
    ap.add_argument("--load", type=Path, nargs="*", default=[], help="cases already scored")
    ap.add_argument("--seal", type=int, metavar="SEED", help="draw the sealed file anew")
    ap.add_argument("--reseal", metavar="REASON", help="record the sealed file's hash")
    args = ap.parse_args()
    doc = args.table or Path("docs/diagnose-suite.md")
    if args.seal is not None:
        write_sealed(SEALED_FILE, args.seal)
        print(f"{SEALED_FILE}: drawn from seed {args.seal}; --reseal REASON")
        return
    if args.reseal:
        sealing.add(doc, SEALED_FILE, args.reseal)
        return
    digest = sealing.check(doc, SEALED_FILE)
    sets = {"tuning": CASES, "sealed": sealed_cases()}
    by_name = {c.name: c for cases in sets.values() for c in cases}
    loaded: dict[str, Score] = {}
    for path in args.load:
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.strip():
                sc = Score.from_json(line, by_name)
                loaded[sc.case.name] = sc
    result: dict[str, list[Score]] = {"tuning": [], "sealed": []}

    def publish() -> None:
        if not args.table:
            return
        done = {s.case.name for v in result.values() for s in v}
        missing = [n for n in by_name if n not in done]
        replace_section(
            args.table, table(result["tuning"], result["sealed"], digest, args.note, missing)
        )

    for which, cases in sets.items():
        for case in cases:
            if case.name in loaded:
                result[which].append(loaded[case.name])
                continue
            if args.set not in (which, "both"):
                continue
            if args.k and case.name not in args.k.split(","):
                continue
            sc = score(case, args.splits)
            for s in sc.splits:
                print(
                    f"{case.name} {s.fit}/{s.val}: {s.found} {s.detail} {s.validation} "
                    f"ls {s.baseline:.2f} {s.seconds:.0f}s",
                    flush=True,
                )
            print(f"{case.name}: passed {sc.passed}, {sc.wall:.0f} s wall, {sc.cpu:.0f} s CPU")
            if args.results:
                with args.results.open("a", encoding="utf-8") as fh:
                    fh.write(sc.to_json() + "\n")
            result[which].append(sc)
            publish()
    publish()


if __name__ == "__main__":
    main()
