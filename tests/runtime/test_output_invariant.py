"""The output contract as a property: whatever the PLC sends and whatever goes wrong, no
frame the gateway writes carries a usable value (status good or substituted) that is not
finite, lies outside what its register carries, comes from data older than
``loop.max_input_age_s``, or is written while the PLC heartbeat has been frozen longer
than ``loop.heartbeat_timeout_s``.

hypothesis drives the real loop (:class:`gateway.runtime.loop.CyclicService`, compensator,
plausibility, the driver base with its output gate) with a scripted driver on a fake
clock: PLC inputs with NaN, infinities, denormals and huge values in every field; the
PLC heartbeat counting, frozen, jumping, wrapping or NaN (float heartbeat); failed reads,
timeouts, dropped connections (reconnects), clock stalls inside a read and between
cycles; random fitted effects of every kind the gateway compensates (eccentricity and
inertia included); function-23-style pipelined writes or immediate ones. Every frame
written is checked against what the script served, not against the loop's own
bookkeeping. ``make test`` runs a bounded number of examples; ``make test-long`` more.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import ChannelStatus, Driver, Inputs, Lifecycle, Outputs
from gateway.errors import DriverIOError, DriverTimeoutError
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import FakeClock, config

CABLES = 8
BAND = (-50.0, 650.0)  # the fake registers' tension band: the range check has work to do
WRENCH_BAND = (-5e3, 5e3)
EPS = 1e-5  # the fake clock ticks 1e-7 per reading: a handful of readings apart
USABLE = int(ChannelStatus.SUBSTITUTED)

HOSTILE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, 5e-324, -5e-324, 1e-310, 1e300, -1e300]),
)


def _array(normal: st.SearchStrategy[float], n: int) -> st.SearchStrategy[list[float]]:
    """Mostly plausible values, sometimes hostile ones, per element."""
    element = st.one_of(normal, normal, normal, HOSTILE)
    return st.lists(element, min_size=n, max_size=n)


@dataclass
class Event:
    kind: str  # ok | io | timeout | drop | stall_read
    raw: list[float] = field(default_factory=list)
    velocity: list[float] = field(default_factory=list)
    length: list[float] = field(default_factory=list)
    pose: list[float] = field(default_factory=list)
    heartbeat: str = "inc"  # inc | same | jump | wrap | nan
    jump_to: int = 0
    stall_s: float = 0.0  # stall_read: inside the read; any event: after the cycle


OK_EVENT = st.builds(
    Event,
    kind=st.just("ok"),
    raw=_array(st.floats(0.0, 480.0), CABLES),
    velocity=_array(st.floats(-0.5, 0.5), CABLES),
    length=_array(st.floats(0.5, 3.0), CABLES),
    pose=st.one_of(
        st.just([0.0, 0.0, 1.5, 0.0, 0.0, 0.0]), _array(st.floats(-0.3, 0.3), 6).map(list)
    ),
    heartbeat=st.sampled_from(["inc"] * 6 + ["same", "jump", "wrap", "nan"]),
    jump_to=st.integers(0, 65535),
    stall_s=st.one_of(st.just(0.0), st.just(0.0), st.just(0.0), st.floats(0.0, 2.5)),
)
FAULT_EVENT = st.builds(
    Event,
    kind=st.sampled_from(["io", "timeout", "drop", "stall_read"]),
    stall_s=st.floats(0.0, 2.5),
)
EVENTS = st.lists(st.one_of(OK_EVENT, OK_EVENT, OK_EVENT, FAULT_EVENT), min_size=20, max_size=160)

EFFECT_DRAWS: dict[str, st.SearchStrategy[dict[str, float]]] = {
    "coulomb": st.fixed_dictionaries({"mu": st.floats(0.0, 0.05), "f0_n": st.floats(0, 3)}),
    "presliding": st.fixed_dictionaries({"sigma_n_m": st.floats(50.0, 5000.0)}),
    "viscous": st.fixed_dictionaries({"c_ns_m": st.floats(-20.0, 60.0)}),
    "stribeck": st.fixed_dictionaries({"k": st.floats(0.0, 1.0), "v_s_m_s": st.floats(0.001, 0.1)}),
    "inertia": st.fixed_dictionaries({"m_eff_kg": st.floats(-30.0, 30.0)}),
    "eccentricity": st.fixed_dictionaries(
        {
            "a_n": st.floats(-5.0, 5.0),
            "r_m": st.floats(0.01, 0.2),
            "phi_rad": st.floats(-3.2, 3.2),
        }
    ),
    "gain": st.fixed_dictionaries({"g": st.floats(-0.05, 0.05)}),
    "offset": st.fixed_dictionaries({"c_n": st.floats(-5.0, 5.0)}),
    "coulomb_directional": st.fixed_dictionaries(
        {"mu_out": st.floats(0.0, 0.5), "mu_in": st.floats(0.0, 0.5), "f0_n": st.floats(0, 3)}
    ),
    "maxwell_slip": st.fixed_dictionaries(
        {"sigma_n_m": st.floats(1.0, 1e6), "w": st.floats(0.0, 1.0)}
    ),
    "cable_stretch": st.fixed_dictionaries({"k_n_m": st.floats(1.0, 1e7)}),
    "backlash": st.fixed_dictionaries({"width_m": st.floats(0.0, 0.05)}),
    "sensor_creep": st.fixed_dictionaries(
        {"c": st.floats(-0.5, 0.5), "tau_s": st.floats(1e-4, 100.0)}
    ),
    "spring": st.fixed_dictionaries(
        {"k_n_m": st.floats(-100.0, 100.0), "l0_m": st.floats(-1.0, 1.0)}
    ),
}
"""Each effect the gateway compensates online, parameters drawn over its valid range."""
EFFECTS = st.fixed_dictionaries({}, optional=EFFECT_DRAWS)

WARM_UP = [
    Event(
        "ok", [200.0 + k] * CABLES, [0.05] * CABLES, [1.5] * CABLES, [0.0, 0.0, 1.5, 0.0, 0.0, 0.0]
    )
    for k in range(30)
]


class ScriptedPlc(Driver):
    """A driver whose every read plays the next event of a script; records every frame
    written (clock time, status, tensions, wrench, state) and what the PLC served."""

    name = "scripted"

    def __init__(
        self,
        cfg: Any,
        clock: FakeClock,
        events: list[Event],
        pipelined: bool,
        float_heartbeat: bool,
    ) -> None:
        super().__init__(cfg)
        self.fake_clock = clock
        self.events = events
        self.pipelined = pipelined
        self.float_heartbeat = float_heartbeat
        self.plc_heartbeat_modulus = 0 if float_heartbeat else 1 << 16
        self.k = 0
        self.dropped = False
        self.heartbeat = 0.0 if float_heartbeat else 0
        self.seq = 0  # orders reads and writes (several may share one clock reading)
        self.frames: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, int, int]] = []
        self.reads: list[tuple[float, int]] = []  # (request time, seq) of good reads
        self.changes: list[tuple[float, int]] = []  # (reply time, seq): heartbeat changed
        self._last_served: float | None = None

    @property
    def combines_write_and_read(self) -> bool:
        return self.pipelined

    def output_bands(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return BAND, WRENCH_BAND

    def _open(self) -> None:
        self.dropped = False

    def _close(self) -> None:
        pass

    def _read(self, inputs: Inputs) -> None:
        requested = self.fake_clock.now
        self.seq += 1
        ev = self.events[self.k % len(self.events)]
        self.k += 1
        if self.dropped:
            raise DriverIOError("scripted: not connected")
        if ev.kind == "drop":
            self.dropped = True
            raise DriverIOError("scripted: connection dropped")
        if ev.kind == "io":
            raise DriverIOError("scripted: exception 4")
        if ev.kind == "timeout":
            raise DriverTimeoutError("scripted: no reply")
        if ev.kind == "stall_read":
            self.fake_clock.advance(ev.stall_s)  # the reply came late; data from then
            ev = WARM_UP[self.k % len(WARM_UP)]
        inputs.tension_raw_n[:] = ev.raw
        inputs.velocity_m_s[:] = ev.velocity
        inputs.length_m[:] = ev.length
        inputs.pose[:] = ev.pose
        inputs.plc_heartbeat = self._next_heartbeat(ev)
        self._served(inputs.plc_heartbeat, requested)

    def _next_heartbeat(self, ev: Event) -> int | float:
        hb = self.heartbeat
        if ev.heartbeat == "inc":
            hb = hb + 1 if self.float_heartbeat else (int(hb) + 1) & 0xFFFF
        elif ev.heartbeat == "jump":
            hb = float(ev.jump_to) if self.float_heartbeat else ev.jump_to
        elif ev.heartbeat == "wrap":
            hb = 65535.0 if self.float_heartbeat else (0 if hb == 65535 else 65535)
        elif ev.heartbeat == "nan" and self.float_heartbeat:
            return math.nan  # this read carries no heartbeat; the counter stays
        self.heartbeat = hb
        return hb

    def _served(self, hb: float, requested: float) -> None:
        self.reads.append((requested, self.seq))
        if math.isfinite(hb):
            if self._last_served is not None and hb != self._last_served:
                self.changes.append((self.fake_clock.now, self.seq))
            self._last_served = hb

    def _write(self, outputs: Outputs) -> None:
        if self.dropped:
            raise DriverIOError("scripted: not connected")
        self.seq += 1
        self.frames.append(
            (
                self.fake_clock.now,
                outputs.channel_status.copy(),
                outputs.tension_corrected_n.copy(),
                outputs.wrench.copy(),
                int(outputs.gateway_state),
                self.seq,
            )
        )


def _check_frames(drv: ScriptedPlc, cfg: Any) -> int:
    """Assert the contract on every frame; return the number of usable values seen."""
    lp = cfg.loop
    max_age = lp.input_age_limit_s
    requested = np.array([r for r, _ in drv.reads])
    read_seq = np.array([s for _, s in drv.reads])
    changed_at = np.array([c for c, _ in drv.changes])
    changed_seq = np.array([s for _, s in drv.changes])
    usable_values = 0
    for t, status, tension, wrench, state, seq in drv.frames:
        usable = status <= USABLE
        where = f"frame at {t:.4f}: status {status}, tension {tension}, wrench {wrench}"
        if state in (Lifecycle.FAULT, Lifecycle.STOPPED):
            assert not usable.any(), where
        if np.isfinite(wrench).any():
            assert usable.all(), where
            assert np.all(np.isfinite(wrench)), where
            assert np.all((wrench >= WRENCH_BAND[0]) & (wrench <= WRENCH_BAND[1])), where
        if not usable.any():
            assert np.all(np.isnan(tension)), where  # invalid carries no value
            continue
        usable_values += int(usable.sum())
        x = tension[usable]
        assert np.all(np.isfinite(x)), where
        assert np.all((x >= BAND[0]) & (x <= BAND[1])), where
        assert np.all(np.isnan(tension[~usable])), where
        # data age: the newest read answered before this send was requested no earlier
        # than max_age before it (the frame cannot be newer than that read)
        before = read_seq < seq
        assert before.any(), where
        assert t - requested[before][-1] <= max_age + EPS, where
        # the PLC heartbeat changed, as served, within the timeout before the send
        seen = changed_at[changed_seq < seq]
        assert seen.size and t - seen[-1] <= lp.heartbeat_timeout_s + EPS, where
    return usable_values


def _run(
    effects: dict, events: list[Event], pipelined: bool, float_hb: bool, between_stall: bool
) -> tuple[ScriptedPlc, Any]:
    cfg = config(busy_wait_s=0.0)
    cfg = dataclasses.replace(cfg, friction=dataclasses.replace(cfg.friction, effects=effects))
    clock = FakeClock()
    script = WARM_UP + events
    drv = ScriptedPlc(cfg, clock, script, pipelined, float_hb)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)

    def stall_between_cycles(inputs: Inputs, comp: Any, now: float) -> None:
        ev = script[(drv.k - 1) % len(script)]
        if between_stall and ev.kind == "ok" and ev.stall_s > 0.0:
            clock.advance(ev.stall_s)

    svc.add_observer(stall_between_cycles)
    svc.run(cycles=len(script) + 5)
    return drv, cfg


def _property(effects, events, pipelined, float_hb, between_stall) -> None:
    drv, cfg = _run(effects, events, pipelined, float_hb, between_stall)
    assert drv.frames, "nothing was written"
    usable = _check_frames(drv, cfg)
    assert usable > 0, "the warm-up gives usable values: the check above is not vacuous"


SETTINGS = {
    "deadline": None,
    "suppress_health_check": [
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.large_base_example,
    ],
}


@settings(max_examples=25, **SETTINGS)
@given(EFFECTS, EVENTS, st.booleans(), st.booleans(), st.booleans())
def test_no_frame_breaks_the_output_contract(effects, events, pipelined, float_hb, stall):
    _property(effects, events, pipelined, float_hb, stall)


@pytest.mark.long
@settings(max_examples=300, **SETTINGS)
@given(EFFECTS, EVENTS, st.booleans(), st.booleans(), st.booleans())
def test_no_frame_breaks_the_output_contract_long(effects, events, pipelined, float_hb, stall):
    _property(effects, events, pipelined, float_hb, stall)


def test_the_effects_drawn_are_every_effect_the_gateway_compensates():
    """A new online effect is fuzzed from the day it is registered, or this fails."""
    from gateway.model.effects.registry import ONLINE_EFFECTS

    assert set(EFFECT_DRAWS) == set(ONLINE_EFFECTS)


def test_the_check_catches_a_gate_that_lets_a_stalled_frame_through(monkeypatch):
    """The property is not vacuous: with the gate switched off, the stalled pipelined
    frame of the failure it guards against breaks it."""
    from drivers import gate

    monkeypatch.setattr(gate.Gate, "__call__", lambda *args: None)
    stall = Event(
        "ok",
        [210.0] * CABLES,
        [0.05] * CABLES,
        [1.5] * CABLES,
        [0.0, 0.0, 1.5, 0.0, 0.0, 0.0],
        stall_s=2.0,
    )
    with pytest.raises(AssertionError, match="frame at"):
        _property({}, [stall, *WARM_UP], True, False, True)
