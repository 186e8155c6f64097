"""The engineer's least squares against the wrench balance: ``baseline.least_squares`` of
the wrench reference (issue 29 item 3; the platform-tension one: :mod:`.lsq`).

Without platform tensions the engineer writes per cable ``i`` a correction of the platform
tension the nominal chain gives from the reading, Coulomb + viscous + offset, with the
signs of :mod:`.lsq`'s ``T_s = T_p - f_c sgn(v) - c v + b`` (to first order through the
chain)::

    T_p,i = T_p,i(nominal) + f_c,i sgn(v_i) + c_i v_i - b_i

which enters the balance through the structure matrix the wrench path uses::

    r = r(nominal) + sum_i A[:, :, i] (f_c,i sgn(v_i) + c_i v_i - b_i)

``3 m`` unknowns, linear: fitted by linear least squares (``numpy.linalg.lstsq``, minimum
norm: a combination of the cables in the null space of ``A`` at every training pose, equal
offsets of a symmetric robot, i.e. pretension, is left at zero) on the diagnosis' own
training samples (its thinned ``rows`` in the even time blocks past the warm-up,
:attr:`WrenchUnit.train_samples`), the residual and the columns whitened as the diagnosis
whitens them (:meth:`.wrench.Prepared.whiten`: the same generalised least squares).
Scored as the wrench report scores the catalogue: the RMS of the force part of the
unweighted residual (N) over every held-out sample and over every sample of the
validation recording (``per_cable_*`` lists are empty: the balance is not per cable).
When the catalogue does not beat it, each term is dropped in turn and the rest refitted.
The report's block itself: :func:`.lsq.assemble`.

Cost (``python -m bench wrench_lsq``, 2-core machine under load): on a 20-s, 250 Hz,
8-cable recording with a validation recording as long, 0.05 s CPU of a ~21 s diagnosis
(with/without side by side: 21.3/20.5 s against 22.5/20.5 s, within the run-to-run
spread); on 10 min at 250 Hz (150 000 samples, 25 000 rows) with its terms dropped too,
2.3 s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gateway.diagnose import lsq
from gateway.diagnose.wrench import STRUCTURE_ROWS, Prepared, WrenchData, WrenchModel

TERMS = lsq.LINEAR_TERMS  # coulomb_n, viscous_ns_m, offset_n
FIT_ROWS = 2048
"""Training rows of the design made at a time (:func:`fit`): 2.4 MiB for 8 cables."""


def _regressors(v: np.ndarray, terms: Sequence[str]) -> list[np.ndarray]:
    """Each term's per-cable factor of the platform-tension correction (n, m)."""
    each = {"coulomb_n": np.sign(v), "viscous_ns_m": v, "offset_n": -np.ones_like(v)}
    return [each[t] for t in terms]


def _correction(v: np.ndarray, params: dict[str, np.ndarray]) -> np.ndarray:
    """The platform-tension correction (n, m) of ``params`` (term -> (m,))."""
    out = np.zeros_like(v)
    for t, x in zip(params, _regressors(v, list(params)), strict=True):
        out += params[t][None, :] * x
    return out


def fit(
    prep: Prepared, r0: np.ndarray, train: np.ndarray, terms: Sequence[str] = TERMS
) -> dict[str, np.ndarray]:
    """Per term its (m,) values, fitted on the samples ``prep.rows[train]`` to the whitened
    nominal residual ``r0`` (rows x 6, flattened or not) (module docstring); a term not in
    ``terms`` is zero."""
    data = prep.model.data
    m = data.cables
    out = {t: np.zeros(m) for t in TERMS}
    rows = prep.rows[train]
    if rows.size == 0 or not terms:
        return out
    # the design and the residual [D | y] reduced to their triangular factor R a part of
    # the training rows at a time (QR of the part stacked under the R so far): lstsq on R
    # gives D's minimum-norm solution, with D's own cutoff of small singular values
    # (numpy's default for D's shape); the whole design and its copies were the report's
    # peak memory on a 10-min recording (~60 MiB)
    width = len(terms) * m
    at = np.nonzero(train)[0]
    a_rows = prep.model.structure_at(prep.rows)
    y_rows = np.asarray(r0).reshape(-1, 6)
    tri = np.zeros((0, width + 1))
    for lo in range(0, at.size, FIT_ROWS):
        part = at[lo : lo + FIT_ROWS]
        a = a_rows[part]  # (n, 6, m)
        x = _regressors(data.v[prep.rows[part]], terms)
        cols = np.concatenate([a * c[:, None, :] for c in x], axis=2)
        design = prep.whiten(cols, among=part).reshape(-1, width)
        stacked = np.vstack([tri, np.column_stack([design, -y_rows[part].reshape(-1)])])
        tri = np.asarray(np.linalg.qr(stacked, mode="r"))
    cutoff = np.finfo(float).eps * max(6 * at.size, width)
    coef, *_ = np.linalg.lstsq(tri[:width, :width], tri[:width, width], rcond=cutoff)
    for k, t in enumerate(terms):
        out[t] = np.array(coef[k * m : (k + 1) * m], dtype=float)
    return out


def _sums(
    data: WrenchData, force0: np.ndarray, mask: np.ndarray | None, fits: list[dict]
) -> list[tuple[float, int]]:
    """Per fit, the sum of squares and count of the force residual ``force0`` (N, 3) with
    its correction, over ``mask`` (default every sample); :data:`STRUCTURE_ROWS` rows of
    ``A`` at a time."""
    sums = [0.0] * len(fits)
    n = data.t.size
    for a0 in range(0, n, STRUCTURE_ROWS):
        part = slice(a0, min(a0 + STRUCTURE_ROWS, n))
        keep = np.ones(part.stop - a0, bool) if mask is None else mask[part]
        if not keep.any():
            continue
        a = data.structure(part)[keep, :3, :]  # (k, 3, m)
        v = data.v[part][keep]
        for j, p in enumerate(fits):
            r = force0[part][keep] + np.einsum("nim,nm->ni", a, _correction(v, p))
            sums[j] += float(np.sum(r**2))
    count = 3 * (n if mask is None else int(mask.sum()))
    return [(s, count) for s in sums]


def block(
    prep: Prepared,
    r0: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
    force_nominal: np.ndarray,
    force_final: np.ndarray,
    validation: tuple[WrenchModel, float] | None = None,
) -> dict:
    """``baseline.least_squares`` of the wrench reference (module docstring): fitted on
    ``prep.rows[train]`` (``r0`` the whitened nominal residual there), scored on the
    held-out samples ``test`` (N,) bool beside the nominal and final force residuals
    ``force_nominal``, ``force_final`` (N, 3), and on the validation recording (its
    model, the final model's force RMS there)."""
    data = prep.model.data
    val = None  # the validation's data, nominal force residual, the final model's force RMS
    if validation is not None:
        vmodel, vfinal = validation
        val = (vmodel.data, vmodel.force_residual({})[0], vfinal)
    params = fit(prep, r0, train)
    score = {k: lsq.Score(1) for k in ("coulomb_viscous", "catalogue")}
    ((sse, n),) = _sums(data, force_nominal, test, [params])
    score["coulomb_viscous"].add_sums(0, 0, sse, n)
    score["catalogue"].add(0, 0, force_final[test].reshape(-1))
    if val is not None:
        ((sse, n),) = _sums(val[0], val[1], None, [params])
        score["coulomb_viscous"].add_sums(1, 0, sse, n)
        score["catalogue"].add_sums(1, 0, val[2] ** 2 * val[1].size, val[1].size)

    def dropped(on: int) -> list[dict]:
        """The fit's error with each term dropped in turn, the rest refitted."""
        fits = [fit(prep, r0, train, [t for t in TERMS if t != term]) for term in TERMS]
        if val is None:
            sums = _sums(data, force_nominal, test, fits)
        else:
            sums = _sums(val[0], val[1], None, fits)
        full = score["coulomb_viscous"].overall(on)
        out = []
        for term, (s, k) in zip(TERMS, sums, strict=True):
            rmse = float(np.sqrt(s / k)) if k else 0.0
            out.append({"term": term, "rmse_without_n": rmse, "rise_n": rmse - full})
        return out

    per_cable = [{t: float(params[t][i]) for t in TERMS} for i in range(data.cables)]
    return lsq.assemble(
        {"coulomb_viscous": per_cable}, score, val is not None, dropped, per_cable=False
    )
