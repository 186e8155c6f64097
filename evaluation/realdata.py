"""Real recordings from public datasets, converted to the project's :class:`Recording`.

The datasets are read where they lie (a directory given by the caller; the project holds
none of them):

* **EMPS** (an electro-mechanical positioning system: a prismatic axis driven by a ball
  screw; nonlinear system identification benchmark, Janot, Gautier and Brunot 2019):
  ``emps/DATA_EMPS.mat`` (fit) and ``emps/DATA_EMPS_PULSES.mat`` (validation), 1 kHz. One
  "cable" without pulleys: the motor force ``gtau * vir`` drives the cart, nothing loads
  it, so ``tension_platform`` is 0 and ``tension_sensor`` is minus the motor force (the
  sensor reads ``T_p - m a - c v - f0 sgn(v) + offset``, docs/physics.md sec. 4, while
  the motor supplies ``m a + c v + f0 sgn(v) + offset_motor``); the velocity is the
  central difference of the motor position ``qm`` (its encoder resolves 0.05 um).
* **da Vinci** (a surgical instrument's cable-and-pulley transmission on a bench, O'Neill
  et al. 2018): ``davinci/<folder>/<trial>.TXT.xz``, 1 kHz, ten columns (the folder's
  README). One cable over a 5 mm capstan: ``tension_sensor`` is the input (back-end)
  torque over the radius, ``tension_platform`` is -0.886 x the output (front-end) torque
  over the radius, the velocity is the radius times the spindle's angular rate (its
  8192-count encoder differentiated by a 21-sample Savitzky-Golay filter: a plain central
  difference of 3.8 um counts swings by 1.9 mm/s at 1 kHz, as large as the motion).
  Trials of one set are joined into one recording with ``JOIN_GAP_S`` between them (the
  diagnosis warms up again after a gap).

:func:`predict` gives a model's sensor reading for a recording (the plant's forms run
with its fitted effects, each trial from a relaxed chain), :func:`rmse` scores it after a
warm-up per trial: the one metric for the diagnosis' fitted model and the baseline
(:mod:`evaluation.baseline`).
"""

from __future__ import annotations

import io
import itertools
import lzma
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gateway.core.config import FrictionConfig, PulleyConfig
from gateway.diagnose.prepare import nominal_from
from gateway.errors import RecordingError
from gateway.model import effects as fx
from gateway.model.chain_runs import run
from gateway.recordings.reader import Recording

EMPS_FIT = "emps/DATA_EMPS.mat"
EMPS_VALIDATION = "emps/DATA_EMPS_PULSES.mat"
EMPS_PUBLISHED = {"m_eff_kg": 95.11, "c_ns_m": 203.5, "f0_n": 20.39, "offset_n": -3.16}
"""The benchmark's published identification (inertia, viscous, Coulomb, motor offset)."""
EMPS_TARGETS = {"m_eff_kg": 0.05, "c_ns_m": 0.10, "f0_n": 0.10}  # relative

DAVINCI_RADIUS_M = 0.005
DAVINCI_OUTPUT_RATIO = -0.886
DAVINCI_NM_PER_COUNT = 0.000039811
DAVINCI_COUNTS_PER_REV = 8192
DAVINCI_SG_WINDOW = 21
L4, L2 = "Tool_4_Maryland_L_4", "Tool_4_Maryland_L_2"
DAVINCI_FIT = (L4, ("01", "04", "07", "21", "24", "27", "41", "44", "47"))
DAVINCI_VALIDATION = (L4, ("12", "15", "18", "32", "35", "38"))
DAVINCI_OTHER_SERIES = (L2, ("11", "13", "31", "33"))
DAVINCI_CUT_S = {(L4, "07"): 10.0}  # its spindle leaves the trajectory at 17.25 s (README)
DAVINCI_TARGETS_N = {"validation": 1.64, "other_series": 1.44}  # the least-squares baseline
JOIN_GAP_S = 1.0
WARMUP_S = 0.5  # scored after this much of each trial (the friction state's unknown start)

EMPS_MODEL = FrictionConfig(model="none", pulleys=())
"""Blank: no friction law, no pulleys (the diagnosis names everything)."""
DAVINCI_MODEL = FrictionConfig(model="coulomb", pulleys=(PulleyConfig(180.0, 0.0),))
"""Blank: one pulley (the capstan's half turn) without friction, the Coulomb law (a
pre-sliding state is a finding of its own). With the Dahl law and its default stiffness
(500 N/m: a relaxation length as long as the whole 5 mm stroke) the diagnosis found
viscous and lowpass instead (validation 13.84 -> 6.93 N)."""


def _mat(path: Path) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    try:
        return {k: np.asarray(v) for k, v in loadmat(path).items() if not k.startswith("__")}
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from exc


def emps(root: Path, name: str = EMPS_FIT) -> Recording:
    """One EMPS file as a one-cable recording (module docstring)."""
    path = Path(root) / name
    data = _mat(path)
    for key in ("t", "qm", "gtau", "vir"):
        if key not in data:
            raise RecordingError(f"{path}: no field {key!r}")
    t = data["t"].ravel().astype(float)
    force = (data["gtau"] * data["vir"]).ravel().astype(float)
    v = np.gradient(data["qm"].ravel().astype(float), t)
    return Recording(
        t=t,
        velocity=v[:, None],
        tension_sensor=-force[:, None],
        tension_platform=np.zeros((t.size, 1)),
        metadata={"source": f"EMPS {name}", "tension_sensor": "minus the motor force"},
        source=str(path),
    )


def _davinci_columns(path: Path) -> np.ndarray:
    try:
        with lzma.open(path, "rt", encoding="ascii") as fh:
            body = "".join(line for line in fh if not line.startswith("%"))
    except (OSError, lzma.LZMAError) as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from exc
    cols = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2)
    if cols.shape[1] != 10:
        raise RecordingError(f"{path}: expected 10 columns, got {cols.shape[1]}")
    return cols


def davinci_trial(root: Path, folder: str, trial: str) -> Recording:
    """One da Vinci trial as a one-cable recording (module docstring)."""
    from scipy.signal import savgol_filter

    path = Path(root) / "davinci" / folder / f"{trial}.TXT.xz"
    cols = _davinci_columns(path)
    cut = DAVINCI_CUT_S.get((folder, trial))
    if cut is not None:
        cols = cols[cols[:, 0] < cut]
    t = cols[:, 0]
    angle = cols[:, 1] * 2.0 * math.pi / DAVINCI_COUNTS_PER_REV
    dt = float(np.median(np.diff(t)))
    rate = savgol_filter(angle, DAVINCI_SG_WINDOW, 2, deriv=1, delta=dt)
    r = DAVINCI_RADIUS_M
    tin = cols[:, 2] * DAVINCI_NM_PER_COUNT
    tout = cols[:, 5] * DAVINCI_NM_PER_COUNT
    return Recording(
        t=t,
        velocity=(r * rate)[:, None],
        tension_sensor=(tin / r)[:, None],
        tension_platform=(DAVINCI_OUTPUT_RATIO * tout / r)[:, None],
        length=(r * angle)[:, None],  # the spindle position as cable travel (m)
        metadata={"source": f"da Vinci {folder}/{trial}"},
        source=str(path),
    )


def join(recs: list[Recording], source: str) -> Recording:
    """Recordings one after the other, ``JOIN_GAP_S`` apart, as one recording."""
    parts, offset = [], 0.0
    for r in recs:
        parts.append(r.t - r.t[0] + offset)
        offset = parts[-1][-1] + JOIN_GAP_S

    def cat(name: str) -> np.ndarray | None:
        arrays = [getattr(r, name) for r in recs]
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    return Recording(
        t=np.concatenate(parts),
        velocity=cat("velocity"),  # type: ignore[arg-type]
        tension_sensor=cat("tension_sensor"),  # type: ignore[arg-type]
        tension_platform=cat("tension_platform"),
        length=cat("length"),
        metadata={"source": source, "trials": str(len(recs))},
        source=source,
    )


def davinci_set(root: Path, which: tuple[str, tuple[str, ...]]) -> Recording:
    folder, trials = which
    return join([davinci_trial(root, folder, tr) for tr in trials], f"{folder} {'/'.join(trials)}")


def segments(t: np.ndarray) -> list[slice]:
    """The trials of a joined recording (split where the time step exceeds half a gap)."""
    cuts = np.nonzero(np.diff(t) > 0.5 * JOIN_GAP_S)[0] + 1
    edges = [0, *cuts.tolist(), t.size]
    return [slice(a, b) for a, b in itertools.pairwise(edges)]


def predict(rec: Recording, friction: FrictionConfig) -> np.ndarray:
    """The sensor reading (N, m) ``friction`` (with its fitted effects) predicts from the
    recording's platform tensions and velocities: the chain, then the path and sensor
    effects (the plant's batch forms); each trial from a relaxed chain."""
    if rec.tension_platform is None:
        raise RecordingError(f"{rec.source}: no platform tensions")
    m = rec.cables
    values = friction.effect_values(m)
    # the diagnosis' nominal chain: a model without pulleys gets one without wrap, where a
    # fitted load-independent Coulomb level acts (a FrictionConfig's own chain drops it)
    params = fx.chain_params(nominal_from(friction), values, m)
    out = np.empty_like(rec.tension_sensor)
    for seg in segments(rec.t):
        t, v = rec.t[seg], rec.velocity[seg]
        ts = run(params, "simulate", rec.tension_platform[seg], v, t)
        x = rec.length[seg] if rec.length is not None else fx.displacement(t, v)

        def acc(t: np.ndarray = t, v: np.ndarray = v) -> np.ndarray:
            return fx.acceleration(t, v)

        series = fx.SeriesData(t, v, x, acc, float(rec.t[0]))
        out[seg] = fx.forward(series, ts, values)
    return out


def scored(t: np.ndarray) -> np.ndarray:
    """(N,) bool: the samples after ``WARMUP_S`` of each trial."""
    keep = np.zeros(t.size, bool)
    for seg in segments(t):
        keep[seg] = t[seg] >= t[seg][0] + WARMUP_S
    return keep


def rmse(rec: Recording, prediction: np.ndarray) -> float:
    """RMSE (N) of ``prediction`` against the recorded sensor reading, warm-ups left out."""
    keep = scored(rec.t)
    return float(np.sqrt(np.mean((rec.tension_sensor[keep] - prediction[keep]) ** 2)))


@dataclass(frozen=True)
class Sets:
    """The recordings of one machine: fit, validation and (da Vinci) another series."""

    fit: Recording
    validation: Recording
    other: Recording | None = None


def emps_sets(root: Path) -> Sets:
    return Sets(emps(root, EMPS_FIT), emps(root, EMPS_VALIDATION))


def davinci_sets(root: Path) -> Sets:
    return Sets(
        davinci_set(root, DAVINCI_FIT),
        davinci_set(root, DAVINCI_VALIDATION),
        davinci_set(root, DAVINCI_OTHER_SERIES),
    )
