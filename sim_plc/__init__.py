"""The soft PLC: plant (truth physics, effects, noise, ADC), trajectories, bus servers."""
