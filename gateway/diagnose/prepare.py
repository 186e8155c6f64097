"""From a recording to what the selection works on: one :class:`CableData` per cable, the
nominal chain, finite rows, the velocity dead band, saturated sensor readings, the held-out
time blocks, the warm-up of the friction state, the candidates each cable's motion can
show, a subset of a long recording, the validation recording's forwards."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.diagnose import locate, stats
from gateway.diagnose.forward import ALL_EFFECTS, CableData, Forward, Nominal, chain_params
from gateway.diagnose.pose_statics import MassSensitivity
from gateway.diagnose.sessions import Sessions, finite_rows
from gateway.diagnose.timebase import gap_starts
from gateway.errors import RecordingError
from gateway.model import effects as fx
from gateway.model.chain_schema import coulomb_coefficients
from gateway.recordings.reader import Recording


def nominal_from(friction: FrictionConfig) -> Nominal:
    """The per-cable nominal chain of a friction config.

    A model without pulleys (a single-axis rig: ``friction: {model: none, pulleys: []}``)
    gets one virtual pulley without wrap or friction (``lambda = 0``), so that the candidate
    ``coulomb`` has a place for its load-independent ``f0`` (its ``mu`` is then not fitted).
    """
    wrap = np.asarray(friction.wrap_rad, dtype=float)
    mu = np.asarray(friction.mu, dtype=float)
    if wrap.size == 0:
        wrap, mu = np.zeros(1), np.zeros(1)
    return Nominal(
        model=friction.model,
        wrap_rad=wrap,
        mu=mu,
        sigma_n_m=friction.sigma_n_m,
        beta=friction.beta,
        viscous_ns_m=friction.viscous_ns_m,
        pulley_radius_m=friction.pulley_radius_m,
    )


VELOCITY_DEADBAND_SIGMAS = 4.0


def velocity_noise(v: np.ndarray) -> float:
    """Robust estimate of white noise on a velocity column (m/s), 0 for a clean setpoint.

    A setpoint is smooth or piecewise linear, so its second difference is zero or tiny
    almost everywhere; white noise of std ``s`` gives second differences of std
    ``sqrt(6) s``. Median absolute deviation, so ramps and steps do not count.
    """
    if v.size < 5:
        return 0.0
    return stats.white_noise(v, order=2)


def deadband(v: np.ndarray) -> np.ndarray:
    """``v`` with values within ``VELOCITY_DEADBAND_SIGMAS`` noise stds of zero set to 0.

    A measured (noisy) velocity logged in place of the setpoint would otherwise flip the
    sign of the simulated friction at every noise sample while the cable stands still.
    Noise below 1e-4 of the typical speed (95th percentile) is left alone.
    """
    noise = velocity_noise(v)
    if v.size == 0 or noise <= 1e-4 * float(np.percentile(np.abs(v), 95)):
        return v  # a clean setpoint (numerical roughness only); never written to
    return np.where(np.abs(v) < VELOCITY_DEADBAND_SIGMAS * noise, 0.0, v)


Sensitivity = np.ndarray | MassSensitivity | None
"""``dT_p/dm``: (N, m) N/kg, or its knots (interpolated per cable when read), or None."""


def cable_data(
    rec: Recording,
    tp: np.ndarray,
    dtp_dm: Sensitivity,
    origin: np.ndarray | None = None,
    sessions: Sessions | None = None,
) -> list[CableData]:
    """One :class:`CableData` per cable; ``tp`` (N, m); velocity through :func:`deadband`.

    ``x`` is the travel since the first sample (from the recording's lengths where it has
    them, else the integrated velocity: :class:`CableData`); with ``origin`` (the diagnosed
    recording's first cable lengths) and lengths in ``rec`` (a validation recording), the
    travel since the diagnosed recording's first sample instead: a length or a phase fitted
    against the diagnosed recording's travel (``spring``, ``eccentricity``) means the same on
    both.

    Memory: the tensions and a clean velocity are views of the recording's columns (not
    copies); displacement and acceleration (16 bytes per sample) and ``dtp_dm`` given as
    :class:`MassSensitivity` (8) are computed when a cable is worked on and freed by
    :meth:`Forward.clear_cache` (float32 would halve them but moves the finite-difference
    fits of eccentricity and inertia). ``sessions``: the recordings a joined series is
    made of (:mod:`.sessions`: each sample's recording and its start)."""
    t0: float | np.ndarray = float(rec.t[0])
    session = None
    if sessions is not None and sessions.count > 1:
        t0, session = sessions.t0(), sessions.index
    x0 = np.zeros(rec.cables)
    if origin is not None and rec.length is not None:
        x0 = np.asarray(rec.length[0], dtype=float) - np.asarray(origin, dtype=float)
    out = []
    for i in range(rec.cables):
        v = deadband(rec.velocity[:, i])
        dm: np.ndarray | Callable[[], np.ndarray] | None = None
        if isinstance(dtp_dm, MassSensitivity):
            dm = partial(dtp_dm.column, rec.t, i)
        elif dtp_dm is not None:
            dm = dtp_dm[:, i]
        length = None if rec.length is None else rec.length[:, i]
        out.append(
            CableData(
                rec.t,
                v,
                tp[:, i],
                rec.tension_sensor[:, i],
                t0,
                dm,
                x0=float(x0[i]),
                length=length,
                session=session,
            )
        )
    return out


CLIP_MIN_SHARE = 0.002
CLIP_MIN_RUN = 3


def clipped_mask(ts: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """(N,) bool: samples of one sensor column that sit at a saturation level; the levels.

    A sensor clipped at its range reports exactly its limit for as long as the force stays
    beyond it, so the column's largest (smallest) value repeats: it counts as a saturation
    level when at least ``CLIP_MIN_SHARE`` of the samples (and 10) equal it, in at least one
    run of ``CLIP_MIN_RUN`` consecutive samples. A genuine extreme is reached a few times at
    most, even with a quantised sensor.
    """
    out = np.zeros(ts.shape, bool)
    levels: list[float] = []
    if ts.size < 10:
        return out, levels
    need = max(10, int(CLIP_MIN_SHARE * ts.size))
    for level in (float(np.max(ts)), float(np.min(ts))):
        at = ts == level
        if int(at.sum()) < need:
            continue
        starts, stops = locate.runs(at)
        if np.any(stops - starts >= CLIP_MIN_RUN):
            out |= at
            levels.append(level)
    return out, levels


WARMUP_LENGTHS = 4.0
"""Relaxation lengths ``F_R / sigma`` of cable travel after which the chain state has
forgotten its unknown start (error ``exp(-4)`` ~ 2 %)."""
WARMUP_MAX_SHARE = 0.1
GAP_WARMUP_MAX_SHARE = 0.5


def warmup_mask(d: CableData, nom: Nominal) -> np.ndarray:
    """(N,) bool: samples the selection may fit and score on (False: warm-up).

    A recording may start in mid-motion with the pulleys' friction state developed, while
    the simulation starts relaxed; the difference decays as ``exp(-sigma |x| / F_R)`` over
    the cable travel ``x``. Samples before the cable has travelled ``WARMUP_LENGTHS``
    relaxation lengths (``F_R``: the largest pulley's Coulomb level at the 99th percentile
    of the platform tension; ``sigma``: the nominal stiffness) are left out, at most
    ``WARMUP_MAX_SHARE`` of the samples. The same after every gap (a step longer than
    ``GAP_SPACINGS`` median spacings: the chain's travel over it, the trapezoid of the two
    velocities, is a guess), while all warm-ups together leave out at most
    ``GAP_WARMUP_MAX_SHARE`` of the samples.
    """
    n = d.t.size
    if nom.model == "none" or nom.mu.size == 0 or n < 2:
        return np.ones(n, bool)
    lam_pos, lam_neg = coulomb_coefficients(chain_params(nom, {}))  # the model's lambda
    lam = float(np.max(0.5 * (lam_pos + lam_neg)))  # mean of the two directions
    f_r = lam * float(np.percentile(np.abs(d.tp), 99))
    after_gaps = gap_starts(d.t)
    steps = np.abs(np.diff(d.x))
    steps[after_gaps - 1] = 0.0  # what x jumps across a gap is no travel the chain stepped
    travel = np.concatenate(([0.0], np.cumsum(steps)))
    need = WARMUP_LENGTHS * f_r / nom.sigma_n_m
    out = np.ones(n, bool)
    budget = int(GAP_WARMUP_MAX_SHARE * n)
    for start in (0, *after_gaps.tolist()):
        if budget <= 0:
            break
        end = int(np.searchsorted(travel, travel[start] + need))
        end = min(end, start + int(WARMUP_MAX_SHARE * n), start + budget)
        out[start:end] = False
        budget -= max(end - start, 0)
    return out


SELECTION_BUDGET = 150_000
"""Samples per cable above which the selection runs on a subset (then refit on all)."""
WARMUP_S = 1.0


def selection_subset(t: np.ndarray, blocks: np.ndarray, budget: int = SELECTION_BUDGET):
    """For long recordings: samples to select on, their blocks and the scoreable ones.

    Only *training* blocks of the whole recording are used (the held-out blocks stay
    unseen by selection and fit alike): evenly chosen training blocks up to ``budget``
    samples, each with ``WARMUP_S`` of the samples before it (simulated, never scored) and
    split into halves that train and test the selection. None: use everything.
    """
    if t.size <= budget:
        return None
    train_blocks = np.unique(blocks[blocks % 2 == 0])
    per_block = t.size / (blocks.max() + 1)
    take = max(2, int(budget // per_block))
    chosen = train_blocks[np.unique(np.linspace(0, train_blocks.size - 1, take).astype(int))]
    idx_parts, blk_parts, use_parts = [], [], []
    for k, b in enumerate(chosen):
        members = np.nonzero(blocks == b)[0]
        lo, hi = members[0], members[-1] + 1
        warm = int(np.searchsorted(t, t[lo] - WARMUP_S))
        rows = np.arange(warm, hi)
        half = lo + (hi - lo) // 2
        idx_parts.append(rows)
        blk_parts.append(np.where(rows < half, 2 * k, 2 * k + 1))
        use_parts.append(rows >= lo)
    idx = np.concatenate(idx_parts)
    idx, first = np.unique(idx, return_index=True)
    return idx, np.concatenate(blk_parts)[first], np.concatenate(use_parts)[first]


def candidates_for(has_mass: bool) -> list[str]:
    """Effects the recording's columns allow (a platform effect needs pose and mass)."""
    return [e for e in ALL_EFFECTS if has_mass or not fx.REGISTRY[e].needs_mass]


def cable_candidates(cands: list[str], d: CableData, nom: Nominal) -> list[str]:
    """Drop what this cable's motion cannot show: an effect that needs motion on a cable
    that never moves, one whose module says the motion cannot show it (e.g. a periodic
    effect over less than half a period of travel: that is an offset)."""
    moving = bool(np.any(d.v != 0))
    return [
        c
        for c in cands
        if (moving or not fx.REGISTRY[c].needs_motion) and fx.REGISTRY[c].applicable(d, nom)
    ]


def validation_forwards(validation, nom: Nominal, cables: int, origin: np.ndarray | None = None):
    """The validation recording's forwards and its valid (unclipped) samples, or None;
    ``origin``: the diagnosed recording's first cable lengths (:func:`cable_data`)."""
    if validation is None:
        return None
    vrec, vtp, vdm = finite_rows(*validation)
    if vrec.cables != cables:
        raise RecordingError(
            f"{vrec.source}: has {vrec.cables} cables, the diagnosed recording {cables}"
        )
    fws = [Forward(d, nom) for d in cable_data(vrec, vtp, vdm, origin)]
    return fws, np.column_stack([~clipped_mask(fw.data.ts)[0] for fw in fws])
