"""A fleet task that cannot fit its worker is refused before it is loaded (issue 30 item
6): its memory told from the header and size (gateway/fleet/sizing.py)."""

from __future__ import annotations

import numpy as np

from gateway.fleet import sizing
from gateway.recordings.reader import Recording, write_recording


def _rec(n: int, m: int) -> Recording:
    rng = np.random.default_rng(0)
    return Recording(
        t=np.arange(n) * 1e-3,
        velocity=rng.normal(0, 0.1, (n, m)),
        tension_sensor=rng.uniform(100, 200, (n, m)),
        tension_platform=rng.uniform(100, 200, (n, m)),
        metadata={"robot": "r"},
    )


def test_rows_and_columns_from_the_header_and_size(tmp_path):
    rec = _rec(20_000, 4)
    for suffix in (".parquet", ".csv", ".csv.gz"):
        path = tmp_path / f"r{suffix}"
        write_recording(path, rec)
        found = sizing.estimate(path)
        assert found is not None and found.columns == 13, (suffix, found)
        if suffix == ".parquet":
            assert found.exact and found.rows == 20_000
        else:  # estimated from the first MiB: within 25 %
            assert 15_000 <= found.rows <= 25_000, (suffix, found)


def test_a_recording_over_the_budget_is_refused_in_one_line(tmp_path):
    path = tmp_path / "big.csv.gz"
    write_recording(path, _rec(20_000, 4))
    need = sizing.estimate(path).need_bytes  # type: ignore[union-attr]
    assert sizing.refusal(path, need + 1) is None
    why = sizing.refusal(path, need - (1 << 20))
    assert why is not None and "\n" not in why and why.startswith(f"{path}: not sent to a worker")
    assert "rows x 13 columns" in why


def test_damage_is_left_to_the_diagnosis(tmp_path):
    path = tmp_path / "bad.parquet"
    path.write_bytes(b"PAR1 nothing PAR1")
    assert sizing.estimate(path) is None and sizing.refusal(path, 1) is None
