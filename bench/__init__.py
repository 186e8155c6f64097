"""Benchmarks: ``python -m bench [NAME ...]`` runs ``bench/bench_NAME.py:run()`` and prints figures.

Benchmarks print medians, percentiles and ratios measured side by side in one run; they
never assert on wall time (the machines are shared and noisy).
"""
