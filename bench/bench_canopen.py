"""CANopen on python-can's virtual bus, real time at 1 kHz in one process.

The soft PLC's thread sends SYNC + analog TPDOs + setpoint PDOs every 1 ms; the gateway
side (this thread, as the loop would) does driver.read_into -> driver.write_from for
``cycles`` complete sets. Prints: cycles, PLC SYNC periods skipped (overruns) %, SYNC
sets the gateway missed %, read timeouts, round trip p50/p99 (SYNC sent -> all per-cycle
PDOs received), read-call wait p50/p99, CPU % of this process. No assertions on time.
"""

from __future__ import annotations

import dataclasses
import resource
import sys
import time

import can
import numpy as np

from drivers.base import Inputs, Outputs
from drivers.canopen import CanopenDriver
from gateway.core.config import load_config
from gateway.errors import DriverTimeoutError
from sim_plc.canopen_nodes import CanopenPlc
from sim_plc.image import ProcessImage


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _run_once(cycles: int) -> None:
    cfg = load_config()
    channel = f"bench-canopen-{time.monotonic_ns()}"
    can_cfg = dataclasses.replace(cfg.bus.canopen, interface="virtual", channel=channel)
    cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, canopen=can_cfg))
    image = ProcessImage(cfg.cables)
    image.raw_counts[:] = np.arange(cfg.cables) * 3000
    plc = CanopenPlc(cfg, image, lambda: can.Bus(interface="virtual", channel=channel))
    gw_bus = can.Bus(interface="virtual", channel=channel)
    driver = CanopenDriver(cfg, bus=gw_bus)
    inputs, outputs = Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
    roundtrip = np.zeros(cycles)
    wait = np.zeros(cycles)
    timeouts = done = 0
    driver.open()
    plc.start(realtime=True)
    wall0, cpu0 = time.perf_counter(), _cpu_s()
    try:
        for _ in range(cycles * 3):  # bounded even if every read times out
            if done == cycles:
                break
            t0 = time.perf_counter()
            try:
                driver.read_into(inputs)
            except DriverTimeoutError:
                timeouts += 1
                continue
            wait[done] = time.perf_counter() - t0
            roundtrip[done] = time.time() - driver.last_sync_timestamp
            outputs.tension_corrected_n[:] = inputs.tension_raw_n
            outputs.gateway_heartbeat = (outputs.gateway_heartbeat + 1) & 0xFFFF
            driver.write_from(outputs)
            done += 1
    finally:
        wall, cpu = time.perf_counter() - wall0, _cpu_s() - cpu0
        plc.stop()
        driver.close()
        gw_bus.shutdown()
    rt, wt = roundtrip[:done] * 1e6, wait[:done] * 1e6
    syncs = max(plc.cycles, 1)
    periods = max(plc.cycles + plc.overruns, 1)
    print(f"canopen.virtual  {done} cycles in {wall:.2f} s ({syncs} SYNCs sent)")
    print(
        f"  PLC SYNC periods skipped {100 * plc.overruns / periods:.2f} %   gateway missed sets "
        f"{100 * (driver.syncs - driver.sets) / max(driver.syncs, 1):.2f} %   "
        f"read timeouts {timeouts}"
    )
    if done:
        print(
            f"  round trip SYNC -> all PDOs: p50 {np.percentile(rt, 50):.0f} us  "
            f"p99 {np.percentile(rt, 99):.0f} us   read wait p50 {np.percentile(wt, 50):.0f} us"
            f"  p99 {np.percentile(wt, 99):.0f} us"
        )
    print(
        f"  CPU {100 * cpu / wall:.0f} % of one core (PLC thread + gateway + virtual bus), "
        f"gateway frames into the image {plc.gateway_frames}"
    )


def run(cycles: int = 5000) -> None:
    """Twice: Python's default GIL switch interval (5 ms), then 0.2 ms. The PLC thread and
    the gateway share one interpreter here; the interval bounds how long one waits for
    the GIL while the other runs."""
    default = sys.getswitchinterval()
    for interval in (default, 2e-4):
        print(f"-- sys.setswitchinterval({interval:g})")
        sys.setswitchinterval(interval)
        try:
            _run_once(cycles)
        finally:
            sys.setswitchinterval(default)


if __name__ == "__main__":
    run()
