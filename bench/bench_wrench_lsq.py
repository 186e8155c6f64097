"""What ``baseline.least_squares`` adds to a wrench diagnosis (gateway/diagnose/wrench_lsq.py).

The soft PLC's plant (tests/diagnose/test_wrench.py's recordings: closed-form tension
distribution, 0.4 N sensor noise, 250 Hz, 8 cables) with a Coulomb ``f0`` of 1 N and
offsets on three cables, pose and mass kept, no platform tensions; a second seed as the
``--validate`` recording. The same diagnosis run side by side in one process, alternately
without the block (:func:`wrench_lsq.block` replaced by a stub) and with it, CPU time
(user + sys of the process) of each; and the block's own CPU time. Then the block alone
on a long recording (:data:`LONG_S` at 250 Hz: the diagnosis' rows thinned to
``wrench.FIT_BUDGET``, the scores over every sample) in its worst case: the nominal model
as the catalogue, which loses, so each term is also dropped and refitted. Run by name
only (minutes): ``python -m bench wrench_lsq``.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from gateway.diagnose import wrench, wrench_lsq, wrench_report
from gateway.diagnose.engine import diagnose
from gateway.diagnose.wrench_reference import WrenchReference
from sim_plc.plant import make_recording
from tests.diagnose.test_wrench import plant_config

SECONDS = 20.0
LONG_S = 600.0
REPEATS = 2
EFFECTS = {
    "coulomb": {"f0_n": 1.0},
    "offset": {"c_n": [1.5, 0.0, 0.0, -1.2, 0.0, 1.0, 0.0, 0.0]},
}


def run() -> None:
    cfg = plant_config(EFFECTS)
    rec = replace(make_recording(cfg, None, SECONDS), tension_platform=None, source="b.csv")
    vcfg = plant_config(EFFECTS, seed=4)
    val = replace(make_recording(vcfg, None, SECONDS), tension_platform=None, source="v.csv")
    real = wrench_lsq.block
    spent: list[float] = []

    def timed(*args, **kwargs):
        t0 = time.process_time()
        out = real(*args, **kwargs)
        spent.append(time.process_time() - t0)
        return out

    def stub(*args, **kwargs):
        return {}

    cpu: dict[str, list[float]] = {"without": [], "with": []}
    for _ in range(REPEATS):
        for name, fn in (("without", stub), ("with", timed)):
            wrench_report.wrench_lsq.block = fn  # type: ignore[attr-defined]
            t0 = time.process_time()
            diagnose(rec, cfg.friction, WrenchReference(cfg), validation=val)
            cpu[name].append(time.process_time() - t0)
    wrench_report.wrench_lsq.block = real  # type: ignore[attr-defined]
    print(f"   {rec.samples} samples x 8 cables, validation {val.samples} samples")
    for name, xs in cpu.items():
        print(f"   diagnosis {name:7s} the block: CPU " + ", ".join(f"{x:.1f}" for x in xs) + " s")
    print("   the block alone: CPU " + ", ".join(f"{x:.3f}" for x in spent) + " s")
    long_block(cfg, vcfg)


def long_block(cfg, vcfg) -> None:
    """The block alone on :data:`LONG_S` s, validation of the same length (docstring)."""
    rec = replace(make_recording(cfg, None, LONG_S), tension_platform=None, source="l.csv")
    val = replace(make_recording(vcfg, None, LONG_S), tension_platform=None, source="lv.csv")
    prep = wrench.prepare(rec, cfg, cfg.friction)
    vmodel = wrench.WrenchModel(wrench.wrench_data(val, cfg), prep.model.nom)
    train = (prep.blocks[prep.rows] % 2 == 0) & prep.warm[prep.rows]
    test = (prep.blocks % 2 == 1) & prep.warm
    r0 = prep.whiten(prep.model.residual({}, rows=prep.rows))
    force = np.ascontiguousarray(prep.model.residual({})[:, :3])
    vnominal = float(np.sqrt(np.mean(vmodel.residual({})[:, :3] ** 2)))
    t0 = time.process_time()
    out = wrench_lsq.block(prep, r0, train, test, force, force, (vmodel, vnominal))
    spent = time.process_time() - t0
    print(
        f"   long: {rec.samples} samples ({prep.rows.size} rows), the block alone with its "
        f"terms dropped ({len(out.get('terms', []))}): CPU {spent:.2f} s"
    )
    print(f"   {out['sentence']}")
