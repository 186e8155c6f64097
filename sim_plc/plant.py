"""The plant: the robot's truth physics from setpoints to the PLC's raw force channels.

One pipeline, written once with :mod:`gateway.model` (run the other way round):

1. trajectory -> pose, pose rates, accelerations; cable lengths and setpoint velocities
   (``kinematics``); the plant follows its setpoints exactly, so setpoint = actual.
2. wrench = gravity with the platform mass ``m(t) = m_0 - q_e t_print`` (the extruder
   takes ``q_e`` kg/s while printing; mass never below 10 % of ``m_0``) + the
   d'Alembert term ``-m a`` (``statics``); platform tensions by the tension
   distribution (eq. 18, 19) with the plant's limits, or the controller's own
   (``sim_plc.distribution``: :mod:`sim_plc.distribution`).
3. the pulley chain run backwards, platform -> sensor (``chain_runs.run``; Dahl by
   default, with the hidden chain-side effects in its :class:`ChainParams`), then the
   hidden path and sensor effects in their order (:func:`gateway.model.effects.forward`).
4. Gaussian noise (std per cable), the sensor's analog output limit ``saturation_n``,
   and the A/D converter in the S7 analog format: ``0..27648`` = ``0..range``; counts
   above the overrange limit 32511 read 32767 (overflow), below the underrange limit
   -4864 read -32768 (underflow); both scale back to NaN (no value).

A hidden statics effect (a platform mass the controller does not know,
:func:`gateway.model.effects.mass_delta`) changes the truth only: the recorded ``mass`` and
``tension_platform`` are what the controller believes (without it), so a diagnosis can find
it. Without one ``tension_platform`` is the truth.

Two forms over the same code: :func:`make_recording` (batch, vectorised) and
:meth:`Plant.step` (one period into a :class:`ProcessImage`; setpoints and statics are
precomputed one chunk ahead, spread evenly over the cycles of the chunk before). The soft
PLC runs that stepping in a worker process and only replays its samples
(:mod:`sim_plc.chunk_worker`, :meth:`Plant.use_chunks`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.s7 import s7_codec
from gateway.core.config import Config
from gateway.core.firstrun import compiling
from gateway.errors import InfeasiblePoseError
from gateway.model import chain_kernels, chain_runs, chain_schema, effects, kinematics, statics
from gateway.recordings.reader import Recording
from sim_plc.config import SimPlcConfig, load_sim_config, per_cable
from sim_plc.distribution import Distributor
from sim_plc.image import ProcessImage
from sim_plc.trajectories import Trajectory, make_trajectory

log = logging.getLogger("cdpr_gateway.sim_plc")

Progress = Callable[[float], None]


def digitise(tension_n: np.ndarray, range_n: float, full_scale: int, saturation_n: float):
    """Analog reading (N) -> int16 S7 counts, with the sensor output limit first."""
    limited = np.clip(tension_n, -saturation_n, saturation_n)
    return s7_codec(range_n, full_scale).encode(limited)


def counts_to_newton(counts: np.ndarray, range_n: float, full_scale: int) -> np.ndarray:
    """S7 counts -> N; outside the S7 window (overflow/underflow codes) -> NaN."""
    return s7_codec(range_n, full_scale).decode(np.asarray(counts))


@dataclass
class Setpoints:
    """Kinematics and statics at N times. Shapes: t, mass (N,); pose (N, 6); the rest
    (N, m) except ``a_mat`` (N, 6, m) and the wrenches (N, 6). ``mass``, ``*_recorded``:
    as recorded; ``*_true``: the truth (they differ only with a hidden mass change)."""

    t: np.ndarray
    pose: np.ndarray
    length: np.ndarray
    velocity: np.ndarray
    a_mat: np.ndarray
    mass: np.ndarray
    wrench_true: np.ndarray
    wrench_recorded: np.ndarray
    tension_true: np.ndarray
    tension_recorded: np.ndarray


def chain_params(sim: SimPlcConfig, cables: int) -> chain_schema.ChainParams:
    """Truth friction of every cable with the chain-side effects applied (the registry's
    :func:`gateway.model.effects.chain_params`)."""
    return effects.chain_params(sim.friction, sim.effects.values, cables)


class PlantModel:
    """Everything fixed of the plant: geometry, trajectory, chain and effect parameters."""

    def __init__(self, cfg: Config, sim: SimPlcConfig | None = None):
        self.cfg = cfg
        self.sim = load_sim_config(cfg) if sim is None else sim
        geo = cfg.geometry
        self.cables = cfg.cables
        self.a = np.asarray(geo.frame_anchors_m, dtype=float)
        self.b = np.asarray(geo.platform_anchors_m, dtype=float)
        self.trajectory: Trajectory = make_trajectory(
            self.sim.trajectory, np.asarray(geo.home_pose), self.sim.base_dir
        )
        self.params = chain_params(self.sim, self.cables)
        self.effects = self.sim.effects.values  # hidden, as per-cable arrays
        self.noise_std = per_cable(self.sim.noise_std_n, self.cables)
        self.hides_mass = effects.mass_delta(self.effects, np.zeros(1), 0.0) is not None
        lim = self.sim.tension  # the controller's distribution (sim_plc.distribution)
        self.distribute = Distributor(self.sim.distribution, lim.min_n, lim.max_n)

    def _traj_time(self, t: np.ndarray) -> np.ndarray:
        dur = self.trajectory.duration_s
        if self.sim.trajectory.repeat and math.isfinite(dur) and dur > 0:
            return np.mod(t, dur)
        return t

    def setpoints(self, t: np.ndarray, progress: Progress | None = None) -> Setpoints:
        """Kinematics and statics at times ``t`` (N,) in s (vectorised but the tensions).

        ``progress(fraction)`` is called every 2 % of the samples when given.
        """
        sp = self.prepare(t)
        every = max(sp.t.size // 50, 1)
        for k in range(sp.t.size):
            self.solve_tensions(sp, k)
            if progress is not None and k % every == 0:
                progress(k / sp.t.size)
        if progress is not None:
            progress(1.0)
        return sp

    def prepare(self, t: np.ndarray) -> Setpoints:
        """Setpoints at times ``t`` (N,) with the tensions not yet solved (NaN)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        tt = self._traj_time(t)
        s = self.trajectory.evaluate(tt)
        m0 = self.sim.initial_mass_kg
        printed = self.trajectory.printing_time(tt)
        mass = np.maximum(m0 - self.sim.extrusion_kg_s * printed, 0.1 * m0)
        omega = kinematics.angular_velocity_from_euler_rates(s.pose[:, 3:], s.velocity[:, 3:])
        twist = np.concatenate([s.velocity[:, :3], omega], axis=1)
        a_mat = kinematics.structure_matrix_batch(self.a, self.b, s.pose)
        vel = kinematics.cable_velocities_from_structure(a_mat, twist)
        length = kinematics.cable_lengths_batch(self.a, self.b, s.pose)
        acc = s.acceleration[:, :3]
        w_rec = self.wrench(mass, s.pose, acc)
        w_true = w_rec
        hidden = effects.mass_delta(self.effects, t, 0.0)
        if hidden is not None:
            w_true = self.wrench(mass + hidden, s.pose, acc)
        nan = np.full((t.size, self.cables), np.nan)
        return Setpoints(t, s.pose, length, vel, a_mat, mass, w_true, w_rec, nan, nan.copy())

    def solve_tensions(self, sp: Setpoints, k: int) -> None:
        """Tension distribution of sample ``k`` of ``sp`` (true and recorded), in place."""
        try:
            sp.tension_recorded[k] = self.distribute(sp.a_mat[k], sp.wrench_recorded[k])
            if sp.wrench_true is sp.wrench_recorded:
                sp.tension_true[k] = sp.tension_recorded[k]
            else:
                sp.tension_true[k] = self.distribute(sp.a_mat[k], sp.wrench_true[k])
        except InfeasiblePoseError as exc:
            pose = np.round(sp.pose[k], 4).tolist()
            raise InfeasiblePoseError(
                f"{self.sim.source or 'config'}: sim_plc.trajectory: pose {pose} at "
                f"t = {sp.t[k]:.3f} s is outside the wrench-feasible workspace: {exc}"
            ) from exc

    def wrench(self, mass: np.ndarray, pose: np.ndarray, acc: np.ndarray) -> np.ndarray:
        """External wrench (N, 6): gravity + d'Alembert ``-m a``."""
        return statics.external_wrench_batch(mass, pose, acc, self.cfg.geometry)

    def adc(self, analog_n: np.ndarray) -> np.ndarray:
        sensor = self.cfg.sensor
        return digitise(analog_n, sensor.range_n, sensor.adc_full_scale, self.sim.saturation_n)

    def reading(self, counts: np.ndarray) -> np.ndarray:
        sensor = self.cfg.sensor
        return counts_to_newton(counts, sensor.range_n, sensor.adc_full_scale)


def _series(sp: Setpoints, cols: slice = slice(None)) -> effects.SeriesData:
    """The forms' view of the setpoints (``cols``: some cables): ``x`` the cable length,
    ``a`` by second-order differences (computed when an effect reads it)."""
    v = sp.velocity[:, cols]
    t0 = float(sp.t[0]) if sp.t.size else 0.0
    return effects.SeriesData(
        sp.t, v, sp.length[:, cols], lambda: effects.acceleration(sp.t, v), t0
    )


def sensor_batch(model: PlantModel, sp: Setpoints, noise: np.ndarray) -> np.ndarray:
    """Analog sensor output (N, m) before the A/D: chain, path/sensor effects, noise."""
    ts = chain_runs.run(model.params, "simulate", sp.tension_true, sp.velocity, sp.t)
    ts = effects.forward(_series(sp), ts, model.effects)
    return ts + noise * model.noise_std


def _cable_effects(eff: effects.Effects, i: int) -> effects.Effects:
    """Cable ``i``'s parameters of ``eff`` (each per-cable field (1,))."""
    return {
        name: {p: (v[i : i + 1] if effects.REGISTRY[name].per_cable else v) for p, v in ps.items()}
        for name, ps in eff.items()
    }


def reading_batch(model: PlantModel, sp: Setpoints, rng: np.random.Generator) -> np.ndarray:
    """``model.reading(model.adc(sensor_batch(model, sp, noise)))`` with ``noise`` the next
    (N, m) standard normals of ``rng``, equal value for value, in one (N, m) array: the
    path and sensor effects run cable by cable (each is per cable), the noise is drawn and
    the A/D applied ``RECORD_CHUNK`` rows at a time (a 10-min run: 40 MB of temporaries
    instead of 300 MB)."""
    ts = chain_runs.run(model.params, "simulate", sp.tension_true, sp.velocity, sp.t)
    m = ts.shape[1]
    for i in range(m):
        col = slice(i, i + 1)
        ts[:, col] = effects.forward(_series(sp, col), ts[:, col], _cable_effects(model.effects, i))
    for start in range(0, ts.shape[0], RECORD_CHUNK):
        rows = ts[start : start + RECORD_CHUNK]
        rows += rng.standard_normal(rows.shape) * model.noise_std
        rows[...] = model.reading(model.adc(rows))
    return ts


def _metadata(model: PlantModel, seconds: float) -> dict[str, str]:
    active = model.sim.effects.active()
    desc = []
    for name, params in active.items():
        desc.append(f"{name}{params}")
    return {
        "source": "sim_plc",
        "config": model.sim.source or "<defaults>",
        "trajectory": model.sim.trajectory.kind,
        "seconds": f"{seconds:g}",
        "period_s": f"{model.sim.period_s:g}",
        "friction": f"{model.params.model} mu={model.sim.friction.mu} "
        f"sigma_n_m={model.sim.friction.sigma_n_m}",
        "effects": "; ".join(desc) if desc else "none",
        "seed": str(model.sim.seed),
        "noise_std_n": str(model.sim.noise_std_n),
        "extrusion_kg_s": f"{model.sim.extrusion_kg_s:g}",
        "tension_platform": "statics with the recorded mass"
        + (" (a mass change hidden)" if model.hides_mass else " (truth)"),
        "tension_sensor": "S7 counts scaled back to N (empty: overflow/underflow)",
    }


RECORD_CHUNK = 20_000  # samples of setpoints prepared at once by make_recording


def _recording_setpoints(model: PlantModel, t: np.ndarray, progress: Progress | None) -> Setpoints:
    """``model.setpoints(t)`` prepared ``RECORD_CHUNK`` samples at a time (every quantity
    is per sample), keeping only what a recording needs: the structure matrices and the
    wrenches of one chunk at a time, never of the whole run (10 min: 1 GB -> < 400 MB)."""
    n, m = t.size, model.cables
    # without a hidden mass change the truth is what is recorded: one array for both
    hidden = model.hides_mass
    keep = ("pose", "length", "velocity", "mass", "tension_recorded") + (
        ("tension_true",) if hidden else ()
    )
    out = {"pose": np.empty((n, 6)), "mass": np.empty(n)}
    out.update({k: np.empty((n, m)) for k in keep if k not in out})
    if not hidden:
        out["tension_true"] = out["tension_recorded"]
    for start in range(0, n, RECORD_CHUNK):
        part = model.prepare(t[start : start + RECORD_CHUNK])
        for k in range(part.t.size):
            model.solve_tensions(part, k)
        for name in keep:
            out[name][start : start + part.t.size] = getattr(part, name)
        if progress is not None:
            progress((start + part.t.size) / n)
    none6 = np.empty((0, 6))
    return Setpoints(t, a_mat=np.empty((0, 6, m)), wrench_true=none6, wrench_recorded=none6, **out)


def make_recording(
    cfg: Config, sim: SimPlcConfig | None, seconds: float, progress: Progress | None = None
) -> Recording:
    """Run the plant for ``seconds`` in batch mode and return the recording.

    Columns: ``t``, setpoint ``velocity``, ``tension_sensor`` (the digitised reading in N),
    ``tension_platform`` (see the module docstring), setpoint ``length``, ``pose``,
    ``mass``. Metadata names the source, the friction, the effects and the seed.
    ``sim`` None: ``load_sim_config(cfg)``. ``progress(fraction)``: optional callback.
    """
    model = PlantModel(cfg, sim)
    n = max(round(seconds / model.sim.period_s), 2)
    t = np.arange(n) * model.sim.period_s
    with compiling(
        "the soft PLC's plant", [chain_kernels.simulate_kernel, statics.wrench_into], log.info
    ):
        sp = _recording_setpoints(model, t, progress)
        reading = reading_batch(model, sp, np.random.default_rng(model.sim.seed))
    return Recording(
        t=t,
        velocity=sp.velocity,
        tension_sensor=reading,
        tension_platform=sp.tension_recorded,
        length=sp.length,
        pose=sp.pose,
        mass=sp.mass,
        metadata=_metadata(model, seconds),
    )


class Plant:
    """Per-cycle plant: ``step()`` advances one period and writes the PLC inputs.

    Setpoints and statics of the next ``chunk`` samples are prepared (vectorised, ~1 ms
    whatever the chunk size) when a chunk starts and their tension distributions solved
    one per cycle, so a cycle costs ~60-100 us and one in ``chunk`` about 1 ms more (the
    runtime catches that up). Agrees with :func:`make_recording` sample by sample.
    """

    def __init__(self, cfg: Config, sim: SimPlcConfig | None = None, chunk: int = 250):
        self.model = PlantModel(cfg, sim)
        self.period_s = self.model.sim.period_s
        self.chunk = max(int(chunk), 2)
        self.analog = np.zeros(self.model.cables)  # last analog reading before the A/D (N)
        self.counts = np.zeros(self.model.cables, dtype=np.int16)
        self.chunks: Any = None  # a source of solved chunks (sim_plc.chunk_worker), or None
        self.reset()

    def use_chunks(self, chunks: Any) -> None:
        """Replay the samples of ``chunks.get(index)`` (:class:`sim_plc.chunk_worker.ChunkWorker`:
        the same plant run in another process) instead of stepping the physics here;
        restarts at t = 0."""
        self.chunks = chunks
        self.reset()

    def reset(self) -> None:
        """Back to t = 0: relaxed pulleys, effect states cleared, noise re-seeded."""
        m = self.model
        self.k = 0
        self.rng = np.random.default_rng(m.sim.seed)
        self.stepper = chain_runs.ChainStepper(m.params, self.period_s, forward=False)
        self.fx = effects.ForwardStepper(m.effects, m.cables, self.period_s)
        if self.chunks is not None:  # the worker's plant runs; this one replays it
            self._cur, self._nxt = self.chunks.get(0), self.chunks.get(1)
        else:
            self._cur = m.setpoints(self._times(0))
            self._nxt = m.prepare(self._times(1))
            self._solved = 0
        self._ts = np.zeros(m.cables)
        self._t3 = np.zeros(3)
        self._v3 = np.zeros((3, m.cables))

    def _times(self, chunk_index: int) -> np.ndarray:
        return (chunk_index * self.chunk + np.arange(self.chunk)) * self.period_s

    @property
    def time_s(self) -> float:
        """Time of the next sample ``step()`` produces (s)."""
        return self.k * self.period_s

    def _replay(self, image: ProcessImage | None) -> None:
        """Sample ``k`` as the worker's plant produced it: a row copy, no physics here."""
        i = self.k % self.chunk
        if i == 0 and self.k > 0:
            self._cur = self._nxt
            self._nxt = self.chunks.get(self.k // self.chunk + 1)
        cur = self._cur
        np.copyto(self.analog, cur.analog[i])
        np.copyto(self.counts, cur.counts[i], casting="unsafe")
        if image is not None:
            with image.lock:
                image.raw_counts[:] = self.counts
                image.velocity_m_s[:] = cur.velocity[i]
                image.length_m[:] = cur.length[i]
                image.pose[:] = cur.pose[i]
                image.platform_mass_kg = float(cur.mass[i])
                image.plc_heartbeat = (image.plc_heartbeat + 1) & 0xFFFF
                image.true_tension_n[:] = cur.tension_true[i]
                image.time_s = float(cur.t[i])
        self.k += 1

    def _advance_chunk(self) -> None:
        while self._solved < self.chunk:
            self.model.solve_tensions(self._nxt, self._solved)
            self._solved += 1
        self._cur = self._nxt
        self._nxt = self.model.prepare(self._times(self.k // self.chunk + 1))
        self._solved = 0

    def step(self, image: ProcessImage | None = None) -> None:
        """Produce sample ``k`` (time ``k * period_s``) and write it into ``image``."""
        if self.chunks is not None:
            self._replay(image)
            return
        m, i = self.model, self.k % self.chunk
        if i == 0 and self.k > 0:
            self._advance_chunk()
        if self._solved < self.chunk:  # spread the next chunk's statics over the cycles
            m.solve_tensions(self._nxt, self._solved)
            self._solved += 1
        cur = self._cur
        t, tp, v = float(cur.t[i]), cur.tension_true[i], cur.velocity[i]
        nxt_t, nxt_v = (
            (cur.t[i + 1], cur.velocity[i + 1])
            if i + 1 < self.chunk
            else (self._nxt.t[0], self._nxt.velocity[0])
        )
        self._t3[:2], self._v3[:2] = self._t3[1:], self._v3[1:]
        self._t3[1:], self._v3[1], self._v3[2] = (t, nxt_t), v, nxt_v
        # no travel at the first sample (as in the batch form); then a period's
        self.stepper.step(tp, v, self._ts, 0.0 if self.k == 0 else -1.0)
        ts = self.fx.step(effects.Sample(self.k, t, self._t3, self._v3, cur.length[i]), self._ts)
        self.analog = ts + self.rng.standard_normal(m.cables) * m.noise_std
        self.counts = m.adc(self.analog)
        if image is not None:
            with image.lock:
                image.raw_counts[:] = self.counts
                image.velocity_m_s[:] = v
                image.length_m[:] = cur.length[i]
                image.pose[:] = cur.pose[i]
                image.platform_mass_kg = float(cur.mass[i])
                image.plc_heartbeat = (image.plc_heartbeat + 1) & 0xFFFF
                image.true_tension_n[:] = tp
                image.time_s = t
        self.k += 1


STREAM_CHUNK = 1000  # samples per block of stream_recording (1 s at 1 kHz)


def stream_recording(
    cfg: Config,
    sim: SimPlcConfig | None,
    seconds: float,
    progress: Progress | None = None,
    chunk: int = STREAM_CHUNK,
) -> Iterator[Recording]:
    """:func:`make_recording` as blocks of ``chunk`` samples, each a :class:`Recording`
    (``metadata`` on every block), computed only when the caller asks for it: ``record``
    writes each block before the next is simulated, so an interrupt keeps what was
    simulated. The friction chain runs as in the batch form with its state carried from
    block to block (value for value the batch's), the noise is drawn in the same order; the
    path and sensor effects, if any, run per sample (:class:`effects.ForwardStepper`, the
    soft PLC's form, ``tests/sim_plc/test_plant.py``: within 1e-9 N of the batch form) and
    look one sample past each block, the last sample of the run included (the batch form
    takes a one-sided difference there)."""
    model = PlantModel(cfg, sim)
    period, m = model.sim.period_s, model.cables
    n = max(round(seconds / period), 2)
    t = np.arange(n + 1) * period  # one sample past the end: the effects' look-ahead
    meta = _metadata(model, seconds)
    rng = np.random.default_rng(model.sim.seed)
    state = chain_runs.new_state(model.params)
    fx = effects.ForwardStepper(model.effects, m, period)
    t3, v3 = np.zeros(3), np.zeros((3, m))
    previous: chain_runs.Previous | None = None  # as the batch form: no travel at t = 0
    chunk = max(int(chunk), 1)
    with compiling(
        "the soft PLC's plant", [chain_kernels.simulate_kernel, statics.wrench_into], log.info
    ):
        for a in range(0, n, chunk):
            b = min(a + chunk, n)
            sp = model.prepare(t[a : b + 1])
            for k in range(sp.t.size):
                model.solve_tensions(sp, k)
            rows = b - a
            vel = sp.velocity[:rows]
            ts = chain_runs.run(
                model.params,
                "simulate",
                sp.tension_true[:rows],
                vel,
                sp.t[:rows],
                state=state,
                previous=previous,
            )
            previous = (float(sp.t[rows - 1]), vel[-1].copy())
            if fx.steppers:
                for i in range(rows):
                    t3[:2], v3[:2] = t3[1:], v3[1:]
                    t3[1:], v3[1:] = sp.t[i : i + 2], sp.velocity[i : i + 2]
                    s = effects.Sample(a + i, float(sp.t[i]), t3, v3, sp.length[i])
                    ts[i] = fx.step(s, ts[i].copy())
            ts += rng.standard_normal(ts.shape) * model.noise_std
            yield Recording(
                t=sp.t[:rows],
                velocity=sp.velocity[:rows],
                tension_sensor=model.reading(model.adc(ts)),
                tension_platform=sp.tension_recorded[:rows],
                length=sp.length[:rows],
                pose=sp.pose[:rows],
                mass=sp.mass[:rows],
                metadata=meta,
            )
            if progress is not None:
                progress(b / n)
