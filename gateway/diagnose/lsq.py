"""The engineer's least-squares baselines: what a competent engineer fits in an afternoon,
to measure the catalogue's diagnosis against (issue 29, item 3).

Per cable, sensor reading ``T_s`` from the platform tension ``T_p``:

* ``coulomb_viscous`` (linear least squares)::

      T_s = T_p - f_c sgn(v) - c v + b

* ``dahl`` (nonlinear least squares)::

      T_s = (1 + g) T_p - F - c v - m a - k x + b
      dF/dx = sigma (1 - F / F_R sgn(dx)),   F_R = mu |T_p| + f0

  a Dahl pre-sliding force ``F`` (stepped exactly over each sample's travel ``dx``) whose
  level grows with the load (:func:`dahl_force`, the law of ``evaluation.baseline`` for the
  real transmissions), a gain ``g``, viscous ``c``, inertia ``m``, a spring ``k`` in the
  position ``x`` and a constant ``b``. The fit is a variable projection: the three
  nonlinear parameters (``mu``, ``f0``, ``log10 sigma``) by
  :func:`scipy.optimize.least_squares` from the best of three stiffness starts, the five
  linear ones by least squares inside each residual evaluation (their pseudo-inverse
  computed once: the linear columns do not depend on the nonlinear parameters).

Both are fitted on the training samples handed in (the diagnosis' training blocks; for
the Dahl fit of a long recording, those of evenly spaced windows, :class:`Design`) and
scored by the caller on every held-out and validation sample. :func:`drop_term` refits
the Dahl baseline with one of its terms dropped (nonlinear parameters kept), to say which
term carries what it explains.

The report's block is written by :func:`assemble`, which the wrench reference's
(:mod:`.wrench_lsq`: Coulomb + viscous + offset through the structure matrix) shares.

Cost: on bench_diagnose's 10-min, 1 kHz, 8-cable recording (hidden case) the block took
17.0 s of a 540 s diagnosis (3.1 %), peak RSS 374 MiB, on a 2-core machine under a load
of 6-9 (about a third of a core; the figures scale together).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

FIT_SAMPLES = 20_000
"""About the training samples a cable's Dahl fit scores (:class:`Design`)."""
WINDOWS = 10
WARM = 0.1
MAX_NFEV = 60
DAHL_LINEAR = ("g", "c_ns_m", "m_kg", "k_n_m", "b_n")
DAHL_TERMS = ("dahl", "g", "c_ns_m", "m_kg", "k_n_m", "b_n")
TERM_WORDS = {
    "dahl": "the load-dependent Dahl (pre-sliding) friction",
    "g": "the gain on the tension",
    "c_ns_m": "the viscous friction",
    "m_kg": "the inertia",
    "k_n_m": "the position spring",
    "b_n": "the constant offset",
    "coulomb_n": "the Coulomb friction",
    "viscous_ns_m": "the viscous friction",
    "offset_n": "the offset",
}


@njit(cache=True)
def _dahl(tp, dx, mu, f0, sigma):  # pragma: no cover - numba
    """Dahl force (N,) over travel ``dx`` (N,) with the level ``mu |T_p| + f0``."""
    out = np.empty(tp.size)
    f = 0.0
    for k in range(tp.size):
        fr = mu * abs(tp[k]) + f0
        d = dx[k]
        if fr > 1e-9 and d != 0.0:
            s = 1.0 if d > 0.0 else -1.0
            f = s * fr - (s * fr - f) * math.exp(-sigma * abs(d) / fr)
        elif fr <= 1e-9:
            f = 0.0
        out[k] = f
    return out


def dahl_force(tp: np.ndarray, dx: np.ndarray, mu: float, f0: float, sigma: float) -> np.ndarray:
    """The Dahl force (N,) from rest over the travel ``dx`` (N,) of each sample, level
    ``mu |tp| + f0`` (N), stiffness ``sigma`` (N/m) (module docstring)."""
    return _dahl(
        np.ascontiguousarray(tp, dtype=float),
        np.ascontiguousarray(dx, dtype=float),
        float(mu),
        float(f0),
        float(sigma),
    )


def travel(x: np.ndarray) -> np.ndarray:
    """Each sample's travel (N,) from the previous one (0 at the first)."""
    dx = np.zeros(x.size)
    dx[1:] = np.diff(x)
    return dx


@dataclass
class Cable:
    """One cable's series for the baselines: platform tension, velocity, acceleration,
    position, reading (N,) each."""

    tp: np.ndarray
    v: np.ndarray
    a: np.ndarray
    x: np.ndarray
    ts: np.ndarray


@dataclass
class Fit:
    """A fitted baseline: its name, parameters and prediction function's inputs."""

    kind: str
    params: dict[str, float]

    def predict(self, c: Cable) -> np.ndarray:
        p = self.params
        if self.kind == "coulomb_viscous":
            return c.tp - p["coulomb_n"] * np.sign(c.v) - p["viscous_ns_m"] * c.v + p["offset_n"]
        return _dahl_predict(p, c)


def _dahl_predict(p: dict[str, float], c: Cable) -> np.ndarray:
    f = dahl_force(c.tp, travel(c.x), p["mu"], p["f0_n"], p["sigma_n_m"])
    return (
        (1.0 + p["g"]) * c.tp
        - f
        - p["c_ns_m"] * c.v
        - p["m_kg"] * c.a
        - p["k_n_m"] * (c.x - c.x[0])
        + p["b_n"]
    )


def fit_coulomb_viscous(c: Cable, train: np.ndarray) -> Fit:
    """``T_s - T_p = -f_c sgn(v) - c v + b`` by linear least squares on ``train`` (bool)."""
    a = np.column_stack([-np.sign(c.v[train]), -c.v[train], np.ones(int(train.sum()))])
    coef = _lstsq(a, (c.ts - c.tp)[train])
    return Fit(
        "coulomb_viscous", dict(zip(("coulomb_n", "viscous_ns_m", "offset_n"), coef, strict=True))
    )


def _lstsq(a: np.ndarray, y: np.ndarray) -> list[float]:
    if a.shape[0] == 0:
        return [0.0] * a.shape[1]
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return [float(x) for x in coef]


def _linear_columns(c: Cable, idx: np.ndarray, drop: Sequence[str] = ()) -> tuple:
    cols = {
        "g": c.tp[idx],
        "c_ns_m": -c.v[idx],
        "m_kg": -c.a[idx],
        "k_n_m": -(c.x[idx] - c.x[0]),
        "b_n": np.ones(idx.size),
    }
    names = [n for n in DAHL_LINEAR if n not in drop]
    return names, np.column_stack([cols[n] for n in names])


def _dahl_linear(c, design, nl, drop=()):
    """The linear parameters given the nonlinear ``nl`` = (mu, f0, log10 sigma): the
    projected residual on the design's scored samples and the parameters. The linear
    columns do not depend on ``nl``: their pseudo-inverse is computed once per design."""
    idx = design.idx
    f = np.zeros(idx.size) if "dahl" in drop else design.force(c, nl)
    key = tuple(drop)
    if key not in design.pinv:
        names, a = _linear_columns(c, idx, drop)
        pinv = np.linalg.pinv(a) if a.shape[0] else np.zeros(a.shape[::-1])
        design.pinv[key] = (names, a, pinv)
    names, a, pinv = design.pinv[key]
    y = c.ts[idx] - c.tp[idx] + f
    coef = pinv @ y
    return a @ coef - y, {n: float(v) for n, v in zip(names, coef, strict=True)}


def _params(nl, lin: dict[str, float], drop=()) -> dict[str, float]:
    mu, f0, lsig = nl
    p = dict.fromkeys(DAHL_LINEAR, 0.0)
    p.update(lin)
    dahl = "dahl" not in drop
    p.update(mu=float(mu) if dahl else 0.0, f0_n=float(f0) if dahl else 0.0)
    p["sigma_n_m"] = float(10.0**lsig)
    return p


class Design:
    """The samples a Dahl fit scores and the stretches its state runs over.

    A recording of at most ``2 FIT_SAMPLES`` samples: the state runs over every sample and
    every training sample is scored. A longer one (a 10-min, 1 kHz recording: a Dahl run
    over 600 000 samples per residual evaluation would cost tens of seconds a cable):
    :data:`WINDOWS` evenly spaced windows of ``2 FIT_SAMPLES / WINDOWS`` samples, the state
    run over each from rest, scored on its training samples past the first
    :data:`WARM` of the window (the state forgets its start within a few Dahl lengths)."""

    def __init__(self, train: np.ndarray, x: np.ndarray, budget: int | None = None) -> None:
        budget = FIT_SAMPLES if budget is None else budget
        n = train.size
        if n <= 2 * budget:
            self.windows = [(0, n)]
            self.idx = np.flatnonzero(train)
            self.local = [self.idx]
        else:
            width = 2 * budget // WINDOWS
            starts = np.linspace(0, n - width, WINDOWS).astype(int)
            self.windows = [(int(a), int(a) + width) for a in starts]
            self.local = []
            for a, b in self.windows:
                w = np.flatnonzero(train[a + int(WARM * (b - a)) : b]) + int(WARM * (b - a))
                self.local.append(w)
            self.idx = np.concatenate(
                [w + a for w, (a, _) in zip(self.local, self.windows, strict=True)]
            )
        self.dx = [travel(x[a:b]) for a, b in self.windows]
        self.pinv: dict[tuple, tuple] = {}

    def force(self, c: Cable, nl) -> np.ndarray:
        """The Dahl force on the scored samples for ``nl`` = (mu, f0, log10 sigma)."""
        mu, f0, lsig = nl
        out = [
            dahl_force(c.tp[a:b], dx, mu, f0, 10.0**lsig)[w]
            for (a, b), dx, w in zip(self.windows, self.dx, self.local, strict=True)
        ]
        return np.concatenate(out) if out else np.zeros(0)


def fit_dahl(c: Cable, train: np.ndarray) -> Fit:
    """The Dahl baseline (module docstring) on ``train`` (bool), on the samples of
    :class:`Design`."""
    from scipy.optimize import least_squares

    design = Design(train, c.x)
    idx = design.idx
    if idx.size < len(DAHL_LINEAR) + 3:
        return Fit("dahl", _params((0.0, 0.0, 4.0), {}))
    # the level's scale from the data: a friction of a few % of the load, a few N
    scale = float(np.std(c.ts[idx] - c.tp[idx])) or 1.0
    lower = np.array([0.0, 0.0, 1.0])
    upper = np.array([1.0, max(10.0 * scale, 1.0), 7.0])

    def resid(nl: np.ndarray) -> np.ndarray:
        return _dahl_linear(c, design, nl)[0]

    # the stiffness is the one non-convex direction: the best of three starts, then one run
    starts = [np.clip(np.array([0.02, 0.2 * scale, lsig]), lower, upper) for lsig in (3, 4, 5)]
    start = min(starts, key=lambda x: float(np.sum(resid(x) ** 2)))
    best = least_squares(resid, start, bounds=(lower, upper), x_scale="jac", max_nfev=MAX_NFEV)
    return Fit("dahl", _params(best.x, _dahl_linear(c, design, best.x)[1]))


def drop_term(c: Cable, train: np.ndarray, fitted: Fit, term: str) -> Fit:
    """``fitted`` (a Dahl fit) refitted without ``term`` (one of :data:`DAHL_TERMS`), its
    nonlinear parameters kept, its linear ones refitted on ``train``."""
    p = fitted.params
    nl = (p["mu"], p["f0_n"], math.log10(p["sigma_n_m"]))
    lin = _dahl_linear(c, Design(train, c.x), nl, drop=(term,))[1]
    return Fit("dahl", _params(nl, lin, drop=(term,)))


def cable_series(d) -> Cable:
    """A :class:`gateway.diagnose.forward.CableData`'s series for the baselines."""
    return Cable(d.tp, d.v, d.a, d.x, d.ts)


def _release(d) -> None:
    if hasattr(d, "release"):
        d.release()


class Score:
    """Per cable squared errors and counts of one predictor on the held-out (row 0) and the
    validation (row 1) samples; pooled RMSE over every cable as the report's."""

    def __init__(self, cables: int) -> None:
        self.sse = np.zeros((2, cables))
        self.n = np.zeros((2, cables))

    def add(self, which: int, i: int, res: np.ndarray) -> None:
        self.sse[which, i] += float(res @ res)
        self.n[which, i] += res.size

    def add_sums(self, which: int, i: int, sse: float, n: int) -> None:
        """Add a sum of squares over ``n`` values computed elsewhere."""
        self.sse[which, i] += sse
        self.n[which, i] += n

    def per_cable(self, which: int) -> list[float]:
        return [
            math.sqrt(s / n) if n else 0.0
            for s, n in zip(self.sse[which], self.n[which], strict=True)
        ]

    def overall(self, which: int) -> float:
        n = self.n[which].sum()
        return math.sqrt(self.sse[which].sum() / n) if n else 0.0


NAMES = {
    "coulomb_viscous": "Coulomb + viscous + offset",
    "dahl": "load-dependent Dahl + gain + viscous + inertia + spring",
}
LINEAR_TERMS = ("coulomb_n", "viscous_ns_m", "offset_n")
TERM_FIT = {**dict.fromkeys(DAHL_TERMS, "dahl"), **dict.fromkeys(LINEAR_TERMS, "coulomb_viscous")}
"""The baseline fit a term of ``terms`` was dropped from (:func:`sentence`)."""
FIT_WORDS = {"coulomb_viscous": "the Coulomb + viscous + offset fit", "dahl": "the Dahl fit"}


def block(
    datas: Sequence,
    train: np.ndarray,
    test: np.ndarray,
    catalogue: Callable[[int], np.ndarray],
    validation: tuple[Sequence, np.ndarray, Callable[[int], np.ndarray]] | None = None,
) -> dict:
    """The report's ``baseline.least_squares`` (docs/recording-format.md): both baselines
    fitted per cable on ``train`` (N, m) bool, scored on ``test`` (N, m) bool and on the
    validation recording (its cable datas, valid mask and the catalogue's prediction),
    beside the catalogue's final model (``catalogue(i)``: cable ``i``'s prediction (N,)).
    One cable at a time: a cable's derived series are released (``release``) after use.
    When the catalogue does not beat the better baseline, each term of the Dahl baseline is
    dropped in turn and the rise of its error says which term carries what it lacks."""
    m = len(datas)
    kinds = ("coulomb_viscous", "dahl")
    fits: dict[str, list[Fit]] = {k: [] for k in kinds}
    score = {k: Score(m) for k in (*kinds, "catalogue")}
    for i, d in enumerate(datas):
        c = cable_series(d)
        tr, te = train[:, i], test[:, i]
        fits["coulomb_viscous"].append(fit_coulomb_viscous(c, tr))
        fits["dahl"].append(fit_dahl(c, tr))
        for k in kinds:
            score[k].add(0, i, (c.ts - fits[k][i].predict(c))[te])
        score["catalogue"].add(0, i, (c.ts - catalogue(i))[te])
        _release(d)
    if validation is not None:
        vdatas, vvalid, vcat = validation
        for i, d in enumerate(vdatas):
            c = cable_series(d)
            ok = vvalid[:, i]
            for k in kinds:
                score[k].add(1, i, (c.ts - fits[k][i].predict(c))[ok])
            score["catalogue"].add(1, i, (c.ts - vcat(i))[ok])
            _release(d)

    def dropped(on: int) -> list[dict]:
        """The Dahl fit's error with each of its terms dropped in turn."""
        full = score["dahl"].overall(on)
        terms: list[dict] = []
        for term in DAHL_TERMS:
            s = Score(m)
            for i, d in enumerate(datas):
                f = drop_term(cable_series(d), train[:, i], fits["dahl"][i], term)
                _release(d)
                if validation is not None:
                    vd = validation[0][i]
                    vc = cable_series(vd)
                    s.add(1, i, (vc.ts - f.predict(vc))[validation[1][:, i]])
                    _release(vd)
                else:
                    c = cable_series(d)
                    s.add(0, i, (c.ts - f.predict(c))[test[:, i]])
                    _release(d)
            rmse = s.overall(on)
            terms.append({"term": term, "rmse_without_n": rmse, "rise_n": rmse - full})
        return terms

    params = {k: [f.params for f in fits[k]] for k in kinds}
    out = assemble(params, score, validation is not None, dropped if m else None)
    return {"fit_samples": FIT_SAMPLES, **out}


def assemble(
    params: dict[str, list[dict[str, float]]],
    score: dict[str, Score],
    validated: bool,
    dropped: Callable[[int], list[dict]] | None,
    per_cable: bool = True,
) -> dict:
    """The block's shape (docs/recording-format.md), shared by both references: per
    baseline ``params`` (one dict per cable) and ``score`` (and the catalogue's,
    ``score["catalogue"]``); ``validated``: the scores' validation row is filled;
    ``dropped(on)``: the terms' errors (each ``term``, ``rmse_without_n``, ``rise_n``),
    asked for only when the catalogue does not beat the better baseline; ``per_cable``:
    False where the errors are not per cable (the wrench balance: empty lists)."""
    on = 1 if validated else 0
    kinds = list(params)

    def errors(s: Score, which: int, key: str) -> dict:
        return {
            f"{key}_rmse_n": s.overall(which),
            f"per_cable_{key}_rmse_n": s.per_cable(which) if per_cable else [],
        }

    out: dict = {"fits": {}}
    for k in kinds:
        ps = params[k]
        entry: dict = {
            "model": NAMES[k],
            "parameters": {p: [float(f[p]) for f in ps] for p in ps[0]} if ps else {},
            **errors(score[k], 0, "holdout"),
        }
        if validated:
            entry.update(errors(score[k], 1, "validation"))
        out["fits"][k] = entry
    cat = score["catalogue"]
    out["catalogue"] = errors(cat, 0, "holdout")
    if validated:
        out["catalogue"].update(errors(cat, 1, "validation"))
    best = min(kinds, key=lambda k: score[k].overall(on))
    ours, theirs = cat.overall(on), score[best].overall(on)
    out["compared_on"] = "validation" if validated else "holdout"
    out["best"] = best
    out["beaten"] = bool(ours <= theirs)
    out["margin"] = (theirs - ours) / theirs if theirs > 0 else 0.0
    if not out["beaten"] and dropped is not None:
        out["terms"] = sorted(dropped(on), key=lambda t: -float(t["rise_n"]))
    out["sentence"] = sentence(out)
    return out


def sentence(lsq: dict) -> str:
    """One sentence: does the catalogue's model beat the baselines, by how much, and if not,
    which baseline term carries what the catalogue lacks."""
    on = lsq["compared_on"]
    where = "the validation recording" if on == "validation" else "the held-out blocks"
    key = f"{on}_rmse_n"
    ours = lsq["catalogue"][key]
    parts = []
    for k, f in lsq["fits"].items():
        rel = (f[key] - ours) / f[key] if f[key] > 0 else 0.0
        word = "lower" if rel >= 0 else "higher"
        parts.append(f"{NAMES[k]} {f[key]:.3f} N (the catalogue's {abs(100 * rel):.1f} % {word})")
    head = (
        f"On {where} the catalogue's model ({ours:.3f} N) "
        f"{'beats' if lsq['beaten'] else 'does not beat'} the engineer's least squares: "
        + "; ".join(parts)
    )
    terms = lsq.get("terms")
    if lsq["beaten"] or not terms:
        return head + "."
    top = terms[0]
    return (
        f"{head}; dropping {TERM_WORDS[top['term']]} from {FIT_WORDS[TERM_FIT[top['term']]]} "
        f"raises its error most "
        f"(+{top['rise_n']:.3f} N): that term carries what the catalogue lacks."
    )
