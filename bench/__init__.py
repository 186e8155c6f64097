"""Benchmarks: ``python -m bench [NAME ...]`` runs ``bench/bench_NAME.py:run()`` and prints figures.

Benchmarks print medians, percentiles and ratios measured side by side in one run; they
never assert on wall time (the machines are shared and noisy).
"""

import subprocess


def stop_process(proc: subprocess.Popen, timeout_s: float = 20.0) -> None:
    """Terminate ``proc`` if it still runs, kill it when it does not end in ``timeout_s``."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)
