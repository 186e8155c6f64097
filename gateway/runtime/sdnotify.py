"""systemd's notification protocol (sd_notify(3)): one datagram per message, no library.

``Notifier.from_env()`` returns ``None`` unless ``NOTIFY_SOCKET`` is set (the service runs
under systemd with ``Type=notify``); otherwise it sends ``READY=1``, ``WATCHDOG=1``,
``STATUS=...`` and ``STOPPING=1`` as single datagrams on a unix datagram socket. An
address starting with ``@`` is in the abstract namespace. ``WATCHDOG_USEC`` (set by
systemd with ``WatchdogSec=``) gives the ping interval: half the watchdog period, as
sd_watchdog_enabled(3) recommends; without it the loop pings once per second. Sending
never blocks and never raises: a notification that cannot be sent is dropped.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

DEFAULT_WATCHDOG_INTERVAL_S = 1.0


class Notifier:
    """Sends sd_notify messages to one socket address."""

    def __init__(self, address: str, watchdog_interval_s: float = DEFAULT_WATCHDOG_INTERVAL_S):
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.watchdog_interval_s = watchdog_interval_s
        self.sent = 0
        self.failed = 0
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)

    @staticmethod
    def from_env(environ: Mapping[str, str] | None = None) -> Notifier | None:
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        if not address:
            return None
        interval = DEFAULT_WATCHDOG_INTERVAL_S
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            interval = int(usec) / 2e6
        return Notifier(address, interval)

    def notify(self, message: str) -> bool:
        """Send one message (``KEY=VALUE`` lines); False when it could not be sent."""
        try:
            self._sock.sendto(message.encode("utf-8", "replace"), self.address)
        except OSError:
            self.failed += 1
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()
