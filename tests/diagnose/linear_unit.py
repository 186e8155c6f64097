"""A linear stand-in for a cable (the selector's :class:`gateway.diagnose.selection.Unit`):
each effect a few regressor columns, fitted by least squares on the training blocks (every
other one of ``n_blocks``), with the coefficients' standard errors. The pooling and the
nested-check tests build their cables from it."""

from __future__ import annotations

import numpy as np

from gateway.diagnose.selection import Model


class LinearUnit:
    """``y`` explained by ``cols`` (effect -> an (n, k) array of its regressors)."""

    def __init__(self, y: np.ndarray, cols: dict[str, np.ndarray], n_blocks: int = 40) -> None:
        n = y.size
        self.y = y
        self.cols = cols
        self.candidates = list(cols)
        self.n_blocks = n_blocks
        self.blocks = np.arange(n) * n_blocks // n
        self.train = self.blocks % 2 == 0
        self.test = self.blocks % 2 == 1

    def _model(self, theta: dict[str, np.ndarray], stderr=None) -> Model:
        pred = sum((self.cols[e] @ v for e, v in theta.items()), np.zeros(self.y.size))
        se = stderr or {e: np.full(v.size, np.nan) for e, v in theta.items()}
        return Model(dict(theta), {e: None for e in theta}, se, self.y - pred)

    def empty(self) -> Model:
        return self._model({})

    def evaluate(self, theta, specs) -> Model:
        return self._model(theta)

    def fit(self, theta, specs, nfev: int = 60) -> Model:
        names = list(theta)
        a = np.column_stack([self.cols[e] for e in names])
        at, yt = a[self.train], self.y[self.train]
        coef, *_ = np.linalg.lstsq(at, yt, rcond=None)
        var = float(np.mean((yt - at @ coef) ** 2)) * np.diag(np.linalg.pinv(at.T @ at))
        out, se, j = {}, {}, 0
        for e in names:
            w = self.cols[e].shape[1]
            out[e], se[e], j = coef[j : j + w], np.sqrt(var[j : j + w]), j + w
        return self._model(out, se)

    def screen(self, model: Model, effect: str) -> Model:
        return self.fit({**model.kept, effect: np.zeros(self.cols[effect].shape[1])}, None)

    def significance(self, model: Model, effect: str) -> float:
        return 10.0
