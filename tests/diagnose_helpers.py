"""Shared helpers of the diagnosis tests: schema check, scenario files on disk, and an
independent generator of "foreign" recordings (:class:`Foreign`, :func:`generate`,
:func:`write_csv`, :func:`model_yaml`).

The foreign generator is written without :mod:`evaluation.scenarios` or :mod:`gateway.model`:
one cable's pulley chain (Coulomb or Dahl, any number of pulleys, wrap angles and mu, normal
force by the law of cosines from the previous step's tensions) integrated by explicit
Euler on a fine time grid, path and sensor effects applied on that grid, then resampled at
the recording's (possibly uneven) times, with non-white noise (coloured, spikes, 50 Hz hum,
0.1 N quantisation), and written as CSV with the quirks docs/recording-format.md allows.
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import jsonschema
import numpy as np
from numba import njit

from evaluation.scenarios import Scenario, make_recording
from gateway.recordings.reader import write_recording

MODEL_YAML = """friction:
  model: {model}
  pulleys:
    - {{wrap_deg: 90.0, mu: 0.015}}
    - {{wrap_deg: 60.0, mu: 0.015}}
    - {{wrap_deg: 30.0, mu: 0.015}}
  sigma_n_m: 500.0
"""


SCHEMA_PATH = Path(__file__).resolve().parent.parent / "docs" / "diagnose-report.schema.json"


def schema() -> dict:
    """The report's JSON schema: the repository's docs/diagnose-report.schema.json (a copy
    of the spec's), or the embedded copy below when docs/ has none."""
    if SCHEMA_PATH.is_file():
        return json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
    return json.loads(SCHEMA)


def check_report(report: dict) -> None:
    """Raise if ``report`` does not follow the schema; also checks per-cable list lengths."""
    jsonschema.validate(report, schema())
    for f in report["findings"]:
        for name, values in f["parameters"].items():
            assert len(values) == len(f["cables"]), (f["effect"], name)


def write_scenario(tmp: Path, sc: Scenario, name: str = "rec.csv") -> tuple[Path, Path]:
    """Write the scenario's recording and its nominal model file; return both paths."""
    rec_path = tmp / name
    write_recording(rec_path, make_recording(sc))
    model = tmp / "model.yaml"
    model.write_text(MODEL_YAML.format(model=sc.nominal_model), encoding="utf-8")
    return rec_path, model


# ---- foreign recordings: an independent generator ----


@dataclass(frozen=True)
class Foreign:
    """A foreign machine and recording. Effects: ids and parameters of docs/recording-format.md."""

    seconds: float = 30.0
    rate_hz: float = 250.0
    fine_hz: float = 5000.0
    jitter: float = 0.0  # relative std of the sample period
    gaps: int = 0  # number of dropped stretches of rows
    cables: int = 1
    pulleys: tuple[tuple[float, float], ...] = ((120.0, 0.02), (45.0, 0.02))  # (wrap deg, mu)
    model: str = "dahl"  # truth chain: coulomb | dahl
    sigma_n_m: float = 800.0
    tension: float = 300.0  # mean platform tension (N); rig: amplitude around zero
    rig: bool = False
    motion: str = "moves"  # moves | slow | constant
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    noise: str = "white"  # white | coloured | wander | spikes | quant | hum | mixed
    noise_n: float = 0.3
    seed: int = 3
    t0: float = 0.5  # time of the first row (s); e.g. a Unix time stamp
    vel_noise: float = 0.0  # std of noise on the velocity column (a measured velocity)
    long_gap_s: float = 0.0  # one stretch of this many seconds without rows, mid-recording
    blanks: int = 0  # rows with an empty tension_sensor field
    jitter_s: float = 0.0  # uniform +-jitter_s on every time stamp (a logger's clock)
    clip_n: float = 0.0  # sensor range: readings clipped to +-clip_n (0: no clipping)
    clip_cables: tuple[int, ...] = ()  # cables (1-based) whose sensor clips; () = all
    vmax: float = 0.25  # largest move speed (m/s) of "moves" / "positioning"


@njit(cache=True)
def _chain(tp, v, dt, wrap, mu, f0, sigma, dahl, sk=0.0, svs=0.01, mu1=0.0):  # pragma: no cover
    """:func:`_chain_directional` with the same coefficients in both directions."""
    return _chain_directional(tp, v, dt, wrap, mu, mu, f0, sigma, dahl, sk, svs, mu1)


@njit(cache=True)
def _chain_directional(  # pragma: no cover
    tp, v, dt, wrap, mu, mu_in, f0, sigma, dahl, sk, svs, mu1
):
    """Sensor tension (N,) from platform tension and velocity; explicit Euler on x.

    ``mu`` are the pulleys' coefficients paying out (``v > 0``) and at rest, ``mu_in``
    hauling in (``v < 0``): ``coulomb_directional`` (docs/physics.md sec. 4: the level the
    friction, or the Dahl state, tends to depends on the direction of travel).

    Dahl: ``dF/dx = sigma (1 - F / F_R sgn(v))`` (beta = 1) exactly as written, without a
    clamp of ``|F|`` to ``F_R`` (a clamp is not Dahl: it snapped the state to a falling
    level at once, even at standstill, and the model rightly does not).

    Normal force from the law of cosines with the pulley's sensor-side tension of the
    previous step (explicit), friction level ``(mu F_N + f0 / p) (1 + sk exp(-(v/svs)^2))``
    per pulley (the load-independent ``f0`` is the cable's, shared by its ``p`` pulleys;
    its own tension drop raises ``F_N`` a little, which the model's ``lambda T + f0``
    leaves out: ~1 % of ``f0``, docs/physics.md);
    without pulleys ``f0`` acts alone: ``- sgn(v) f0`` (a rig's seals and guides).

    ``mu1``: each pulley's coefficient grows with the load it carries, ``mu + mu1 |T|``
    (``coulomb_load``, docs/physics.md sec. 4; ``T`` the pulley's platform-side tension),
    that coefficient times the normal force as it stands, not the model's first order in
    ``mu`` (so the two differ by O(mu), a few per cent of the growth)."""
    n, p = tp.size, wrap.size
    out = np.empty(n)
    if p == 0:
        for k in range(n):
            s = 1.0 if v[k] > 0 else (-1.0 if v[k] < 0 else 0.0)
            out[k] = tp[k] - s * f0 * (1.0 + sk * math.exp(-((v[k] / svs) ** 2)))
        return out
    f0 = f0 / p
    f = np.zeros(p)
    prev = np.full(p, tp[0])
    for k in range(n):
        tj = tp[k]
        s = 1.0 if v[k] > 0 else (-1.0 if v[k] < 0 else 0.0)
        dx = v[k] * dt
        for j in range(p - 1, -1, -1):
            tb = prev[j]
            fn = math.sqrt(max(tb * tb - 2.0 * tb * tj * math.cos(wrap[j]) + tj * tj, 0.0))
            mu_j = (mu_in[j] if s < 0 else mu[j]) + mu1 * abs(tj)
            fr = (mu_j * fn + f0) * (1.0 + sk * math.exp(-((v[k] / svs) ** 2)))
            if dahl:
                if fr > 0:
                    # eq. 14 as it stands: no clamp |F| <= F_R (a falling level is
                    # approached over travel, and nothing moves while dx = 0); Euler
                    # sub-steps keep sigma |dx| / F_R <= 0.05 per sub-step
                    sub = max(1, math.ceil(sigma * abs(dx) / fr / 0.05))
                    for _ in range(sub):
                        f[j] += sigma * (1.0 - f[j] / fr * s) * dx / sub
                else:
                    f[j] = 0.0
            else:
                f[j] = s * fr
            tj = tj - f[j]
            prev[j] = tj
        out[k] = tj
    return out


DRIVE_EFFECTS = ("maxwell_slip", "cable_stretch", "backlash")
"""Effects the foreign generator runs through :func:`_chain_drive` (docs/physics.md sec. 3)."""


@njit(cache=True)
def _chain_drive(  # pragma: no cover
    tp, v, dt, wrap, mu, f0, sigma, w1, k_inv, width, sk, svs, mu1
):
    """Sensor tension (N,) of a presliding chain whose state may have two elements
    (Maxwell-slip), a stretching cable and a dead zone in its drive, written from
    docs/physics.md sec. 3 and 4 (not from :mod:`gateway.model`), explicit Euler like
    :func:`_chain`:

    * each pulley carries two elements, ``dF_q/dx = w_q sigma_q (1 - F_q / (w_q F_R) s)``
      with ``w = (w1, 1 - w1)``, ``sigma = (sigma, sigma / 10)`` (``w1 = 1``: Dahl);
    * the drive of a (sub-)step of setpoint travel ``dx`` is ``d' = dx - dF / k`` with
      ``dF = S d`` the Euler change of the pulleys' friction ``F = sum_j F_j``
      (``S = sum_j sum_q w_q sigma_q (1 - F_q / (w_q F_R) s)``), so ``d' = dx / (1 + S / k)``;
    * through the play operator of width ``b``: the gap ``g`` (0 at the start) moves by the
      travel while ``|g + dx| <= b / 2`` and the drive stands; beyond, the drive is
      ``(g + dx - b/2) / (1 + S / k)`` (or ``+ b/2``) and ``g`` sits at the edge.

    Levels ``((mu + mu1 |T|) F_N + f0 / p) (1 + sk exp(-(v/svs)^2))`` (as :func:`_chain`'s)
    from the law of cosines on the
    previous step's sensor-side tension of each pulley and its platform side this step
    (the friction of the pulleys nearer the platform from the previous step)."""
    n, p = tp.size, wrap.size
    out = np.empty(n)
    f0 = f0 / p
    ws = np.array([w1, 1.0 - w1])
    sig = np.array([sigma, sigma / 10.0])
    f = np.zeros((p, 2))
    prev = np.full(p, tp[0])
    fr = np.zeros(p)
    gap = 0.0
    half = 0.5 * width
    for k in range(n):
        strib = 1.0 + sk * math.exp(-((v[k] / svs) ** 2))
        tj = tp[k]
        for j in range(p - 1, -1, -1):  # levels, platform to sensor
            tb = prev[j]
            fn = math.sqrt(max(tb * tb - 2.0 * tb * tj * math.cos(wrap[j]) + tj * tj, 0.0))
            fr[j] = ((mu[j] + mu1 * abs(tj)) * fn + f0) * strib
            tj = tj - (f[j, 0] + f[j, 1])
        dx = v[k] * dt
        big = 0.0
        for j in range(p):
            if fr[j] > 0:
                big = max(big, sigma * abs(dx) / fr[j])
        sub = max(1, math.ceil(big / 0.05))
        for _ in range(sub):
            step = dx / sub
            if abs(gap + step) <= half:
                gap += step
                continue
            edge = half if gap + step > 0 else -half
            raw = gap + step - edge
            gap = edge
            s = 1.0 if raw > 0 else -1.0
            slope = 0.0
            for j in range(p):
                if fr[j] > 0:
                    for q in range(2):
                        if ws[q] > 0:
                            slope += ws[q] * sig[q] * (1.0 - f[j, q] / (ws[q] * fr[j]) * s)
            d = raw / (1.0 + slope * k_inv)
            for j in range(p):
                for q in range(2):
                    if fr[j] > 0 and ws[q] > 0:
                        f[j, q] += ws[q] * sig[q] * (1.0 - f[j, q] / (ws[q] * fr[j]) * s) * d
                    else:
                        f[j, q] = 0.0
        tj = tp[k]
        for j in range(p - 1, -1, -1):
            tj = tj - (f[j, 0] + f[j, 1])
            prev[j] = tj
        out[k] = tj
    return out


def _drive_chain(fo: Foreign, tn, v, wrap, mu, f0, sigma, st) -> np.ndarray:
    """The chain of :func:`_chain_drive` with ``fo``'s Maxwell-slip, stretch and backlash."""
    e = fo.effects
    slip = e.get("maxwell_slip", {})
    k = e.get("cable_stretch", {}).get("k_n_m", math.inf)
    return _chain_drive(
        tn,
        v,
        1.0 / fo.fine_hz,
        wrap,
        mu,
        f0,
        slip.get("sigma_n_m", sigma),
        slip.get("w", 1.0),
        1.0 / k,
        e.get("backlash", {}).get("width_m", 0.0),
        st["k"],
        st["v_s_m_s"],
        fo.effects.get("coulomb_load", {}).get("mu1_per_n", 0.0),
    )


def _spring_and_creep(fo: Foreign, t, x, ts) -> np.ndarray:
    """docs/physics.md sec. 4: ``spring`` (path) ``+ k (x - l0)`` with ``x`` the travel since
    the first sample (a foreign recording has no lengths), then ``sensor_creep`` (the first
    sensor effect) ``(1 - c) T + c 1/(tau s + 1) T`` with the generator's own filter."""
    e = fo.effects
    if "spring" in e:
        ts = ts + e["spring"]["k_n_m"] * (x - e["spring"].get("l0_m", 0.0))
    if "sensor_creep" in e:
        c, tau = e["sensor_creep"]["c"], e["sensor_creep"].get("tau_s", 1.0)
        ts = (1.0 - c) * ts + c * _lowpass_fast(t, ts, tau)
    return ts


def _motion(fo: Foreign, t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Fine-grid velocity (m/s) and platform tension (N) for one cable."""
    n = t.size
    if fo.motion == "positioning":  # constant-speed moves, short ramps, many reversals
        v = np.zeros(n)
        k, dt, sign = 0, t[1] - t[0], 1.0
        while k < n:
            dur = rng.uniform(0.6, 2.0)
            vmax = rng.choice([0.35, 1.0, 1.0, 1.0]) * fo.vmax * sign  # few speed levels
            sign = -sign if rng.uniform() < 0.8 else sign
            m = int(dur / dt)
            tt = np.arange(m) * dt
            ramp = np.clip(np.minimum(tt, dur - tt) / 0.1, 0, 1)  # jerk-limited: smoothstep
            v[k : k + m] = (ramp * ramp * (3 - 2 * ramp) * vmax)[: n - k]
            k += m + int(rng.uniform(0.0, 0.3) / dt)
    elif fo.motion == "constant":
        v = 0.05 + 0.002 * np.sin(2 * math.pi * 0.05 * t)
    elif fo.motion == "slow":
        v = 0.04 * np.sin(2 * math.pi * t / max(fo.seconds, 1.0) + 0.3)
    else:  # point-to-point moves: trapezoid profiles between random waypoints, pauses
        v = np.zeros(n)
        k, dt = 0, t[1] - t[0]
        while k < n:
            dur = rng.uniform(0.8, 3.0)
            vmax = rng.uniform(0.12, 1.0) * fo.vmax * rng.choice([-1, 1])
            ramp = rng.uniform(0.05, 0.3)
            m = int(dur / dt)
            tt = np.arange(m) * dt
            prof = np.clip(np.minimum(tt, dur - tt) / ramp, 0, 1) * vmax
            v[k : k + m] = prof[: n - k]
            k += m + int(rng.uniform(0.0, 0.6) / dt)
    x = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))))
    if fo.rig:
        tp = fo.tension * (np.sin(2 * math.pi * 0.09 * t + 1) + 0.3 * np.sin(2 * math.pi * 0.6 * t))
    else:
        tp = fo.tension * (1 + 0.3 * np.sin(2 * math.pi * 0.05 * t) + 0.4 * np.tanh(3 * x))
        steps = np.sort(rng.uniform(t[0], t[-1], int(fo.seconds / 4) + 1))
        for when in steps:
            tp = tp + 0.08 * fo.tension * rng.choice([-1, 1]) * np.clip((t - when) / 0.03, 0, 1)
    return v, tp, x


def _effects(fo: Foreign, t, v, x, ts) -> np.ndarray:
    e = fo.effects
    a = np.gradient(v, t)
    if "inertia" in e:
        ts = ts - e["inertia"]["m_eff_kg"] * a
    if "eccentricity" in e:
        p = e["eccentricity"]
        ts = ts + p["a_n"] * np.sin(x / p["r_m"] + p.get("phi_rad", 0.0))
    ts = _spring_and_creep(fo, t, x, ts)
    if "gain" in e:
        ts = ts * (1 + e["gain"]["g"])
    if "offset" in e:
        ts = ts + e["offset"]["c_n"]
    if "drift" in e:
        ts = ts + e["drift"]["k_n_s"] * (t - t[0])
    if "lowpass" in e:
        ts = _lowpass_fast(t, ts, e["lowpass"]["tau_s"])
    if "delay" in e:
        ts = np.interp(t - e["delay"]["d_s"], t, ts)
    return ts


@njit(cache=True)
def _lowpass_fast(t, y, tau):  # pragma: no cover - numba
    out = np.empty_like(y)
    out[0] = y[0]
    for k in range(1, y.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau)
        out[k] = a * out[k - 1] + (1 - a) * y[k]
    return out


def _noise(fo: Foreign, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    n, s = t.size, fo.noise_n
    kinds = {"coloured", "spikes", "hum", "white"} if fo.noise == "mixed" else {fo.noise}
    out = np.zeros(n)
    if "white" in kinds or "spikes" in kinds or "quant" in kinds or "hum" in kinds:
        out += rng.normal(0, s, n)
    for kind, tau in (("coloured", 0.05), ("wander", 3.0)):
        if kind in kinds:
            col = _lowpass_fast(t, rng.normal(0, 1, n), tau)
            out += s * col / col.std()
    if "hum" in kinds:
        out += 1.5 * s * np.sin(2 * math.pi * 50.0 * t + 0.4)
    if "spikes" in kinds:
        idx = rng.choice(n, max(3, n // 2000), replace=False)
        out[idx] += rng.choice([-1, 1], idx.size) * rng.uniform(20, 60, idx.size) * s
    return out


def sample_times(fo: Foreign, rng: np.random.Generator) -> np.ndarray:
    """Recording times (s): the rate, with jitter and gaps (dropped stretches)."""
    n = int(fo.seconds * fo.rate_hz)
    dt = np.full(n, 1.0 / fo.rate_hz)
    if fo.jitter:
        dt = dt * np.clip(1 + fo.jitter * rng.normal(0, 1, n), 0.2, 3)
    t = np.concatenate(([0.0], np.cumsum(dt[1:]))) + 0.5
    if fo.jitter_s:
        t = t + rng.uniform(-fo.jitter_s, fo.jitter_s, t.size)
        t = t[np.concatenate(([True], np.diff(t) > 0))]
    t = t[t < fo.seconds]
    keep = np.ones(t.size, bool)
    if fo.long_gap_s:
        mid = 0.5 * fo.seconds
        keep &= (t < mid) | (t > mid + fo.long_gap_s)
    for _ in range(fo.gaps):
        lo = rng.integers(0, t.size)
        keep[lo : lo + rng.integers(5, max(6, t.size // 50))] = False
    return t[keep]


def generate(fo: Foreign) -> dict[str, np.ndarray]:
    """Columns of the recording: ``t``, and per cable velocity/tension_sensor/platform."""
    rng = np.random.default_rng(fo.seed)
    fine = np.arange(0.0, fo.seconds + 0.1, 1.0 / fo.fine_hz)
    ts_out = sample_times(fo, rng)
    cols: dict[str, np.ndarray] = {"t": ts_out - 0.5 + fo.t0}
    wrap = np.radians([p[0] for p in fo.pulleys])
    mu = np.array([p[1] for p in fo.pulleys])
    f0 = fo.effects.get("coulomb", {}).get("f0_n", 0.0)
    if "coulomb" in fo.effects and "mu" in fo.effects["coulomb"]:
        mu = mu * fo.effects["coulomb"]["mu"] / mu.mean()
    mu_in = mu
    directional = fo.effects.get("coulomb_directional", {})
    if directional:  # absolute per direction, every pulley alike (as coulomb.mu)
        if any(n in fo.effects for n in DRIVE_EFFECTS):
            raise ValueError("coulomb_directional with a drive effect: not generated")
        f0 = directional.get("f0_n", f0)
        mu, mu_in = (
            mu * directional.get(name, mu.mean()) / mu.mean() for name in ("mu_out", "mu_in")
        )
    mu1 = fo.effects.get("coulomb_load", {}).get("mu1_per_n", 0.0)
    sigma = fo.effects.get("presliding", {}).get("sigma_n_m", fo.sigma_n_m)
    dahl = fo.model == "dahl" or "presliding" in fo.effects
    for i in range(1, fo.cables + 1):
        v, tp, x = _motion(fo, fine, rng)
        st = fo.effects.get("stribeck", {"k": 0.0, "v_s_m_s": 0.01})
        # viscous bearing friction at the platform end of the path (docs/physics.md: the
        # last pulley's tension is T_p - c v), then the pulleys towards the sensor
        tn = tp - fo.effects.get("viscous", {}).get("c_ns_m", 0.0) * v
        if any(n in fo.effects for n in DRIVE_EFFECTS) and (dahl or "maxwell_slip" in fo.effects):
            ts = _drive_chain(fo, tn, v, wrap, mu, f0, sigma, st)
        else:
            ts = _chain_directional(
                tn,
                v,
                1.0 / fo.fine_hz,
                wrap,
                mu,
                mu_in,
                f0,
                sigma,
                dahl,
                st["k"],
                st["v_s_m_s"],
                mu1,
            )
        ts = _effects(fo, fine, v, x, ts)
        sens = np.interp(ts_out, fine, ts) + _noise(fo, ts_out, rng)
        if fo.noise in ("quant", "mixed"):
            sens = np.round(sens / 0.1) * 0.1
        if fo.clip_n and (not fo.clip_cables or i in fo.clip_cables):
            sens = np.clip(sens, -fo.clip_n, fo.clip_n)
        if fo.blanks:
            sens[rng.choice(sens.size, fo.blanks, replace=False)] = np.nan
        cols[f"velocity_{i}"] = (
            np.interp(ts_out, fine, v) + rng.normal(0, 1, sens.size) * fo.vel_noise
        )
        cols[f"tension_sensor_{i}"] = sens
        cols[f"tension_platform_{i}"] = np.interp(ts_out, fine, tp)
    return cols


def recording_of(cols: dict[str, np.ndarray], source: str = "foreign"):
    """A :class:`gateway.recordings.reader.Recording` of the generated columns."""
    from gateway.recordings.reader import Recording

    m = sum(1 for k in cols if k.startswith("velocity_"))

    def stack(name: str) -> np.ndarray:
        return np.column_stack([cols[f"{name}_{i}"] for i in range(1, m + 1)])

    return Recording(
        t=cols["t"],
        velocity=stack("velocity"),
        tension_sensor=stack("tension_sensor"),
        tension_platform=stack("tension_platform"),
        source=source,
    )


def run_foreign(fo: Foreign, nominal: str | None = None, pulleys=None, validate: bool = False):
    """Diagnose a foreign recording through the Python API; the :class:`Diagnosis`.

    ``nominal``: the nominal model (default: the truth's chain); ``pulleys``: the nominal
    pulleys (default: the truth's); ``validate``: also score a second recording of the same
    machine (seed + 100)."""
    from dataclasses import replace

    from gateway.core.config import FrictionConfig, PulleyConfig
    from gateway.diagnose.engine import diagnose

    fr = FrictionConfig(
        model=nominal or fo.model,  # type: ignore[arg-type]
        pulleys=tuple(
            PulleyConfig(w, mu) for w, mu in (fo.pulleys if pulleys is None else pulleys)
        ),
        sigma_n_m=fo.sigma_n_m,
    )
    validation = None
    if validate:
        vrec = recording_of(generate(replace(fo, seed=fo.seed + 100)), "validation")
        validation = (vrec, vrec.tension_platform, None)
    diag = diagnose(recording_of(generate(fo)), fr, validation=validation)
    check_report(diag.report)
    return diag


def model_yaml(pulleys, model: str = "dahl", sigma: float = 800.0, radius: float = 0.05) -> str:
    """A nominal model file for ``pulleys`` ((wrap deg, mu), ...)."""
    rows = "".join(f"    - {{wrap_deg: {w}, mu: {m}}}\n" for w, m in pulleys)
    return (
        f"# nominal model of a foreign machine\nfriction:\n  model: {model}\n  pulleys:\n{rows}"
        f"  sigma_n_m: {sigma}\n  pulley_radius_m: {radius}\n"
    )


def write_csv(path: Path, cols: dict[str, np.ndarray], quirks: bool = False) -> Path:
    """Write ``cols``; with ``quirks``: metadata, shuffled columns, an extra unknown column,
    CRLF endings, scientific notation (gzip if ``path`` ends in .gz)."""
    names = list(cols)
    rng = np.random.default_rng(0)
    fmt = "{:.15g}"
    lines = []
    if quirks:
        names = [names[k] for k in rng.permutation(len(names))]
        names.insert(1, "temperature_c")
        cols = {**cols, "temperature_c": 21.5 + 0 * cols["t"]}
        fmt = "{:.14e}"
        lines += ["# source: someone else's logger", "# operator: x: y", "# units: SI"]
    lines.append(",".join(names))
    data = np.column_stack([cols[n] for n in names])
    lines += [",".join("" if v != v else fmt.format(v) for v in row) for row in data]
    nl = "\r\n" if quirks else "\n"
    text = nl.join(lines) + nl
    if path.suffix == ".gz":
        with gzip.open(path, "wt", encoding="utf-8", newline="") as fh:
            fh.write(text)
    else:
        path.write_text(text, encoding="utf-8", newline="")
    return path


SCHEMA = r"""
{
 "$schema": "https://json-schema.org/draft/2020-12/schema",
 "title": "cdpr-gateway diagnose report",
 "description": "The JSON written by `cdpr-gateway diagnose --json`; see docs/recording-format.md.",
 "type": "object",
 "required": [
  "cables",
  "samples",
  "baseline",
  "mismatch",
  "findings",
  "final"
 ],
 "properties": {
  "cables": {
   "type": "integer",
   "minimum": 1
  },
  "samples": {
   "type": "integer",
   "minimum": 1
  },
  "baseline": {
   "type": "object",
   "required": [
    "rmse_n",
    "per_cable_rmse_n"
   ],
   "properties": {
    "rmse_n": {
     "type": "number",
     "minimum": 0
    },
    "per_cable_rmse_n": {
     "type": "array",
     "items": {
      "type": "number",
      "minimum": 0
     }
    }
   }
  },
  "mismatch": {
   "type": "array",
   "items": {
    "type": "object",
    "required": [
     "cable",
     "start_s",
     "end_s",
     "regime",
     "share"
    ],
    "properties": {
     "cable": {
      "type": "integer",
      "minimum": 1
     },
     "start_s": {
      "type": "number"
     },
     "end_s": {
      "type": "number"
     },
     "regime": {
      "type": "string"
     },
     "share": {
      "type": "number",
      "minimum": 0,
      "maximum": 1
     }
    }
   }
  },
  "findings": {
   "type": "array",
   "items": {
    "type": "object",
    "required": [
     "effect",
     "cables",
     "parameters",
     "evidence",
     "rmse_before_n",
     "rmse_after_n",
     "holdout_rmse_before_n",
     "holdout_rmse_after_n"
    ],
    "properties": {
     "effect": {
      "enum": [
       "coulomb",
       "presliding",
       "viscous",
       "stribeck",
       "inertia",
       "delay",
       "lowpass",
       "gain",
       "offset",
       "drift",
       "eccentricity",
       "mass_change"
      ]
     },
     "cables": {
      "type": "array",
      "items": {
       "type": "integer",
       "minimum": 1
      }
     },
     "parameters": {
      "type": "object",
      "additionalProperties": {
       "type": "array",
       "items": {
        "type": "number"
       }
      }
     },
     "stderr": {
      "type": "object",
      "additionalProperties": {
       "type": "array",
       "items": {
        "type": "number"
       }
      }
     },
     "evidence": {
      "type": "string",
      "minLength": 1
     },
     "rmse_before_n": {
      "type": "number"
     },
     "rmse_after_n": {
      "type": "number"
     },
     "holdout_rmse_before_n": {
      "type": "number"
     },
     "holdout_rmse_after_n": {
      "type": "number"
     },
     "validation_rmse_before_n": {
      "type": "number"
     },
     "validation_rmse_after_n": {
      "type": "number"
     }
    }
   }
  },
  "final": {
   "type": "object",
   "required": [
    "rmse_n",
    "holdout_rmse_n"
   ],
   "properties": {
    "rmse_n": {
     "type": "number"
    },
    "holdout_rmse_n": {
     "type": "number"
    },
    "validation_rmse_before_n": {
     "type": "number"
    },
    "validation_rmse_after_n": {
     "type": "number"
    }
   }
  }
 }
}
"""


def wrench_recordings(tmp: Path, config: Path, seconds: float, seeds: list[int]) -> list[Path]:
    """Recordings of the soft PLC's plant as a real robot has them (``record --seed K``;
    no platform tensions, thinned to 100 Hz): the wrench reference's input, small."""
    import dataclasses

    from gateway.cli import main
    from gateway.recordings.reader import read_recording

    out = []
    for seed in seeds:
        raw = tmp / f"raw-{seed}.parquet"
        argv = ["record", "--config", str(config), "--seconds", str(seconds), "--out", str(raw)]
        assert main([*argv, "--quiet", "--seed", str(seed)]) == 0
        rec = read_recording(raw)
        k = np.arange(0, rec.samples, 10)

        def rows(a: np.ndarray | None, k: np.ndarray = k) -> np.ndarray | None:
            return None if a is None else a[k]

        thin = dataclasses.replace(
            rec,
            t=rec.t[k],
            velocity=rec.velocity[k],
            tension_sensor=rec.tension_sensor[k],
            tension_platform=None,  # what a real robot has
            length=rows(rec.length),
            pose=rows(rec.pose),
            mass=rows(rec.mass),
            extra={n: v[k] for n, v in rec.extra.items()},
        )
        path = tmp / f"run-{seed}.csv"
        write_recording(path, thin)
        raw.unlink()
        out.append(path)
    return out
