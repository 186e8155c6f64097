"""What an effect of the catalogue is (docs/physics.md sec. 4): one object per effect,
defined in a module of its own, carrying every behaviour the project needs of it.

An :class:`Effect` has

* its **parameters** (:class:`Param`: report name, unit, the value that means "absent",
  admissible range, a typical size), the only names a report, a model file's
  ``friction.effects`` and the soft PLC's ``sim_plc.effects`` use;
* where it acts (:data:`Stage`) and its **forms** there:

  - ``statics``: the platform mass the truth has beyond the recorded one
    (:meth:`Effect.mass_delta`);
  - ``chain``: how it changes the friction chain (:meth:`Effect.apply_chain` edits a
    :class:`gateway.model.chain_schema.ChainDraft`, whose columns
    :data:`gateway.model.chain_schema.COLUMNS` declares once; the compiled pulley step
    dispatches the friction *law* from the chain's law table,
    :data:`gateway.model.chain_schema.LAWS`);
  - ``path`` and ``sensor``: the batch forward form (truth -> reading,
    :meth:`Effect.forward`), its batch inverse (:meth:`Effect.inverse`), the plant's
    per-sample form (:meth:`Effect.stepper`) and, when the gateway removes it each cycle,
    the causal per-cycle inverse compiled with numba (:attr:`Effect.online_kernel`);

* whether the gateway compensates it online (:class:`Online`: how, or why not);
* its **fit**: internal parameters (:meth:`Effect.internal` / :meth:`Effect.report`),
  standard errors of the reported ones, the fit specification (:meth:`Effect.spec`:
  neutral vector, bounds, linear parameters, scales, starting points), the significance
  of a fitted value, whether the motion can show it (:attr:`Effect.needs_motion`,
  :meth:`Effect.applicable`), whether the wrench reference can identify it;
* the **reading** of a finding: the evidence sentence (:attr:`Effect.look`), the signal the
  residual is plotted against (:attr:`Effect.plot`), the group of effects it is confused
  with (:attr:`Effect.group`);
* how a correction found on top of a model **composes** with the model's value
  (:meth:`Effect.compose`) and what a model file needs done to it (:meth:`Effect.from_fit`,
  :meth:`Effect.to_model`);
* an example size that a test recording shows (:attr:`Effect.example`).

Arrays: a form takes ``y`` (N,) for one cable or (N, m) for m cables and parameters
``p = {name: (m,) array}`` (size 1 for one cable); the time ``t`` is (N,). Nothing here
names another effect: what serves every effect loops over :data:`.registry.REGISTRY`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Protocol

import numpy as np

from gateway.model.chain_schema import ChainDraft

Stage = Literal["statics", "chain", "path", "sensor"]
STAGES: tuple[Stage, ...] = ("statics", "chain", "path", "sensor")
"""The order in which the stages act from the platform to the reading."""

Values = dict[str, np.ndarray]
"""One effect's parameters by report name, each (m,) (or (1,) for a platform effect)."""
Effects = dict[str, Values]
"""Validated effect values: ``{effect: {parameter: (m,) array}}``."""

INF = math.inf


@dataclass(frozen=True)
class Param:
    """One parameter of an effect.

    ``default``: the value that means the effect is absent (NaN: the nominal model's value,
    see ``nominal``); ``low`` / ``high``: what a model file admits (``low_open``: strictly
    above ``low``); ``truth_low``: what a truth (the soft PLC's hidden effect) admits when
    it is stricter (a correction may be negative, the physics not); ``step``: a typical
    change in report units (fit scale, finite-difference step); ``nominal``: the attribute
    of the nominal friction whose value stands in when this one is NaN or not given
    (e.g. ``pulley_radius_m``, ``mu_mean``).
    """

    name: str
    unit: str
    default: float
    low: float = -INF
    low_open: bool = False
    high: float = INF
    step: float = 1.0
    truth_low: float | None = None
    nominal: str | None = None
    doc: str = ""

    def check(self, value: np.ndarray) -> str | None:
        """None when every finite value is admissible, else the reason."""
        v = value[np.isfinite(value)]
        if self.low_open and np.any(v <= self.low):
            return f"must be > {self.low:g}"
        if not self.low_open and np.any(v < self.low):
            return f"must be >= {self.low:g}"
        if np.any(v > self.high):
            return f"must be <= {self.high:g}"
        return None

    def admissible(self, value: float) -> float:
        """``value`` moved to the nearest admissible value (a fit may leave the range)."""
        low = self.low + (max(abs(self.low), 1.0) * 1e-9 if self.low_open else 0.0)
        return float(min(max(value, low), self.high))


@dataclass(frozen=True)
class Online:
    """Whether the gateway removes the effect every cycle: ``how``, or why not."""

    compensable: bool
    how: str


class NominalChain(Protocol):
    """What an effect reads of the nominal friction (``FrictionConfig`` and the
    diagnosis' ``Nominal`` have it)."""

    @property
    def model(self) -> str: ...
    @property
    def wrap_rad(self) -> Any: ...
    @property
    def mu(self) -> Any: ...
    @property
    def sigma_n_m(self) -> float: ...
    @property
    def beta(self) -> float: ...
    @property
    def viscous_ns_m(self) -> Any: ...
    @property
    def pulley_radius_m(self) -> float: ...


def nominal_mu_mean(nom: NominalChain) -> float:
    """The nominal pulleys' mean bearing coefficient (0 without pulleys or friction)."""
    mu = np.asarray(nom.mu, dtype=float)
    return float(np.mean(mu)) if mu.size and nom.model != "none" else 0.0


def nominal_value(nom: NominalChain, key: str) -> float:
    """A nominal quantity a parameter defaults to (:attr:`Param.nominal`)."""
    if key == "mu_mean":
        return nominal_mu_mean(nom)
    return float(getattr(nom, key))


class Series(Protocol):
    """What the path and sensor forms read of a recording: times ``t`` (N,), velocity
    ``v``, cable position ``x`` (the cable length where known, else the travel since
    the first sample) and acceleration ``a`` (each (N,) or (N, m)), first time ``t0``.
    A series whose ``x`` and ``a`` are made anew each time they are read may say so with
    an attribute ``fresh = True`` (:func:`fresh`): a form may then write into them."""

    @property
    def t(self) -> np.ndarray: ...
    @property
    def v(self) -> np.ndarray: ...
    @property
    def x(self) -> np.ndarray: ...
    @property
    def a(self) -> np.ndarray: ...
    @property
    def t0(self) -> float: ...


def fresh(s: Series, x: np.ndarray, other: object) -> np.ndarray | None:
    """``x`` (just read of ``s``: its ``x`` or ``a``) when a form may write its result
    with ``other`` into it (``s.fresh``, and the result has ``x``'s shape and type), else
    None: the ``out`` of a ufunc, the same values as a new array without a copy of the
    series (37 MiB for a 10-min 1 kHz 8-cable recording)."""
    if not getattr(s, "fresh", False) or x.dtype != np.float64:
        return None
    o = np.asarray(other)
    if o.dtype != np.float64 or np.broadcast_shapes(x.shape, o.shape) != x.shape:
        return None
    return x


@dataclass
class SeriesData:
    """A plain :class:`Series`; ``x`` and ``a`` may be callables computed when first read."""

    t: np.ndarray
    v: np.ndarray
    x_source: np.ndarray | Callable[[], np.ndarray]
    a_source: np.ndarray | Callable[[], np.ndarray]
    t0: float = 0.0

    @property
    def x(self) -> np.ndarray:
        if callable(self.x_source):
            self.x_source = self.x_source()
        return self.x_source

    @property
    def a(self) -> np.ndarray:
        if callable(self.a_source):
            self.a_source = self.a_source()
        return self.a_source


@dataclass(frozen=True)
class Sample:
    """One sample for the plant's per-sample forms: index ``k``, time ``t``, the times
    ``t3`` (3,) and velocities ``v3`` (3, m) of the previous, this and the next sample
    (the truth may look one sample ahead), the cable length ``x`` (m,)."""

    k: int
    t: float
    t3: np.ndarray
    v3: np.ndarray
    x: np.ndarray


class Stepper(Protocol):
    """An effect's per-sample forward form (state carried from one sample to the next)."""

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray: ...


class FitData(Protocol):
    """One cable's series as the fit reads them (the diagnosis' ``CableData``)."""

    @property
    def t(self) -> np.ndarray: ...
    @property
    def v(self) -> np.ndarray: ...
    @property
    def x(self) -> np.ndarray: ...
    @property
    def ts(self) -> np.ndarray: ...
    @property
    def tp(self) -> np.ndarray: ...


@dataclass(frozen=True)
class Spec:
    """How to fit one effect on one cable, in its internal parameters: the neutral
    vector (the nominal model), bounds, the indices of the (nearly) linear parameters,
    finite-difference steps (also the fit's scales) and starting points."""

    neutral: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    linear: tuple[int, ...]
    step: np.ndarray
    starts: tuple[np.ndarray, ...]

    def clip(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` within the bounds: one cable's (k,) or every cable's (k, m)."""
        shape = (-1,) + (1,) * (np.ndim(theta) - 1)
        return np.clip(theta, self.lower.reshape(shape), self.upper.reshape(shape))


def speeds(d: FitData) -> tuple[float, float]:
    """95th percentile of |v| (m/s) and the median sample period (s) of a cable."""
    v95 = float(np.percentile(np.abs(d.v), 95)) or 1e-3
    dt = float(np.median(np.diff(d.t))) if d.t.size > 1 else 1e-3
    return v95, dt


@dataclass(frozen=True)
class Compose:
    """What composing a correction onto a model's value needs: the nominal pulleys' mean
    ``mu`` and ``outer_gain`` (m,), the factor by which the model's own sensor effects
    scale what passes through them (a correction found inside them is scaled by it)."""

    nominal_mu: float
    outer_gain: np.ndarray


@dataclass
class ModelFile:
    """What writing a fitted value into a model file may need: the nominal friction, the
    recording's first cable lengths (m,) (None: not recorded) and mean sensor readings
    (m,), and the notes that name every value changed on the way."""

    friction: NominalChain
    length0: np.ndarray | None
    mean_reading: np.ndarray | None
    notes: list[str] = field(default_factory=list)


class Effect:
    """One effect of the catalogue (module docstring). Subclasses set the class
    attributes and override the forms of their stage."""

    name: ClassVar[str]
    stage: ClassVar[Stage]
    params: ClassVar[tuple[Param, ...]]
    physics: ClassVar[str]
    """The law in one line (docs, ``--help``, the report's schema)."""
    online: ClassVar[Online]
    order: ClassVar[int] = 0
    """Position within the stage (forward order, smallest acts first)."""
    per_cable: ClassVar[bool] = True
    per_recording: ClassVar[bool] = False
    """A session's property, not the machine's (a sensor's zero, its drift): diagnosed on
    several recordings of one machine it gets one parameter vector per recording (a path
    or sensor effect only; :mod:`gateway.diagnose.sessions`); a machine's property (a
    friction coefficient) one for all."""
    needs_motion: ClassVar[bool] = False
    needs_mass: ClassVar[bool] = False
    """The recording must carry pose and mass (a platform effect)."""
    wrench: ClassVar[bool] = False
    """The wrench reference (pose and mass, no platform tensions) identifies it."""
    group: ClassVar[str] = ""
    """Effects of the same group explain much the same residual (they are each other's
    rivals, reported as alternatives where the data cannot tell them apart)."""
    look: ClassVar[str] = ""
    """What to look for on the plot (the finding's evidence sentence)."""
    plot: ClassVar[str] = "t"
    """The signal the residual is plotted against (:mod:`gateway.diagnose.signals`)."""
    nests: ClassVar[tuple[Effect, ...]] = ()
    """Simpler effects this one reduces to (``coulomb_directional`` with ``mu_out = mu_in``
    is ``coulomb``): it is kept only where it fits held-out data clearly better."""
    beyond: ClassVar[tuple[float, ...]] = ()
    """Weights on the internal parameters whose combination is zero where this effect
    reduces to the simpler one it nests (``coulomb_directional``: ``mu_out - mu_in``): what
    the cables' pooled test of it against the simpler one measures
    (:func:`gateway.diagnose.pooling.richer`); empty: not tested that way."""
    separate: ClassVar[str] = ""
    """The motion that tells it from its group (said when the data cannot)."""
    example: ClassVar[Mapping[str, float]] = {}
    """A size that a 30-s test recording of the soft PLC shows clearly."""
    online_kernel: ClassVar[Any] = None
    """Per-cycle inverse, ``kernel(p (k, m), y (m,), v, v_prev, dt, length)`` in place."""
    online_state: ClassVar[int] = 0
    """Rows of ``p`` after the parameters that the online kernel keeps its state in (a
    filter's last input and output; zeros at the start); 0: stateless."""

    # ---- parameters ----
    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)

    def neutral(self, nom: NominalChain) -> dict[str, float]:
        """Report values meaning "nothing beyond the nominal model"."""
        return {
            p.name: nominal_value(nom, p.nominal)
            if p.nominal and math.isnan(p.default)
            else p.default
            for p in self.params
        }

    def present(self, values: Values, nom: NominalChain) -> np.ndarray:
        """(m,) bool: the cables on which ``values`` differ from the nominal model."""
        neutral = self.neutral(nom)
        out = np.zeros(np.asarray(next(iter(values.values()))).size, bool)
        for name, v in values.items():
            v = np.asarray(v, dtype=float)
            out |= np.isfinite(v) & ~np.isclose(v, neutral[name], rtol=1e-12, atol=0.0)
        return out

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        """Report values -> the internal vector the fit varies (identity by default)."""
        return np.array([float(values[p.name]) for p in self.params])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        """Internal vector -> report values."""
        return {p.name: float(v) for p, v in zip(self.params, theta, strict=True)}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        """Standard errors of the report values (delta method through the transform)."""
        return {p.name: float(s) for p, s in zip(self.params, se, strict=True)}

    def report_arrays(self, theta: np.ndarray) -> Values:
        """Internal vector -> report values as (1,) arrays (one cable's forms)."""
        return {k: np.array([v]) for k, v in self.report(theta).items()}

    def significance(self, theta: np.ndarray, se: np.ndarray, neutral: np.ndarray) -> float:
        """Largest |parameter - neutral| / standard error (internal parameters)."""
        dev = np.abs(np.asarray(theta) - neutral)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, dev / se, 0.0)
        return float(np.nanmax(z)) if z.size else 0.0

    def linear_spec(self, nom: NominalChain) -> Spec:
        """The spec of an effect whose parameters act (nearly) linearly: neutral start,
        report bounds, steps."""
        neutral = self.internal(self.neutral(nom))
        lo = np.array([p.low for p in self.params])
        hi = np.array([p.high for p in self.params])
        step = np.array([p.step for p in self.params])
        return Spec(neutral, lo, hi, tuple(range(len(self.params))), step, (neutral,))

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        """How to fit it on one cable (``resid``: the current residual, ``mask``: the
        training samples)."""
        return self.linear_spec(nom)

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        """Whether this cable's motion can show it at all (beyond :attr:`needs_motion`)."""
        return True

    # ---- forms ----
    def mass_delta(self, t: np.ndarray, t0: float, p: Values) -> np.ndarray:
        """``statics``: the platform mass (kg) the truth has beyond the recorded one at
        times ``t`` (N,), ``t0`` the recording's first time."""
        raise NotImplementedError(self.name)

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        """``chain``: change the chain of every cable (in place)."""
        raise NotImplementedError(self.name)

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        """``path``/``sensor``: the reading with the effect, from the reading without."""
        raise NotImplementedError(self.name)

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        """``path``/``sensor``: :meth:`forward` undone (batch; causal for an online
        effect, where ``s.a`` is the backward-difference acceleration)."""
        raise NotImplementedError(self.name)

    def stepper(self, p: Values, cables: int, period_s: float) -> Stepper:
        """``path``/``sensor``: the per-sample form of :meth:`forward` (the plant)."""
        raise NotImplementedError(self.name)

    def gain_factor(self, p: Values) -> np.ndarray | None:
        """How much the effect scales what passes through it (a sensor gain), or None."""
        return None

    # ---- model files ----
    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        """The model's value ``old`` with the correction ``new`` a diagnosis relative to
        the model found (default: the new value replaces the old)."""
        return {k: v.copy() for k, v in new.items()}

    def from_fit(self, values: Values, ctx: ModelFile) -> None:
        """A finding's values as a model file means them, in place (default: the same; e.g.
        a phase fitted against the travel since the first sample -> the cable length)."""

    def to_model(self, values: Values, ctx: ModelFile) -> None:
        """The model's values (composed with the findings) made admissible for a file, in
        place, each change named in ``ctx.notes`` (default: nothing)."""
