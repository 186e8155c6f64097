"""What runs around the cycle: the daemon, ``check``, the metrics and their exporter, the
recorder and its writer process."""
