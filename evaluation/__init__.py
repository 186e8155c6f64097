"""How well the product works, measured: the diagnosis' scenario suites and their sealed
draws, the real recordings' converters and the engineer's least-squares baseline they are
scored against, the bus fault proxy of the soak, and the suite tables of
docs/diagnose-suite.md. Used by the tests and the benchmarks only; not in the wheel.
"""
