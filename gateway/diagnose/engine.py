"""The diagnosis: nominal simulation, residual, location, selection per cable, scores.

``diagnose(rec, friction)`` returns a :class:`Diagnosis` whose ``report`` is the JSON
report of recording.md. Each cable is selected on its own (effects act per cable), then
the effects are gathered into findings over the cables that kept them, ordered by how
much held-out residual energy they explain together (drop-one from the final model).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.core.heap import return_large_frees
from gateway.diagnose.fit import joint_fit
from gateway.diagnose.forward import ALL_EFFECTS, CableData, Forward, Nominal, chain_params
from gateway.diagnose.prepare import (  # noqa: F401 - re-exported
    Sensitivity,
    cable_data,
    clipped_mask,
    deadband,
    finite_rows,
    nominal_from,
    time_blocks,
    velocity_noise,
)
from gateway.diagnose.report import Diagnosis, build_report, validation_forwards
from gateway.diagnose.select import CableOutcome, CableSelector, Thresholds, drop_unvalidated
from gateway.errors import RecordingError
from gateway.model import effects as fx
from gateway.model.chain import coulomb_coefficients
from gateway.recordings.reader import Recording

Progress = Callable[[str], None]


WARMUP_LENGTHS = 4.0
"""Relaxation lengths ``F_R / sigma`` of cable travel after which the chain state has
forgotten its unknown start (error ``exp(-4)`` ~ 2 %)."""
WARMUP_MAX_SHARE = 0.1
GAP_SPACINGS = 10.0
"""A step longer than this many median sample spacings is a gap (rows missing): how the
cable moved in it is unknown, so the friction state after it is too, as at the start."""
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
    travel = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(d.x)))))
    need = WARMUP_LENGTHS * f_r / nom.sigma_n_m
    dt = np.diff(d.t)
    after_gaps = np.nonzero(dt > GAP_SPACINGS * float(np.median(dt)))[0] + 1
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


def refit_full(fw: Forward, outcome: CableOutcome, train: np.ndarray) -> CableOutcome:
    """Refit the effects selected on a subset jointly on the training samples ``train``."""
    if not outcome.kept:
        return outcome
    stride = max(1, int(train.sum()) // SELECTION_BUDGET)
    fit = joint_fit(fw, outcome.theta, outcome.specs, train, max_nfev=20, stride=stride)
    if fit.ok:
        outcome.theta, outcome.stderr = fit.theta, fit.stderr
    return outcome


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


def diagnose(
    rec: Recording,
    friction: FrictionConfig,
    tp: np.ndarray | None = None,
    dtp_dm: Sensitivity = None,
    validation: tuple[Recording, np.ndarray, Sensitivity] | None = None,
    thresholds: Thresholds | None = None,
    progress: Progress | None = None,
) -> Diagnosis:
    """Diagnose ``rec`` against the nominal ``friction`` model (see the module docstring).

    ``tp`` (N, m): platform tensions (default: the recording's); ``dtp_dm`` (N, m) N/kg
    or its knots (:class:`gateway.diagnose.platform.MassSensitivity`): platform tension
    per kg of platform mass (enables ``mass_change``); ``validation``:
    a second recording of the same machine, its platform tensions and dtp_dm.
    """
    say = progress or (lambda _msg: None)
    return_large_frees()  # many (N,) temporaries: freed ones must not stay resident
    th = thresholds or Thresholds()
    tp = rec.tension_platform if tp is None else tp
    if tp is None:
        raise RecordingError(f"{rec.source}: no platform tensions")
    nom = nominal_from(friction)
    rec, tp, dtp_dm = finite_rows(rec, tp, dtp_dm)
    datas = cable_data(rec, tp, dtp_dm)
    blocks, nb = time_blocks(rec.t)
    all_cands = candidates_for(dtp_dm is not None)
    subset = selection_subset(rec.t, blocks)
    valid = np.empty((rec.samples, rec.cables), bool)
    levels = []
    for i, d in enumerate(datas):
        mask, at = clipped_mask(d.ts)
        valid[:, i] = ~mask
        levels.append(at)
        if at:
            say(f"cable {i + 1}: {int(mask.sum())} clipped readings excluded")
    vsel = validation_forwards(validation, nom, rec.cables)
    vblocks = None if vsel is None else time_blocks(vsel[0][0].data.t)
    outcomes, forwards = [], []
    for i, d in enumerate(datas):
        fw = Forward(d, nom)
        cands = cable_candidates(all_cands, d, nom)
        warm = warmup_mask(d, nom) & valid[:, i]
        say(
            f"cable {i + 1}/{rec.cables}: selecting among {len(cands)} candidate effects"
            + ("" if subset is None else f" on {subset[0].size} of {rec.samples} samples")
        )
        if subset is None:
            outcome = CableSelector(fw, blocks, nb, cands, th, usable=warm).run()
        else:
            idx, sub_blocks, usable = subset
            sub_fw = Forward(d.subset(idx), nom)
            outcome = CableSelector(
                sub_fw, sub_blocks, int(sub_blocks.max()) + 1, cands, th, usable=usable & warm[idx]
            ).run()
            del sub_fw  # its series and cached simulations, before the full-length refit
            d.release()  # x and a: recomputed only if a kept effect needs them
            outcome = refit_full(fw, outcome, (blocks % 2 == 0) & warm)
        if vsel is not None and vblocks is not None:
            vfw, vvalid = vsel
            outcome, dropped = drop_unvalidated(
                fw, vfw[i], vvalid[:, i], *vblocks, outcome, (blocks % 2 == 0) & warm, th
            )
            if dropped:
                say(f"cable {i + 1}: {', '.join(dropped)} did not lower the validation error")
            vfw[i].clear_cache()
        say(f"cable {i + 1}/{rec.cables}: kept {', '.join(outcome.kept) or 'nothing'}")
        fw.clear_cache()
        outcomes.append(outcome)
        forwards.append(fw)
    clipped = {"per_cable": [int((~valid[:, i]).sum()) for i in range(rec.cables)],
               "levels_n": levels}  # fmt: skip
    diag = build_report(rec, forwards, outcomes, blocks, vsel, nom, valid, clipped)
    diag.report["reference"] = "platform_tension"
    return diag


# ---- reference mode (issue 10 part 2): per-cable platform tension or the wrench balance ----
def reference_mode(rec: Recording) -> str:
    """``platform_tension`` when the recording has ``tension_platform_i`` columns, else
    ``wrench``: the platform's wrench balance from pose, mass and a model file with a
    geometry (:mod:`gateway.diagnose.wrench`; no tension distribution is assumed)."""
    return "platform_tension" if rec.tension_platform is not None else "wrench"
