"""The diagnosis: nominal simulation, residual, location, selection per cable, scores.

``diagnose(rec, friction)`` returns a :class:`Diagnosis` whose ``report`` is the JSON
report of recording.md. Each cable is selected on its own (effects act per cable), then
the effects are gathered into findings over the cables that kept them, ordered by how
much held-out residual energy they explain together (drop-one from the final model).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gateway.config import FrictionConfig
from gateway.diagnose import locate
from gateway.diagnose.forward import ALL_EFFECTS, CableData, Forward, Nominal
from gateway.diagnose.select import CableOutcome, CableSelector, Thresholds
from gateway.errors import RecordingError
from gateway.recording import Recording

Progress = Callable[[str], None]


def nominal_from(friction: FrictionConfig) -> Nominal:
    """The per-cable nominal chain of a friction config."""
    return Nominal(
        model=friction.model, wrap_rad=np.asarray(friction.wrap_rad, dtype=float),
        mu=np.asarray(friction.mu, dtype=float), sigma_n_m=friction.sigma_n_m,
        beta=friction.beta, viscous_ns_m=friction.viscous_ns_m,
        pulley_radius_m=friction.pulley_radius_m,
    )  # fmt: skip


def cable_data(rec: Recording, tp: np.ndarray, dtp_dm: np.ndarray | None) -> list[CableData]:
    """One :class:`CableData` per cable; ``tp``, ``dtp_dm``: (N, m)."""
    t0 = float(rec.t[0])
    return [
        CableData(rec.t, rec.velocity[:, i].copy(), tp[:, i].copy(),
                  rec.tension_sensor[:, i].copy(), t0,
                  None if dtp_dm is None else dtp_dm[:, i].copy())  # fmt: skip
        for i in range(rec.cables)
    ]


def time_blocks(t: np.ndarray) -> tuple[np.ndarray, int]:
    """Block index (N,) of interleaved time blocks; even blocks train, odd ones are held out.

    About one block per second of recording, between 10 and 40 blocks (an even number).
    """
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    nb = int(np.clip(round(span / 1.0), 10, 40))
    nb += nb % 2
    edges = t[0] + span * np.arange(1, nb) / nb
    return np.searchsorted(edges, t, side="right").astype(np.int64), nb


@dataclass
class Diagnosis:
    """Everything the report and the pictures are made of."""

    report: dict
    t: np.ndarray
    measured: np.ndarray
    nominal_pred: np.ndarray
    final_pred: np.ndarray
    regime: np.ndarray
    regions: list[locate.Region]
    outcomes: list[CableOutcome]
    findings_order: list[str]
    forwards: list[Forward] = field(default_factory=list)


def _rmse(res: np.ndarray, mask: np.ndarray | None = None) -> float:
    r = res if mask is None else res[mask]
    return float(math.sqrt(np.mean(r**2))) if r.size else 0.0


def candidates_for(has_mass: bool) -> list[str]:
    """Effects the recording's columns allow (mass_change needs pose and mass)."""
    return [e for e in ALL_EFFECTS if has_mass or e != "mass_change"]


def diagnose(
    rec: Recording,
    friction: FrictionConfig,
    tp: np.ndarray | None = None,
    dtp_dm: np.ndarray | None = None,
    validation: tuple[Recording, np.ndarray, np.ndarray | None] | None = None,
    thresholds: Thresholds | None = None,
    progress: Progress | None = None,
) -> Diagnosis:
    """Diagnose ``rec`` against the nominal ``friction`` model (see the module docstring).

    ``tp`` (N, m): platform tensions (default: the recording's); ``dtp_dm`` (N, m) N/kg:
    platform tension per kg of platform mass (enables ``mass_change``); ``validation``:
    a second recording of the same machine, its platform tensions and dtp_dm.
    """
    say = progress or (lambda _msg: None)
    th = thresholds or Thresholds()
    tp = rec.tension_platform if tp is None else tp
    if tp is None:
        raise RecordingError(f"{rec.source}: no platform tensions")
    nom = nominal_from(friction)
    datas = cable_data(rec, tp, dtp_dm)
    blocks, nb = time_blocks(rec.t)
    cands = candidates_for(dtp_dm is not None)
    stride = max(1, rec.samples // 200_000)
    outcomes, forwards = [], []
    for i, d in enumerate(datas):
        fw = Forward(d, nom)
        say(f"cable {i + 1}/{rec.cables}: selecting among {len(cands)} candidate effects")
        outcome = CableSelector(fw, blocks, nb, cands, th, stride=stride).run()
        say(f"cable {i + 1}/{rec.cables}: kept {', '.join(outcome.kept) or 'nothing'}"
            f" ({fw.simulations} chain simulations)")  # fmt: skip
        outcomes.append(outcome)
        forwards.append(fw)
    from gateway.diagnose.report import build_report  # local: report imports engine types

    return build_report(rec, forwards, outcomes, blocks, validation, nom)
