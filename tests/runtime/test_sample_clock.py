"""The one sample clock (gateway/runtime/clock.py) and the life-bit hole it closes.

Issue 30: a PLC whose heartbeat is a 0/1 life bit, read by a gateway that took every
heartbeat for a sample counter modulo 2**16, made 1 -> 0 count as 65 535 samples: the
chain integrated 100 ms of travel every other sample and the tensions after each
velocity reversal were off by up to 5.9 N, every one written good (status 0).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.base import ChannelStatus, Inputs, Outputs
from gateway.core.config import SPACING_TOLERANCE, HeartbeatConfig, config_from_mapping, load_config
from gateway.errors import ConfigError
from gateway.model import effects as fx
from gateway.model.chain_runs import ChainStepper, run
from gateway.runtime.clock import MAX_GAP_PERIODS, SampleClock, warm_travel_m
from gateway.runtime.compensator import Compensator
from tests.loop_helpers import config

T = 1e-3
GOOD = int(ChannelStatus.GOOD)
CABLES = 8


def _plant(seconds: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PLC samples every ``T``: setpoint velocities reversing ~1.4 times a second, the
    sensor readings of the gateway's own (default) model: (t, v, ts)."""
    cfg = config(period_s=T)
    n = int(seconds / T)
    t = np.arange(n) * T
    ph = np.random.default_rng(3).uniform(0, 2 * math.pi, (2, CABLES))
    v = 0.08 * np.sin(2 * math.pi * 0.7 * t[:, None] + ph[0])
    tp = 200.0 + 60.0 * np.sin(2 * math.pi * 0.4 * t[:, None] + ph[1])
    values = cfg.friction.effect_values(CABLES)
    ts = run(fx.chain_params(cfg.friction, values, CABLES), "simulate", tp, v, t)
    return t, v, ts


def _gateway(heartbeat: HeartbeatConfig | None, hb_of: object) -> tuple[np.ndarray, ...]:
    """The gateway reading every PLC sample once, a little after it was made, with the
    heartbeat ``hb_of(k)``; its tensions and statuses, and the model on the true time base
    (the same chain stepped every ``T``)."""
    cfg = config(period_s=T, stuck_after_s=10.0)
    if heartbeat is not None:
        cfg = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, heartbeat=heartbeat))
    t, v, ts = _plant()
    comp = Compensator(cfg)
    inp, out = Inputs.allocate(CABLES), Outputs.allocate(CABLES)
    inp.pose[:] = cfg.geometry.home_pose
    ref = ChainStepper(comp.params, T)
    want = np.empty_like(ts)
    got = np.empty_like(ts)
    status = np.empty(ts.shape, dtype=int)
    jitter = np.random.default_rng(5).uniform(0.0, 0.3 * T, t.size)
    for k in range(t.size):
        inp.tension_raw_n[:] = ts[k]
        inp.velocity_m_s[:] = v[k]
        inp.plc_heartbeat = hb_of(k)  # type: ignore[operator]
        now = 100.0 + t[k] + jitter[k]
        inp.read_time_s = now
        comp.step(inp, now, out)
        got[k], status[k] = out.tension_corrected_n, out.channel_status
        ref.step(ts[k], v[k], want[k], 0.0 if k == 0 else T)
    return got, status, want


def test_a_life_bit_read_as_a_counter_never_writes_a_wrong_tension_good():
    """The hole: the default declaration (a counter) and a PLC that toggles a bit. Every
    1 -> 0 is a counter stepping back 65 535 samples: never integrated, so the chain is
    never warm and nothing after the first steps is written good; before the fix the
    good values were up to several N off the model on the true time base."""
    got, status, want = _gateway(None, lambda k: k & 1)
    good = status == GOOD
    err = np.abs(got - want)[good]  # the first two: a start on one jittered spacing
    assert err.size == 0 or err.max() <= 1e-3, f"a good value {err.max():.3f} N off"
    assert not good[2:].any()


def test_a_life_bit_declared_a_toggle_gives_the_model_on_the_true_time_base():
    got, status, want = _gateway(HeartbeatConfig("toggle", period_s=T), lambda k: k & 1)
    good = status == GOOD
    assert good[1:].mean() > 0.99  # read once per PLC cycle: every change is one cycle
    np.testing.assert_allclose(got[good], want[good], rtol=0, atol=1e-6)


def test_a_counter_gives_the_model_on_the_true_time_base_within_the_averaged_spacing():
    got, status, want = _gateway(None, lambda k: k & 0xFFFF)
    good = status == GOOD
    assert good.all()
    late = slice(1000, None)  # the averaged spacing has settled (1 % of a jittered start)
    np.testing.assert_allclose(got[late], want[late], rtol=0, atol=0.05)


# --- the clock alone ----------------------------------------------------------------------


def _counter(modulus: int = 1 << 16, register: int | None = None) -> SampleClock:
    return SampleClock("counter", modulus, T, register_values=register)


def _run(clock: SampleClock, reads: list[tuple[float, float]]) -> list[tuple[bool, float, bool]]:
    out = []
    for now, hb in reads:
        clock.tick(now, hb, False)
        out.append((clock.new, clock.dt, clock.vouched))
    return out


def _counting(clock: SampleClock, n: int, start: int = 0, t0: float = 0.0) -> float:
    for k in range(n):
        clock.tick(t0 + k * T, float((start + k) & 0xFFFF), False)
        assert clock.vouched
    return t0 + (n - 1) * T


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(1, MAX_GAP_PERIODS), min_size=1, max_size=60), st.integers(0, 65535))
def test_a_counter_read_on_time_is_vouched_for_every_step_it_counts(steps, start):
    """Reads when the samples were made, however many the gateway missed (a stall, an
    overrun; wraps included): dt = steps x T, vouched."""
    clock = _counter()
    now = _counting(clock, 20, start, 10.0)
    hb = (start + 19) & 0xFFFF
    for s in steps:
        now += s * T
        hb = (hb + s) & 0xFFFF
        clock.tick(now, float(hb), False)
        assert clock.vouched and clock.new
        assert clock.dt == pytest.approx(s * T, rel=1e-6)


LAG = 0.11  # the clock's lag bound: loop.heartbeat_timeout_s + loop.max_input_age_s


def _allowed(elapsed: float) -> int:
    """The most samples a count may say were made in ``elapsed`` of the gateway's time."""
    return math.floor((elapsed + LAG) * (1.0 + SPACING_TOLERANCE) / T)


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 65535), st.integers(0, 65535), st.integers(1, 200))
def test_a_count_is_vouched_for_exactly_when_the_time_allows_it(step, start, waited):
    """Any step on (a step back of ``b`` reads ``65536 - b`` on) after ``waited`` periods
    on the gateway's clock is integrated if and only if that many samples can have been
    made in the time plus the lag bound (the last sample read up to LAG after it was
    made) and it is under half the wrap (serial-number arithmetic; a whole wrap more never
    fits 0.47 s here)."""
    clock = _counter()
    assert clock.lag_bound_s == LAG
    now = _counting(clock, 20, start, 10.0)
    clock.tick(now + waited * T, float((start + 19 + step) & 0xFFFF), False)
    ok = step <= _allowed(waited * T) and 2 * step < 65536
    assert clock.new and clock.vouched == ok
    assert clock.dt == (pytest.approx(step * clock.plc_period_s) if ok else 0.0)


def test_the_lag_bound_is_the_watchdog_and_the_age_limit():
    comp = Compensator(config(period_s=T, heartbeat_timeout_s=0.2, stale_after_s=0.02))
    assert comp.clock.lag_bound_s == pytest.approx(0.22)


def test_a_restart_is_not_integrated_and_the_count_starts_afresh():
    clock = _counter()
    now = _counting(clock, 50, 30000)
    clock.tick(now + 2.0, 0.0, False)  # the PLC restarted: 0 again
    assert not clock.vouched and clock.dt == 0.0
    clock.tick(now + 2.0 + T, 1.0, False)
    assert clock.vouched and clock.dt == pytest.approx(T)


def test_a_jump_no_plc_can_have_made_in_the_time_is_not_integrated():
    clock = _counter()
    now = _counting(clock, 50)
    clock.tick(now + T, 49.0 + _allowed(T) + 1, False)  # more than 0.1665 s in 1 ms
    assert not clock.vouched
    clock.tick(now + 2 * T, 49.0 + _allowed(T) + 2, False)  # and on from there
    assert clock.vouched and clock.dt == pytest.approx(T)


def test_a_gap_the_counter_may_have_wrapped_in_is_not_integrated():
    """A 9-bit counter at 1 ms: ``k`` is known modulo 512; 600 samples in 0.6 s read 88 on,
    and 88 or 600 both fit (0.6 s + 0.11 s) x 1.5."""
    clock = _counter(512)
    now = _counting(clock, 50)
    clock.tick(now + 0.15, float((49 + 150) % 512), False)  # 150 on: 662 > 390 does not fit
    assert clock.vouched
    clock.tick(now + 0.75, float((49 + 750) % 512), False)  # 600 on, read as 88
    assert not clock.vouched


def test_a_plc_catching_up_its_start_is_not_a_jump():
    """The revert of the first clock: its check of the count since the first sample
    against the time since took the first sample's delay for none and refused the soft
    PLC catching up after its first chunk (8 samples in 1.5 ms, 7.5 ms ahead of that first
    sample's schedule); the gateway stayed cold for seconds. A PLC that falls behind by up
    to 0.1 s and catches up in bursts is integrated, every step its count."""
    rng = np.random.default_rng(11)
    clock = _counter()
    read, now, k_read = 0, 100.02, 0
    behind = 0.0095  # its first samples read 9.5 ms after they were made
    for i in range(3000):
        now += T * rng.uniform(0.7, 1.3)
        if i >= 30:  # then it catches up in bursts, falls behind again now and then
            if rng.random() < 0.01:
                behind = rng.uniform(0.0, 0.1)
            behind = max(0.0, behind - T * rng.uniform(0.0, 3.0))
        k_read = max(k_read, int((now - 100.0 - behind) / T))
        clock.tick(now, float(k_read & 0xFFFF), False)
        assert clock.vouched, (i, k_read, behind)
        read += clock.new
    assert read > 1000 and clock.resyncs == 0


def test_a_plc_catching_up_after_a_stall_of_its_own_is_vouched():
    clock = _counter()
    now = _counting(clock, 50)
    for j in range(1, 101):  # the PLC's replies held 100 ms: the same sample read again
        clock.tick(now + j * T, 49.0, False)
        assert not clock.new
    clock.tick(now + 101 * T, 49.0 + 101.0, False)  # it caught up
    assert clock.vouched and clock.dt == pytest.approx(101 * T)
    clock.tick(now + 102 * T, 49.0 + 101.0 + 60.0, False)  # and its backlog came late
    assert clock.vouched and clock.dt == pytest.approx(60 * T)


def test_a_value_outside_the_declared_modulus_is_no_count():
    clock = _counter(1000, register=1 << 16)
    now = _counting(clock, 20)
    clock.tick(now + T, 1000.0, False)
    assert not clock.vouched


def test_a_toggle_missed_is_unknowable():
    clock = SampleClock("toggle", 0, T, toggle_period_s=T)
    got = _run(clock, [(0.0, 0.0), (T, 1.0), (2 * T, 0.0), (3 * T, 0.0), (4 * T, 1.0)])
    assert got[1] == (True, T, True) and got[2] == (True, T, True)
    assert got[3] == (False, 0.0, True)  # one cycle unchanged: no room for two changes
    assert got[4] == (True, 0.0, False)  # 2 cycles after the last change: 1 or 3 samples
    clock.tick(6 * T, 1.0, False)  # 2 cycles unchanged: held, or changed twice
    assert (clock.new, clock.vouched) == (False, False)


def test_no_heartbeat_clock_is_the_gateways_own():
    clock = SampleClock("none", 0, T)
    clock.tick(0.0, 0.0, True)
    clock.tick(0.0013, 0.0, True)
    assert clock.vouched and clock.dt == pytest.approx(0.0013)
    clock.tick(0.0020, 0.0, False)
    assert not clock.new
    clock.tick(0.0020, 1.0, False)  # a new heartbeat value is a new sample too
    assert clock.new and clock.dt == pytest.approx(0.0007)


def test_an_outage_the_count_agrees_with_is_a_gap_not_a_jump():
    clock = _counter()
    now = _counting(clock, 50)
    clock.tick(now + 2.0, float((49 + 2000) & 0xFFFF), False)  # 2 s later, 2000 on
    assert clock.vouched and clock.dt == pytest.approx(2.0, rel=1e-6)


@pytest.mark.parametrize("effects", [{}, {"coulomb_load": {"mu1_per_n": 2e-5}}])
def test_the_warm_travel_is_where_two_dahl_states_agree_to_the_tolerance(effects):
    """Two chains started 2 F_R apart (either saturated) and stepped over the same travel
    agree to 0.05 N after warm_travel_m, not long before; also where the coefficient
    grows with the tension (a level well above the constant coefficient's)."""
    import dataclasses

    cfg = config(period_s=T)
    cfg = dataclasses.replace(cfg, friction=dataclasses.replace(cfg.friction, effects=effects))
    comp = Compensator(cfg)
    x_warm = warm_travel_m(comp.params, cfg.sensor.range_n)
    a, b = ChainStepper(comp.params, T), ChainStepper(comp.params, T)
    tension, out = np.full(CABLES, cfg.sensor.range_n), np.zeros(CABLES)
    for _ in range(2000):  # saturate them in opposite directions
        a.step(tension, np.full(CABLES, 0.1), out, T)
        b.step(tension, np.full(CABLES, -0.1), out, T)
    travelled, v = 0.0, np.full(CABLES, 0.05)
    while travelled < x_warm:
        oa, ob = np.zeros(CABLES), np.zeros(CABLES)
        a.step(tension, v, oa, T)
        b.step(tension, v, ob, T)
        travelled += 0.05 * T
        if travelled < 0.3 * x_warm:
            assert np.max(np.abs(oa - ob)) > 0.05  # not warm long before
    assert np.max(np.abs(oa - ob)) <= 0.05


# --- the declaration ----------------------------------------------------------------------


def _mapping(heartbeat: dict, register: str = "uint16") -> dict:
    from gateway.core.configtypes import read_yaml
    from gateway.core.resources import data_file

    data = read_yaml(data_file("default.yaml"))
    data["loop"]["heartbeat"] = heartbeat
    data["bus"]["modbus_tcp"]["registers"]["plc_heartbeat"] = {"address": 52, "type": register}
    return data


@pytest.mark.parametrize(
    ("heartbeat", "register", "says"),
    [
        ({"kind": "counter", "modulus": 65537}, "uint16", "modulus: 65537 is more than"),
        ({"kind": "counter", "modulus": 2**25}, "float32", "(float32) can count"),
        ({"kind": "toggle", "modulus": 2}, "uint16", "modulus: only for a counter"),
        ({"kind": "counter", "period_s": 0.001}, "uint16", "period_s: only for a toggle"),
        ({"kind": "tick"}, "uint16", "heartbeat.kind"),
    ],
)
def test_check_refuses_a_heartbeat_its_register_cannot_be(heartbeat, register, says):
    with pytest.raises(ConfigError, match=r"^cfg\.yaml: ") as err:
        config_from_mapping(_mapping(heartbeat, register), "cfg.yaml")
    assert says in str(err.value) and "\n" not in str(err.value)


def test_the_shipped_configs_declare_todays_counter():
    cfg = load_config()
    assert cfg.loop.heartbeat == HeartbeatConfig("counter", 65536)
    ok = config_from_mapping(_mapping({"kind": "counter", "modulus": 2**32}, "uint32"))
    assert ok.loop.heartbeat.modulus == 2**32
