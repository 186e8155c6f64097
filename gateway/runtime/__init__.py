"""The 1 ms cycle: the loop, its pacing, validation and compensation, cycle statistics,
real-time settings and systemd notifications. No I/O but the driver's inside a cycle."""
