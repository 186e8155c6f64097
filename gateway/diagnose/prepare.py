"""From a recording to one :class:`CableData` per cable: the nominal chain, finite rows,
the velocity dead band, saturated sensor readings and the held-out time blocks."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.diagnose import locate
from gateway.diagnose.forward import CableData, Nominal
from gateway.diagnose.platform import MassSensitivity
from gateway.errors import RecordingError
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
    d2 = np.diff(v, 2)
    return float(np.median(np.abs(d2)) / 0.6745 / math.sqrt(6.0))


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


def cable_data(rec: Recording, tp: np.ndarray, dtp_dm: Sensitivity) -> list[CableData]:
    """One :class:`CableData` per cable; ``tp`` (N, m); velocity through :func:`deadband`.

    Memory: the tensions and a clean velocity are views of the recording's columns (not
    copies); displacement and acceleration (16 bytes per sample) and ``dtp_dm`` given as
    :class:`MassSensitivity` (8) are computed when a cable is worked on and freed by
    :meth:`Forward.clear_cache` (float32 would halve them but moves the finite-difference
    fits of eccentricity and inertia)."""
    t0 = float(rec.t[0])
    out = []
    for i in range(rec.cables):
        v = deadband(rec.velocity[:, i])
        dm: np.ndarray | Callable[[], np.ndarray] | None = None
        if isinstance(dtp_dm, MassSensitivity):
            dm = partial(dtp_dm.column, rec.t, i)
        elif dtp_dm is not None:
            dm = dtp_dm[:, i]
        out.append(CableData(rec.t, v, tp[:, i], rec.tension_sensor[:, i], t0, dm))
    return out


def finite_rows(rec: Recording, tp: np.ndarray, dtp_dm: Sensitivity):
    """Drop the samples where any cable lacks a finite value (counted in skipped_rows);
    a :class:`MassSensitivity` stays as it is (read at the kept samples' times)."""
    ok = np.isfinite(rec.velocity).all(1) & np.isfinite(rec.tension_sensor).all(1)
    ok &= np.isfinite(tp).all(1)
    if ok.all():
        return rec, tp, dtp_dm
    if not ok.any():
        raise RecordingError(f"{rec.source}: no sample has every required value")
    sub = replace(
        rec,
        t=rec.t[ok],
        velocity=rec.velocity[ok],
        tension_sensor=rec.tension_sensor[ok],
        tension_platform=None if rec.tension_platform is None else rec.tension_platform[ok],
        length=None,
        pose=None if rec.pose is None else rec.pose[ok],
        mass=None if rec.mass is None else rec.mass[ok],
        extra={},
        skipped_rows=rec.skipped_rows + int((~ok).sum()),
    )
    return sub, tp[ok], dtp_dm[ok] if isinstance(dtp_dm, np.ndarray) else dtp_dm


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


def time_blocks(t: np.ndarray) -> tuple[np.ndarray, int]:
    """Block index (N,) of interleaved time blocks; even blocks train, odd ones are held out.

    About one block per second of recording, between 10 and 40 blocks (an even number).
    """
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    nb = int(np.clip(round(span / 1.0), 10, 40))
    nb += nb % 2
    edges = t[0] + span * np.arange(1, nb) / nb
    return np.searchsorted(edges, t, side="right").astype(np.int64), nb
