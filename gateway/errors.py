"""The project's exception tree (python-can's, the house style): only the loop catches driver
errors."""

from __future__ import annotations


class GatewayError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(GatewayError):
    """A configuration file is unreadable, has an unknown key or a bad value.

    The message names the file and the dotted key path (``friction.pulleys[1].mu``).
    """


class TemporaryError(GatewayError):
    """Something the program needs is not available now but may be later (a port another
    process holds): the command line exits 75 (EX_TEMPFAIL), not 2, so a service manager
    that does not restart after a configuration error (exit 2) restarts after this."""


class RecordingError(GatewayError):
    """A recording is malformed; the message names the file, line and column."""


class InfeasiblePoseError(GatewayError):
    """No tension distribution within the limits balances the wrench at this pose."""


class DriverError(GatewayError):
    """Base of fieldbus driver errors; other libraries' errors are chained with ``from``."""


class DriverInitError(DriverError):
    """The driver could not be configured or connected."""


class DriverIOError(DriverError):
    """A transaction failed (exception reply, malformed frame, dropped connection)."""


class DriverTimeoutError(DriverIOError):
    """A transaction got no reply in time."""
