"""cdpr-gateway: pulley-friction compensation next to the PLC of a cable robot."""

__version__ = "0.1.0"
