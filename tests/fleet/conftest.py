"""The fleet tests' recordings, made once per module that uses them."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fleet.fleet_helpers import make_recordings


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three short recordings of robots hiding different effects (Parquet and CSV.gz, one
    in a Hive tree) and one broken file."""
    return make_recordings(tmp_path_factory)
