"""The cable path between force sensor and platform, both ways (physics.md sec. 2, 3).

``m`` cables, each passing ``n`` pulleys numbered from the sensor towards the platform.
Per pulley ``T_j = T_{j-1} + F_j`` where ``F_j`` is

* ``coulomb``: ``sgn(v) F_Rj`` (eq. 8, 11, 12),
* ``dahl``: the pre-sliding state stepped with :func:`friction.dahl_step` over the
  cable travel of each step (eq. 14), carried between calls,
* ``maxwell_slip``: ``K`` Dahl elements in parallel (generalised Maxwell-slip): element
  ``q`` holds the fraction ``w_q`` of the Coulomb level and has the stiffness
  ``w_q sigma_q``, each stepped like the Dahl state; ``F_j`` is their sum (one element
  with ``w = 1`` is ``dahl``). An element is carried per unit fraction, ``G_q`` with the
  whole level ``F_R`` and the stiffness ``sigma_q`` (``F_q = w_q G_q`` exactly: the Dahl
  step is homogeneous in level and stiffness), so ``F_j`` is linear in the fractions,
* ``none``: 0,

with the Coulomb level ``F_Rj = ((lambda_ij(s) + g_j mu1_i |T_j|) |T_j| + f0_i / n) S_i(v)``
(:func:`_level`; ``g_j mu1_i``: the coefficient's growth with the load, ``coulomb_load``;
physics.md:
``F_Rj = lambda_j T_j``, the level the Dahl state tends to): ``lambda_ij(s)`` is taken at
the exact per-direction Coulomb ratio ``n_j(s)`` (eq. 11, 12 solved as a quadratic, see
:func:`coulomb_coefficients`), so at steady sliding Dahl equals Coulomb exactly; ``f0`` is
a load-independent part (seals, preload; split evenly over the pulleys) and
``S = 1 + k exp(-(v / v_s)^2)`` the Stribeck factor. Viscous friction ``c_i v`` is added
at the platform end: ``T_p = T_n + c v``. ``|T|`` makes the law hold for push forces too
(a single-axis test rig).

Cable travel (the one definition every form uses): the setpoint travel
(:func:`travel_into`), the trapezoid over the actual sample times,
``dx_k = (v_{k-1} + v_k) / 2 (t_k - t_{k-1})``, ``dx_0 = 0``; then, per cable, in the
kernels (:func:`_step_cable`): minus the stretch change ``(F_k - F_{k-1}) c`` of the cable
between winch and pulleys (compliance ``c = 1 / k``; ``F = sum_j F_j`` the tension the
pulleys hold back, so the stretch the friction itself causes), then through the play
operator of width ``b`` (:func:`_play`, backlash: the drive stands still until the
setpoint has travelled ``b`` back across the gap). The Dahl and Maxwell-slip states
advance by that travel and take their direction from it, while the Coulomb sign, the
Stribeck factor and the viscous term take the sample's own ``v_k``.
(Stepping with ``v_k dt_k`` instead makes an error of the order ``a dt^2 / 2`` per step
that sampling jitter turns into noise: 0.13 N RMS on a noise-free 100 Hz +-2 ms recording.)

Simulation (platform -> sensor) is explicit: ``F_Rj`` follows from the known platform-side
tension, so each pulley is one exact Dahl step. Compensation (sensor -> platform) is
implicit in ``T_j``: Newton's iteration seeded with the previous cycle (``T_{j-1} +
F_old``) converges to 1e-9 N in one or two passes at 1 kHz (tests check it), stopping at
``tol_n`` or after ``max_iter`` passes. With a stretching cable the travel depends on the
friction the step produces: both directions solve for the drive per sample by a bracketed
secant (:func:`_step_cable`), and both read the same drive, so each inverts the other.

* :func:`compensate` / :class:`ChainStepper`: sensor reading ``T_s`` and setpoint velocity
  -> platform tension ``T_p`` (what the gateway does each cycle).
* :func:`simulate`: platform tension and velocity -> the sensor reading ``T_s`` (the plant).

Two compiled kernels (:func:`compensate_kernel`, :func:`simulate_kernel`) share the pulley
step and read their parameters from one :class:`KernelParams` and their state from one
:class:`ChainState`; ``compensate(simulate(T))`` returns ``T``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import numpy as np
from numba import njit

from gateway.fastcall import entry_point
from gateway.model.friction import FR_FLOOR_N, coulomb_ratio_exact, dahl_step_power, dahl_step_slope

LAWS = {"none": 0, "coulomb": 1, "dahl": 2, "maxwell_slip": 3}
"""The law table: a friction law's name -> its code in the compiled pulley step
(:func:`_pulley` dispatches on it; the multi-element law in :func:`_slip`). A new
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


_NEWTON_CURVATURE = 1.0
"""Bound, in 1/N, on |g''/(2 g')| for the pulley equation g(T) = T - T_a - F(T): F depends on
T only through F_R = lambda S |T| (+ f0), so g'' carries (lambda S)^2 ~ 1e-3 times the
Dahl step's curvature in F_R, far below 1/N for any tension that carries friction.
Newton's next correction is at most this times step^2, so a pass whose correction has
step^2 * bound <= tol leaves an error below tol: no confirming pass is needed."""


POS, NEG, LOAD = 0, 1, 2
"""The planes of :attr:`KernelParams.lam`."""


class KernelParams(NamedTuple):
    """What the compiled kernels read, as one numba-compatible structure.

    ``lam`` (m, n, 3): per pulley the Coulomb coefficients for v > 0 and v < 0 and their
    growth with the tension ``2 sin(wrap / 2) mu_load`` (1/N) (planes :data:`POS`,
    :data:`NEG`, :data:`LOAD`; read by :func:`_level` only); ``cable``
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
    nothing (:func:`_elements`), so no step allocates.
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


@njit(cache=True, inline="always")
def _level(p, i, j, t_b, dx, strib):
    """The Coulomb level ``F_R`` of pulley ``j`` of cable ``i`` whose platform-side tension
    is ``t_b``, moving in the direction of ``dx`` (not 0), and ``dF_R / dt_b``: the chain's
    law of the level, written once (module docstring)."""
    lam = p.lam[i, j, POS] if dx > 0.0 else p.lam[i, j, NEG]
    growth = p.lam[i, j, LOAD] * abs(t_b)  # coulomb_load: mu + mu1 |T|, to first order
    fr = ((lam + growth) * abs(t_b) + p.cable[i, F0] / p.lam.shape[1]) * strib
    return fr, (lam + 2.0 * growth) * strib * (1.0 if t_b >= 0.0 else -1.0)


@njit(cache=True, inline="always")
def _pulley(p, i, j, t_b, f_old, dx, strib):
    """Friction force of pulley ``j`` of cable ``i`` whose platform-side tension is
    ``t_b``, and dF/dt_b, by the chain's law (:data:`LAWS`; ``maxwell_slip``:
    :func:`_slip`).

    ``dx``: the step's cable travel (Dahl) or, for Coulomb, anything with the sign of
    the sample's velocity (only its sign is read); ``strib``: the Stribeck factor."""
    law = p.law
    if dx == 0.0:
        return (0.0 if law == LAW_COULOMB else f_old), 0.0
    s = 1.0 if dx > 0.0 else -1.0
    fr, dfr = _level(p, i, j, t_b, dx, strib)
    if law == LAW_COULOMB:
        return s * fr, s * dfr
    # LAW_DAHL
    if fr <= FR_FLOOR_N:
        return 0.0, 0.0
    sigma = p.cable[i, SIGMA]
    if p.beta == 1.0:
        f_new, slope = dahl_step_slope(f_old, fr, dx, sigma)
        return f_new, slope * dfr
    f_new = dahl_step_power(f_old, fr, dx, sigma, p.beta)
    return f_new, s * (1.0 - math.exp(-sigma * abs(dx) / fr)) * dfr  # quasi-Newton slope


@njit(cache=True, inline="always")
def _elements(p, i, j, t_b, f, dx, strib, store):
    """The presliding laws (Dahl, Maxwell-slip) of pulley ``j`` of cable ``i`` whose
    platform-side tension is ``t_b``, for the drive ``dx``: its elements ``f[i, j]`` (per
    unit fraction; Dahl: one with ``w = 1``) stepped, and stored back into ``f[i, j]``
    when ``store`` (a commit; else a trial, which stores nothing). Returns the force
    ``sum_q w_q G_q``, its derivative in ``t_b`` and in ``dx`` (at fixed ``t_b``). Element
    ``q`` per unit fraction is a Dahl state with the whole level ``F_R`` and the stiffness
    ``sigma_q`` (its relaxation length ``F_R / sigma_q``).

    ``store`` is a constant at every call site, so the compiler keeps only one branch. A
    trial that wrote its states into a scratch array cost three times a committed step:
    the compiler cannot tell the scratch from the parameters and states it reads, and
    reloads them after every store (measured, ``simulate`` of 150 000 samples of one
    stretching 3-pulley Dahl cable, k = 10^4 N/m, 2.9 trials a sample: 152 ms with scratch
    trials, 96 ms without; 6 ms for a rigid cable). The trial and the commit are compiled
    as two functions (:func:`_trial`, :func:`_commit`): inlined into the kernels they ran
    in 83 ms but took 2.8 GB and 65 s to compile, against 0.58 GB and 48 s.

    numba inlines at its own IR level and types every inlined copy again, so each copy
    costs compile time: the sample that needs no solve commits through :func:`_commit`
    (not a third inlined :func:`_through`), and the ``beta != 1`` step is
    :func:`friction.dahl_step_power`, without the checks and the ``beta = 1`` step that a
    whole :func:`friction.dahl_step` carried into every copy. Measured side by side (CPU
    seconds, a cold cache, the batch plant's kernels with the four test chains of
    ``simulate``): 146 s before, 102 s after; 150 000 x 8 samples of a stretching Dahl
    chain 910-1055 ms before, 977-1084 ms after, Maxwell-slip with play 1404-1466 and
    1182-1468 ms (five runs each, interleaved, machine shared). Keeping the inlining but
    calling ``dahl_step_power`` out of line compiled in 66 s but ran 20 % slower, although
    the stretching Dahl chain never takes that branch: a call in the loop costs more than
    its execution."""
    k_el = f.shape[2]
    total = 0.0
    if dx == 0.0:
        for q in range(k_el):
            total += p.slip[i, q, 0] * f[i, j, q]
        return total, 0.0, 0.0
    s = 1.0 if dx > 0.0 else -1.0
    fr, dfr = _level(p, i, j, t_b, dx, strib)
    if fr <= FR_FLOOR_N:
        if store:
            for q in range(k_el):
                f[i, j, q] = 0.0
        return 0.0, 0.0, 0.0
    slope = 0.0
    ddx = 0.0
    for q in range(k_el):
        w = p.slip[i, q, 0]
        sigma = p.slip[i, q, 1]
        g = f[i, j, q]
        e = math.exp(-sigma * abs(dx) / fr)
        if p.beta == 1.0:
            rest = g - s * fr
            g_new = s * fr + rest * e
            sl = s * (1.0 - e) + rest * e * sigma * abs(dx) / (fr * fr)
            ddx += w * sigma * (1.0 - s * g / fr) * e
        else:
            g_new = dahl_step_power(g, fr, dx, sigma, p.beta)
            sl = s * (1.0 - e)  # quasi-Newton slopes
            ddx += w * sigma * e
        if store:
            f[i, j, q] = g_new
        total += w * g_new
        slope += w * sl
    return total, slope * dfr, ddx


@njit(cache=True, inline="always")
def _stribeck(p, i, v):
    if p.cable[i, STRIB_K] == 0.0:
        return 1.0
    return 1.0 + p.cable[i, STRIB_K] * math.exp(-((v / p.cable[i, STRIB_V]) ** 2))


@njit(cache=True)
def travel_into(vel, dt, v_prev, dx):
    """Setpoint travel of each step (m), the trapezoid over the actual sample spacing:
    ``dx[k, i] = (v_prev[i] + vel[k, i]) / 2 * dt[k]`` with ``v_prev`` the velocity of the
    step before, updated in place (so a per-cycle caller carries it). ``vel``, ``dx``
    (N, m); ``dt`` (N,); ``v_prev`` (m,). The kernels drive the friction state with it
    through :func:`_step_cable` (stretch, backlash)."""
    for k in range(vel.shape[0]):
        for i in range(vel.shape[1]):
            dx[k, i] = 0.5 * (v_prev[i] + vel[k, i]) * dt[k]
            v_prev[i] = vel[k, i]


@njit(cache=True, inline="always")
def _play(gap, d, width):
    """The play operator: the drive's position in the dead zone ``gap`` moved by ``d``;
    returns (the drive's travel, the new gap). Inside ``[-width/2, width/2]`` nothing
    moves; at an edge the drive follows."""
    g = gap + d
    half = 0.5 * width
    if g > half:
        return g - half, half
    if g < -half:
        return g + half, -half
    return 0.0, g


@njit(cache=True, inline="always")
def _direction(law, v, dx):
    """What sets the pulley's direction: the velocity for Coulomb, the travel for Dahl
    and Maxwell-slip."""
    return v if law == LAW_COULOMB else dx


@njit(cache=True, inline="always")
def _chain_force(p, f, i):
    """Cable ``i``'s pulleys' friction, ``sum_j F_j``, from the element states ``f``."""
    total = 0.0
    for j in range(f.shape[1]):
        for q in range(f.shape[2]):
            total += p.slip[i, q, 0] * f[i, j, q]
    return total


@njit(cache=True, inline="always")
def _through(p, st, i, forward, t_known, v, strib, d_raw, store):
    """Cable ``i`` through its pulleys for one sample whose drive before the dead zone is
    ``d_raw``: from the sensor side (``forward``: ``t_known`` the sensor-side tension,
    Newton per pulley) or from the platform side (``t_known`` the platform tension,
    explicit). The element states come from ``st.f`` and, when ``store`` (a commit; else a
    trial), go back there (:func:`_elements`). Returns the other end's tension, the
    pulleys' friction ``F = sum_j F_j``, ``dF / d(d_raw)`` at fixed tensions, and the most
    Newton passes."""
    n = p.lam.shape[1]
    d = d_raw
    moving = 1.0
    if p.cable[i, PLAY] != 0.0:
        d = _play(st.gap[i], d_raw, p.cable[i, PLAY])[0]
        moving = 1.0 if d != 0.0 else 0.0
    coulomb = p.law == LAW_COULOMB
    dx = v if coulomb else d
    worst = 0
    force = 0.0
    slope_d = 0.0
    if p.law == LAW_NONE:
        out = t_known + p.cable[i, VISCOUS] * v if forward else t_known - p.cable[i, VISCOUS] * v
        return out, 0.0, 0.0, 0
    if forward:
        t_a = t_known
        for j in range(n):
            f_old = _chain_force_pulley(p, st.f, i, j)
            t_b = t_a + f_old
            it = 0
            while it < p.max_iter:
                it += 1
                if coulomb:
                    f_new, d_b = _pulley(p, i, j, t_b, f_old, dx, strib)
                else:
                    f_new, d_b, _ = _elements(p, i, j, t_b, st.f, dx, strib, False)
                step = (t_b - t_a - f_new) / (1.0 - d_b)
                t_prev = t_b
                t_b -= step
                # as in _compensate_plain: a step that crossed or landed on T = 0 (the kink
                # of |T|) is not confirmed by the curvature bound
                if step * step * _NEWTON_CURVATURE <= p.tol and t_prev * t_b > 0.0:
                    break
            if coulomb:
                if store:
                    st.f[i, j, 0] = t_b - t_a
            else:
                f_new, _, dd = _elements(p, i, j, t_b, st.f, dx, strib, store)
                slope_d += dd
            worst = max(worst, it)
            t_a = t_b
        force = t_a - t_known
        return t_a + p.cable[i, VISCOUS] * v, force, slope_d * moving, worst
    t_b = t_known - p.cable[i, VISCOUS] * v
    for j in range(n - 1, -1, -1):
        if coulomb:
            f_new, _ = _pulley(p, i, j, t_b, st.f[i, j, 0], dx, strib)
            if store:
                st.f[i, j, 0] = f_new
        else:
            f_new, _, dd = _elements(p, i, j, t_b, st.f, dx, strib, store)
            slope_d += dd
        t_b -= f_new
        force += f_new
    return t_b, force, slope_d * moving, 0


@njit(cache=True, inline="always")
def _chain_force_pulley(p, f, i, j):
    """Pulley ``j`` of cable ``i``'s friction force from its elements."""
    total = 0.0
    for q in range(f.shape[2]):
        total += p.slip[i, q, 0] * f[i, j, q]
    return total


@njit(cache=True)
def _trial(p, st, i, forward, t_known, v, strib, d):
    """:func:`_through` storing nothing: the pulleys' friction and its slope in ``d``."""
    return _through(p, st, i, forward, t_known, v, strib, d, False)[1:3]


@njit(cache=True)
def _commit(p, st, i, forward, t_known, v, strib, d):
    """:func:`_through` storing the states."""
    return _through(p, st, i, forward, t_known, v, strib, d, True)


@njit(cache=True)
def _step_cable(p, st, i, forward, t_known, v, strib, dx_set):
    """One sample of cable ``i`` (general path): with a stretching cable the drive ``d``
    solves ``g(d) = d - dx_set + (F(d) - F_old) c = 0`` (``F`` the pulleys' friction after
    the step, ``F_old`` before it) by Newton's iteration from ``dx_set`` with the slope
    ``1 + c dF/dd``, kept inside the bracket its own steps find (bisection where a step
    leaves it: ``g`` has kinks where the drive changes sign or meets the dead zone's edge).
    ``g`` rises with slope >= 1 wherever the friction grows with its travel, so the root
    is unique. Once a step is below 1e-9 of the drive it is taken without another trial
    (Newton's error after it is about (1e-9)^2 of the drive). The trials store nothing;
    the root is evaluated once more to commit its states, and the dead zone moved. Returns
    the other end's tension and the most Newton passes."""
    c = p.cable[i, STRETCH]
    if c == 0.0 or p.law == LAW_NONE or p.law == LAW_COULOMB:
        out, _, _, worst = _commit(p, st, i, forward, t_known, v, strib, dx_set)
        if p.cable[i, PLAY] != 0.0:
            st.gap[i] = _play(st.gap[i], dx_set, p.cable[i, PLAY])[1]
        return out, worst
    f_old = _chain_force(p, st.f, i)
    lo, hi = -math.inf, math.inf
    d = dx_set
    passes = 4 * p.max_iter + 20
    for it in range(passes):
        force, slope = _trial(p, st, i, forward, t_known, v, strib, d)
        g = d - dx_set + c * (force - f_old)
        if g == 0.0:
            break
        if g > 0.0:
            hi = min(hi, d)
        else:
            lo = max(lo, d)
        gp = 1.0 + c * slope
        nxt = d - g / (gp if gp > 0.5 else 1.0)
        if not lo < nxt < hi and math.isfinite(lo) and math.isfinite(hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - d) <= 1e-18 + 1e-9 * abs(nxt):
            d = nxt  # Newton's error after a step of 1e-9 d: about (1e-9)^2 d
            break
        if it == passes - 1:
            break  # out of passes: commit the last d evaluated
        d = nxt
    out, _, _, worst = _commit(p, st, i, forward, t_known, v, strib, d)
    if p.cable[i, PLAY] != 0.0:
        st.gap[i] = _play(st.gap[i], d, p.cable[i, PLAY])[1]
    return out, worst


@njit(cache=True, inline="always")
def _rigid(p):
    """True when the chain has a presliding state and no cable stretches: its drive is
    explicit (the setpoint travel, through a dead zone where there is one)."""
    if p.law != LAW_DAHL and p.law != LAW_SLIP:
        return False
    for i in range(p.cable.shape[0]):  # noqa: SIM110 (numba: a plain loop)
        if p.cable[i, STRETCH] != 0.0:
            return False
    return True


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _simulate_rigid(p, t_in, vel, dx_all, st, out):
    """:func:`simulate_kernel` for a :func:`_rigid` chain (the general path's explicit
    case, without its per-sample solve)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
    f_state = st.f
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = dx_all[k, i]
            width = p.cable[i, PLAY]
            if width != 0.0:
                dx, st.gap[i] = _play(st.gap[i], dx, width)
            t_b = t_in[k, i] - p.cable[i, VISCOUS] * v
            strib = _stribeck(p, i, v)
            for j in range(n - 1, -1, -1):
                t_b -= _elements(p, i, j, t_b, f_state, dx, strib, True)[0]
            out[k, i] = t_b
    return 0


@njit(cache=True, inline="always")
def _plain(p):
    """True when the chain is one-element (not Maxwell-slip) and every cable's travel is
    the setpoint's (no stretch, no dead zone): the kernels' fast path."""
    if p.law == LAW_SLIP:
        return False
    for i in range(p.cable.shape[0]):
        if p.cable[i, STRETCH] != 0.0 or p.cable[i, PLAY] != 0.0:
            return False
    return True


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _compensate_plain(p, t_in, vel, dx_all, f_state, out):
    """:func:`compensate_kernel` for a :func:`_plain` chain, ``f_state`` (m, n)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
    worst = 0
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = _direction(p.law, v, dx_all[k, i])
            t_a = t_in[k, i]
            if p.law != LAW_NONE:
                strib = _stribeck(p, i, v)
                for j in range(n):
                    f_old = f_state[i, j]
                    t_b = t_a + f_old
                    it = 0
                    while it < p.max_iter:
                        it += 1
                        f_new, d_b = _pulley(p, i, j, t_b, f_old, dx, strib)
                        step = (t_b - t_a - f_new) / (1.0 - d_b)
                        t_prev = t_b
                        t_b -= step
                        # the curvature bound holds on one side of T = 0 (|T| has its kink
                        # there): a step that crossed it or landed on it is not confirmed
                        if step * step * _NEWTON_CURVATURE <= p.tol and t_prev * t_b > 0.0:
                            break
                    f_state[i, j] = t_b - t_a
                    worst = max(worst, it)
                    t_a = t_b
            out[k, i] = t_a + p.cable[i, VISCOUS] * v
    return worst


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def compensate_kernel(p, t_in, vel, dx_all, st, out):
    """Sensor -> platform for (N, m) ``t_in``, ``vel``, setpoint travel ``dx_all``
    (:func:`travel_into`) and ``out``; ``st`` (:class:`ChainState`) in/out. Each pulley's
    implicit equation by Newton, seeded with the previous cycle's force. Returns the largest
    number of Newton passes any pulley needed."""
    n_samples, m = t_in.shape
    if _plain(p):
        f_state = st.f
        return _compensate_plain(p, t_in, vel, dx_all, f_state.reshape((m, f_state.shape[1])), out)
    worst = 0
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            strib = _stribeck(p, i, v)
            out[k, i], it = _step_cable(p, st, i, True, t_in[k, i], v, strib, dx_all[k, i])
            worst = max(worst, it)
    return worst


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _simulate_plain(p, t_in, vel, dx_all, f_state, out):
    """:func:`simulate_kernel` for a :func:`_plain` chain, ``f_state`` (m, n)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = _direction(p.law, v, dx_all[k, i])
            t_b = t_in[k, i] - p.cable[i, VISCOUS] * v
            if p.law != LAW_NONE:
                strib = _stribeck(p, i, v)
                for j in range(n - 1, -1, -1):
                    f_new, _ = _pulley(p, i, j, t_b, f_state[i, j], dx, strib)
                    f_state[i, j] = f_new
                    t_b -= f_new
            out[k, i] = t_b
    return 0


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def simulate_kernel(p, t_in, vel, dx_all, st, out):
    """Platform -> sensor, same arguments as :func:`compensate_kernel`; explicit (each
    pulley's Coulomb level follows from its known platform-side tension) but for a
    stretching cable (:func:`_step_cable`)."""
    n_samples, m = t_in.shape
    if _plain(p):
        f_state = st.f
        return _simulate_plain(p, t_in, vel, dx_all, f_state.reshape((m, f_state.shape[1])), out)
    if _rigid(p):
        return _simulate_rigid(p, t_in, vel, dx_all, st, out)
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            strib = _stribeck(p, i, v)
            out[k, i] = _step_cable(p, st, i, False, t_in[k, i], v, strib, dx_all[k, i])[0]
    return 0


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


BATCH_ROWS = 32768  # rows per kernel call in the batch forms (bounds the travel array)


def _time_steps(t: np.ndarray | float, n_samples: int) -> np.ndarray:
    """``dt_k = t_k - t_{k-1}`` with ``dt_0 = 0`` (no travel before the first sample)."""
    if np.ndim(t) == 0:
        dt = np.full(n_samples, float(t))
        dt[0] = 0.0
        return dt
    t_arr = np.asarray(t, dtype=float)
    if t_arr.shape != (n_samples,):
        raise ValueError(f"t: expected shape ({n_samples},), got {t_arr.shape}")
    return np.concatenate(([0.0], np.diff(t_arr)))


def travel(t: np.ndarray | float, velocity: np.ndarray) -> np.ndarray:
    """Cable travel (N, m) of each step, m, for velocity (N, m) at times ``t`` (N,) or a
    constant period: :func:`travel_into` with no travel at the first sample."""
    vel = np.ascontiguousarray(velocity, dtype=float)
    dx = np.empty_like(vel)
    if vel.shape[0]:
        travel_into(vel, _time_steps(t, vel.shape[0]), vel[0].copy(), dx)
    return dx


def new_state(params: ChainParams) -> ChainState:
    """Friction state of ``params``' chain: relaxed (every pulley force zero)."""
    return ChainState.relaxed(params)


def _run_batch(
    params: ChainParams,
    forward: bool,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None,
    tol_n: float,
    max_iter: int,
) -> np.ndarray:
    out = np.empty(np.shape(tension))
    for _ in _batches(params, forward, tension, velocity, t, state, tol_n, max_iter, out):
        pass
    return out


def _batches(
    params: ChainParams,
    forward: bool,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None,
    tol_n: float,
    max_iter: int,
    out: np.ndarray,
    rolling: bool = False,
) -> Iterator[int]:
    """The batch forms' work into ``out`` (N, m), one kernel call per :data:`BATCH_ROWS`
    rows; yields the rows done after each call (``out[:b]`` is final). ``rolling``:
    ``out`` holds one batch (``BATCH_ROWS``, m), each batch's rows from its start (the
    kernels only write ``out``)."""
    t_in = np.ascontiguousarray(tension, dtype=float)
    vel = np.ascontiguousarray(velocity, dtype=float)
    if t_in.ndim != 2 or t_in.shape[1] != params.cables or vel.shape != t_in.shape:
        raise ValueError(
            f"tension and velocity must both have shape (N, {params.cables}); "
            f"got {t_in.shape} and {vel.shape}"
        )
    f_state = new_state(params) if state is None else state
    kernel = compensate_kernel if forward else simulate_kernel
    p = kernel_params(params, tol_n, max_iter)
    n = t_in.shape[0]
    if n == 0:
        return
    dt = _time_steps(t, n)
    # the travel in row blocks (the friction state and the previous velocity carried
    # across): a 10-min, 8-cable run would otherwise hold a 38 MB travel array
    dx = np.empty((min(n, BATCH_ROWS), t_in.shape[1]))
    v_prev = vel[0].copy()
    for a in range(0, n, BATCH_ROWS):
        b = min(a + BATCH_ROWS, n)
        travel_into(vel[a:b], dt[a:b], v_prev, dx[: b - a])
        kernel(p, t_in[a:b], vel[a:b], dx[: b - a], f_state, out[: b - a] if rolling else out[a:b])
        yield b


def simulate_rows(
    params: ChainParams,
    tension_platform: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    out: np.ndarray,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> Iterator[int]:
    """:func:`simulate` (from the relaxed state) into ``out`` (N, m), yielding the rows done
    so far after each batch of :data:`BATCH_ROWS` (the values bit for bit those of
    :func:`simulate`): a caller may stop early, e.g. once the error of the rows done
    already rules a trial out."""
    return _batches(params, False, tension_platform, velocity, t, None, tol_n, max_iter, out)


def simulate(
    params: ChainParams,
    tension_platform: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None = None,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray:
    """Sensor reading (N, m) from platform tension and cable velocity, both (N, m).

    ``t``: sample times (N,) in s, or a constant period. ``state``
    (:class:`ChainState`): carried in and updated in place (relaxed if None).
    """
    return _run_batch(params, False, tension_platform, velocity, t, state, tol_n, max_iter)


def compensate(
    params: ChainParams,
    tension_sensor: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None = None,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray:
    """Platform tension (N, m) from the sensor reading and the setpoint velocity."""
    return _run_batch(params, True, tension_sensor, velocity, t, state, tol_n, max_iter)


def compensate_rows(
    params: ChainParams,
    tension_sensor: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    rows: np.ndarray,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray:
    """:func:`compensate` (from the relaxed state) kept at the samples ``rows`` only
    (increasing indices): (n, m), bit for bit ``compensate(...)[rows]``. The chain runs
    over every sample, a batch of :data:`BATCH_ROWS` at a time into one batch's buffer:
    a caller that reads a thinned set of samples holds no (N, m) output (37 MiB for a
    10-min 1 kHz 8-cable recording)."""
    rows = np.asarray(rows, dtype=np.intp)
    if rows.size > 1 and np.any(np.diff(rows) <= 0):
        raise ValueError("rows must be increasing")
    out = np.empty((rows.size, params.cables))
    for a, b, part in compensate_pieces(params, tension_sensor, velocity, t, tol_n, max_iter):
        lo, hi = np.searchsorted(rows, (a, b))
        out[lo:hi] = part[rows[lo:hi] - a]
    return out


def compensate_pieces(
    params: ChainParams,
    tension_sensor: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> Iterator[tuple[int, int, np.ndarray]]:
    """:func:`compensate` (from the relaxed state) one batch of :data:`BATCH_ROWS` at a
    time: yields ``(a, b, T_p[a:b])``, bit for bit ``compensate(...)[a:b]``, in one
    buffer that the next batch overwrites (read it before asking for the next)."""
    n = np.shape(tension_sensor)[0]
    buf = np.empty((max(1, min(n, BATCH_ROWS)), params.cables))
    a = 0
    for b in _batches(params, True, tension_sensor, velocity, t, None, tol_n, max_iter, buf, True):
        yield a, b, buf[: b - a]
        a = b


class ChainStepper:
    """Per-cycle form: one sample for every cable on preallocated buffers.

    The friction state (:attr:`chain_state`) and the previous step's velocity (for the
    travel, :func:`travel_into`) are carried between calls. ``step`` allocates nothing. The
    first step after construction or :meth:`reset` has no previous velocity: it takes its
    own (``dx = v dt``; the batch form takes no travel at its first sample, ``dt = 0``).
    """

    def __init__(
        self,
        params: ChainParams,
        period_s: float,
        forward: bool = True,
        tol_n: float = 1e-9,
        max_iter: int = 8,
    ) -> None:
        m = params.cables
        self.params = params
        self.forward = forward
        self.period_s = float(period_s)
        self.chain_state = new_state(params)
        self.iterations = 0
        self._in = np.zeros((1, m))
        self._vel = np.zeros((1, m))
        self._out = np.zeros((1, m))
        self._dx = np.zeros((1, m))
        self._v_prev = np.zeros(m)
        self._primed = False
        self._dt = np.array([self.period_s])
        self._p = kernel_params(params, tol_n, max_iter)
        self._travel = entry_point(travel_into, self._vel, self._dt, self._v_prev, self._dx)
        # a plain chain steps its (m, n) forces directly (a view of the state): the kernel's
        # fast path without the per-call check
        if _plain(self._p):
            kernel = _compensate_plain if forward else _simulate_plain
            self._held: ChainState | np.ndarray = self.chain_state.f.reshape(m, params.pulleys)
        else:
            kernel = compensate_kernel if forward else simulate_kernel
            self._held = self.chain_state
        self._kernel = entry_point(
            kernel, self._p, self._in, self._vel, self._dx, self._held, self._out
        )

    @property
    def state(self) -> np.ndarray:
        """(m, n) friction force of each pulley (N): the sum of its state elements."""
        return self.chain_state.pulley_forces(self._p)

    def reset(self) -> None:
        """Relax every pulley (e.g. after a long outage when the real state is unknown);
        the next step has no previous velocity."""
        self.chain_state.reset()
        self._primed = False

    def step(
        self, tension: np.ndarray, velocity: np.ndarray, out: np.ndarray, dt: float = -1.0
    ) -> int:
        """Advance by ``dt`` (s; negative: the period); write the result (m,) into ``out``;
        return the Newton passes (0 when simulating)."""
        self._in[0] = tension
        self._vel[0] = velocity
        if not self._primed:
            self._v_prev[:] = self._vel[0]
            self._primed = True
        self._dt[0] = self.period_s if dt < 0.0 else dt  # own buffers: types fixed
        self._travel(self._vel, self._dt, self._v_prev, self._dx)
        self.iterations = self._kernel(
            self._p, self._in, self._vel, self._dx, self._held, self._out
        )
        out[:] = self._out[0]
        return self.iterations
