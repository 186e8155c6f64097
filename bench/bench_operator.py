"""The default config as an operator runs it: ``cdpr-gateway sim-plc`` and ``cdpr-gateway
run`` as plain processes (no chrt, no --realtime for the soft PLC), side by side in one
run: the shipped config (``loop.realtime`` on by default: the gateway tries it) and the
same file with ``realtime: {enabled: false}``, alternating.

``python -m bench operator`` (``BENCH_SECONDS``, default 30 s per run; ``BENCH_PAIRS``,
default 2 pairs). Per run, from the gateway's own metrics scraped 1 s before it ends and
its stop line: cycles with data (``cycle_seconds_count``), overruns and their share, the
cycle-start lateness p99.9 as a bucket bound (``jitter_seconds``), and the gateway's RSS
(``process_resident_memory_bytes``) with its real-time line. Goals: overruns
<= 0.1 % and lateness p99.9 <= 200 us with the defaults, <= 0.05 % with the real-time
settings; RSS <= 200 MB. Figures only: nothing here asserts on time.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import yaml

from bench import stop_process
from gateway.core.config import DEFAULT_CONFIG_PATH


def _scrape(port: int) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        text = reply.read().decode()
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def _p999_bound(m: dict[str, float], name: str) -> str:
    total = m.get(f'{name}_bucket{{le="+Inf"}}', 0.0)
    if not total:
        return "n/a"
    bounds = sorted(
        (float(k.split('le="')[1].rstrip('"}')), v)
        for k, v in m.items()
        if k.startswith(f"{name}_bucket") and "+Inf" not in k
    )
    for le, count in bounds:
        if count >= 0.999 * total:
            return f"<= {le * 1e6:.0f} us"
    return f"> {bounds[-1][0] * 1e6:.0f} us"


def _one(config: Path, seconds: float, label: str) -> None:
    plc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "sim-plc", "--config", str(config), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    gw = None
    try:
        assert plc.stdout is not None
        port = int(re.search(r":(\d+)\s*$", plc.stdout.readline()).group(1))  # type: ignore[union-attr]
        data = yaml.safe_load(config.read_text())
        data["bus"]["modbus_tcp"]["port"] = port
        data["metrics"]["port"] = 0
        run_cfg = config.with_name(f"run-{label}.yaml")
        run_cfg.write_text(yaml.safe_dump(data))
        argv = ["run", "--config", str(run_cfg), "--seconds", str(seconds)]
        gw = subprocess.Popen(
            [sys.executable, "-m", "gateway", *argv], stderr=subprocess.PIPE, text=True
        )
        assert gw.stderr is not None
        lines, mport = [], None
        for line in gw.stderr:
            lines.append(line)
            found = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/", line)
            if found:
                mport = int(found.group(1))
                break
        time.sleep(max(seconds - 1.0, 0.5))
        m = _scrape(mport) if mport else {}
        lines += gw.stderr.readlines()
        gw.wait(timeout=60)
        rt = next((ln.split(": ", 1)[1].strip() for ln in lines if ": real-time: " in ln), "?")
        cycles = m.get("cdpr_gateway_cycle_seconds_count", 0.0)
        over = m.get("cdpr_gateway_overruns_total", 0.0)
        share = 100.0 * over / cycles if cycles else float("nan")
        rss = m.get("process_resident_memory_bytes", 0.0) / 1e6
        print(
            f"  {label:9} cycles {cycles:7.0f}  overruns {over:5.0f} ({share:.3f} %)  "
            f"lateness p99.9 {_p999_bound(m, 'cdpr_gateway_jitter_seconds'):>10}  "
            f"RSS {rss:5.0f} MB",
            flush=True,
        )
        print(f"            {rt}", flush=True)
    finally:
        if gw is not None:
            stop_process(gw)
        stop_process(plc)


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "30"))
    pairs = int(os.environ.get("BENCH_PAIRS", "2"))
    with tempfile.TemporaryDirectory() as tmp:
        shipped = Path(tmp) / "default.yaml"
        shipped.write_text(DEFAULT_CONFIG_PATH.read_text())
        data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
        data["loop"]["realtime"] = {"enabled": False}
        off = Path(tmp) / "rt-off.yaml"
        off.write_text(yaml.safe_dump(data))
        print(
            f"  {seconds:g} s per run, {pairs} pairs, sim-plc and run as plain processes "
            f"(uid {os.getuid()}), alternating",
            flush=True,
        )
        for _ in range(pairs):
            _one(shipped, seconds, "shipped")
            _one(off, seconds, "RT off")
