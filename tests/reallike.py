"""A "real-like" generator of cable-robot logs (issue 29 items 4 and 6), independent of
:mod:`gateway.model` and of sim_plc's plant: its own statics, motion and friction integration.

A *machine* is a point-mass platform hung from 4-8 winches whose anchors sit on a circle above
it. Every winch has the same drive train (the friction is shared across winches):

- a direction-dependent load-proportional loss, written as one 180-degree pulley of bearing
  coefficient ``mu_out`` paying out and ``mu_in`` hauling in (docs/physics.md sec. 3:
  ``lambda_s = 2 mu_s / (1 + s mu_s)`` for a 180-degree wrap), plus a Coulomb level ``f0_n``;
- viscous friction ``c_ns_m`` at the platform end (``T = T_p - c v``);
- with ``sigma_n_m > 0``, Dahl pre-sliding: the friction is a state ``F`` stepped over the
  travel ``dx = v dt`` by the exact exponential update towards ``s L`` (``L = lambda_s T + f0``),
  so the force held at rest remembers the last direction; with ``sigma_n_m = 0`` the
  Coulomb law (``F = sgn(v) L``, nothing held at rest).

The drive reports its motor current: ``i = r T_s / k_true + i_0``. The logger converts it with
the datasheet constant ``k_nom``, so the reading in N is ``(1 + g) T_s + c`` with
``g = k_nom / k_true - 1`` (the catalogue's ``gain``) and ``c`` (its ``offset``), plus noise of
10-20 % of the cable's mean load and a current quantum. Logs are 10-100 Hz with timing jitter,
dropped stretches (gaps), a few blank fields and long standstills under load.

Each recording of one machine has its own motion (seed); the machine (friction, scale,
offset) is the same in every recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit

G = 9.81
MU_NOM = 0.01
"""The datasheet loss the nominal model file states (one 180-degree pulley, Coulomb)."""
FINE_HZ = 500.0


@dataclass(frozen=True)
class Machine:
    """One robot: geometry, drive train (the same on every winch) and the reading's scale."""

    cables: int = 4
    mass_kg: float = 30.0
    radius_m: float = 1.5
    height_m: float = 2.5
    pretension_n: float = 40.0
    mu_out: float = MU_NOM
    mu_in: float = MU_NOM
    f0_n: float = 0.0
    c_ns_m: float = 0.0
    sigma_n_m: float = 0.0
    gain: float = 0.0
    offset_n: float = 0.0
    noise_frac: float = 0.15
    quantum_n: float = 0.5


@dataclass(frozen=True)
class Run:
    """One recording's motion and logging."""

    seed: int = 0
    rate_hz: float = 10.0
    seconds: float = 400.0
    vmax: float = 0.25
    dwell_s: tuple[float, float] = (3.0, 25.0)
    gaps: int = 3
    blanks: int = 5
    jitter: float = 0.05
    """Timing jitter as a fraction of the sample period."""


def anchors(m: Machine) -> np.ndarray:
    """(cables, 3) anchor points on a circle at ``height_m``."""
    ang = 2 * np.pi * np.arange(m.cables) / m.cables + 0.3
    return np.column_stack(
        [m.radius_m * np.cos(ang), m.radius_m * np.sin(ang), np.full(m.cables, m.height_m)]
    )


def statics(m: Machine, p: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Cable tensions (n, cables) holding the platform at ``p`` (n, 3) with acceleration
    ``acc``: ``U T = m (a + g e_z)``, the solution nearest the pretension."""
    d = anchors(m)[None, :, :] - p[:, None, :]
    u = np.swapaxes(d / np.linalg.norm(d, axis=2)[:, :, None], 1, 2)  # n x 3 x cables
    w = m.mass_kg * (acc + np.array([0.0, 0.0, G]))
    pre = np.full(m.cables, m.pretension_n)
    rhs = w - u @ pre
    # the minimum-norm correction pinv(U) r = U^T (U U^T)^-1 r, batched
    y = np.linalg.solve(u @ np.swapaxes(u, 1, 2), rhs[:, :, None])[:, :, 0]
    return pre + np.einsum("nkc,nk->nc", u, y)


def _min_jerk(s: np.ndarray) -> np.ndarray:
    return s**3 * (10 - 15 * s + 6 * s**2)


def motion(m: Machine, run: Run, t: np.ndarray, rng: np.random.Generator):
    """Pose-to-pose moves with long dwells: position, velocity, acceleration (n, 3)."""
    p = np.zeros((t.size, 3))
    v = np.zeros_like(p)
    acc = np.zeros_like(p)
    here = np.array([0.0, 0.0, 0.8])
    now = t[0]
    k = 0
    while now < t[-1]:
        dwell = rng.uniform(*run.dwell_s)
        stop = np.searchsorted(t, now + dwell)
        p[k:stop] = here
        k, now = stop, now + dwell
        target = np.array(
            [*rng.uniform(-0.45, 0.45, 2) * m.radius_m, rng.uniform(0.5, 1.3)], dtype=float
        )
        dist = float(np.linalg.norm(target - here))
        dur = max(1.875 * dist / run.vmax, 1.0)  # min-jerk peak speed 1.875 d / T
        stop = np.searchsorted(t, now + dur)
        s = (t[k:stop] - now) / dur
        d = target - here
        p[k:stop] = here + _min_jerk(s)[:, None] * d
        v[k:stop] = (30 * s**2 * (1 - s) ** 2 / dur)[:, None] * d
        acc[k:stop] = ((60 * s - 180 * s**2 + 120 * s**3) / dur**2)[:, None] * d
        here, k, now = target, stop, now + dur
    return p, v, acc


def cable_velocity(m: Machine, p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``dL/dt`` per cable (positive paying out): ``-u . v``."""
    d = anchors(m)[None, :, :] - p[:, None, :]
    u = d / np.linalg.norm(d, axis=2)[:, :, None]
    return -np.einsum("nkj,nj->nk", u, v)


def lambdas(m: Machine) -> tuple[float, float]:
    """The load-proportional loss paying out and hauling in (180-degree pulley)."""
    return 2 * m.mu_out / (1 + m.mu_out), 2 * m.mu_in / (1 - m.mu_in)


@njit(cache=True)
def _friction(tn, vc, dt, lam_out, lam_in, f0, sigma):  # pragma: no cover - numba
    """The friction state F (n, cables) the winch side lacks: ``T_s = T_n - F``."""
    n, c = tn.shape
    out = np.zeros((n, c))
    for j in range(c):
        f = 0.0
        last = 1.0
        for k in range(n):
            v = vc[k, j]
            s = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
            if s != 0.0:
                last = s
            lam = lam_out if last > 0 else lam_in
            level = lam * abs(tn[k, j]) + f0
            if sigma <= 0.0:
                f = s * level
            elif s != 0.0 and level > 0.0:
                dx = abs(v) * dt
                f = s * level + (f - s * level) * math.exp(-sigma * dx / level)
            out[k, j] = f
    return out


@dataclass
class Truth:
    """The noise-free fine-grid series a test checks the physics on."""

    t: np.ndarray
    tp: np.ndarray
    v: np.ndarray
    friction: np.ndarray
    ts: np.ndarray
    reading: np.ndarray
    pos: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    acc: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))


def simulate(m: Machine, run: Run) -> Truth:
    """Integrate one recording on the fine grid (noise-free)."""
    rng = np.random.default_rng(run.seed)
    t = np.arange(0.0, run.seconds, 1.0 / FINE_HZ)
    p, v, acc = motion(m, run, t, rng)
    tp = statics(m, p, acc)
    vc = cable_velocity(m, p, v)
    tn = tp - m.c_ns_m * vc
    lo, li = lambdas(m)
    fr = _friction(tn, vc, 1.0 / FINE_HZ, lo, li, m.f0_n, m.sigma_n_m)
    ts = tn - fr
    reading = (1 + m.gain) * ts + m.offset_n
    return Truth(t, tp, vc, fr, ts, reading, p, acc)


def generate(m: Machine, run: Run) -> dict[str, np.ndarray]:
    """The recording's columns: ``t`` and per cable velocity/tension_sensor/platform."""
    tr = simulate(m, run)
    rng = np.random.default_rng(run.seed + 7919)
    dt = 1.0 / run.rate_hz
    ts_out = np.arange(1.0, run.seconds - 1.0, dt)
    ts_out = ts_out + rng.uniform(-run.jitter, run.jitter, ts_out.size) * dt
    keep = np.ones(ts_out.size, bool)
    for _ in range(run.gaps):  # the logger dropped 2-8 s
        a = rng.uniform(ts_out[0], ts_out[-1])
        keep &= ~((ts_out > a) & (ts_out < a + rng.uniform(2.0, 8.0)))
    ts_out = ts_out[keep]
    cols: dict[str, np.ndarray] = {"t": ts_out}
    for i in range(m.cables):
        tp = np.interp(ts_out, tr.t, tr.tp[:, i])
        sd = m.noise_frac * float(tr.tp[:, i].mean())
        read = np.interp(ts_out, tr.t, tr.reading[:, i]) + rng.normal(0.0, sd, ts_out.size)
        read = np.round(read / m.quantum_n) * m.quantum_n
        read[rng.choice(read.size, run.blanks, replace=False)] = np.nan
        cols[f"velocity_{i + 1}"] = np.interp(ts_out, tr.t, tr.v[:, i])
        cols[f"tension_sensor_{i + 1}"] = read
        cols[f"tension_platform_{i + 1}"] = tp
    return cols


def write(path: Path, cols: dict[str, np.ndarray], note: str = "") -> Path:
    """Plain CSV in the recording format (docs/recording-format.md sec. 1), blanks empty."""
    names = list(cols)
    lines = ["# source: tests/reallike.py", f"# note: {note}" if note else "# note: -"]
    lines.append(",".join(names))
    data = np.column_stack([cols[n] for n in names])
    lines += [",".join("" if x != x else f"{x:.10g}" for x in row) for row in data]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def model_yaml() -> str:
    """The nominal model the engineer hands in: the datasheet loss, Coulomb."""
    return (
        "# nominal model of a real-like machine: the drive's datasheet loss\n"
        f"friction:\n  model: coulomb\n  pulleys:\n    - {{wrap_deg: 180.0, mu: {MU_NOM}}}\n"
    )


def truth_effects(m: Machine) -> dict[str, dict[str, float]]:
    """The catalogue effects (gateway/model/effects registry names) that are this machine's
    truth against :func:`model_yaml`, with their reported parameters."""
    out: dict[str, dict[str, float]] = {}
    if m.mu_out != m.mu_in:
        out["coulomb_directional"] = {"mu_out": m.mu_out, "mu_in": m.mu_in}
        if m.f0_n:
            out["coulomb_directional"]["f0_n"] = m.f0_n
    elif m.mu_out != MU_NOM or m.f0_n:
        out["coulomb"] = {"f0_n": m.f0_n}
        if m.mu_out != MU_NOM:
            out["coulomb"]["mu"] = m.mu_out
    if m.c_ns_m:
        out["viscous"] = {"c_ns_m": m.c_ns_m}
    if m.sigma_n_m > 0:
        out["presliding"] = {"sigma_n_m": m.sigma_n_m}
    if m.gain:
        out["gain"] = {"g": m.gain}
    if m.offset_n:
        out["offset"] = {"c_n": m.offset_n}
    return out
