"""Config: defaults load; unknown keys and bad values are errors naming file and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.core.config import DEFAULT_CONFIG_PATH, load_config, load_friction
from gateway.errors import ConfigError

GEOMETRY = """
geometry:
  frame_anchors_m: [[0, 0, 1]]
  platform_anchors_m: [[0, 0, 0]]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


def test_default_config_is_the_paper_stand_in() -> None:
    cfg = load_config(DEFAULT_CONFIG_PATH)
    assert cfg.cables == 8
    assert len(cfg.friction.pulleys) == 3
    assert cfg.friction.sigma_n_m == 500.0
    assert cfg.sensor.range_n == 500.0
    assert cfg.metrics.host == "127.0.0.1"
    assert cfg.bus.modbus_tcp.registers.raw_tensions.format == "s7_analog"
    assert cfg.bus.modbus_tcp.registers.corrected_tensions.end == 116


@pytest.mark.parametrize(
    ("snippet", "message"),
    [
        ("friction:\n  sigma: 5\n", r"cfg.yaml: friction.sigma: unknown key"),
        ("friction:\n  pulleys:\n    - {wrap_deg: 90, mu: 0.01, r: 1}\n", r"pulleys\[0\].r"),
        ("friction:\n  model: lugre\n", r"friction.model: 'lugre' is not one of"),
        (
            "friction:\n  sigma_n_m: -1\n",
            r"friction\.sigma_n_m: must be in 1e-06\.\.1e\+09, got -1",
        ),
        ("loop:\n  period_s: fast\n", r"loop.period_s: expected a number, got 'fast'"),
        ("bus:\n  modbus_tcp:\n    port: 70000\n", r"bus\.modbus_tcp\.port: must be in 1\.\.65535"),
        ("metrics:\n  enabled: 1\n", r"metrics.enabled: expected true or false"),
        ("sensors: {}\n", r"sensors: unknown key"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path: Path, snippet: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, GEOMETRY + snippet))


def test_missing_geometry_and_mismatched_anchors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="geometry: required key is missing"):
        load_config(write(tmp_path, "friction: {}\n"))
    bad = "geometry:\n  frame_anchors_m: [[0,0,1],[1,0,1]]\n  platform_anchors_m: [[0,0,0]]\n"
    with pytest.raises(ConfigError, match=r"geometry\.frame_anchors_m: has 2 entries but"):
        load_config(write(tmp_path, bad))
    with pytest.raises(ConfigError, match=r"frame_anchors_m\[0\]: expected 3 items"):
        load_config(write(tmp_path, "geometry:\n  frame_anchors_m: [[0,0]]\n"))


def test_yaml_syntax_error_names_line(tmp_path: Path) -> None:
    text = "friction:\n  model: dahl\n  sigma_n_m: : 5\n"
    with pytest.raises(ConfigError, match=r"cfg.yaml: line 3, column 14: not valid YAML"):
        load_config(write(tmp_path, text))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_nominal_model_file_alone_or_in_full_config(tmp_path: Path) -> None:
    alone = tmp_path / "model.yaml"
    alone.write_text("friction:\n  model: coulomb\n  pulleys:\n    - {wrap_deg: 45, mu: 0.02}\n")
    fr = load_friction(alone)
    assert fr.model == "coulomb" and fr.mu == (0.02,)
    assert load_friction(DEFAULT_CONFIG_PATH).model == "dahl"
    alone.write_text("friction:\n  modle: dahl\n")
    with pytest.raises(ConfigError, match=r"model\.yaml: friction\.modle: unknown key"):
        load_friction(alone)


def test_listeners_beyond_loopback_are_called_out() -> None:
    from gateway.core.config import exposure_warning, is_loopback_host

    assert all(is_loopback_host(h) for h in ("127.0.0.1", "127.3.0.9", "::1", "localhost"))
    assert not any(is_loopback_host(h) for h in ("0.0.0.0", "10.0.0.5", "::", "plc.example"))
    assert exposure_warning("metrics.host", "127.0.0.1", 9109) is None
    line = exposure_warning("metrics.host", "0.0.0.0", 9109, "site.yaml")
    assert line is not None and "metrics.host in site.yaml binds 0.0.0.0:9109" in line


def test_unknown_key_lists_only_keys_a_file_may_hold(tmp_path):
    """'source' is filled in by the loader; the error must not offer it."""
    path = tmp_path / "c.yaml"
    path.write_text(DEFAULT_CONFIG_PATH.read_text() + "\nsauce: 1\n")
    with pytest.raises(ConfigError, match=r"sauce: unknown key \(known here: ") as exc:
        load_config(path)
    known = str(exc.value).split("known here: ")[1].rstrip(")").split(", ")
    assert "source" not in known and "geometry" in known and "sim_plc" in known
