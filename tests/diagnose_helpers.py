"""Shared helpers of the diagnosis tests: schema check, scenario files on disk."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema

from gateway.recording import write_recording
from sim_plc.scenarios import Scenario, make_recording

MODEL_YAML = """friction:
  model: {model}
  pulleys:
    - {{wrap_deg: 90.0, mu: 0.015}}
    - {{wrap_deg: 60.0, mu: 0.015}}
    - {{wrap_deg: 30.0, mu: 0.015}}
  sigma_n_m: 500.0
"""


def schema() -> dict:
    """The report's JSON schema: a verbatim copy of spec/diagnose-report.schema.json."""
    return json.loads(SCHEMA)


def check_report(report: dict) -> None:
    """Raise if ``report`` does not follow the schema; also checks per-cable list lengths."""
    jsonschema.validate(report, schema())
    for f in report["findings"]:
        for name, values in f["parameters"].items():
            assert len(values) == len(f["cables"]), (f["effect"], name)


def write_scenario(tmp: Path, sc: Scenario, name: str = "rec.csv") -> tuple[Path, Path]:
    """Write the scenario's recording and its nominal model file; return both paths."""
    rec_path = tmp / name
    write_recording(rec_path, make_recording(sc))
    model = tmp / "model.yaml"
    model.write_text(MODEL_YAML.format(model=sc.nominal_model), encoding="utf-8")
    return rec_path, model


SCHEMA = r"""
{
 "$schema": "https://json-schema.org/draft/2020-12/schema",
 "title": "cdpr-gateway diagnose report",
 "description": "The JSON written by `cdpr-gateway diagnose --json`; see recording.md.",
 "type": "object",
 "required": [
  "cables",
  "samples",
  "baseline",
  "mismatch",
  "findings",
  "final"
 ],
 "properties": {
  "cables": {
   "type": "integer",
   "minimum": 1
  },
  "samples": {
   "type": "integer",
   "minimum": 1
  },
  "baseline": {
   "type": "object",
   "required": [
    "rmse_n",
    "per_cable_rmse_n"
   ],
   "properties": {
    "rmse_n": {
     "type": "number",
     "minimum": 0
    },
    "per_cable_rmse_n": {
     "type": "array",
     "items": {
      "type": "number",
      "minimum": 0
     }
    }
   }
  },
  "mismatch": {
   "type": "array",
   "items": {
    "type": "object",
    "required": [
     "cable",
     "start_s",
     "end_s",
     "regime",
     "share"
    ],
    "properties": {
     "cable": {
      "type": "integer",
      "minimum": 1
     },
     "start_s": {
      "type": "number"
     },
     "end_s": {
      "type": "number"
     },
     "regime": {
      "type": "string"
     },
     "share": {
      "type": "number",
      "minimum": 0,
      "maximum": 1
     }
    }
   }
  },
  "findings": {
   "type": "array",
   "items": {
    "type": "object",
    "required": [
     "effect",
     "cables",
     "parameters",
     "evidence",
     "rmse_before_n",
     "rmse_after_n",
     "holdout_rmse_before_n",
     "holdout_rmse_after_n"
    ],
    "properties": {
     "effect": {
      "enum": [
       "coulomb",
       "presliding",
       "viscous",
       "stribeck",
       "inertia",
       "delay",
       "lowpass",
       "gain",
       "offset",
       "drift",
       "eccentricity",
       "mass_change"
      ]
     },
     "cables": {
      "type": "array",
      "items": {
       "type": "integer",
       "minimum": 1
      }
     },
     "parameters": {
      "type": "object",
      "additionalProperties": {
       "type": "array",
       "items": {
        "type": "number"
       }
      }
     },
     "stderr": {
      "type": "object",
      "additionalProperties": {
       "type": "array",
       "items": {
        "type": "number"
       }
      }
     },
     "evidence": {
      "type": "string",
      "minLength": 1
     },
     "rmse_before_n": {
      "type": "number"
     },
     "rmse_after_n": {
      "type": "number"
     },
     "holdout_rmse_before_n": {
      "type": "number"
     },
     "holdout_rmse_after_n": {
      "type": "number"
     },
     "validation_rmse_before_n": {
      "type": "number"
     },
     "validation_rmse_after_n": {
      "type": "number"
     }
    }
   }
  },
  "final": {
   "type": "object",
   "required": [
    "rmse_n",
    "holdout_rmse_n"
   ],
   "properties": {
    "rmse_n": {
     "type": "number"
    },
    "holdout_rmse_n": {
     "type": "number"
    },
    "validation_rmse_before_n": {
     "type": "number"
    },
    "validation_rmse_after_n": {
     "type": "number"
    }
   }
  }
 }
}
"""
