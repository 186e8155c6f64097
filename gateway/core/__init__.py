"""The floor every other part stands on: the config and its types, the register map, the
shipped resources, the heap settings. Imports only :mod:`gateway.model` (the effect
registry validates ``friction.effects``) and :mod:`gateway.errors`."""
