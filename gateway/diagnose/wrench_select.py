"""Selection, fit and report of the wrench reference (:mod:`.wrench`).

Every candidate's per-cable parameters are identified jointly across cables through the
varying structure matrix. The residual is whitened by the noise the sensors put on the
wrench (:class:`wrench.Prepared`): generalised least squares.

1. **Sensitivities**: the Jacobian of the weighted residual with respect to every
   candidate's parameters at the nominal model; per candidate and cable its variance
   inflation decides identifiability (:func:`wrench.identifiability`): unidentifiable
   cables are not fitted and the report says so (``identifiability``).
2. **Selection** on the linearised residual, with the held-out machinery of
   :mod:`.select` (interleaved time blocks, :func:`select.holdout_z`, the same
   :class:`select.Thresholds`): forward steps (best held-out candidate, lenient test),
   then a strict backward check (each kept effect lowers the held-out SSE by >= 0.3 % and
   >= ``z_holdout`` standard errors against the model refitted without it, and some
   parameter differs from the nominal by >= ``z_min`` standard errors); until stable.
3. **Refit** of the kept effects by Gauss-Newton on the nonlinear residual (the Jacobian
   recomputed at the estimate), on the training blocks.
4. **Report**: every ``*_rmse_n`` is the RMS of the force part of the unweighted wrench
   residual (N, over the three components and the samples); moments in ``wrench``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gateway.core.config import Config, FrictionConfig
from gateway.diagnose import locate
from gateway.diagnose.engine import Diagnosis
from gateway.diagnose.report import rmse_pairs
from gateway.diagnose.select import Thresholds, holdout_z, overlaps
from gateway.diagnose.wrench import (
    PER_CABLE,
    SUBPARAMS,
    VIF_MAX,
    WRENCH_EFFECTS,
    Prepared,
    WrenchModel,
    identifiability,
    identifiable_cables,
    neutral,
    prepare,
    wrench_data,
)
from gateway.model import effects as fx
from gateway.recordings.reader import Recording

ROUNDS = 3
GN_ITERATIONS = 3
NOT_CANDIDATES = tuple(n for n in fx.EFFECT_NAMES if n not in WRENCH_EFFECTS)

Col = tuple[int, int]  # (sub-parameter index, cable)
SIGNATURE_POINTS = 20000


@dataclass
class WrenchDiagnosis(Diagnosis):
    """A :class:`Diagnosis` of the wrench reference. ``measured`` is zero (the balance),
    ``nominal_pred`` and ``final_pred`` minus the force residuals (N, 3) of the nominal and
    the final model (held: the balance is not per cable); ``signatures``: per finding,
    its contribution to the force residual and the residual the final model leaves
    without it (both flattened, thinned), for :mod:`.wrench_plots`."""

    signatures: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    nominal_pred: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    final_pred: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class WrenchSelector:
    """Selection over ``candidates`` on prepared data (see the module docstring)."""

    def __init__(self, prep: Prepared, candidates: tuple[str, ...], th: Thresholds) -> None:
        self.prep, self.th = prep, th
        self.model = prep.model
        self.rows = prep.rows
        self.blocks = prep.blocks[self.rows]
        use = prep.warm[self.rows]
        self.train = np.repeat((self.blocks % 2 == 0) & use, 6)
        self.test_s = (self.blocks % 2 == 1) & use
        self.r0 = prep.whiten(self.model.residual({})[self.rows]).reshape(-1)
        self.cols: dict[str, list[Col]] = {}
        self.design: dict[str, np.ndarray] = {}
        self.ident: dict[str, list[dict]] = {}
        for e in candidates:
            self.ident[e], self.cols[e], mats = [], [], []
            for j, jb in enumerate(self.model.jacobian({}, e, self.rows)):
                jw = prep.whiten(jb)
                idn = identifiability(jw, use)
                self.ident[e].append(idn)
                for i in identifiable_cables(idn):
                    mats.append(jw[:, :, i].reshape(-1))
                    self.cols[e].append((j, i))
            if mats:
                self.design[e] = np.column_stack(mats)
        self.candidates = [e for e in candidates if e in self.design]

    # ---- linear fits and held-out scores ----
    def _gram(self) -> None:
        """Normal equations of every candidate column on the training rows, once."""
        names = list(self.design)
        d = np.column_stack([self.design[e] for e in names])
        dt = d[self.train]
        self._gram_m = dt.T @ dt
        self._rhs = dt.T @ self.r0[self.train]
        self._rr = float(self.r0[self.train] @ self.r0[self.train])
        edges = np.cumsum([0] + [self.design[e].shape[1] for e in names])
        self._span = {e: np.arange(edges[k], edges[k + 1]) for k, e in enumerate(names)}

    def fit(self, effects: list[str]) -> tuple[dict[str, np.ndarray], dict, np.ndarray]:
        """Increments and standard errors per effect, and the weighted residual (N*6,)."""
        if not effects:
            return {}, {}, self.r0
        if not hasattr(self, "_gram_m"):
            self._gram()
        idx = np.concatenate([self._span[e] for e in effects])
        g, b = self._gram_m[np.ix_(idx, idx)], self._rhs[idx]
        ginv = np.linalg.pinv(g)
        phi = -ginv @ b
        resid = self.r0 + np.column_stack([self.design[e] for e in effects]) @ phi
        dof = max(int(self.train.sum()) - phi.size, 1)
        s2 = max(self._rr + 2 * float(phi @ b) + float(phi @ g @ phi), 0.0) / dof
        se = np.sqrt(np.maximum(np.diag(ginv) * s2, 0.0))
        sizes = np.cumsum([self.design[e].shape[1] for e in effects])[:-1]
        return (
            dict(zip(effects, np.split(phi, sizes), strict=True)),
            dict(zip(effects, np.split(se, sizes), strict=True)),
            resid,
        )

    def _block_sse(self, resid: np.ndarray) -> np.ndarray:
        per = np.sum(resid.reshape(-1, 6) ** 2, axis=1)
        sse = np.bincount(self.blocks[self.test_s], per[self.test_s], self.prep.n_blocks)
        return sse[1::2]

    def z(self, ra: np.ndarray, rb: np.ndarray) -> float:
        """Held-out z of model B (residual ``rb``) over model A (``ra``)."""
        cross = np.sum((rb * (ra - rb)).reshape(-1, 6), axis=1)
        per_block = np.bincount(self.blocks[self.test_s], cross[self.test_s], self.prep.n_blocks)
        return holdout_z(self._block_sse(ra), self._block_sse(rb), per_block)

    def accept(self, ra: np.ndarray, rb: np.ndarray, z_min: float) -> bool:
        before, after = float(self._block_sse(ra).sum()), float(self._block_sse(rb).sum())
        gain = before - after
        return gain >= self.th.rel_min * before and self.z(ra, rb) >= z_min

    # ---- selection ----
    def run(self) -> list[str]:
        kept: list[str] = []
        for _ in range(ROUNDS):
            before = list(kept)
            kept = self._forward(kept)
            kept = self._backward(kept)
            if kept == before:
                break
        return self._prefer_nested(kept)

    def _prefer_nested(self, kept: list[str]) -> list[str]:
        """A kept effect that reduces to a simpler one (``Effect.nests``) stays only if it
        passes the strict test against the model with the simpler one in its place."""
        for effect in list(kept):
            for simpler in fx.REGISTRY[effect].nests:
                if simpler.name in kept or simpler.name not in self.candidates:
                    continue
                trial = [simpler.name if e == effect else e for e in kept]
                _, _, full = self.fit(kept)
                _, _, reduced = self.fit(trial)
                if not self.accept(reduced, full, self.th.z_holdout):
                    kept = trial
        return kept

    def _forward(self, kept: list[str]) -> list[str]:
        kept = list(kept)
        while len(kept) < self.th.max_effects:
            _, _, base = self.fit(kept)
            best = None
            for e in (c for c in self.candidates if c not in kept and not overlaps(c, kept)):
                _, _, r = self.fit([*kept, e])
                sse = float(self._block_sse(r).sum())
                if self.accept(base, r, self.th.z_screen) and (best is None or sse < best[1]):
                    best = (e, sse)
            if best is None:
                break
            kept.append(best[0])
        return kept

    def _backward(self, kept: list[str]) -> list[str]:
        kept = list(kept)
        while kept:
            phi, se, full = self.fit(kept)
            weakest, worst = None, math.inf
            for e in kept:
                _, _, reduced = self.fit([k for k in kept if k != e])
                with np.errstate(divide="ignore", invalid="ignore"):
                    z_par = float(np.nanmax(np.where(se[e] > 0, np.abs(phi[e]) / se[e], 0.0)))
                ok = self.accept(reduced, full, self.th.z_holdout) and z_par >= self.th.z_min
                score = self.z(reduced, full)
                if not ok and score < worst:
                    weakest, worst = e, score
            if weakest is None:
                break
            kept.remove(weakest)
        return kept

    # ---- nonlinear refit ----
    def theta_of(self, increments: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        m = self.model.data.cables
        theta = {}
        for e, inc in increments.items():
            th = neutral(e, self.model.nom, m)
            for (j, i), dv in zip(self.cols[e], inc, strict=True):
                th[j, i] += dv
            theta[e] = th
        return theta

    def refit(self, kept: list[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Gauss-Newton on the nonlinear residual; returns theta and the stderr per column."""
        phi, se, _ = self.fit(kept)
        theta = self.theta_of(phi)
        for _ in range(GN_ITERATIONS if kept else 0):
            r = self.prep.whiten(self.model.residual(theta)[self.rows]).reshape(-1)
            cols = []
            for e in kept:
                blocks = [self.prep.whiten(b) for b in self.model.jacobian(theta, e, self.rows)]
                cols += [blocks[j][:, :, i].reshape(-1) for j, i in self.cols[e]]
            d = np.column_stack(cols)
            step, *_ = np.linalg.lstsq(d[self.train], -r[self.train], rcond=None)
            sizes = np.cumsum([len(self.cols[e]) for e in kept])[:-1]
            for e, inc in zip(kept, np.split(step, sizes), strict=True):
                for (j, i), dv in zip(self.cols[e], inc, strict=True):
                    theta[e][j, i] += dv
            if (
                np.max(np.abs(step) / np.maximum(np.concatenate([se[e] for e in kept]), 1e-300))
                < 1e-3
            ):
                break
        return theta, se


def force_rms(resid: np.ndarray, mask: np.ndarray | None = None) -> float:
    """RMS (N) of the force part of a wrench residual (N, 6) over components and samples."""
    f = resid[:, :3] if mask is None else resid[mask, :3]
    return float(math.sqrt(np.mean(f**2))) if f.size else 0.0


def _per_cable(effect: str) -> bool:
    return fx.REGISTRY[effect].per_cable


def _report_values(effect: str, theta: np.ndarray, cables: list[int]) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for j, name in enumerate(SUBPARAMS[effect]):
        out[name] = [float(theta[j, i if _per_cable(effect) else 0]) for i in cables]
    return out


def _fitted_cables(sel: WrenchSelector, effect: str) -> list[int]:
    if not _per_cable(effect):
        return list(range(sel.model.data.cables))
    return sorted({i for _, i in sel.cols[effect]})


def _stderr_values(sel: WrenchSelector, effect: str, se: np.ndarray, cables: list[int]) -> dict:
    table = {(j, i): float(s) for (j, i), s in zip(sel.cols[effect], se, strict=True)}
    out: dict[str, list[float]] = {}
    for j, name in enumerate(SUBPARAMS[effect]):
        out[name] = [table.get((j, i if _per_cable(effect) else 0), -1.0) for i in cables]
    return out


def _identifiability(sel: WrenchSelector) -> dict:
    """Per candidate: the cables the motion identifies (variance inflation <= VIF_MAX for
    every sub-parameter), the others, the inflations and the block's condition number."""
    out: dict[str, dict] = {}
    for e, blocks in sel.ident.items():
        if not _per_cable(e):
            out[e] = {"identifiable": bool(blocks[0]["live"][0]), "platform": True}
            continue
        ok = sorted(set.intersection(*(set(identifiable_cables(b)) for b in blocks)))
        vif = np.max(np.column_stack([b["vif"] for b in blocks]), axis=1)
        out[e] = {
            "identifiable_cables": [i + 1 for i in ok],
            "unidentifiable_cables": [i + 1 for i in range(vif.size) if i not in ok],
            "max_variance_inflation": [float(v) if math.isfinite(v) else -1.0 for v in vif],
            "condition": max(
                float(b["condition"]) if math.isfinite(b["condition"]) else -1.0 for b in blocks
            ),
        }
    return out


def _order(model: WrenchModel, theta: dict, mask: np.ndarray) -> list[str]:
    """Kept effects by the force residual energy each explains in the final model."""
    full = force_rms(model.residual(theta), mask) ** 2
    worth = {e: force_rms(model.residual({k: v for k, v in theta.items() if k != e}), mask) ** 2
             - full for e in theta}  # fmt: skip
    return sorted(theta, key=lambda e: worth[e], reverse=True)


def _missing(cables: list[int]) -> str:
    if not cables:
        return ""
    return f" Not identifiable from this motion on cables {cables} (not fitted there)."


def _evidence(effect: str, cables: list[int], values: dict, before: float, after: float) -> str:
    pct = 100.0 * (1.0 - after / before) if before > 0 else 0.0
    vals = ", ".join(
        f"{k} = {min(v):.4g}..{max(v):.4g}" if len(set(v)) > 1 else f"{k} = {v[0]:.4g}"
        for k, v in values.items()
    )
    where = (
        "the platform (one value for the whole recording)"
        if not _per_cable(effect)
        else f"cable{'s' if len(cables) > 1 else ''} {', '.join(str(c + 1) for c in cables)}"
    )
    return (
        f"Wrench balance (no platform tensions): {effect} on {where}, identified jointly "
        f"across cables through the varying structure matrix; fitted {vals}; it lowers the "
        f"held-out RMS of the force residual from {before:.3g} N to {after:.3g} N ({pct:.1f} %)."
    )


def diagnose_wrench(
    rec: Recording,
    friction: FrictionConfig,
    cfg: Config | None,
    validation: Recording | None = None,
    thresholds: Thresholds | None = None,
    progress=None,
) -> WrenchDiagnosis:
    """Diagnose ``rec`` against the platform's wrench balance (module docstring)."""
    say = progress or (lambda _msg: None)
    prep = prepare(rec, cfg, friction)
    data, model = prep.model.data, prep.model
    say(f"{rec.source}: wrench reference, {data.t.size} samples, sensitivities of "
        f"{len(WRENCH_EFFECTS)} candidate effects")  # fmt: skip
    sel = WrenchSelector(prep, WRENCH_EFFECTS, thresholds or Thresholds())
    kept = sel.run()
    say(f"wrench reference: kept {', '.join(kept) or 'nothing'}")
    theta, se = sel.refit(kept)
    test = (prep.blocks % 2 == 1) & prep.warm  # held-out samples, all of them
    order = _order(model, theta, test) if theta else []
    vmodel = None
    if validation is not None:
        vmodel = WrenchModel(wrench_data(validation, cfg), model.nom)

    def scores(effects: list[str]) -> tuple[float, float, float | None, np.ndarray]:
        th = {e: theta[e] for e in effects}
        r = model.residual(th)
        v = None if vmodel is None else force_rms(vmodel.residual(th))
        return force_rms(r), force_rms(r, test), v, r

    before = scores([])
    r_nominal = before[3]
    findings = []
    for k, e in enumerate(order):
        after = scores(order[: k + 1])
        cables = _fitted_cables(sel, e)
        values = _report_values(e, theta[e], cables)
        missing = [i + 1 for i in range(data.cables) if i not in cables]
        f = {
            "effect": e,
            "cables": [c + 1 for c in cables],
            "parameters": values,
            "stderr": _stderr_values(sel, e, se[e], cables),
            "evidence": _evidence(e, cables, values, before[1], after[1]) + _missing(missing),
            **rmse_pairs(before, after, vmodel is not None),
        }
        findings.append(f)
        before = after
    diag = _build(rec, prep, sel, findings, order, r_nominal, before, vmodel)
    step = max(1, data.t.size * 3 // SIGNATURE_POINTS)
    for e in order:
        without = model.residual({k: v for k, v in theta.items() if k != e})[:, :3]
        contrib = (without - before[3][:, :3]).reshape(-1)[::step]
        diag.signatures[e] = (contrib, without.reshape(-1)[::step])
    return diag


def _build(rec, prep, sel, findings, order, r_nominal, final, vmodel) -> WrenchDiagnosis:
    data = prep.model.data
    r_final = final[3]
    fs = np.median(np.abs(np.diff(r_final[:, :3], axis=0)), axis=0) / 0.6745 / math.sqrt(2)
    noise = float(math.sqrt(np.mean(fs**2)))
    fin = {
        "rmse_n": final[0],
        "holdout_rmse_n": final[1],
        "noise_n": noise,
        "unexplained_n": math.sqrt(max(final[1] ** 2 - noise**2, 0.0)),
        "moment_rmse_nm": float(math.sqrt(np.mean(r_final[:, 3:] ** 2))),
    }
    if vmodel is not None:
        fin["validation_rmse_before_n"] = force_rms(vmodel.residual({}))
        fin["validation_rmse_after_n"] = float(final[2] or 0.0)
    norm0 = np.linalg.norm(r_nominal[:, :3], axis=1)[:, None]
    regime = locate.regimes(data.speed, np.gradient(data.speed, data.t))[:, None]
    regions = [
        locate.Region(0, r.start_s, r.end_s, r.regime, r.share)
        for r in locate.regions(data.t, norm0, regime)
    ]
    report = {
        "reference": "wrench",
        "cables": rec.cables,
        "samples": int(data.t.size),
        "skipped_rows": rec.skipped_rows + (rec.samples - int(data.t.size)),
        "baseline": {"rmse_n": force_rms(r_nominal), "per_cable_rmse_n": []},
        **locate.report_fields(regions, norm0, regime),
        "findings": findings,
        "final": fin,
        "identifiability": _identifiability(sel),
        "wrench": {
            "candidates": list(WRENCH_EFFECTS),
            "not_candidates": list(NOT_CANDIDATES),
            "variance_inflation_max": VIF_MAX,
            "baseline_moment_rmse_nm": float(math.sqrt(np.mean(r_nominal[:, 3:] ** 2))),
            "per_cable_effects": list(PER_CABLE),
        },
    }
    zeros = np.zeros((data.t.size, 3))
    regimes = np.repeat(regime, 3, axis=1)
    return WrenchDiagnosis(report, data.t, zeros, regimes, regions, [], order, [],
                           nominal_pred=-r_nominal[:, :3], final_pred=-r_final[:, :3])  # fmt: skip
