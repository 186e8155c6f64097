"""The chain's parameters, stated once: the schema every form of the chain reads.

:data:`LAWS` (a friction law's name -> its code in the compiled pulley step), the per-cable
columns (:data:`COLUMNS`: name, shape, unit, neutral value, the effect that sets it),
:class:`ChainParams` (a validated chain), :class:`ChainDraft` (the chain while the chain-side
effects edit it), and the records the compiled kernels take (:class:`KernelParams`, built by
:func:`kernel_params`; :class:`ChainState`, what they carry from one sample to the next).
The law itself is in :mod:`gateway.model.chain_kernels` (physics.md sec. 2, 3); the batch
and per-cycle runs in :mod:`gateway.model.chain_runs`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import numpy as np

from gateway.model.friction import coulomb_ratio_exact

LAWS = {"none": 0, "coulomb": 1, "dahl": 2, "maxwell_slip": 3}
"""The law table: a friction law's name -> its code in the compiled pulley step
(:func:`gateway.model.chain_kernels._pulley` dispatches on it; the multi-element law in
:func:`gateway.model.chain_kernels._elements`). A new
chain-side law is one row here and its branch there; the effects that switch a chain to
it say so in their module."""
LAW_NONE, LAW_COULOMB, LAW_DAHL = LAWS["none"], LAWS["coulomb"], LAWS["dahl"]
LAW_SLIP = LAWS["maxwell_slip"]
ModelName = Literal["none", "coulomb", "dahl", "maxwell_slip"]


Shape = Literal["cable", "pulley", "element"]
"""A column's values per cable: one number (``cable``, (m,)), one per pulley (``pulley``,
(m, n)) or one per Maxwell-slip element (``element``, (m, K))."""


@dataclass(frozen=True)
class Column:
    """One per-cable parameter of the chain, declared once (:data:`COLUMNS`).

    ``default``: its value on a chain without the effect that sets it (the neutral value), or
    the name of the column whose value it takes then (``mu_in`` is ``mu``); ``owner``: the
    effect that sets it (its module), or ``nominal`` when the configured friction gives it
    (an attribute of the same name; effects may still change it); ``low`` / ``low_open``:
    what the chain admits."""

    name: str
    shape: Shape
    unit: str
    default: float | str
    owner: str
    doc: str
    low: float = -math.inf
    low_open: bool = False

    def check(self, value: np.ndarray) -> None:
        if (self.low_open and np.any(value <= self.low)) or np.any(value < self.low):
            raise ValueError(f"{self.name} must be {'>' if self.low_open else '>='} {self.low:g}")


COLUMNS: tuple[Column, ...] = (
    Column("mu", "pulley", "1", math.nan, "nominal", "bearing coefficient paying out (v > 0)"),
    Column("mu_in", "pulley", "1", "mu", "coulomb_directional", "bearing coefficient hauling in"),
    Column("sigma_n_m", "cable", "N/m", 500.0, "nominal", "presliding stiffness"),
    Column("viscous_ns_m", "cable", "N s/m", 0.0, "nominal", "viscous coefficient"),
    Column("f0_n", "cable", "N", 0.0, "coulomb", "load-independent Coulomb level of the chain"),
    Column("mu_load", "cable", "1/N", 0.0, "coulomb_load", "growth of mu with the tension", 0.0),
    Column("stribeck_k", "cable", "1", 0.0, "stribeck", "Stribeck excess at standstill"),
    Column("stribeck_v_m_s", "cable", "m/s", 0.01, "stribeck", "Stribeck speed", 0.0, True),
    Column("slip_w", "element", "1", 1.0, "maxwell_slip", "element fractions of the level"),
    Column(
        "slip_sigma", "element", "N/m", "sigma_n_m", "maxwell_slip", "element stiffness", 0.0, True
    ),
    Column("stretch_c", "cable", "m/N", 0.0, "cable_stretch", "compliance winch-pulleys", 0.0),
    Column("backlash_m", "cable", "m", 0.0, "backlash", "dead zone of the travel", 0.0),
)
"""The chain's per-cable parameters: :class:`ChainParams`' columns, :class:`ChainDraft`'s,
the keywords of :meth:`ChainParams.build` and (``cable`` ones) the columns of
:attr:`KernelParams.cable` are these, in this order."""
COLUMN = {c.name: c for c in COLUMNS}
CABLE_COLUMNS = tuple(c.name for c in COLUMNS if c.shape == "cable")
"""The columns of :attr:`KernelParams.cable`, in order."""
F0, STRIB_K, STRIB_V, VISCOUS, SIGMA, STRETCH, PLAY = (
    CABLE_COLUMNS.index(n)
    for n in (
        "f0_n",
        "stribeck_k",
        "stribeck_v_m_s",
        "viscous_ns_m",
        "sigma_n_m",
        "stretch_c",
        "backlash_m",
    )
)
"""Where the kernels read each ``cable`` column (numba takes them as constants)."""

ArrayLike = float | np.ndarray | tuple[float, ...]


def _shaped(col: Column, value: ArrayLike, cables: int, width: int) -> np.ndarray:
    """``value`` as ``col``'s (m,) or (m, width) array: a scalar, one value per pulley or
    element (width,), or the whole array; a (m,) column's value stands for every pulley or
    element of its cable when it is another column's default."""
    arr = np.asarray(value, dtype=float)
    if col.shape == "cable":
        if arr.ndim == 0:
            return np.full(cables, float(arr))
        if arr.shape != (cables,):
            raise ValueError(f"{col.name}: expected a scalar or shape ({cables},), got {arr.shape}")
        return arr.copy()
    shape = (cables, width)
    try:
        return np.broadcast_to(arr, shape).copy()
    except ValueError:
        raise ValueError(
            f"{col.name}: expected a scalar, ({width},) or {shape}, got {arr.shape}"
        ) from None


@dataclass(frozen=True, eq=False)
class ChainParams:
    """Friction parameters of ``m`` cable chains of ``n`` pulleys each.

    ``model``: the friction law (a key of :data:`LAWS`); ``wrap_rad`` (n,); ``beta``: Dahl
    shape exponent; ``columns``: every :data:`COLUMNS` entry by name, read as attributes
    (``params.mu``): ``mu``, ``mu_in`` (m, n) the bearing coefficients paying out (v > 0) and
    hauling in (v < 0); ``slip_w``, ``slip_sigma`` (m, K) the Maxwell-slip elements'
    fractions of the level (summing to 1 per cable; a fraction outside [0, 1] is the linear
    extension a fit's finite difference may step to) and stiffnesses per unit fraction
    (read by ``maxwell_slip`` only; default one element, ``w = 1``, ``sigma_n_m``); the
    others (m,) (:data:`COLUMNS` says what each is).
    """

    model: ModelName
    wrap_rad: np.ndarray
    beta: float
    columns: dict[str, np.ndarray]

    def __getattr__(self, name: str) -> np.ndarray:
        if name in COLUMN:
            return self.columns[name]
        raise AttributeError(name)

    @staticmethod
    def build(
        model: ModelName,
        cables: int,
        wrap_rad: np.ndarray | tuple[float, ...],
        mu: ArrayLike,
        *,
        beta: float = 1.0,
        **columns: ArrayLike | None,
    ) -> ChainParams:
        """Each column of :data:`COLUMNS` from ``mu`` and ``columns`` (None or absent: its
        default): a scalar, per pulley (n,) or per element (K,), or the whole array."""
        if model not in LAWS:
            raise ValueError(f"model must be one of {sorted(LAWS)}, got {model!r}")
        unknown = sorted(set(columns) - set(COLUMN))
        if unknown:
            raise ValueError(f"unknown chain parameter(s) {unknown} (known: {sorted(COLUMN)})")
        given = {**columns, "mu": mu}
        wrap = np.asarray(wrap_rad, dtype=float).reshape(-1)
        slip_w = np.asarray(1.0 if given.get("slip_w") is None else given["slip_w"], dtype=float)
        width = {"pulley": wrap.size, "element": slip_w.shape[-1] if slip_w.ndim else 1}
        out: dict[str, np.ndarray] = {}
        for col in COLUMNS:
            raw = given.get(col.name)
            if raw is None and isinstance(col.default, str):
                source = out[col.default]
                raw = source[:, None] if source.ndim == 1 and col.shape != "cable" else source
            elif raw is None:
                raw = float(col.default)
            value = _shaped(col, raw, cables, width.get(col.shape, 0))
            col.check(value)
            out[col.name] = value
        if np.any(np.abs(out["slip_w"].sum(axis=1) - 1.0) > 1e-9):
            raise ValueError("slip_w: fractions summing to 1")
        return ChainParams(model=model, wrap_rad=wrap, beta=float(beta), columns=out)

    @staticmethod
    def from_friction(friction: object, cables: int) -> ChainParams:
        """The nominal chain of a :class:`gateway.core.config.FrictionConfig` (same for every
        cable), without its fitted ``effects``: for those use
        :func:`gateway.model.effects.chain_params`."""
        return ChainDraft.nominal(friction, cables).params()

    def with_model(self, model: ModelName) -> ChainParams:
        return replace(self, model=model)

    @property
    def cables(self) -> int:
        return int(self.mu.shape[0])

    @property
    def pulleys(self) -> int:
        return int(self.wrap_rad.size)

    @property
    def elements(self) -> int:
        """State elements per pulley: the Maxwell-slip law's ``K``, else 1."""
        return int(self.slip_w.shape[1]) if LAWS[self.model] == LAW_SLIP else 1


class ChainDraft:
    """The friction chain of ``m`` cables while the chain-side effects edit it
    (:meth:`gateway.model.effects.base.Effect.apply_chain`), then :meth:`params`.

    ``law`` (a key of :data:`LAWS`), ``wrap_rad``, ``beta`` and every column of
    :data:`COLUMNS` as an attribute (``draft.stribeck_k``), each a whole array. A column
    whose default is another column's (``slip_sigma``: ``sigma_n_m``) follows that column
    until it is set itself.
    """

    law: str
    wrap_rad: np.ndarray
    beta: float
    _columns: dict[str, np.ndarray]
    _set: set[str]

    def __init__(self, law: str, wrap_rad: np.ndarray, beta: float, columns: dict[str, np.ndarray]):
        object.__setattr__(self, "_columns", columns)
        object.__setattr__(self, "_set", set())
        self.law, self.wrap_rad, self.beta = law, wrap_rad, beta

    @staticmethod
    def nominal(nom: object, cables: int) -> ChainDraft:
        """The nominal chain (a :class:`gateway.model.effects.base.NominalChain`: the
        ``nominal`` columns its attributes of the same names), every other column at its
        default."""
        given = {c.name: getattr(nom, c.name) for c in COLUMNS if c.owner == "nominal"}
        model = nom.model  # type: ignore[attr-defined]
        p = ChainParams.build(model, cables, nom.wrap_rad, **given)  # type: ignore[attr-defined]
        return ChainDraft(model, p.wrap_rad, float(nom.beta), dict(p.columns))  # type: ignore[attr-defined]

    def __getattr__(self, name: str) -> np.ndarray:
        if name in COLUMN:
            return self._columns[name]
        raise AttributeError(name)

    def __setattr__(self, name: str, value: object) -> None:
        if name not in COLUMN:
            object.__setattr__(self, name, value)
            return
        self._set.add(name)
        arr = np.asarray(value, dtype=float)
        self._columns[name] = arr
        for col in COLUMNS:  # a column that follows this one, unless set itself
            if col.default == name and col.name not in self._set:
                self._columns[col.name] = arr[:, None].copy() if arr.ndim == 1 else arr.copy()

    def needs_friction(self) -> None:
        """A friction effect on a frictionless nominal chain switches it to Coulomb."""
        if self.law == "none":
            self.law = "coulomb"

    def params(self) -> ChainParams:
        """The chain's parameters (validated)."""
        cables = int(self._columns["mu"].shape[0])
        return ChainParams.build(
            self.law,  # type: ignore[arg-type]
            cables,
            self.wrap_rad,
            beta=self.beta,
            **self._columns,
        )


POS, NEG, LOAD = 0, 1, 2
"""The planes of :attr:`KernelParams.lam`."""


class KernelParams(NamedTuple):
    """What the compiled kernels read, as one numba-compatible structure.

    ``lam`` (m, n, 3): per pulley the Coulomb coefficients for v > 0 and v < 0 and their
    growth with the tension ``2 sin(wrap / 2) mu_load`` (1/N) (planes :data:`POS`,
    :data:`NEG`, :data:`LOAD`; read by :func:`gateway.model.chain_kernels._level` only); ``cable``
    (m, C): the ``cable`` columns of :data:`COLUMNS` (:data:`CABLE_COLUMNS`, read at
    :data:`F0` .. :data:`PLAY`; one array: every array of the structure costs unboxing
    time per call);
    ``slip`` (m, K, 2): per Maxwell-slip element its fraction ``w`` and stiffness per unit
    fraction; ``beta``; ``law`` (:data:`LAWS`); Newton's ``tol`` (N^2 on the squared step)
    and ``max_iter``.
    """

    lam: np.ndarray
    cable: np.ndarray
    slip: np.ndarray
    beta: float
    law: int
    tol: float
    max_iter: int


def kernel_params(params: ChainParams, tol_n: float = 1e-10, max_iter: int = 20) -> KernelParams:
    """The kernels' view of ``params`` (Coulomb coefficients solved once here)."""
    load = params.mu_load[:, None] * 2.0 * np.sin(0.5 * params.wrap_rad)  # d lambda / d mu
    lam = np.stack([*coulomb_coefficients(params), load], axis=2)
    cable = np.column_stack([params.columns[n] for n in CABLE_COLUMNS])
    if params.elements > 1 or LAWS[params.model] == LAW_SLIP:
        slip = np.stack([params.slip_w, params.slip_sigma], axis=2)
    else:  # one element: the Dahl state (w = 1, sigma)
        slip = np.stack([np.ones(params.cables), params.sigma_n_m], axis=1)[:, None, :]
    return KernelParams(
        lam=np.ascontiguousarray(lam),
        cable=np.ascontiguousarray(cable),
        slip=np.ascontiguousarray(slip),
        beta=float(params.beta),
        law=LAWS[params.model],
        tol=float(tol_n),
        max_iter=int(max_iter),
    )


class ChainState(NamedTuple):
    """What the kernels carry from one sample to the next (updated in place).

    ``f`` (m, n, K): each state element of each pulley (K = 1 but for the Maxwell-slip
    law, whose elements are carried per unit fraction: a pulley's friction force is
    ``sum_q w_q f[i, j, q]``, :meth:`pulley_forces`); ``gap`` (m,): where the drive stands
    in the backlash's dead zone (in ``[-b/2, b/2]``, 0 at the start). Trial steps store
    nothing (:func:`gateway.model.chain_kernels._elements`), so no step allocates.
    """

    f: np.ndarray
    gap: np.ndarray

    @staticmethod
    def relaxed(params: ChainParams) -> ChainState:
        """The state of a chain at rest: every element force zero."""
        m, n, k = params.cables, params.pulleys, params.elements
        return ChainState(np.zeros((m, n, k)), np.zeros(m))

    def reset(self) -> None:
        """Every pulley relaxed, the drive centred in its dead zone."""
        self.f[:] = 0.0
        self.gap[:] = 0.0

    def pulley_forces(self, p: KernelParams) -> np.ndarray:
        """(m, n) friction force of each pulley (its elements weighted by their
        fractions), N."""
        if self.f.shape[2] == 1:
            return self.f[:, :, 0].copy()
        return np.einsum("ijq,iq->ij", self.f, p.slip[:, :, 0])


def coulomb_coefficients(params: ChainParams) -> tuple[np.ndarray, np.ndarray]:
    """``lambda_ij`` (m, n) for paying out and for reeling in, from the exact ratio.

    At sliding, ``T_j - T_{j-1} = s lambda_j T_j`` with ``n_j = 1 - s lambda_j`` the exact
    root of the Coulomb quadratic (:func:`friction.coulomb_ratio_exact`), so
    ``lambda = 1 - n(+)`` paying out (with ``mu``) and ``n(-) - 1`` reeling in (with
    ``mu_in``).
    """
    mu_in = params.mu_in if params.mu_in.shape == params.mu.shape else params.mu
    lam_pos = np.empty_like(params.mu)
    lam_neg = np.empty_like(params.mu)
    for (i, j), mu in np.ndenumerate(params.mu):
        wrap = float(params.wrap_rad[j])
        lam_pos[i, j] = 1.0 - coulomb_ratio_exact(float(mu), wrap, 1.0)
        lam_neg[i, j] = coulomb_ratio_exact(float(mu_in[i, j]), wrap, -1.0) - 1.0
    return lam_pos, lam_neg
