"""The memory restructuring keeps every result: streamed forms equal the whole."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from gateway.core.heap import drop_clean_pages, return_large_frees
from gateway.diagnose import locate
from gateway.diagnose.forward import CableData
from gateway.recordings import reader as recording
from gateway.recordings.reader import Recording, read_recording, write_recording


def test_energy_map_cable_by_cable_equals_the_whole() -> None:
    rng = np.random.default_rng(3)
    n, m = 4000, 3
    t = np.arange(n) * 1e-3
    resid = rng.standard_normal((n, m))
    resid[1000:1200, 1] += 6.0  # a concentrated region on cable 2
    regime = rng.integers(0, len(locate.REGIMES), (n, m)).astype(np.int8)
    whole = locate.regions(t, resid, regime)
    emap = locate.EnergyMap(t)
    for i in range(m):
        emap.add(i + 1, resid[:, i], regime[:, i])
    parts = emap.regions()
    assert [(r.cable, r.start_s, r.end_s, r.regime) for r in parts] == [
        (r.cable, r.start_s, r.end_s, r.regime) for r in whole
    ]
    assert_allclose([r.share for r in parts], [r.share for r in whole], rtol=1e-12)
    fields, expect = emap.report_fields(parts), locate.report_fields(whole, resid, regime)
    for k, v in expect["regime_shares"].items():
        assert_allclose(fields["regime_shares"][k]["energy"], v["energy"], rtol=1e-12)
        assert fields["regime_shares"][k]["samples"] == pytest.approx(v["samples"], rel=1e-15)


def test_cable_data_recomputes_x_and_a_identically_after_release() -> None:
    t = np.cumsum(np.full(500, 1e-3))
    v = np.sin(3 * t)
    d = CableData(t, v, v, v, 0.0)
    x, a = d.x.copy(), d.a.copy()
    d.release()
    assert d._x is None and d._a is None
    assert_array_equal(d.x, x)
    assert_array_equal(d.a, a)
    given = CableData(t, v, v, v, 0.0, None, x, a)
    given.release()  # given arrays are kept
    assert given.x is x


def test_reader_grows_its_arrays_over_many_chunks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(recording, "CHUNK_ROWS", 7)
    monkeypatch.setattr(recording._Columns, "FIRST_ROWS", 5)
    n = 200
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(1)
    rec = Recording(
        t=t,
        velocity=rng.standard_normal((n, 2)),
        tension_sensor=rng.standard_normal((n, 2)) + 100,
        tension_platform=rng.standard_normal((n, 2)) + 100,
        mass=np.full(n, 40.0),
        extra={"temperature": np.linspace(20, 21, n)},
    )
    path = tmp_path / "r.csv"
    write_recording(path, rec)
    back = read_recording(path)
    assert back.samples == n and back.t.shape == (n,) and back.velocity.shape == (n, 2)
    assert_allclose(back.tension_sensor, rec.tension_sensor, rtol=1e-9)
    assert_allclose(back.extra["temperature"], rec.extra["temperature"], rtol=1e-9)
    assert back.mass is not None and back.mass.shape == (n,)
    assert back.length is None and back.pose is None


def test_dropping_llvms_clean_pages_keeps_the_kernels_working() -> None:
    """LLVM's pages are given back (those that are copies of the file only); a kernel run
    after it, and a kernel loaded after it, give the same numbers as before."""
    from gateway.model.effects.forms import lowpass

    t = np.arange(2000) * 1e-3
    y = np.sin(7 * t)[:, None]
    before = lowpass(t, y, 0.01)
    drop_clean_pages()
    assert drop_clean_pages() >= 0
    np.testing.assert_array_equal(lowpass(t, y, 0.01), before)
    assert drop_clean_pages(("no-such-library",)) == 0


def test_return_large_frees_is_idempotent() -> None:
    first = return_large_frees()
    assert return_large_frees() == first  # a second call changes nothing


@pytest.mark.parametrize(
    "effects",
    [
        {
            "inertia": {"m_eff_kg": 0.3},
            "lowpass": {"tau_s": [0.0, 0.01] * 4},
            "delay": {"d_s": 0.004},
        },
        {"mass_change": {"q_kg_s": 0.01}, "offset": {"c_n": [0.3, -0.2] * 4}},
    ],
)
def test_reading_batch_equals_the_whole_run_formula(effects: dict) -> None:
    from evaluation.scenarios import Scenario, plant_config
    from sim_plc import plant

    sc = Scenario("x", effects, cables=8, seconds=2.0, plant=True, seed=3)
    model = plant.PlantModel(plant_config(sc), None)
    t = np.arange(2000) * model.sim.period_s
    sp = plant._recording_setpoints(model, t, None)
    noise = np.random.default_rng(model.sim.seed).standard_normal((t.size, model.cables))
    whole = model.reading(model.adc(plant.sensor_batch(model, sp, noise)))
    chunked = plant.reading_batch(model, sp, np.random.default_rng(model.sim.seed))
    assert_array_equal(chunked, whole)


def _with_lengths_and_pose(n: int) -> Recording:
    rng = np.random.default_rng(5)
    return Recording(
        t=np.arange(n) * 1e-3,
        velocity=rng.standard_normal((n, 2)),
        tension_sensor=rng.standard_normal((n, 2)) + 100,
        tension_platform=rng.standard_normal((n, 2)) + 100,
        length=rng.standard_normal((n, 2)) + 2,
        pose=rng.standard_normal((n, 6)),
        mass=np.full(n, 40.0),
    )


def test_reader_keeps_the_first_row_only_where_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(recording, "CHUNK_ROWS", 7)
    path = tmp_path / "r.csv"
    write_recording(path, _with_lengths_and_pose(100))
    whole = read_recording(path)
    head = read_recording(path, first_row_only=("length", "pose", "mass"))
    assert head.length is not None and head.pose is not None and head.mass is not None
    assert head.length.shape == (1, 2) and head.pose.shape == (1, 6) and head.mass.shape == (1,)
    assert_array_equal(head.length, whole.length[:1])  # type: ignore[index]
    assert_array_equal(head.pose, whole.pose[:1])  # type: ignore[index]
    for name in ("t", "velocity", "tension_sensor", "tension_platform"):
        assert_array_equal(getattr(head, name), getattr(whole, name))
    with pytest.raises(ValueError, match="first_row_only"):
        read_recording(path, first_row_only=("velocity",))


def test_reader_refuses_a_bad_value_in_a_column_read_for_its_first_row(tmp_path: Path) -> None:
    from gateway.errors import RecordingError

    path = tmp_path / "r.csv"
    write_recording(path, _with_lengths_and_pose(50))
    lines = path.read_text().splitlines()
    names = next(x for x in lines if not x.startswith("#")).split(",")
    at = len(lines) - 10
    fields = lines[at].split(",")
    fields[names.index("length_2")] = "1e300"
    lines[at] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordingError, match="length_2"):
        read_recording(path, first_row_only=("length",))


def test_mass_sensitivity_knots_read_per_cable_equal_the_whole() -> None:
    from gateway.diagnose.pose_statics import MassSensitivity
    from gateway.diagnose.prepare import cable_data, finite_rows

    rec = _with_lengths_and_pose(300)
    rec.tension_sensor[17, 1] = np.nan  # a row finite_rows drops
    knots = MassSensitivity(rec.t[::37].copy(), np.random.default_rng(2).random((9, 2)))
    full = knots.full(rec.t)
    assert full.shape == (300, 2)
    sub, tp, lazy = finite_rows(rec, rec.tension_platform, knots)  # type: ignore[arg-type]
    assert lazy is knots and sub.samples == 299
    _, _, eager = finite_rows(rec, rec.tension_platform, full)  # type: ignore[arg-type]
    for i, d in enumerate(cable_data(sub, tp, lazy)):
        assert_array_equal(d.dtp_dm, eager[:, i])  # type: ignore[index]
        d.release()
        assert d._dm is None  # computed per cable when read, dropped after
        assert_array_equal(d.dtp_dm, eager[:, i])  # type: ignore[index]


def test_chain_batch_in_row_blocks_equals_one_block(monkeypatch) -> None:
    """simulate/compensate run the kernel in row blocks (the travel array stays small);
    the friction state and the previous velocity carried across give the same bits."""
    from gateway.model import chain_runs
    from sim_plc.plant import PlantModel
    from tests.plant_helpers import make_config

    params = PlantModel(make_config()).params
    rng = np.random.default_rng(3)
    n, m = 5003, params.cables
    t = np.cumsum(rng.uniform(0.0008, 0.0012, n))
    v = np.cumsum(rng.normal(0, 0.002, (n, m)), axis=0)
    tp = 300 + np.cumsum(rng.normal(0, 1, (n, m)), axis=0)
    whole = (
        chain_runs.run(params, "simulate", tp, v, t),
        chain_runs.run(params, "compensate", tp, v, t),
    )
    monkeypatch.setattr(chain_runs, "BATCH_ROWS", 97)
    blocks = (
        chain_runs.run(params, "simulate", tp, v, t),
        chain_runs.run(params, "compensate", tp, v, t),
    )
    np.testing.assert_array_equal(blocks[0], whole[0])
    np.testing.assert_array_equal(blocks[1], whole[1])
