"""Platform trajectories for the plant: poses, pose rates and accelerations at given times.

Every trajectory is vectorised: ``evaluate(t)`` with ``t`` (N,) in s returns a
:class:`TrajectorySample` of arrays (N, 6) - pose ``(x, y, z, rx, ry, rz)`` in m and rad,
its time derivative (m/s, rad/s; Euler-angle rates, not the angular velocity) and second
derivative - and a flag (N,) that is true while the extruder prints. ``printing_time(t)``
gives the time spent printing up to ``t`` (s), from which the plant's mass follows.

* :class:`PaperPath` - eq. 20 (physics.md sec. 4), in mm:
  ``x = 200 sin(5 - u)``, ``y = 15 (15 - u)``, ``z = 10 u``. We take **u in [0, 15]**:
  ``y = 15 (15 - u)`` ends at y = 0 for u = 15, so [0, 15] is the range the formula
  suggests; it is 2.4 periods of the sine and spans 0.40 x 0.225 x 0.15 m (~2.0 m of
  path per layer), well inside the 4 x 3 x 3 m frame. The path is centred on the home
  pose. Constant path speed 0.04 m/s by arc-length reparametrisation: ``u(s)`` from a
  dense arc-length table refined by Newton steps; velocity and acceleration follow
  analytically, so ``|dp/dt|`` is exactly the speed. Two layers: layer 2 is the path
  lifted by ``layer_height_m`` and printed backwards (one continuous bead) after a
  vertical lift; each segment starts and stops at rest with cycloidal speed ramps (no
  step in acceleration).
* :class:`CyclicMotion` - sinusoids in all six DOF through one point (paper Fig. 9).
* :class:`RandomMotion` - seeded sums of sinusoids: smooth, bounded, many reversals.
* :class:`FileTrajectory` - a CSV of poses over time, cubic-spline interpolated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from scipy.interpolate import CubicSpline

from gateway.errors import ConfigError
from sim_plc.config import (
    CyclicConfig,
    FileTrajectoryConfig,
    PaperPathConfig,
    RandomConfig,
    TrajectoryConfig,
)

MM = 1e-3


@dataclass
class TrajectorySample:
    """Arrays at N times: pose, velocity, acceleration (N, 6); printing (N,) bool."""

    pose: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    printing: np.ndarray


class Trajectory(Protocol):
    duration_s: float  # math.inf for endless motion

    def evaluate(self, t: np.ndarray) -> TrajectorySample: ...

    def printing_time(self, t: np.ndarray) -> np.ndarray: ...


def _empty(n: int) -> TrajectorySample:
    z = np.zeros((n, 6))
    return TrajectorySample(z, z.copy(), z.copy(), np.zeros(n, dtype=bool))


# --- arc-length segments -------------------------------------------------------------


class _Curve(Protocol):
    u0: float
    u1: float

    def derivs(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


class Eq20Curve:
    """Eq. 20 in metres, ``p(u) = offset + 1e-3 (200 sin(5-u), 15 (15-u), 10 u)``.

    ``reverse`` runs it from ``u1`` to ``u0`` (parameter ``u' = u0 + u1 - u``).
    """

    def __init__(self, u0: float, u1: float, offset: np.ndarray, reverse: bool = False):
        self.u0, self.u1 = u0, u1
        self.offset = np.asarray(offset, dtype=float)
        self.reverse = reverse

    def derivs(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """p, dp/du, d2p/du2, each (N, 3) in m."""
        s = -1.0 if self.reverse else 1.0
        uu = self.u0 + self.u1 - u if self.reverse else u
        sn, cs = np.sin(5.0 - uu), np.cos(5.0 - uu)
        p = np.column_stack([200 * sn, 15 * (15 - uu), 10 * uu]) * MM + self.offset
        d1 = np.column_stack([-200 * cs, np.full_like(uu, -15.0), np.full_like(uu, 10.0)])
        d2 = np.column_stack([-200 * sn, np.zeros_like(uu), np.zeros_like(uu)])
        return p, s * d1 * MM, d2 * MM


class LineCurve:
    """Straight line from ``p0`` to ``p1``, parametrised by arc length."""

    def __init__(self, p0: np.ndarray, p1: np.ndarray):
        self.p0 = np.asarray(p0, dtype=float)
        d = np.asarray(p1, dtype=float) - self.p0
        self.u0, self.u1 = 0.0, float(np.linalg.norm(d))
        self.dir = d / self.u1 if self.u1 > 0 else np.zeros(3)

    def derivs(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = self.p0 + u[:, None] * self.dir
        return p, np.broadcast_to(self.dir, p.shape).copy(), np.zeros_like(p)


def speed_profile(tau: np.ndarray, length: float, speed: float, ramp: float):
    """Arc length s, ds/dt, d2s/dt2 (N,) on a segment at times ``tau`` from its start.

    Cycloidal ramps of duration ``ramp`` (shortened if the segment is too short) from
    rest to ``speed`` and back; duration ``length / speed + ramp``.
    """
    ramp = min(ramp, length / speed)
    dur = length / speed + ramp
    tau = np.clip(tau, 0.0, dur)
    s = np.empty_like(tau)
    v = np.full_like(tau, speed)
    a = np.zeros_like(tau)
    if ramp > 0:
        w = 2 * math.pi / ramp
        up = tau < ramp
        x = tau[up]
        s[up] = speed * (x * x / (2 * ramp) + (np.cos(w * x) - 1) / (w * w * ramp))
        v[up] = speed * (x / ramp - np.sin(w * x) / (w * ramp))
        a[up] = speed * (1 - np.cos(w * x)) / ramp
        down = tau > dur - ramp
        x = dur - tau[down]
        s[down] = length - speed * (x * x / (2 * ramp) + (np.cos(w * x) - 1) / (w * w * ramp))
        v[down] = speed * (x / ramp - np.sin(w * x) / (w * ramp))
        a[down] = -speed * (1 - np.cos(w * x)) / ramp
        mid = ~(up | down)
    else:
        mid = np.ones_like(tau, dtype=bool)
    s[mid] = speed * (tau[mid] - ramp / 2)
    return s, v, a


class ArcSegment:
    """A curve traversed at ``speed`` (m/s) by arc length, starting and ending at rest."""

    def __init__(self, curve: _Curve, speed: float, ramp: float, printing: bool, n: int = 20001):
        self.curve, self.speed, self.printing = curve, speed, printing
        u = np.linspace(curve.u0, curve.u1, n)
        g = np.linalg.norm(curve.derivs(u)[1], axis=1)
        self._u = u
        self._s = np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(u))])
        self.length = float(self._s[-1])
        self.ramp = min(ramp, self.length / speed)
        self.duration = self.length / speed + self.ramp

    def u_of_s(self, s: np.ndarray) -> np.ndarray:
        """Invert the arc-length table; two Newton steps on the local trapezoid rule."""
        u = np.interp(s, self._s, self._u)
        for _ in range(2):
            k = np.clip(np.searchsorted(self._u, u) - 1, 0, self._u.size - 2)
            g_k = np.linalg.norm(self.curve.derivs(self._u[k])[1], axis=1)
            g_u = np.linalg.norm(self.curve.derivs(u)[1], axis=1)
            s_u = self._s[k] + (u - self._u[k]) * 0.5 * (g_k + g_u)
            u = np.clip(u - (s_u - s) / g_u, self.curve.u0, self.curve.u1)
        return u

    def evaluate(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (N, 3) at times ``tau`` from the start."""
        s, sd, sdd = speed_profile(tau, self.length, self.speed, self.ramp)
        p, d1, d2 = self.curve.derivs(self.u_of_s(s))
        g = np.linalg.norm(d1, axis=1)
        ud = sd / g
        udd = (sdd - ud * ud * np.einsum("ij,ij->i", d1, d2) / g) / g
        return p, d1 * ud[:, None], d2 * (ud * ud)[:, None] + d1 * udd[:, None]


class SegmentTrajectory:
    """Arc-length segments in sequence (translation only); holds the last pose after."""

    def __init__(self, segments: list[ArcSegment]):
        self.segments = segments
        self.starts = np.cumsum([0.0] + [s.duration for s in segments])
        self.duration_s = float(self.starts[-1])

    def evaluate(self, t: np.ndarray) -> TrajectorySample:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = _empty(t.size)
        idx = np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.segments) - 1)
        for k, seg in enumerate(self.segments):
            sel = idx == k
            if np.any(sel):
                p, v, a = seg.evaluate(t[sel] - self.starts[k])
                out.pose[sel, :3], out.velocity[sel, :3], out.acceleration[sel, :3] = p, v, a
                inside = (t[sel] >= self.starts[k]) & (t[sel] < self.starts[k + 1])
                out.printing[sel] = seg.printing & inside
        return out

    def printing_time(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        total = np.zeros_like(t)
        for k, seg in enumerate(self.segments):
            if seg.printing:
                total += np.clip(t - self.starts[k], 0.0, seg.duration)
        return total


def paper_path(cfg: PaperPathConfig, home: np.ndarray) -> SegmentTrajectory:
    """The eq. 20 path in ``cfg.layers`` layers (see the module docstring)."""
    top = cfg.layer_height_m * (cfg.layers - 1)
    if cfg.offset_m is None:
        probe = Eq20Curve(cfg.u_start, cfg.u_end, np.zeros(3))
        pts = probe.derivs(np.linspace(cfg.u_start, cfg.u_end, 20001))[0]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        hi[2] += top
        offset = np.asarray(home[:3], dtype=float) - 0.5 * (lo + hi)
    else:
        offset = np.asarray(cfg.offset_m, dtype=float)
    segments: list[ArcSegment] = []
    for layer in range(cfg.layers):
        lift = np.array([0.0, 0.0, cfg.layer_height_m * layer])
        curve = Eq20Curve(cfg.u_start, cfg.u_end, offset + lift, reverse=layer % 2 == 1)
        if layer > 0 and cfg.layer_height_m > 0:
            end = segments[-1].curve.derivs(np.array([segments[-1].curve.u1]))[0][0]
            lift_line = LineCurve(end, end + np.array([0.0, 0.0, cfg.layer_height_m]))
            segments.append(ArcSegment(lift_line, cfg.speed_m_s, cfg.ramp_s, False, 101))
        segments.append(ArcSegment(curve, cfg.speed_m_s, cfg.ramp_s, True))
    return SegmentTrajectory(segments)


class PaperPath(SegmentTrajectory):
    def __init__(self, cfg: PaperPathConfig, home: np.ndarray):
        super().__init__(paper_path(cfg, home).segments)


# --- periodic and random motion ------------------------------------------------------


class SineSumMotion:
    """``pose_d(t) = center_d + sum_k A_dk sin(2 pi f_dk t + phi_dk)`` (never prints)."""

    duration_s = math.inf

    def __init__(self, center, amp, freq, phase):
        self.center = np.asarray(center, dtype=float)  # (6,)
        self.amp = np.asarray(amp, dtype=float)  # (6, K)
        self.omega = 2 * math.pi * np.asarray(freq, dtype=float)  # (6, K)
        self.phase = np.asarray(phase, dtype=float)  # (6, K)

    def evaluate(self, t: np.ndarray) -> TrajectorySample:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        arg = t[:, None, None] * self.omega + self.phase  # (N, 6, K)
        sn, cs = np.sin(arg), np.cos(arg)
        pose = self.center + np.sum(self.amp * sn, axis=2)
        vel = np.sum(self.amp * self.omega * cs, axis=2)
        acc = -np.sum(self.amp * self.omega**2 * sn, axis=2)
        return TrajectorySample(pose, vel, acc, np.zeros(t.size, dtype=bool))

    def printing_time(self, t: np.ndarray) -> np.ndarray:
        return np.zeros_like(np.asarray(t, dtype=float))


def cyclic_motion(cfg: CyclicConfig, home: np.ndarray) -> SineSumMotion:
    center = np.asarray(home if cfg.center is None else cfg.center, dtype=float)
    col = lambda v: np.asarray(v, dtype=float)[:, None]  # noqa: E731
    return SineSumMotion(center, col(cfg.amplitude), col(cfg.frequency_hz), col(cfg.phase_rad))


def random_motion(cfg: RandomConfig, home: np.ndarray) -> SineSumMotion:
    """Seeded random sinusoid sums; ``sum |A_dk| = amplitude_d`` bounds each DOF."""
    rng = np.random.default_rng(cfg.seed)
    k = cfg.components
    freq = rng.uniform(cfg.min_frequency_hz, cfg.max_frequency_hz, (6, k))
    phase = rng.uniform(0, 2 * math.pi, (6, k))
    weights = rng.uniform(0.2, 1.0, (6, k))
    amp = weights / weights.sum(axis=1, keepdims=True) * np.asarray(cfg.amplitude)[:, None]
    center = np.asarray(home if cfg.center is None else cfg.center, dtype=float)
    return SineSumMotion(center, amp, freq, phase)


class FileTrajectory:
    """Poses over time from a CSV (header t, x, y, z, rx, ry, rz [, printing]).

    Cubic spline through the samples (time shifted to start at 0); before and after the
    file the end poses hold at rest.
    """

    def __init__(self, path: str | Path):
        path = Path(path)
        try:
            with open(path, encoding="utf-8") as fh:
                header = [c.strip() for c in fh.readline().split(",")]
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{path}: cannot read trajectory: {exc}") from exc
        need = ["t", "x", "y", "z", "rx", "ry", "rz"]
        missing = [c for c in need if c not in header]
        if missing or data.shape[0] < 2:
            raise ConfigError(f"{path}: trajectory needs columns {need} and >= 2 rows")
        t = data[:, header.index("t")]
        if np.any(np.diff(t) <= 0):
            raise ConfigError(f"{path}: column 't' must increase strictly")
        self.t = t - t[0]
        self.spline = CubicSpline(self.t, data[:, [header.index(c) for c in need[1:]]])
        flag = data[:, header.index("printing")] if "printing" in header else 0 * t
        self.flag = flag != 0
        steps = 0.5 * (self.flag[1:] + self.flag[:-1].astype(float)) * np.diff(self.t)
        self._printed = np.concatenate([[0.0], np.cumsum(steps)])
        self.duration_s = float(self.t[-1])

    def evaluate(self, t: np.ndarray) -> TrajectorySample:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        tc = np.clip(t, 0.0, self.duration_s)
        inside = (t >= 0) & (t <= self.duration_s)
        vel = self.spline(tc, 1) * inside[:, None]
        acc = self.spline(tc, 2) * inside[:, None]
        k = np.clip(np.searchsorted(self.t, tc, side="right") - 1, 0, self.t.size - 1)
        return TrajectorySample(self.spline(tc), vel, acc, self.flag[k] & inside)

    def printing_time(self, t: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(t, dtype=float), self.t, self._printed)


def make_trajectory(cfg: TrajectoryConfig, home: np.ndarray, base_dir: str = ".") -> Trajectory:
    """The trajectory ``cfg.kind`` names; ``home`` (6,) is the default centre."""
    home = np.asarray(home, dtype=float)
    if cfg.kind == "paper":
        return PaperPath(cfg.paper, home)
    if cfg.kind == "cyclic":
        return cyclic_motion(cfg.cyclic, home)
    if cfg.kind == "random":
        return random_motion(cfg.random, home)
    return file_trajectory(cfg.file, base_dir)


def file_trajectory(cfg: FileTrajectoryConfig, base_dir: str) -> FileTrajectory:
    path = Path(cfg.path)
    return FileTrajectory(path if path.is_absolute() else Path(base_dir) / path)
