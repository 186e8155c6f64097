"""The floor every other part stands on: the config and its types, the one YAML loader,
the register map, the shipped resources, the heap settings. Imports only
:mod:`gateway.errors` at import time, and loads no numba: the effects registry
(:mod:`gateway.model`) checks ``friction.effects`` and turns them into per-cable values
only when a config has effects or a caller asks for them (``tests/core/test_floor.py``)."""
