"""The start-up transient of a recording, said in the report (``diagnose``, ``calibrate``).

A recording that starts in mid-motion (``run --record``: the gateway joins a machine
that is already moving) holds pulleys whose friction state is developed, while the
diagnosis' chain starts relaxed: until the cables have travelled a few relaxation lengths
(:func:`gateway.diagnose.prepare.warmup_mask`), the residual is the diagnosis' own
warm-up, not physics. The selection and the fit already leave those samples out (and
the held-out scores with them); :func:`annotate` says so in the report: ``warmup``
(``until_s`` on the recording's clock, its length ``seconds``, ``samples``, how it was
treated) and the mismatch regions that lie inside
the warm-up moved from ``mismatch`` to ``warmup.regions``, so that no region is listed as a
mismatch that is only the start. ``baseline.rmse_n`` and ``final.rmse_n`` still cover
every sample (that is why ``final.rmse_n`` may exceed ``final.holdout_rmse_n``).

The recording itself is not cut: the gateway cannot know when the diagnosis' chain will
have forgotten its start (the diagnosis' model, not the gateway's, decides), and a cut
recording would start cold all the same.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gateway.core.config import FrictionConfig
from gateway.diagnose.forward import CableData
from gateway.diagnose.prepare import nominal_from, warmup_mask
from gateway.recordings.reader import Recording

TREATMENT = (
    "left out of the selection, the fit and the held-out scores (the chain starts relaxed, "
    "the recorded machine may not); baseline and final rmse_n include it"
)


def warmup_until_s(rec: Recording, friction: FrictionConfig) -> tuple[float, int]:
    """(the recording's time, samples) until every cable's chain has forgotten its start,
    by the rule the selection uses (the slowest cable decides); the time is on the
    recording's own clock, as the report's regions are."""
    nom = nominal_from(friction)
    t = np.asarray(rec.t, dtype=float)
    tension = np.asarray(rec.tension_sensor, dtype=float)
    first_warm = 0
    for i in range(rec.cables):
        d = CableData(
            t,
            np.asarray(rec.velocity[:, i], dtype=float),
            tension[:, i],
            tension[:, i],
            float(t[0]),
        )
        warm = warmup_mask(d, nom)
        cold = np.flatnonzero(~warm[: max(1, warm.size // 2)])  # the start's warm-up
        if cold.size and cold[0] == 0:
            first_warm = max(first_warm, int(cold[-1]) + 1)
    return float(t[min(first_warm, t.size - 1)]), first_warm


def annotate(report: dict[str, Any], rec: Recording, friction: FrictionConfig) -> None:
    """Add ``warmup`` to ``report`` and move warm-up regions out of ``mismatch`` (in place)."""
    until, samples = warmup_until_s(rec, friction)
    regions = report.get("mismatch") or []
    inside = [r for r in regions if samples and r["end_s"] <= until + 1e-9]
    report["mismatch"] = [r for r in regions if r not in inside]
    report["warmup"] = {
        "until_s": until,
        "seconds": until - float(rec.t[0]) if samples else 0.0,
        "samples": samples,
        "treatment": TREATMENT,
        "regions": inside,
    }
