"""The wrench reference: diagnosis without platform tensions (physics.md sec. 1, 5).

A real robot has no load cell at the platform. With pose and mass columns and a geometry
the sensor readings are carried through the chain to the platform (nominal model plus
the candidate effects, the compensation direction: from ``T_s`` and ``v`` to ``T_p``) and
must satisfy the platform's wrench balance

    r(t) = A(pose) T_p(theta) + w(pose, m(t), acc) = 0,

``w`` = gravity ``m g`` (moment of an off-centre centre of mass included) + d'Alembert
``-m acc``, ``acc`` the second derivative of the recorded position over the recorded
timestamps (``np.gradient`` twice, as the statics route does). Rotational inertia of the
platform is neglected (as in :func:`gateway.model.statics.inertial_wrench`: far below
the tension resolution at printing speeds; a config carries no inertia tensor).
No tension distribution is assumed: the null space of ``A`` (2-D for 8 cables) is not
observable from pose and mass, and nothing here invents it.

This module holds the data (:class:`WrenchData`), the model ``T_p(theta)`` and the
residual (:class:`WrenchModel`), the sensitivity Jacobian of the residual with respect
to every candidate's per-cable parameters and the identifiability read from it
(:func:`identifiability`). The unit of selection: :mod:`.wrench_unit`; the reference's
stages: :mod:`.wrench_reference`; the report: :mod:`.wrench_report`.

Candidates: the effects whose module says the wrench balance identifies them
(``Effect.wrench``), each with its parameters per cable (a platform effect: one value),
applied in the inverse order of the plant: the path and sensor effects undone in reverse
acting order (:func:`gateway.model.effects.inverse`), then the chain with the chain-side
ones compensated; a statics effect changes the mass in the balance
(:func:`gateway.model.effects.mass_delta`). The others are not candidates in this mode.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import InitVar, dataclass, field, replace

import numpy as np
from scipy.ndimage import uniform_filter1d

from gateway.core.config import Config, FrictionConfig
from gateway.diagnose.forward import CableData, Nominal
from gateway.diagnose.pose_statics import require_geometry
from gateway.diagnose.prepare import deadband, nominal_from, warmup_mask
from gateway.diagnose.sessions import Sessions
from gateway.diagnose.sessions import time_blocks as session_blocks
from gateway.diagnose.stats import white_noise_columns
from gateway.diagnose.timebase import time_blocks
from gateway.errors import RecordingError
from gateway.model import chain_runs, chain_schema, kinematics, statics
from gateway.model import effects as fx
from gateway.recordings.reader import Recording

WRENCH_EFFECTS = tuple(n for n, e in fx.REGISTRY.items() if e.wrench)
PER_CABLE = tuple(n for n in WRENCH_EFFECTS if fx.REGISTRY[n].per_cable)
SUBPARAMS: dict[str, tuple[str, ...]] = {n: fx.REGISTRY[n].param_names for n in WRENCH_EFFECTS}
STRUCTURE_ROWS = 8_192
"""Rows of ``A`` made at a time for a residual over every sample (3 MiB for 8 cables; its
making holds ~3 times that in temporaries: at 32 768 rows they were the diagnosis' peak
memory on a 10-min recording, +40 MiB)."""
FIT_BUDGET = 25_000
"""Samples the selection and the fit use at most (memory: ~48 columns x 6 rows each)."""
INSTRUMENT_S = 0.05
DERIVATIVE_S = 0.2
"""Moving average (s) before the pose is differentiated, on jittered time stamps only
(:func:`_smooth_derivatives`): a 0.3 Hz motion loses 2 % of its acceleration."""
"""Moving-average window (s) of the readings the Jacobian is computed on."""
VIF_MAX = 1000.0
"""A cable's parameter of an effect is identifiable when its variance inflation
``(J^T J)_ii ((J^T J)^-1)_ii`` among the effect's per-cable columns is at most this: its
standard error at most ~30 times what it would be were it the only unknown. Above, the
cables' parameters combine (nearly) into the null space of ``A`` at every recorded pose:
e.g. an equal offset on every cable of a symmetric robot is internal pretension, which
no wrench shows; a robot that stands still leaves every offset unidentifiable."""


@dataclass
class WrenchData:
    """A recording ready for the wrench balance. ``N`` samples, ``m`` cables.

    Held per sample: ``t`` (N,); ``v``, ``ts`` (N, m) setpoint velocity (dead band as the
    engine; the recording's own array when the dead band changes nothing) and sensor
    reading; ``pose`` (N, 6), ``mass`` (N,) and ``acc`` (N, 3) the platform's
    acceleration; ``speed`` (N,) platform speed; ``anchors`` (frame, platform).
    Made from them where they are needed, never held for every sample (on a 10-min
    1 kHz 8-cable recording each (N, m) array is 37 MiB, each (N, 6) one 27 MiB, and
    the diagnosis' peak memory was their sum): the structure matrices ``A`` (N, 6, m)
    (:meth:`structure`), the external wrench ``w0`` with the recorded mass and the
    wrench per kg ``dw_dm`` (N, 6) (:meth:`external`), the cable acceleration ``a``
    and ``ts_smooth`` (N, m), the reading's moving average over :data:`INSTRUMENT_S`
    (the instrument the Jacobian is computed on, see :meth:`WrenchModel.jacobian`).
    Each is computed row by row, so a part of it holds the same values as the whole.
    """

    t: np.ndarray
    v: np.ndarray
    ts: np.ndarray
    pose: np.ndarray
    anchors: tuple[np.ndarray, np.ndarray]
    mass: np.ndarray
    acc: np.ndarray
    gravity: float
    com: np.ndarray
    speed: np.ndarray
    source: str = ""
    kept: dict[str, np.ndarray] = field(default_factory=dict)
    """A :meth:`thinned` copy's ``a``, ``ts_smooth`` and ``x`` (the travel), made at the
    full rate and thinned (empty: made from this data where asked for)."""

    @property
    def cables(self) -> int:
        return int(self.ts.shape[1])

    @property
    def a(self) -> np.ndarray:
        """Cable acceleration (N, m): the first of :func:`_smooth_derivatives` of ``v``."""
        if "a" in self.kept:
            return self.kept["a"].copy()  # an effect may write into it (`_Series.fresh`)
        return _smooth_derivative(self.t, self.v)

    @property
    def ts_smooth(self) -> np.ndarray:
        """The reading's moving average over :data:`INSTRUMENT_S` (N, m)."""
        if "ts_smooth" in self.kept:
            return self.kept["ts_smooth"]
        return uniform_filter1d(self.ts, _window(self.t), axis=0, mode="nearest")

    @property
    def x(self) -> np.ndarray:
        """Cable travel (N, m) from the setpoint velocity."""
        if "x" in self.kept:
            return self.kept["x"].copy()
        return fx.displacement(self.t, self.v)

    def thinned(self, step: int) -> WrenchData:
        """Every ``step``-th sample, each array a copy (the full ones may go): what is
        derived over time (the platform's acceleration and speed, the cable acceleration,
        the readings' moving average, the travel) made at the full rate and thinned, so
        that the thinned copy holds the same values at its samples; only the chain runs
        at the lower rate. The moving average thinned keeps the instruments' noise that
        of :data:`INSTRUMENT_S` at the full rate (made at 42 Hz it averaged 2 samples)."""

        def sub(x: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(x[::step])

        return replace(
            self,
            t=sub(self.t),
            v=sub(self.v),
            ts=sub(self.ts),
            pose=sub(self.pose),
            mass=sub(self.mass),
            acc=sub(self.acc),
            speed=sub(self.speed),
            kept={"a": sub(self.a), "ts_smooth": sub(self.ts_smooth), "x": sub(self.x)},
        )

    @property
    def w0(self) -> np.ndarray:
        """External wrench (N, 6) with the recorded mass: gravity (moment of an
        off-centre centre of mass included) + d'Alembert."""
        return self.external()[0]

    @property
    def dw_dm(self) -> np.ndarray:
        """External wrench per kg (N, 6)."""
        return self.external()[1]

    def external(self, rows: np.ndarray | slice | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``w0`` and ``dw_dm`` (n, 6) at the samples ``rows`` (default all)."""
        sel = slice(None) if rows is None else rows
        mass, pose, acc = self.mass[sel], self.pose[sel], self.acc[sel]
        ones = np.ones_like(mass)
        w0 = statics.gravity_wrench_batch(mass, self.gravity, pose, self.com)
        w0 = w0 + statics.inertial_wrench(mass, acc)
        dw = statics.gravity_wrench_batch(ones, self.gravity, pose, self.com)
        return w0, dw + statics.inertial_wrench(ones, acc)

    def structure(self, rows: np.ndarray | slice | None = None) -> np.ndarray:
        """``A`` (n, 6, m) at the samples ``rows`` (default all)."""
        pose = self.pose if rows is None else self.pose[rows]
        return kinematics.structure_matrix_batch(self.anchors[0], self.anchors[1], pose)

    def balance(
        self,
        tp: np.ndarray | Iterable[tuple[int, int, np.ndarray]],
        delta: np.ndarray | None = None,
    ) -> np.ndarray:
        """The wrench residual ``A T_p + w0 (+ delta dw_dm)`` (N, 6) over every sample,
        :data:`STRUCTURE_ROWS` rows of ``A``, ``w0`` and ``dw_dm`` at a time (the same
        values as from whole arrays); ``delta`` (N,) a change of the mass (kg). ``tp``
        (N, m), or its pieces ``(a, b, T_p[a:b])`` in order
        (:func:`gateway.model.chain_runs.run`'s ``pieces``: no (N, m) array at all)."""
        return self._balance(tp, delta, 6)[0]

    def force_balance(
        self,
        tp: np.ndarray | Iterable[tuple[int, int, np.ndarray]],
        delta: np.ndarray | None = None,
    ) -> tuple[np.ndarray, float]:
        """The force part (N, 3) of :meth:`balance` and the mean square of its moment
        part (N m^2): the same values, without the (N, 6) array (27 MiB for 10 min)."""
        force, moment_ss = self._balance(tp, delta, 3)
        return force, moment_ss / max(3 * self.t.size, 1)

    def _balance(self, tp, delta, keep: int) -> tuple[np.ndarray, float]:
        """:meth:`balance`'s first ``keep`` components and the moment part's sum of
        squares."""
        pieces = _row_pieces(tp) if isinstance(tp, np.ndarray) else tp
        out = np.empty((self.t.size, keep))
        moment_ss = 0.0
        for a, b, piece in pieces:  # a chain's piece may be longer: cut again
            for lo in range(a, b, STRUCTURE_ROWS):
                part = slice(lo, min(lo + STRUCTURE_ROWS, b))
                w0, dw = self.external(part)
                r = np.einsum("nim,nm->ni", self.structure(part), piece[lo - a : part.stop - a])
                r += w0
                if delta is not None:
                    r += delta[part][:, None] * dw
                out[part] = r[:, :keep]
                moment_ss += float(np.sum(r[:, 3:] ** 2))
        return out, moment_ss


def _row_pieces(x: np.ndarray) -> Iterable[tuple[int, int, np.ndarray]]:
    """``(a, b, x[a:b])`` of :data:`STRUCTURE_ROWS` rows each."""
    n = x.shape[0]
    return (
        (a, min(a + STRUCTURE_ROWS, n), x[a : a + STRUCTURE_ROWS])
        for a in range(0, n, STRUCTURE_ROWS)
    )


def usable(rec: Recording, cfg: Config | None) -> bool:
    """True when ``rec`` can be diagnosed against the wrench balance."""
    return rec.pose is not None and rec.mass is not None and cfg is not None


def wrench_data(
    rec: Recording, cfg: Config | None, session: np.ndarray | None = None
) -> WrenchData:
    """Build :class:`WrenchData`; rows without every value are dropped (counted by caller).
    ``session`` (N,): several recordings joined (:func:`.sessions.join_wrench`), each
    sample's recording; the pose is differentiated within each, never across a join."""
    if rec.pose is None or rec.mass is None:
        raise RecordingError(
            f"{rec.source}: no tension_platform_i columns and no pose and mass columns: "
            "neither reference (platform tension, wrench balance) is available"
        )
    cfg = require_geometry(cfg, rec, "the wrench balance")
    ok = np.isfinite(rec.velocity).all(1) & np.isfinite(rec.tension_sensor).all(1)
    ok &= np.isfinite(rec.pose).all(1) & np.isfinite(rec.mass)
    if ok.sum() < 10:
        raise RecordingError(f"{rec.source}: fewer than 10 samples have every value")
    keep = slice(None) if ok.all() else ok  # views of the recording when nothing is dropped
    t, pose, mass = rec.t[keep], rec.pose[keep], rec.mass[keep]
    ts = np.asarray(rec.tension_sensor[keep], dtype=float)
    geo = cfg.geometry
    if session is None:
        vel, acc = _smooth_derivatives(t, pose[:, :3])
    else:
        vel, acc = _derivatives_per_session(t, pose[:, :3], session[keep])
    speed = np.linalg.norm(vel, axis=1)
    del vel
    velocity = rec.velocity[keep]
    raw = [velocity[:, i] for i in range(rec.cables)]
    columns = [deadband(c) for c in raw]
    if all(c is r for c, r in zip(columns, raw, strict=True)):
        v = velocity  # a clean setpoint, the dead band returned it: no copy of 37 MiB
    else:
        v = np.column_stack(columns)
    del raw, columns
    return WrenchData(
        t=t,
        v=v,
        ts=ts,
        pose=pose,
        anchors=(np.asarray(geo.frame_anchors_m), np.asarray(geo.platform_anchors_m)),
        mass=mass,
        acc=acc,
        gravity=geo.gravity_m_s2,
        com=np.asarray(geo.center_of_mass_m, dtype=float),
        speed=speed,
        source=rec.source,
    )


def _smooth_derivatives(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivative of ``x`` (N, k). On evenly spaced rows plain
    differences; otherwise over a moving average of :data:`DERIVATIVE_S` of ``x`` and of
    ``t`` (odd reflection at the ends keeps a ramp a ramp). A recording made by the gateway
    stamps each row with its read time (jitter of a cycle): plain differences of such rows
    turn that jitter into accelerations of tens of m/s^2. On a setpoint trajectory (< a
    few Hz) the average changes nothing else."""
    n = _window(t, DERIVATIVE_S) | 1
    if _plain_steps(t, n):
        vel = np.gradient(x, t, axis=0)
        return vel, np.gradient(vel, t, axis=0)
    ts = _box(t, n)
    if np.any(np.diff(ts) <= 0):
        ts = t
    vel = np.gradient(_box(x, n), ts, axis=0)
    return vel, np.gradient(_box(vel, n), ts, axis=0)


def _derivatives_per_session(
    t: np.ndarray, x: np.ndarray, session: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_smooth_derivatives` of each recording of a joined series on its own."""
    vel, acc = np.empty_like(x, dtype=float), np.empty_like(x, dtype=float)
    cuts = [0, *(np.nonzero(np.diff(session))[0] + 1).tolist(), t.size]
    for a, b in itertools.pairwise(cuts):
        vel[a:b], acc[a:b] = _smooth_derivatives(t[a:b], x[a:b])
    return vel, acc


def _plain_steps(t: np.ndarray, n: int) -> bool:
    """True when :func:`_smooth_derivatives` takes plain differences (evenly spaced rows,
    or too few for a window of ``n``)."""
    steps = np.diff(t)
    return steps.size < 2 or np.std(steps) <= 1e-6 * np.median(steps) or t.size <= n + 2


def _smooth_derivative(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The first derivative of :func:`_smooth_derivatives`, the same values: on evenly
    spaced rows :func:`gateway.model.effects.acceleration` (numpy's gradient bit for bit,
    in pieces: ``np.gradient`` of a 10-min 8-cable series made ~5 copies of it, 190 MiB
    at once, and the second derivative is not needed)."""
    if _plain_steps(t, _window(t, DERIVATIVE_S) | 1):
        return fx.acceleration(t, x)
    return _smooth_derivatives(t, x)[0]


def _box(x: np.ndarray, n: int) -> np.ndarray:
    """Moving average over ``n`` (odd) rows, the ends extended by odd reflection."""
    h = n // 2
    lo = 2.0 * x[:1] - x[h:0:-1]
    hi = 2.0 * x[-1:] - x[-2 : -h - 2 : -1]
    padded = np.concatenate([lo, x, hi])
    return uniform_filter1d(padded, n, axis=0, mode="nearest")[h : h + x.shape[0]]


def _window(t: np.ndarray, seconds: float = INSTRUMENT_S) -> int:
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    return int(max(1, min(round(seconds / max(dt, 1e-9)), t.size // 10 or 1)))


def neutral(effect: str, nom: Nominal, m: int) -> np.ndarray:
    """Internal parameters (k, m) of ``effect`` at the nominal model (k parameters; (k, 1)
    for a platform effect): :meth:`Effect.internal` of its neutral report values, the
    coordinates the wrench fit varies (``1 / k`` for a stiffness, ``(k, k l0)`` for a
    spring, a logarithm for a time constant: the effect's own fit coordinates)."""
    e = fx.REGISTRY[effect]
    values = e.internal(e.neutral(nom))
    return np.array([[v] * (m if e.per_cable else 1) for v in values])


def report_columns(effect: str, theta: np.ndarray) -> dict[str, np.ndarray]:
    """Internal parameters (k, m) of ``effect`` -> report values by name, each (m,)."""
    e = fx.REGISTRY[effect]
    th = np.asarray(theta, dtype=float)
    cols = [e.report(th[:, i]) for i in range(th.shape[1])]
    return {p: np.array([c[p] for c in cols]) for p in e.param_names}


def values_of(theta: dict[str, np.ndarray], *stages: str) -> fx.Effects:
    """``theta`` (effect -> internal (k, m)) as report values by parameter name, of
    ``stages``."""
    return {e.name: report_columns(e.name, theta[e.name]) for e in fx.ordered(theta, *stages)}


class _Series:
    """What the path and sensor effects read (:class:`gateway.model.effects.Series`) of
    :class:`WrenchData`: the cable travel ``x`` and acceleration ``a`` (N, m) are made
    each time an effect reads them, never kept (a spring's and an inertia's candidates
    read them; kept, they were 37 MiB each on a 10-min 8-cable recording); ``fresh``:
    an effect may write into them (:func:`gateway.model.effects.base.fresh`)."""

    fresh = True

    def __init__(self, data: WrenchData, t0: float) -> None:
        self.data, self.t0 = data, t0

    @property
    def t(self) -> np.ndarray:
        return self.data.t

    @property
    def v(self) -> np.ndarray:
        return self.data.v

    @property
    def x(self) -> np.ndarray:
        return self.data.x

    @property
    def a(self) -> np.ndarray:
        return self.data.a


class WrenchModel:
    """``T_p(theta)`` and the wrench residual for a nominal chain on :class:`WrenchData`.

    ``theta``: effect id -> (k, m) array of internal parameters (:func:`neutral` shape);
    missing effects neutral.
    """

    def __init__(self, data: WrenchData, nom: Nominal) -> None:
        self.data, self.nom = data, nom
        self.t0 = float(data.t[0])
        self.series = _Series(data, self.t0)
        self._specs: dict[str, fx.Spec] = {}
        self._structure: tuple[np.ndarray, np.ndarray] | None = None

    def spec(self, effect: str) -> fx.Spec:
        """``effect``'s fit specification in its internal coordinates (finite-difference
        steps, starting points) on this recording, from its first cable's series (what a
        spec reads of a cable: the sampling, the span of the travel)."""
        if effect not in self._specs:
            d, n = self.data, self.data.t.size
            cable = CableData(d.t, d.v[:, 0], d.ts[:, 0], d.ts[:, 0], self.t0)
            self._specs[effect] = fx.REGISTRY[effect].spec(
                cable, self.nom, np.zeros(n), np.ones(n, bool)
            )
        return self._specs[effect]

    def step(self, effect: str, j: int) -> float:
        """The finite-difference step of ``effect``'s internal parameter ``j``."""
        return float(self.spec(effect).step[j])

    def chain_params(self, theta: dict[str, np.ndarray]) -> chain_schema.ChainParams:
        return fx.chain_params(self.nom, values_of(theta, "chain"), self.data.cables)

    def platform_tension(
        self,
        theta: dict[str, np.ndarray],
        ts: np.ndarray | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, m), or (n, m) at the samples ``rows`` (the chain runs over every sample
        either way, :func:`gateway.model.chain_runs.run`): the readings (``ts``, default the
        recorded ones) with the sensor and path effects undone, compensated through the
        chain."""
        d = self.data
        y = self._chain_input(theta, ts)
        return chain_runs.run(self.chain_params(theta), "compensate", y, d.v, d.t, rows=rows)

    def _chain_input(self, theta: dict[str, np.ndarray], ts: np.ndarray | None) -> np.ndarray:
        """The readings (``ts``, default the recorded ones), sensor and path effects undone."""
        y = self.data.ts if ts is None else ts
        return fx.inverse(self.series, y, values_of(theta, "path", "sensor"))

    def structure_at(self, rows: np.ndarray) -> np.ndarray:
        """``A`` (n, 6, m) at ``rows``, kept for the last ``rows`` asked for (the
        selection's samples: asked for again and again)."""
        if self._structure is None or not np.array_equal(self._structure[0], rows):
            self._structure = (rows, self.data.structure(rows))
        return self._structure[1]

    def residual(
        self,
        theta: dict[str, np.ndarray],
        tp: np.ndarray | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Wrench residual ``A T_p + w`` (force N, moment N m) at ``rows`` (n, 6), default
        every sample (N, 6); the chain runs over every sample either way."""
        d = self.data
        delta = fx.mass_delta(values_of(theta, "statics"), d.t, self.t0)
        if rows is None:  # the chain's output a batch at a time, each taken by the balance
            if tp is not None:
                return d.balance(tp, delta)
            y = self._chain_input(theta, None)
            pieces = chain_runs.run(
                self.chain_params(theta), "compensate", y, d.v, d.t, pieces=True
            )
            return d.balance(pieces, delta)
        tp = self.platform_tension(theta, rows=rows) if tp is None else tp[rows]
        w0, dw = d.external(rows)
        r = np.einsum("nim,nm->ni", self.structure_at(rows), tp) + w0
        if delta is not None:
            r = r + delta[rows][:, None] * dw
        return r

    def force_residual(self, theta: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        """The force part (N, 3) of :meth:`residual` over every sample and the mean
        square of its moment part (:meth:`WrenchData.force_balance`)."""
        d = self.data
        delta = fx.mass_delta(values_of(theta, "statics"), d.t, self.t0)
        y = self._chain_input(theta, None)
        pieces = chain_runs.run(self.chain_params(theta), "compensate", y, d.v, d.t, pieces=True)
        return d.force_balance(pieces, delta)

    def jacobian(
        self, theta: dict[str, np.ndarray], effect: str, rows: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """Per sub-parameter of ``effect``, d residual / d parameter at the samples ``rows``
        (default all): (n, 6, m) (one column per cable; (n, 6, 1) for a platform effect), by
        forward differences (the chain itself runs over every sample):
        :meth:`expand` of :meth:`sensitivities`."""
        rows = np.arange(self.data.t.size) if rows is None else rows
        return [self.expand(effect, s, rows) for s in self.sensitivities(theta, effect, rows)]

    def sensitivities(
        self, theta: dict[str, np.ndarray], effect: str, rows: np.ndarray
    ) -> list[np.ndarray]:
        """Per sub-parameter of ``effect`` what its Jacobian is made of at ``rows``
        (:meth:`expand`): d T_p / d parameter (n, m), or, for a statics effect, d mass /
        d parameter (n,); 1/6 of the Jacobian's size for 8 cables, what a linearisation
        keeps (:class:`gateway.diagnose.wrench_unit.WrenchUnit`).

        The chains of the cables are independent, so one perturbed run of all cables at
        once gives every cable's column. It is computed on the smoothed readings
        (``ts_smooth``): a sensitivity proportional to the reading (gain, Coulomb) would
        otherwise carry the same sensor noise as the residual, and with the per-cable
        parameters nearly collinear through the null space of ``A`` that correlation biases
        the fit (errors in variables: +30 % on a gain at 0.8 N noise in a test); the
        smoothed sensitivities are instruments uncorrelated with the noise.
        """
        d = self.data
        base_theta = {**theta}
        base_theta.setdefault(effect, neutral(effect, self.nom, d.cables))
        out = []
        if fx.REGISTRY[effect].stage == "statics":  # through the mass: linear in dw_dm
            base = fx.mass_delta(values_of(base_theta, "statics"), d.t[rows], self.t0)
            for j in range(len(SUBPARAMS[effect])):
                pert = base_theta[effect].copy()
                pert[j] += self.step(effect, j)
                moved = fx.mass_delta(
                    values_of({**base_theta, effect: pert}, "statics"), d.t[rows], self.t0
                )
                out.append((moved - base) / self.step(effect, j))  # type: ignore[operator]
            return out
        smooth = d.ts_smooth
        tp0 = self.platform_tension(base_theta, smooth, rows)
        for j in range(len(SUBPARAMS[effect])):
            pert = base_theta[effect].copy()
            pert[j] += self.step(effect, j)
            tp1 = self.platform_tension({**base_theta, effect: pert}, smooth, rows)
            out.append((tp1 - tp0) / self.step(effect, j))
        return out

    def expand(self, effect: str, sens: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """One sub-parameter's Jacobian (n, 6, m) ((n, 6, 1) for a statics effect) at
        ``rows`` from its :meth:`sensitivities` (the same values each time)."""
        if fx.REGISTRY[effect].stage == "statics":
            return (sens[:, None] * self.data.external(rows)[1])[:, :, None]
        return self.structure_at(rows) * sens[:, None, :]


def noise_scale(resid: np.ndarray) -> np.ndarray:
    """Per wrench component (6,), the white-noise std of a residual (N, 6): median absolute
    first difference / 0.6745 / sqrt 2 (:func:`.stats.white_noise_columns`: robust to the
    slow part); the weights of the fit."""
    s = white_noise_columns(resid)
    floor = 1e-9 * max(float(np.max(s)), 1e-12)
    return np.maximum(s, floor)


def identifiability(jac: np.ndarray, rows: np.ndarray) -> dict:
    """What one sub-parameter block (N, 6, m) of the whitened Jacobian lets the motion
    identify, on the samples ``rows``.

    Returns the per-cable variance inflation ``vif`` (m,) (inf: in the null space of the
    stacked balance), the column norms ``norm`` (m,), ``live`` (m,) bool (the cable has any
    sensitivity) and ``condition`` of the column-normalised block (ratio of its extreme
    singular values; inf when a combination of cables has no effect on the wrench, i.e.
    lies in the null space of ``A`` at every recorded pose).
    """
    # one copy of the block at ``rows``, normalised in place (the squares, the live
    # columns and their quotient were three more, 10 MiB each at the fit budget's rows)
    j = jac[rows].reshape(-1, jac.shape[2])
    if np.may_share_memory(j, jac):  # ``rows`` a slice: a view, normalised below
        j = j.copy()
    norm = np.sqrt(np.einsum("ij,ij->j", j, j))
    live = norm > 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)
    vif = np.full(jac.shape[2], np.inf)
    cond = math.inf
    if live.any():
        jn = j if live.all() else j[:, live]
        jn /= norm[live]
        del j
        gram = jn.T @ jn
        sv = np.linalg.svd(jn, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 1e-12 * sv[0] else math.inf
        try:
            inv = np.linalg.inv(gram)
            vif[live] = np.where(np.diag(inv) > 0, np.diag(inv) * np.diag(gram), np.inf)
        except np.linalg.LinAlgError:
            pass
    return {"vif": vif, "norm": norm, "live": live, "condition": cond}


def identifiable_cables(ident: dict) -> list[int]:
    """0-based cables whose parameter the motion identifies (see :data:`VIF_MAX`); the
    others are not fitted (a value along the null space would be invented)."""
    return [i for i in range(ident["vif"].size) if ident["live"][i] and ident["vif"][i] <= VIF_MAX]


@dataclass
class Prepared:
    """Everything the selection needs: model, whitening, blocks, warm-up mask.

    Selection and fit use the samples ``rows``: every sample, or evenly thinned to
    :data:`FIT_BUDGET` on long recordings (the chain still runs over every sample; the
    scores are over all of them).
    The residual is whitened per sample by the noise the sensors put on the wrench: white
    noise ``e`` of equal std on the readings gives ``A e`` with covariance ``s^2 A A^T``
    (pose-dependent, correlated across components), so ``L^-1 r / s`` with
    ``L L^T = A A^T`` (Cholesky) has unit white noise; ``s`` is estimated from the nominal
    residual's sample-to-sample differences. Generalised least squares: unbiased standard
    errors, forces and moments weighted by what the sensors can tell.
    """

    model: WrenchModel
    rows: np.ndarray
    chol: InitVar[np.ndarray]
    """``L`` (n, 6, 6) at ``rows``: made into the whitening (``L^-1 / s``), not kept (7 MiB
    at :data:`FIT_BUDGET` rows, held to the end of the diagnosis when it was)."""
    sigma: float
    blocks: np.ndarray
    n_blocks: int
    warm: np.ndarray
    nominal: np.ndarray | None = None
    """The nominal model's residual (n, 6) at ``rows`` (unwhitened), made once."""

    def __post_init__(self, chol: np.ndarray) -> None:
        # ``L^-1 / s`` once: a whitening is then one batched product, where a batched
        # ``solve`` factored every 6 x 6 ``L`` again on each call (a fifth of the
        # diagnosis' CPU on a 2-min recording); the same values to rounding
        self._scale = np.linalg.inv(chol) / self.sigma

    def whiten(self, x: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
        """(n, 6) or (n, 6, k) residual or Jacobian at the samples ``rows`` (or at
        ``rows[among]``, ``among`` a bool mask of ``rows`` or indices into it) -> whitened."""
        scale = self._scale if among is None else self._scale[among]
        if x.ndim == 2:
            return np.einsum("nij,nj->ni", scale, x)
        return np.matmul(scale, x)


def load_inverse_kernels(cables: int) -> None:
    """Load the compiled kernels of the candidates' inverse forms (numba's cache: the
    filter of ``sensor_creep``) on three samples. :func:`prepare` does, before the
    diagnosis gives LLVM's pages back (:func:`gateway.core.heap.trim_heap`): loaded by the
    first ``sensor_creep`` candidate, they stayed resident to the end of the selection's
    first pass (measured on a 10-min 8-cable recording: +47 MiB there, the peak)."""
    t = np.arange(3) * 1e-3
    y = np.full((3, cables), 100.0)
    s = fx.SeriesData(t, np.zeros_like(y), np.zeros_like(y), np.zeros_like(y), 0.0)
    for name in WRENCH_EFFECTS:
        e = fx.REGISTRY[name]
        if e.stage in ("path", "sensor"):
            e.inverse(s, y, {p: np.full(cables, v) for p, v in e.example.items()})


def prepare(
    rec: Recording,
    cfg: Config | None,
    friction: FrictionConfig,
    sessions: Sessions | None = None,
    step: int = 1,
) -> Prepared:
    """Data, nominal model, whitening (from the nominal residual), time blocks, warm-up.
    ``sessions``: ``rec`` is several recordings joined (:func:`.sessions.join_wrench`):
    the time blocks are drawn within each (:func:`.sessions.time_blocks`), the pose
    differentiated within each; the warm-up after each join is the one after any gap.
    ``step`` > 1: on every ``step``-th sample (:meth:`WrenchData.thinned`)."""
    data = wrench_data(rec, cfg, None if sessions is None else sessions.index)
    if step > 1:
        data = data.thinned(step)
    load_inverse_kernels(data.cables)
    nom = nominal_from(friction)
    model = WrenchModel(data, nom)
    rows = np.arange(0, data.t.size, max(1, math.ceil(data.t.size / FIT_BUDGET)))
    a_rows = model.structure_at(rows)
    chol = np.linalg.cholesky(np.einsum("nim,njm->nij", a_rows, a_rows))
    nominal = model.residual({}, rows=rows)
    unit = np.linalg.solve(chol, nominal[:, :, None])[:, :, 0]
    sigma = float(math.sqrt(np.mean(noise_scale(unit) ** 2)))
    blocks, nb = time_blocks(data.t) if sessions is None else session_blocks(data.t, sessions)
    warm = np.ones(data.t.size, bool)
    for i in range(data.cables):
        warm &= warmup_mask(
            CableData(data.t, data.v[:, i], data.ts[:, i], data.ts[:, i], float(data.t[0])), nom
        )
    return Prepared(model, rows, chol, max(sigma, 1e-12), blocks, nb, warm, nominal)
