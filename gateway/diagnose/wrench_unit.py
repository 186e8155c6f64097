"""The wrench balance (:mod:`.wrench`) as one unit of the one selector
(:class:`gateway.diagnose.selection.Unit`): every candidate's per-cable parameters
identified jointly across cables through the varying structure matrix, on the residual
whitened by the noise the sensors put on the wrench (:class:`wrench.Prepared`):
generalised least squares.

- **Sensitivities**: the Jacobian of the weighted residual with respect to every
  candidate's internal parameters (its own fit coordinates, :meth:`Effect.internal`) at
  its anchor: the nominal model, or the start its module declares (``Spec.starts``) that
  fits best, refined by Gauss-Newton steps; per candidate and cable its variance inflation
  decides identifiability (:func:`wrench.identifiability`): unidentifiable cables are not
  fitted and the report says so (``identifiability``).
- **Linear model**: the linearised residual fitted by linear least squares on the training
  samples (normal equations formed once), what the selector screens and tests.
- **Refit** of the kept effects by Gauss-Newton on the nonlinear residual (the Jacobian
  recomputed at the estimate), and their confirmation on it (:meth:`WrenchUnit.confirm`).

The stages that use it: :class:`gateway.diagnose.wrench_reference.WrenchReference`.
"""

from __future__ import annotations

import math

import numpy as np

from gateway.diagnose.selection import Model, Selector
from gateway.diagnose.wrench import (
    Prepared,
    identifiability,
    identifiable_cables,
    neutral,
)
from gateway.model import effects as fx

GN_ITERATIONS = 3
ANCHOR_STEPS = 5
"""Linearisations after the best anchor, each at the previous one's fit alone (kept where
the training error there is below the previous anchor's)."""
ANCHOR_GAIN = 1e-3
"""A step is not taken where the linear fit predicts less than this share of the training
error from it (a finding must lower the held-out error by ``Thresholds.rel_min``, 0.3 %)."""

Col = tuple[int, int]  # (sub-parameter index, cable)


class WrenchUnit:
    """The wrench balance as one selection unit (:class:`gateway.diagnose.selection.Unit`):
    every candidate's identifiable per-cable parameters enter the linearised, whitened
    residual (elements: sample x wrench component), fitted by linear least squares on the
    training samples (normal equations formed once).

    Each candidate is linearised at an **anchor** in its internal coordinates
    (:meth:`Effect.internal`): the nominal model, or one of the starting points its module
    declares (:attr:`Spec.starts`: a grid of stiffnesses, widths, time constants), the one
    whose linear fit alone leaves the least training error, then once more at that fit
    (:data:`ANCHOR_STEPS`). An effect that is nonlinear at its absent value (a dead zone of
    width 0, a rigid cable, a creep whose time constant means nothing at ``c = 0``) shows
    nothing to a linearisation there; from a start of its own size it does. Its model is
    ``r0 + shift + design phi``: ``shift`` the residual the anchor changes (zero at the
    nominal), ``phi`` the increments from the anchor.

    A candidate's design (elements x its columns, the whitened Jacobian) is never made
    for the linear model: column ``(j, i)`` is the whitened structure's column ``i`` at
    each sample times the sensitivity ``s_j[:, i]`` (a statics effect: the whitened
    wrench per kg times ``s_j``), so with ``X[n]`` the whitened structure and wrench per
    kg at sample ``n`` (6, m + 1) and ``G[n] = X[n]^T X[n]`` its per-sample Gram
    matrix, the normal equations are ``sum_n s_c[n] s_d[n] G[n, i_c, i_d]`` and
    ``sum_n s_c[n] (X[n]^T r[n])_{i_c}``, and a fit's residual is ``r + X[n] u[n]``
    with ``u[n, i] = sum_c phi_c s_c[n]`` over the columns of slot ``i``
    (:meth:`_gram`, :meth:`_applied`). What is kept is the sensitivities
    (:meth:`WrenchModel.sensitivities` at the rows, (n, m) per sub-parameter, 1/6 of a
    design for 8 cables). Made and kept, the designs were the diagnosis' peak memory
    (three kept, and two more made per block of the normal equations: ~150 MiB at
    :data:`wrench.FIT_BUDGET` rows of 8 cables) and a third of its CPU."""

    def __init__(
        self,
        prep: Prepared,
        candidates: tuple[str, ...],
        at: dict[str, np.ndarray] | None = None,
    ) -> None:
        self.prep = prep
        self.model = prep.model
        self.rows = prep.rows
        sample_blocks = prep.blocks[self.rows]
        use = prep.warm[self.rows]
        self.use = use
        self.blocks = np.repeat(sample_blocks, 6)
        self.n_blocks = prep.n_blocks
        self.train_samples = (sample_blocks % 2 == 0) & use
        self.train = np.repeat(self.train_samples, 6)
        self.test = np.repeat((sample_blocks % 2 == 1) & use, 6)
        # the whitened structure matrix and wrench per kg at the rows, made once: a
        # candidate's whitened Jacobian is then one product with its sensitivities
        # (:meth:`_whitened`), where each design made again was a product with ``A``, a
        # whitening and a copy column by column (half the selection's CPU on a 2-min
        # recording)
        # (n, 6, m + 1): the whitened structure matrix, and in the last column the
        # whitened wrench per kg (a statics effect's column)
        wa = prep.whiten(self.model.structure_at(self.rows))
        wdw = prep.whiten(self.model.data.external(self.rows)[1])
        self._m = wa.shape[2]
        self._wx = np.concatenate([wa, wdw[:, :, None]], axis=2)
        del wa, wdw
        self._last: tuple[list, np.ndarray] | None = None
        self.r0 = self._whitened_residual({})
        self.cols: dict[str, list[Col]] = {}
        self.sens: dict[str, dict[int, np.ndarray]] = {}
        self.ident: dict[str, list[dict]] = {}
        self.anchor: dict[str, np.ndarray] = {}
        self.shift: dict[str, np.ndarray] = {}
        at = at or {}
        self.at = at
        self.base = self.r0
        if at:
            self.base = self._whitened_residual(at)
        for e in candidates:
            if e in at:
                self._take_anchor(e, at[e], self._linearise(e, at[e], design=False))
            else:
                self._choose_anchor(e)
        self.candidates = [e for e in candidates if e in self.cols]
        self._gram(self.train)

    # ---- anchors ----
    def _anchors(self, effect: str) -> list[np.ndarray]:
        """The nominal model and the module's starting points, each (k, m)."""
        m = self.model.data.cables
        base = neutral(effect, self.model.nom, m)
        out = [base]
        for start in self.model.spec(effect).starts:
            a = np.repeat(np.asarray(start, dtype=float)[:, None], base.shape[1], axis=1)
            if not any(np.allclose(a, b, rtol=0.0, atol=0.0) for b in out):
                out.append(a)
        return out

    def _context(self, effect: str, anchor: np.ndarray) -> tuple[dict, bool]:
        """The parameters ``effect`` is linearised at (on top of ``at`` unless it is one
        of them) and whether its anchor is the nominal model."""
        at_nominal = np.array_equal(anchor, neutral(effect, self.model.nom, anchor.shape[1]))
        context = {} if effect in self.at else dict(self.at)
        return (context if at_nominal else {**context, effect: anchor}), at_nominal

    def _shift(self, effect: str, anchor: np.ndarray) -> np.ndarray | None:
        """What the anchor changes in the residual (None at the nominal model); an effect
        not in ``at`` on top of ``at``."""
        theta, at_nominal = self._context(effect, anchor)
        if at_nominal:
            return None
        below = self.r0 if effect in self.at or not self.at else self.base
        return self._whitened_residual(theta) - below

    def _whitened_residual(self, theta: dict[str, np.ndarray]) -> np.ndarray:
        """The whitened residual at the rows (elements,) of ``theta``: the nominal one
        from :class:`wrench.Prepared`, the last other one asked for kept (with one kept
        effect, ``at`` and that effect's anchor are the same parameters: one chain run
        over every sample, not two)."""
        if not theta and self.prep.nominal is not None:
            return self.prep.whiten(self.prep.nominal).reshape(-1)
        key = [(e, v.shape, v.tobytes()) for e, v in sorted(theta.items())]
        if self._last is None or self._last[0] != key:
            resid = self.prep.whiten(self.model.residual(theta, rows=self.rows)).reshape(-1)
            self._last = (key, resid)
        return self._last[1].copy()

    def _linearise(self, effect: str, anchor: np.ndarray, shift=False, design=True):
        """(identifiability per sub-parameter, columns, design, shift, sensitivities) at
        ``anchor`` (``shift``: the anchor's, when already known; ``design``: False, None
        in its place). The design at the training elements only (:meth:`_alone` reads
        no other; the same values as ``design[train]``)."""
        theta, _ = self._context(effect, anchor)
        ident, cols, mats = [], [], []
        sens = self.model.sensitivities(theta, effect, self.rows)
        for j, sj in enumerate(sens):
            jw = self._whitened(effect, sj)
            idn = identifiability(jw, self.use)
            ident.append(idn)
            for i in identifiable_cables(idn):
                if design:
                    mats.append(jw[self.train_samples, :, i].reshape(-1))
                cols.append((j, i))
            del jw
        design = np.column_stack(mats) if mats else None
        del mats
        shift = self._shift(effect, anchor) if shift is False else shift
        return ident, cols, design, shift, sens

    def _whitened(self, effect: str, sens: np.ndarray) -> np.ndarray:
        """One sub-parameter's whitened Jacobian (n, 6, m) at the rows ((n, 6, 1) for a
        statics effect): the whitening of :meth:`WrenchModel.expand` (linear, so the
        whitened ``A`` times the sensitivities, the same values to rounding)."""
        if fx.REGISTRY[effect].stage == "statics":
            return (sens[:, None] * self._wx[:, :, self._m])[:, :, None]
        return self._wx[:, :, : self._m] * sens[:, None, :]

    def _slot(self, effect: str, i: int) -> int:
        """The column of :attr:`_wx` a column ``(j, i)`` of ``effect`` scales: its cable,
        or the wrench per kg (``m``) for a statics effect."""
        return self._m if fx.REGISTRY[effect].stage == "statics" else i

    def _sens(self, effect: str, j: int, i: int) -> np.ndarray:
        """The sensitivity (n,) of column ``(j, i)`` of ``effect`` at the rows."""
        s = self.sens[effect][j]
        return s if s.ndim == 1 else s[:, i]

    def _applied(self, increments: dict[str, np.ndarray]) -> np.ndarray:
        """``sum_e design_e @ phi_e`` (elements,) without a design (class docstring)."""
        u = np.zeros((self.rows.size, self._m + 1))
        for e, phi in increments.items():
            for (j, i), p in zip(self.cols[e], phi, strict=True):
                u[:, self._slot(e, i)] += p * self._sens(e, j, i)
        return np.einsum("nik,nk->ni", self._wx, u).reshape(-1)

    def _samples(self, elements: np.ndarray) -> np.ndarray:
        """A mask of the elements (n * 6,) as a mask of the samples (n,): every mask the
        unit is given holds a sample's six wrench components together (blocks, warm-up)."""
        per = np.asarray(elements, bool).reshape(-1, 6)
        whole = np.asarray(per.all(axis=1), dtype=bool)
        if not np.array_equal(whole, per.any(axis=1)):
            raise ValueError("a mask of the wrench unit splits a sample's components")
        return whole

    def _columns(self, effect: str) -> int:
        return len(self.cols[effect])

    def _alone(self, design: np.ndarray, shift: np.ndarray | None):
        """Training sum of squares and increments of one linearisation fitted alone on top
        of :attr:`base` (the nominal residual, or the one at ``at``); ``design`` at the
        training elements (:meth:`_linearise`)."""
        r = self.base if shift is None else self.base + shift
        tr = self.train
        if not np.all(np.isfinite(design)) or not np.all(np.isfinite(r[tr])):
            return math.inf, None
        phi, *_ = np.linalg.lstsq(design, -r[tr], rcond=None)
        res = r[tr] + design @ phi
        return float(res @ res), phi

    def _cost(self, shift: np.ndarray | None) -> float:
        """Training sum of squares of the residual at an anchor (no linear step), on top of
        :attr:`base`."""
        r = (self.base if shift is None else self.base + shift)[self.train]
        return float(r @ r) if np.all(np.isfinite(r)) else math.inf

    def _choose_anchor(self, effect: str) -> None:
        """The anchor of ``effect`` (class docstring): the start whose linear fit alone
        leaves the least training error, then up to :data:`ANCHOR_STEPS` Gauss-Newton
        steps, each taken where the error at the new anchor is below the one at the old
        (also for an effect declared linear: a Coulomb level is not exactly linear through
        the chain, and without the steps the wrench round trip wrote ``mu`` 0.029 for
        0.025)."""
        best = None
        for anchor in self._anchors(effect):
            lin = self._linearise(effect, anchor)
            if effect not in self.ident:
                self.ident[effect] = lin[0]  # the nominal's, unless an anchor is taken
            if lin[2] is None:
                continue
            sse, phi = self._alone(lin[2], lin[3])
            lin = (*lin[:2], None, *lin[3:])  # made again when used (class docstring)
            if best is None or sse < best[0]:
                best = (sse, anchor, lin, phi)
        cost = self._cost(best[2][3]) if best is not None else math.inf
        steps = ANCHOR_STEPS if best is not None else 0
        for _ in range(steps):
            assert best is not None
            sse, anchor, lin, phi = best
            if phi is None or cost - sse < ANCHOR_GAIN * cost:
                break  # the step would change next to nothing
            moved = anchor.copy()
            for (j, i), dv in zip(lin[1], phi, strict=True):
                moved[j, i] += dv
            moved = self.bounded(effect, moved)
            if np.array_equal(moved, anchor):
                break
            moved_shift = self._shift(effect, moved)
            moved_cost = self._cost(moved_shift)
            if not moved_cost < cost:
                break  # the step does not lower the error it predicted: keep the anchor
            moved_lin = self._linearise(effect, moved, moved_shift)
            if moved_lin[2] is None:
                break
            sse, moved_phi = self._alone(moved_lin[2], moved_lin[3])
            moved_lin = (*moved_lin[:2], None, *moved_lin[3:])
            best, cost = (sse, moved, moved_lin, moved_phi), moved_cost
        if best is None:
            return
        self._take_anchor(effect, best[1], best[2])

    def _take_anchor(self, effect: str, anchor: np.ndarray, lin) -> None:
        ident, cols, _, shift, sens = lin
        self.anchor[effect], self.ident[effect] = anchor, ident
        if not cols:
            return
        self.cols[effect] = cols
        self.sens[effect] = {j: sens[j] for j in sorted({j for j, _ in cols})}
        if shift is not None:
            self.shift[effect] = shift

    def bounded(self, effect: str, theta: np.ndarray) -> np.ndarray:
        """``theta`` (k, m) within the effect's fit bounds (:attr:`Spec.lower`, ``upper``)."""
        return self.model.spec(effect).clip(theta)

    # ---- the linear model ----
    def _gram(self, train: np.ndarray, only: list[str] | None = None) -> None:
        """Normal equations of every candidate column (of the candidates ``only``) on the
        elements ``train`` (whole samples), from the sensitivities and the per-sample Gram
        matrices of the whitened structure (class docstring): no design is made. Each
        block's values do not depend on which others are formed."""
        names = [e for e in self.cols if only is None or e in only]
        edges = np.cumsum([0] + [self._columns(e) for e in names])
        k = int(edges[-1])
        samples = self._samples(train)
        wx = self._wx[samples]
        per_sample = np.einsum("nik,nil->nkl", wx, wx)  # (s, m + 1, m + 1)
        slots: dict[int, list[int]] = {}
        entries: dict[int, list[tuple[str, int, int]]] = {}
        for a, e in enumerate(names):
            for c, (j, i) in enumerate(self.cols[e]):
                slot = self._slot(e, i)
                slots.setdefault(slot, []).append(int(edges[a]) + c)
                entries.setdefault(slot, []).append((e, j, i))
        at = {q: np.asarray(c) for q, c in slots.items()}
        # each slot's sensitivities at the samples written into one array, column by
        # column: a list of the columns' copies stacked after held them twice (~14 MiB
        # more at the selection's peak on a 10-min 8-cable recording)
        n_samples = int(np.count_nonzero(samples))
        smat = {}
        for q, cols in entries.items():
            smat[q] = np.empty((n_samples, len(cols)))
            for c, (e, j, i) in enumerate(cols):
                smat[q][:, c] = self._sens(e, j, i)[samples]
        gram = np.zeros((k, k))
        order = sorted(at)
        for x, p in enumerate(order):
            for q in order[x:]:
                block = smat[p].T @ (per_sample[:, p, q, None] * smat[q])
                gram[np.ix_(at[p], at[q])] = block
                gram[np.ix_(at[q], at[p])] = block.T
        del per_sample

        def rhs_of(r: np.ndarray) -> np.ndarray:
            proj = np.einsum("nik,ni->nk", wx, r.reshape(-1, 6)[samples])  # X^T r
            out = np.zeros(k)
            for q in order:
                out[at[q]] = smat[q].T @ proj[:, q]
            return out

        rhs = rhs_of(self.r0)
        shift_rhs = {e: rhs_of(s) for e, s in self.shift.items()} if names else {}
        self._gram_m, self._rhs, self._shift_rhs = gram, rhs, shift_rhs
        self._mask = train
        self._dof = int(train.sum())
        self._span = {e: np.arange(edges[a], edges[a + 1]) for a, e in enumerate(names)}

    def _base(self, effects) -> np.ndarray:
        """The residual of ``effects`` at their anchors (``r0`` plus their shifts)."""
        r = self.r0
        for e in effects:
            if e in self.shift:
                r = r + self.shift[e]
        return r

    def linear(self, effects: list[str]) -> tuple[dict[str, np.ndarray], dict, np.ndarray]:
        """Increments (from the anchors) and standard errors per effect, and the weighted
        residual (N*6,)."""
        if not effects:
            return {}, {}, self.r0
        idx = np.concatenate([self._span[e] for e in effects])
        g, b = self._gram_m[np.ix_(idx, idx)], self._rhs[idx]
        for e in effects:
            if e in self._shift_rhs:
                b = b + self._shift_rhs[e][idx]
        ginv = np.linalg.pinv(g)
        phi = -ginv @ b
        sizes = np.cumsum([self._columns(e) for e in effects])[:-1]
        parts = np.split(phi, sizes)
        resid = self._base(effects) + self._applied(dict(zip(effects, parts, strict=True)))
        dof = max(self._dof - phi.size, 1)
        left = resid[self._mask]
        s2 = float(left @ left) / dof
        se = np.sqrt(np.maximum(np.diag(ginv) * s2, 0.0))
        return (
            dict(zip(effects, parts, strict=True)),
            dict(zip(effects, np.split(se, sizes), strict=True)),
            resid,
        )

    def _model(self, effects: list[str]) -> Model:
        phi, se, resid = self.linear(effects)
        return Model(phi, dict.fromkeys(effects), se, resid)

    def empty(self) -> Model:
        return Model({}, {}, {}, self.r0)

    def evaluate(self, theta: dict[str, np.ndarray], specs: dict) -> Model:
        resid = self._base(theta) + self._applied(theta) if theta else self._base(theta)
        nan = {e: np.full(v.size, np.nan) for e, v in theta.items()}
        return Model(dict(theta), dict(specs), nan, resid)

    def screen(self, model: Model, effect: str) -> Model:
        return self._model([*model.kept, effect])

    def fit(self, theta: dict[str, np.ndarray], specs: dict, nfev: int = 60) -> Model:
        return self._model(list(theta))

    def refit_on(self, model: Model, mask: np.ndarray, nfev: int = 20) -> dict[str, np.ndarray]:
        """The kept effects' increments fitted on the elements ``mask`` only."""
        whole = (self._gram_m, self._rhs, self._shift_rhs, self._mask, self._dof, self._span)
        self._gram(mask, list(model.kept))  # the kept effects' blocks only
        phi = self.linear(list(model.kept))[0]
        self._gram_m, self._rhs, self._shift_rhs, self._mask, self._dof, self._span = whole
        return phi

    def contribution(self, theta: dict[str, np.ndarray], effect: str) -> np.ndarray:
        """What ``effect`` adds to the (whitened, linearised) residual on the training
        elements (its anchor's shift included)."""
        c = self._applied({effect: theta[effect]})
        if effect in self.shift:
            c = c + self.shift[effect]
        return c[self.train]

    def significance(self, model: Model, effect: str) -> float:
        """How far ``effect`` lies from the nominal model: per cable its module's
        :meth:`Effect.significance` (internal parameters against their standard errors;
        parameters not fitted have none), the largest over the cables."""
        e = fx.REGISTRY[effect]
        theta = self.theta_of({effect: model.kept[effect]})[effect]
        se = np.zeros_like(theta)
        for (j, i), s in zip(self.cols[effect], model.stderr[effect], strict=True):
            se[j, i] = s
        base = neutral(effect, self.model.nom, theta.shape[1])
        cables = sorted({i for _, i in self.cols[effect]})
        with np.errstate(divide="ignore", invalid="ignore"):
            z = [e.significance(theta[:, i], se[:, i], base[:, i]) for i in cables]
        z = [v for v in z if math.isfinite(v)] or [0.0]
        return float(max(z))

    def drop_designs(self) -> None:
        """After the selection and the refit: what the designs are made of goes (the
        report reads :attr:`cols`, :attr:`ident` and the anchors only; ~37 MiB of
        sensitivities at :data:`wrench.FIT_BUDGET` rows of 8 cables, 11 MiB of whitened
        structure)."""
        self.sens.clear()
        self._wx = np.zeros((0, 6, self._m + 1))

    # ---- nonlinear refit ----
    def theta_of(self, increments: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Increments from the anchors -> internal parameters (k, m) per effect."""
        theta = {}
        for e, inc in increments.items():
            th = self.anchor[e].copy()
            for (j, i), dv in zip(self.cols[e], inc, strict=True):
                th[j, i] += dv
            theta[e] = th
        return theta

    def refit(self, kept: list[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Gauss-Newton on the nonlinear residual; returns theta and the stderr per column."""
        phi, se, _ = self.linear(kept)
        theta = {e: self.bounded(e, v) for e, v in self.theta_of(phi).items()}
        train = self.train
        for _ in range(GN_ITERATIONS if kept else 0):
            r = self.prep.whiten(self.model.residual(theta, rows=self.rows)).reshape(-1)
            cols = []
            for e in kept:
                blocks = [self.prep.whiten(b) for b in self.model.jacobian(theta, e, self.rows)]
                cols += [blocks[j][:, :, i].reshape(-1) for j, i in self.cols[e]]
            d = np.column_stack(cols)
            step, *_ = np.linalg.lstsq(d[train], -r[train], rcond=None)
            sizes = np.cumsum([len(self.cols[e]) for e in kept])[:-1]
            for e, inc in zip(kept, np.split(step, sizes), strict=True):
                for (j, i), dv in zip(self.cols[e], inc, strict=True):
                    theta[e][j, i] += dv
                theta[e] = self.bounded(e, theta[e])
            if (
                np.max(np.abs(step) / np.maximum(np.concatenate([se[e] for e in kept]), 1e-300))
                < 1e-3
            ):
                break
        return theta, se

    def nonlinear(self, theta: dict[str, np.ndarray]) -> Model:
        """The model at ``theta`` (internal parameters) with its nonlinear residual,
        whitened like the linear one (what the selector's held-out tests compare)."""
        resid = self.prep.whiten(self.model.residual(theta, rows=self.rows)).reshape(-1)
        return Model({}, {}, {}, resid)

    def confirm(
        self, selector: Selector, kept: list[str], say
    ) -> tuple[list[str], dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The kept effects checked on the nonlinear residual: each must pass the forward
        test (``z_screen``) against the refit without it; the weakest that does not is
        dropped and the rest refitted, until all pass. The linearisation a selection
        relies on is exact for a linear effect only: one linearised far from where it
        ends (a creep anchored on the nominal residual, then screened on top of a
        Maxwell-slip fit) can look better on held-out data than it is (measured: a creep
        kept with a Maxwell-slip raised the held-out force residual, 0.6529 -> 0.6555 N).
        Returns the kept effects, their refit and standard errors."""
        theta, se = self.refit(kept)
        while kept:
            full = self.nonlinear(theta)
            weakest: tuple[float, str] | None = None
            for e in kept:
                rest = [k for k in kept if k != e]
                reduced = self.nonlinear(self.refit(rest)[0] if rest else {})
                if not selector.accept(reduced, full, selector.th.z_screen):
                    z = selector.z(reduced, full)
                    if weakest is None or z < weakest[0]:
                        weakest = (z, e)
            if weakest is None:
                break
            say(f"{weakest[1]} not confirmed on the nonlinear residual (z {weakest[0]:.1f})")
            kept = [k for k in kept if k != weakest[1]]
            theta, se = self.refit(kept)
        return kept, theta, se


def force_rms(resid: np.ndarray, mask: np.ndarray | None = None) -> float:
    """RMS (N) of the force part of a wrench residual (N, 6), or of the force residual
    (N, 3), over components and samples."""
    f = resid[:, :3] if mask is None else resid[mask, :3]
    return float(math.sqrt(np.mean(f**2))) if f.size else 0.0
