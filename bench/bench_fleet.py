"""A fleet's recordings diagnosed three ways, side by side: sequential ``diagnose`` runs,
``fleet`` on a LocalCluster of 2 workers, ``fleet`` against a separately started ``dask
scheduler`` with 2 ``dask worker`` processes on 127.0.0.1.

``python -m bench fleet`` (``BENCH_FLEET_SECONDS``, default 120 s per recording;
``BENCH_FLEET_COUNT``, default 12): the recordings are made by ``cdpr-gateway record``
from config/calibrate/*.yaml (each hides one effect), two robots per config (seeds 1, 2),
as Parquet. Printed: wall time of each way, and whether every report of the two fleet
runs is byte for byte the report of the sequential ``diagnose`` run. Figures only.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.dask_helpers import dask_cluster

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "config" / "default.yaml"


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "gateway.cli", *args]


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # as make test: the same numbers everywhere
    return env


def _record(out: Path, count: int, seconds: float) -> list[Path]:
    configs = sorted((ROOT / "config" / "calibrate").glob("*.yaml"))
    paths = []
    for i in range(count):
        cfg = configs[i % len(configs)]
        seed = 1 + i // len(configs)
        path = out / f"{cfg.stem}-{seed}.parquet"
        subprocess.run(
            _cli(
                "record",
                "--config",
                str(cfg),
                "--seconds",
                f"{seconds:g}",
                "--out",
                str(path),
                "--seed",
                str(seed),
                "--quiet",
                "--robot",
                f"{cfg.stem}-{seed}",
            ),
            check=True,
            env=_env(),
        )
        paths.append(path)
    return paths


def _sequential(paths: list[Path], out: Path) -> tuple[float, dict[str, bytes]]:
    reports = {}
    t0 = time.perf_counter()
    for i, path in enumerate(paths):
        rep = out / f"{i}.json"
        cmd = _cli("diagnose", str(path), "--model", str(MODEL), "--json", str(rep), "--quiet")
        subprocess.run(cmd, check=True, env=_env(), stdout=subprocess.DEVNULL)
        reports[str(path.resolve())] = rep.read_bytes()
    return time.perf_counter() - t0, reports


def _fleet(paths: list[Path], out: Path, *extra: str) -> tuple[float, dict[str, bytes], str]:
    """Wall time, the reports by recording, the summary line."""
    t0 = time.perf_counter()
    res = subprocess.run(
        _cli(
            "fleet", *map(str, paths), "--model", str(MODEL), "--out", str(out), "--quiet", *extra
        ),
        env=_env(),
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(res.stderr)
    import pyarrow.parquet as pq

    rows = pq.read_table(out / "fleet.parquet", columns=["recording", "report"]).to_pylist()
    reports = {
        r["recording"]: (out / "reports" / r["report"]).read_bytes() for r in rows if r["report"]
    }
    return wall, reports, res.stdout.strip().splitlines()[0]


def run() -> None:
    seconds = float(os.environ.get("BENCH_FLEET_SECONDS", "120"))
    count = int(os.environ.get("BENCH_FLEET_COUNT", "12"))
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as name:
        tmp = Path(name)
        t0 = time.perf_counter()
        paths = _record(tmp, count, seconds)
        print(
            f"  {count} recordings of {seconds:g} s (record, Parquet, "
            f"{sum(p.stat().st_size for p in paths) / 1e6:.0f} MB) in "
            f"{time.perf_counter() - t0:.0f} s; load {os.getloadavg()[0]:.2f}"
        )
        seq, single = _sequential(paths, tmp)
        print(
            f"  sequential diagnose, one after another: {seq:.1f} s; load {os.getloadavg()[0]:.2f}"
        )
        local, local_reports, _ = _fleet(paths, tmp / "local", "--workers", "2")
        print(
            f"  fleet, LocalCluster(2 workers):           {local:.1f} s "
            f"({seq / local:.2f}x); load {os.getloadavg()[0]:.2f}"
        )
        with dask_cluster(tmp, workers=2) as address:
            ext, ext_reports, _ = _fleet(paths, tmp / "ext", "--scheduler", address)
        print(
            f"  fleet, dask scheduler + 2 dask workers:    {ext:.1f} s "
            f"({seq / ext:.2f}x); load {os.getloadavg()[0]:.2f}"
        )
        same_local = local_reports == single
        same_ext = ext_reports == single
        print(
            f"  reports byte-identical to diagnose alone: LocalCluster {same_local}, "
            f"scheduler {same_ext} ({len(single)} reports)"
        )
        verdicts = {
            Path(k).stem: ",".join(f["effect"] for f in json.loads(v)["findings"]) or "none"
            for k, v in sorted(single.items())
        }
        print("  verdicts: " + "; ".join(f"{k} {v}" for k, v in verdicts.items()))
