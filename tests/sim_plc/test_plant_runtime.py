"""PlcRuntime (real time and stepped) and the sim-plc command's lifecycle."""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from sim_plc import cli as sim_cli
from sim_plc.image import ProcessImage
from sim_plc.plant import Plant
from sim_plc.runtime import PlcRuntime
from tests.plant_helpers import REPLICATE_YAML, ROOT, make_config


class CountingPlant:
    def __init__(self) -> None:
        self.steps = 0

    def step(self, image: ProcessImage | None = None) -> None:
        self.steps += 1
        if image is not None:
            image.plc_heartbeat = (image.plc_heartbeat + 1) & 0xFFFF


def test_step_mode_advances_exactly_n_cycles() -> None:
    plant, image = CountingPlant(), ProcessImage(8)
    rt = PlcRuntime(plant, image)
    rt.step(25)
    assert plant.steps == 25 and rt.stats.cycles == 25 and image.plc_heartbeat == 25


def test_real_time_start_stop_is_safe_twice() -> None:
    plant, image = Plant(make_config()), ProcessImage(8)
    rt = PlcRuntime(plant, image, period_s=0.001)
    rt.stop()  # before start: harmless
    rt.start()
    rt.start()  # already running: no second thread
    deadline = time.monotonic() + 10.0
    while image.plc_heartbeat < 50 and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(RuntimeError):
        rt.step(1)
    rt.stop()
    rt.stop()
    assert not rt.running and rt.error is None
    assert image.plc_heartbeat >= 50
    assert rt.stats.cycles == image.plc_heartbeat
    assert image.time_s == pytest.approx((rt.stats.cycles - 1) * 0.001)
    beat = image.plc_heartbeat
    time.sleep(0.02)
    assert image.plc_heartbeat == beat  # stopped means stopped


def test_missed_deadlines_are_counted_and_skipped() -> None:
    now = [0.0]

    class SlowPlant(CountingPlant):
        def step(self, image=None) -> None:
            super().step(image)
            now[0] += 0.0035 if self.steps == 3 else 0.0001  # cycle 3 overruns

    plant = SlowPlant()
    rt = PlcRuntime(plant, ProcessImage(8), 0.001, clock=lambda: now[0], max_catch_up=0)

    def fake_sleep(dt: float) -> None:
        now[0] += dt
        if plant.steps >= 10:
            rt._stop.set()

    rt._sleep = fake_sleep
    rt._run()
    assert plant.steps == 10
    assert rt.stats.missed == 2  # 3.5 ms late start of cycle 4: 2 whole periods skipped


def test_late_cycles_are_caught_up_back_to_back() -> None:
    now, sleeps = [0.0], []

    class SlowPlant(CountingPlant):
        def step(self, image=None) -> None:
            super().step(image)
            now[0] += 0.0035 if self.steps == 3 else 0.0001

    plant = SlowPlant()
    rt = PlcRuntime(plant, ProcessImage(8), 0.001, clock=lambda: now[0])

    def fake_sleep(dt: float) -> None:
        sleeps.append(plant.steps)
        now[0] += dt
        if plant.steps >= 10:
            rt._stop.set()

    rt._sleep = fake_sleep
    rt._run()
    assert rt.stats.missed == 0 and rt.stats.late == 2
    assert 4 not in sleeps and 5 not in sleeps  # cycles 4 and 5 ran without waiting
    assert now[0] == pytest.approx(0.010, abs=2e-4)  # 10 cycles in 10 ms of plant clock


def test_runtime_keeps_the_error_that_ended_it() -> None:
    class Broken:
        def step(self, image=None) -> None:
            raise ValueError("boom")

    rt = PlcRuntime(Broken(), ProcessImage(8))
    rt.start()
    deadline = time.monotonic() + 5.0
    while rt.running and time.monotonic() < deadline:
        time.sleep(0.01)
    rt.stop()
    assert isinstance(rt.error, ValueError)


def test_sim_plc_serves_then_ends_cleanly(monkeypatch, capsys) -> None:
    served = {}

    class FakeServer:
        def stop(self) -> None:
            served["stopped"] = True

    def fake_server(cfg, image, bus, host, port, tls=None):
        served["image"], served["bus"] = image, bus
        return FakeServer(), f"{bus} on {host}:{port}"

    monkeypatch.setattr(sim_cli, "_server", fake_server)
    args = argparse.Namespace(
        config=str(REPLICATE_YAML), host="127.0.0.1", port=0, bus=None, seconds=0.3
    )
    assert sim_cli.run_command("sim-plc", args) == 0
    out = capsys.readouterr()
    assert "sim-plc: serving modbus_tcp on 127.0.0.1:0" in out.out
    assert served["stopped"] and served["bus"] == "modbus_tcp"
    assert served["image"].plc_heartbeat > 10
    assert np.any(served["image"].raw_counts > 0)
    assert "stopped after" in out.err


@pytest.mark.loopback
def test_sim_plc_subprocess_serves_modbus_and_stops_on_sigterm() -> None:
    pytest.importorskip("sim_plc.modbus_server")
    from pymodbus.client import ModbusTcpClient

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [
        sys.executable,
        "-m",
        "gateway.cli",
        "sim-plc",
        "--config",
        str(REPLICATE_YAML),
        "--host",
        "127.0.0.1",
        "--port",
        "0",
    ]
    with subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as proc:
        try:
            line = proc.stdout.readline() if proc.stdout else ""
            match = re.match(r"sim-plc: serving modbus_tcp on ([\d.]+):(\d+)", line)
            assert match, line
            client = ModbusTcpClient(match.group(1), port=int(match.group(2)))
            assert client.connect()
            first = client.read_holding_registers(52, count=1).registers[0]
            time.sleep(0.2)
            regs = client.read_holding_registers(0, count=53).registers
            client.close()
            assert regs[52] != first  # the heartbeat advances
            assert all(0 < r < 27648 for r in regs[:8])  # raw counts of 20..490 N
        finally:
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "stopped after" in err


def test_plant_with_chunks_from_a_worker_matches_the_in_process_plant() -> None:
    """Same samples whether chunks are prepared here or by the worker, across chunk
    boundaries and a reset; the worker has them ready (few waits)."""
    from numpy.testing import assert_allclose, assert_array_equal

    from sim_plc.chunk_worker import ChunkWorker

    cfg = make_config()
    ref, fed = Plant(cfg, chunk=40), Plant(cfg, chunk=40)
    with ChunkWorker(fed.model.cfg, fed.model.sim, fed.chunk) as worker:
        fed.use_chunks(worker)
        for rounds in (130, 90):
            got, want = [], []
            for _ in range(rounds):
                ref.step()
                fed.step()
                got.append(fed.analog.copy())
                want.append(ref.analog.copy())
                assert_array_equal(fed.counts, ref.counts)
            assert_allclose(np.array(got), np.array(want), rtol=1e-12, atol=1e-9)
            ref.reset()
            fed.reset()
        assert worker.waits <= 10  # start-up and catching up back to back, not every get
    with pytest.raises(Exception, match="not started or closed"):
        worker.get(0)


def test_sim_plc_realtime_flag_reports_one_line(monkeypatch, capsys, tmp_path) -> None:
    """--realtime applies loop.realtime (here SCHED_OTHER, which any process may) and
    says so in one line; --chunks-in-process serves without the worker."""
    import yaml

    data = yaml.safe_load(REPLICATE_YAML.read_text())
    data.setdefault("loop", {})["realtime"] = {
        "policy": "other",
        "priority": 0,
        "lock_memory": False,
        "gc_off": False,
        "cpu_dma_latency_us": None,
    }
    path = tmp_path / "rt.yaml"
    path.write_text(yaml.safe_dump(data))

    class FakeServer:
        def stop(self) -> None:
            pass

    monkeypatch.setattr(sim_cli, "_server", lambda *a, **k: (FakeServer(), "fake on x:0"))
    args = argparse.Namespace(
        config=str(path),
        host="127.0.0.1",
        port=0,
        bus=None,
        seconds=0.2,
        realtime=True,
        chunks_in_process=True,
    )
    assert sim_cli.run_command("sim-plc", args) == 0
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("sim-plc: real-time")]
    assert lines == ["sim-plc: real-time: applied SCHED_OTHER; refused nothing"]


def test_sim_plc_fifo_with_the_chunk_worker_serves_then_stops(monkeypatch, capsys, tmp_path):
    """SCHED_FIFO where permitted (root here): the worker is put at FIFO 1 and serving
    goes on; without the permission both are refused, named, and serving goes on too."""
    import yaml

    data = yaml.safe_load(REPLICATE_YAML.read_text())
    data.setdefault("loop", {})["realtime"] = {
        "lock_memory": False,
        "gc_off": False,
        "cpu_dma_latency_us": None,
    }
    path = tmp_path / "rt.yaml"
    path.write_text(yaml.safe_dump(data))

    class FakeServer:
        def stop(self) -> None:
            pass

    monkeypatch.setattr(sim_cli, "_server", lambda *a, **k: (FakeServer(), "fake on x:0"))
    args = argparse.Namespace(
        config=str(path),
        host="127.0.0.1",
        port=0,
        bus=None,
        seconds=0.3,
        realtime=True,
        chunks_in_process=False,
    )
    before = os.sched_getscheduler(0)
    assert sim_cli.run_command("sim-plc", args) == 0
    assert os.sched_getscheduler(0) == before  # undone at the end (in process)
    err = capsys.readouterr().err
    line = next(x for x in err.splitlines() if x.startswith("sim-plc: real-time"))
    assert (
        "SCHED_FIFO priority 50, chunk worker SCHED_FIFO priority 1" in line
        or "refused SCHED_FIFO priority 50: not permitted" in line
    ), line
    assert "stopped after" in err
