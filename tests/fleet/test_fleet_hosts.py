"""How the fleet scales past one machine: ``fleet --scheduler`` against a ``dask
scheduler`` whose workers are on other hosts. Here the hosts are network namespaces this
test creates (a scheduler's and two workers', joined by veth pairs on private /24s, nothing
of the machine's own network touched): the workers reach the scheduler only over those
links, read the recordings from the shared file system, and each report is still the bytes
``diagnose`` writes alone. The table's ``worker`` column says which host ran what: both
hosts did. Skipped when not root or without ``ip``."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.dask_helpers import dask_hosts
from tests.fleet.fleet_helpers import check_fleet_output, fleet_on_scheduler, single_reports


@pytest.mark.long
def test_fleet_against_workers_on_two_other_hosts(recordings: list[Path], tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("iproute2 'ip' not installed")
    out = tmp_path / "fleet"
    with dask_hosts(tmp_path, hosts=2) as (in_scheduler_ns, address, hosts):
        assert address.startswith("tcp://10.213.1.1:")
        fleet_on_scheduler(recordings, out, address, tuple(in_scheduler_ns))
    workers = {r["worker"] for r in pq.read_table(out / "fleet.parquet").to_pylist()}
    ran_on = {w.removeprefix("tcp://").rsplit(":", 1)[0] for w in workers if w}
    assert ran_on == set(hosts), workers  # both hosts took recordings, no other did
    check_fleet_output(out, recordings, single_reports(recordings, tmp_path))
