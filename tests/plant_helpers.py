"""Shared helpers of the plant tests: configs built from config/replicate.yaml."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

from gateway.core.config import Config, config_from_mapping
from gateway.core.configtypes import read_yaml

ROOT = Path(__file__).resolve().parent.parent
REPLICATE_YAML = ROOT / "config" / "replicate.yaml"


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def make_config(sim_plc: dict[str, Any] | None = None, **sections: Any) -> Config:
    """The replicate config with ``sim_plc`` (and other sections) merged over it."""
    data = read_yaml(REPLICATE_YAML)
    data = _merge(data, {"sim_plc": sim_plc or {}, **sections})
    return config_from_mapping(data, str(REPLICATE_YAML))


def cyclic_config(effects: dict[str, Any] | None = None, **sim: Any) -> Config:
    """Fast cyclic motion (0.5 Hz, every cable reverses), noise off, Coulomb truth."""
    base: dict[str, Any] = {
        "noise_std_n": 0.0,
        "friction": {"model": "coulomb"},
        "trajectory": {"kind": "cyclic", "cyclic": {"frequency_hz": [0.5] * 6}},
        "effects": effects or {},
    }
    return make_config(_merge(base, sim))
