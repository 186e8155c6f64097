"""One machine, many recordings (issue 29 item 1): several recordings of one machine
diagnosed as one, for one set of findings.

The recordings are joined into one series (:func:`join`), each behind a gap that the
diagnosis already treats as one (:func:`.timebase.gap_starts`: the friction state warms up
again after it, as at a start; refits for the standard errors leave whole pieces, here
whole recordings, out: :func:`.significance.block_refits`). What that gives:

- **held out**: the time blocks are drawn within each recording (:func:`time_blocks`:
  about one a second, even ones train, odd ones are held out), so every recording trains
  and is held out, and one statistic per effect and cable pools the held-out blocks of all
  of them;
- **recordings left out**: each kept effect is also tested on recordings left out in turn
  (:meth:`.reference.CableUnit.recordings_left_out`); it must pass both (the smaller z,
  the larger p: :func:`.significance.score`), and that one p per effect and cable goes into
  the significance stage and the cross-cable pooling (:mod:`.pooling`) as for one
  recording;
- **parameters**: fitted jointly on the training blocks of every recording; a machine's
  property (a friction coefficient, a gain) is one value for all, a session's property
  (``Effect.per_recording``: an offset, a drift, each recording's sensor zero) one value
  per recording (:func:`tile_spec`, :func:`session_values`). The report gives such an
  effect's mean over the recordings in ``parameters`` (what ``--write-model`` writes: the
  next session's zero is not known) and each recording's in ``per_recording``;
- **the validation recording** (``--validate``) is scored with those means and never
  decides what is kept.

A single recording goes through none of this: the same code path and report as before.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gateway.diagnose.pose_statics import MassSensitivity
from gateway.diagnose.timebase import time_blocks as one
from gateway.errors import RecordingError
from gateway.model import effects as fx
from gateway.model.effects import Spec
from gateway.recordings.reader import Recording

JOIN_SPACINGS = 40.0
"""The gap put between two joined recordings, in the larger median sample spacing (a gap
is anything over :data:`.timebase.GAP_SPACINGS` = 10)."""


@dataclass(frozen=True)
class Sessions:
    """Which recording each sample of the joined series comes from."""

    names: list[str]
    index: np.ndarray
    """(N,) int: the recording of each sample (0-based, in the order given)."""
    starts: np.ndarray
    """(R,) the first (joined) time of each recording: a drift's ``t_0``."""
    durations_s: list[float]
    samples: list[int]

    @property
    def count(self) -> int:
        return len(self.names)

    def t0(self) -> np.ndarray:
        """(N,) each sample's recording start."""
        return self.starts[self.index]

    def report(self) -> list[dict]:
        """The report's ``recordings``: ``start_s`` is where each begins on the joined
        clock, which the report's times (``mismatch`` regions, ``warmup``) are on."""
        return [
            {"name": n, "samples": s, "duration_s": d, "start_s": float(t0)}
            for n, s, d, t0 in zip(
                self.names, self.samples, self.durations_s, self.starts, strict=True
            )
        ]


def _shape(rec: Recording, dm) -> dict[str, object]:
    return {
        "cables": rec.cables,
        "platform tension columns": rec.tension_platform is not None,
        "pose columns": rec.pose is not None,
        "mass column": rec.mass is not None,
        "extra columns": sorted(rec.extra or {}),
        "mass sensitivity (pose, mass and a geometry)": dm is not None,
    }


def check_alike(parts: list[tuple[Recording, np.ndarray, Any]], names: list[str]) -> None:
    """One line naming the first recording whose cable set or columns differ from the
    first recording's (:class:`RecordingError`)."""
    ref = _shape(parts[0][0], parts[0][2])
    for (rec, _tp, dm), name in zip(parts[1:], names[1:], strict=True):
        mine = _shape(rec, dm)
        for key, want in ref.items():
            if mine[key] != want:
                raise RecordingError(
                    f"{name}: {key} {mine[key]} differ from {names[0]}'s ({want}): the "
                    "recordings diagnosed together must be of one machine, with the same columns"
                )


def finite_rows(rec: Recording, tp: np.ndarray, dtp_dm: np.ndarray | MassSensitivity | None):
    """Drop the samples where any cable lacks a finite value (counted in skipped_rows);
    a :class:`MassSensitivity` stays as it is (read at the kept samples' times)."""
    ok = np.isfinite(rec.velocity).all(1) & np.isfinite(rec.tension_sensor).all(1)
    ok &= np.isfinite(tp).all(1)
    if ok.all():
        return rec, tp, dtp_dm
    if not ok.any():
        raise RecordingError(f"{rec.source}: no sample has every required value")
    kept = replace(rec, length=None, extra={}).take(ok)
    sub = replace(kept, skipped_rows=rec.skipped_rows + int((~ok).sum()))
    return sub, tp[ok], dtp_dm[ok] if isinstance(dtp_dm, np.ndarray) else dtp_dm


def join(
    parts: list[tuple[Recording, np.ndarray, Any]], names: list[str]
) -> tuple[Recording, np.ndarray, np.ndarray | None, Sessions]:
    """The recordings (each with its platform tensions and dT_p/dm) as one series: rows
    without a required value dropped per recording, times shifted so that each starts
    ``JOIN_SPACINGS`` sample spacings after the previous one ends; dT_p/dm as an (N, m)
    array (None when the recordings have none)."""
    check_alike(parts, names)
    clean = []
    for rec, tp, dm in parts:
        if isinstance(dm, MassSensitivity):
            dm = dm.full(rec.t)
        clean.append(finite_rows(rec, tp, dm))
    ts, starts = _clock([r for r, _, _ in clean])
    first = clean[0][0]
    extra = {k: np.concatenate([r.extra[k] for r, _, _ in clean]) for k in first.extra or {}}
    joined = replace(
        first,
        t=np.concatenate(ts),
        velocity=np.concatenate([r.velocity for r, _, _ in clean]),
        tension_sensor=np.concatenate([r.tension_sensor for r, _, _ in clean]),
        tension_platform=None,
        length=None,
        pose=None,
        mass=None,
        extra=extra,
        skipped_rows=sum(r.skipped_rows for r, _, _ in clean),
        source=" + ".join(names),
    )
    tp = np.concatenate([p for _, p, _ in clean])
    dms = [d for _, _, d in clean]
    dm = None if dms[0] is None else np.concatenate(dms)
    return joined, tp, dm, _sessions([r for r, _, _ in clean], names, starts)


def _clock(recs: list[Recording]) -> tuple[list[np.ndarray], list[float]]:
    """Each recording's times on the joined clock, and where each starts: one after the
    other, ``JOIN_SPACINGS`` of the larger median sample spacing apart."""
    spacing = max(float(np.median(np.diff(r.t))) if r.samples > 1 else 0.0 for r in recs)
    gap = JOIN_SPACINGS * max(spacing, 1e-6)
    ts, starts, cursor = [], [], 0.0
    for rec in recs:
        t = rec.t - float(rec.t[0]) + cursor
        ts.append(t)
        starts.append(cursor)
        cursor = float(t[-1]) + gap
    return ts, starts


def _sessions(recs: list[Recording], names: list[str], starts: list[float]) -> Sessions:
    return Sessions(
        [Path(n).name for n in names],
        np.concatenate([np.full(r.samples, k, np.int64) for k, r in enumerate(recs)]),
        np.array(starts),
        [float(r.t[-1] - r.t[0]) for r in recs],
        [r.samples for r in recs],
    )


def join_wrench(recs: list[Recording], names: list[str]) -> tuple[Recording, Sessions]:
    """Recordings without platform tensions (the wrench reference: pose and mass columns)
    as one series, as :func:`join` does: the rows without every value the wrench balance
    reads (velocity, readings, pose, mass) dropped per recording, each recording behind a
    gap; pose and mass kept, of the cable lengths the first row of the first recording (the
    model writer's eccentricity phase; the diagnosis reads none). The wrench
    reference differentiates the pose within each recording (``Sessions.index``), never
    across a join (:func:`gateway.diagnose.wrench.wrench_data`)."""
    check_alike([(r, np.empty(0), None) for r in recs], names)
    if any(r.pose is None or r.mass is None for r in recs):
        bad = next(n for r, n in zip(recs, names, strict=True) if r.pose is None or r.mass is None)
        raise RecordingError(
            f"{bad}: no tension_platform_i columns and no pose and mass columns: several "
            "recordings are diagnosed together against platform tensions or the wrench balance"
        )
    clean = []
    for rec, name in zip(recs, names, strict=True):
        assert rec.pose is not None and rec.mass is not None
        ok = np.isfinite(rec.velocity).all(1) & np.isfinite(rec.tension_sensor).all(1)
        ok &= np.isfinite(rec.pose).all(1) & np.isfinite(rec.mass)
        if ok.sum() < 10:
            raise RecordingError(f"{name}: fewer than 10 samples have every value")
        clean.append(rec if ok.all() else _rows(rec, ok))
    ts, starts = _clock(clean)
    first = clean[0]
    joined = replace(
        first,
        t=np.concatenate(ts),
        velocity=np.concatenate([r.velocity for r in clean]),
        tension_sensor=np.concatenate([r.tension_sensor for r in clean]),
        tension_platform=None,
        length=None if first.length is None else first.length[:1],  # what the writer reads
        pose=np.concatenate([r.pose for r in clean]),
        mass=np.concatenate([r.mass for r in clean]),
        extra={k: np.concatenate([r.extra[k] for r in clean]) for k in first.extra or {}},
        skipped_rows=sum(r.skipped_rows for r in clean),
        source=" + ".join(names),
    )
    return joined, _sessions(clean, names, starts)


def _rows(rec: Recording, ok: np.ndarray) -> Recording:
    """``rec`` with the rows ``ok`` only (the others counted in ``skipped_rows``)."""
    return replace(rec.take(ok), skipped_rows=rec.skipped_rows + int((~ok).sum()))


def time_blocks(t: np.ndarray, sessions: Sessions | None) -> tuple[np.ndarray, int]:
    """:func:`.timebase.time_blocks` within each recording (numbered on: every recording's
    count is even, so even blocks train and odd ones are held out in each)."""
    if sessions is None or sessions.count == 1:
        return one(t)
    out = np.empty(t.size, np.int64)
    total = 0
    for k in range(sessions.count):
        where = np.nonzero(sessions.index == k)[0]
        b, nb = one(t[where])
        out[where] = b + total
        total += nb
    return out, total


def per_recording(effect: str, size: int) -> int:
    """How many recordings the internal vector of ``effect`` of length ``size`` holds (1:
    one for all)."""
    e = fx.REGISTRY[effect]
    k = len(e.params)
    return size // k if e.per_recording and k and size > k and size % k == 0 else 1


def tile_spec(spec: Spec, k: int, count: int) -> Spec:
    """One recording's fitting recipe (``k`` internal parameters) repeated for ``count``
    recordings: recording ``r``'s parameters at ``r k .. r k + k - 1``."""
    return Spec(
        np.tile(spec.neutral, count),
        np.tile(spec.lower, count),
        np.tile(spec.upper, count),
        tuple(j + r * k for r in range(count) for j in spec.linear),
        np.tile(spec.step, count),
        tuple(np.tile(s, count) for s in spec.starts),
    )


def rows(effect: str, theta: np.ndarray) -> np.ndarray:
    """(R, k) an effect's internal vector, one row per recording (one row when shared)."""
    theta = np.asarray(theta, dtype=float)
    return theta.reshape(per_recording(effect, theta.size), -1)


def mean_theta(effect: str, theta: np.ndarray) -> np.ndarray:
    """The internal vector as one recording's: the mean over the recordings (a new
    session's zero is not known; the mean is the best guess for it)."""
    return rows(effect, theta).mean(axis=0)


def mean_stderr(effect: str, theta: np.ndarray, se: np.ndarray) -> np.ndarray:
    """The standard error of :func:`mean_theta` (the recordings' estimates independent)."""
    r = rows(effect, theta).shape[0]
    s = np.asarray(se, dtype=float).reshape(r, -1)
    return np.sqrt(np.sum(s**2, axis=0)) / r


def session_values(effect: str, theta: np.ndarray, session: np.ndarray | None) -> fx.Values:
    """The report values of a path or sensor effect for the forward model: (1,) arrays
    when shared (or for a series of one recording: the mean over the fitted ones), else
    (N,) arrays, each sample its recording's value."""
    e = fx.REGISTRY[effect]
    if per_recording(effect, np.size(theta)) == 1:
        return e.report_arrays(np.asarray(theta, dtype=float))
    r = rows(effect, theta)
    if session is None:
        return e.report_arrays(r.mean(axis=0))
    per = [e.report(row) for row in r]
    return {name: np.array([p[name] for p in per])[session] for name in e.param_names}
