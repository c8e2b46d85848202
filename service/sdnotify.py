"""sd_notify(3) without a dependency: READY=1, WATCHDOG=1, STATUS=... over $NOTIFY_SOCKET.

systemd (Type=notify) passes the path of an AF_UNIX datagram socket in NOTIFY_SOCKET; a leading
'@' names a Linux abstract socket (the '@' becomes a NUL byte). With WatchdogSec= set, systemd
also passes WATCHDOG_USEC (and WATCHDOG_PID); the service must send WATCHDOG=1 more often than
that, conventionally every half period. Outside systemd every call is a no-op returning False.

The daemon calls:
    notifier = Notifier.from_env()
    notifier.notify("READY=1\nSTATUS=waiting for the flight controller on URL")   # once it runs,
                                               # before the FC answers (service/daemon.py)
    if notifier.watchdog_due(now_s): notifier.notify("WATCHDOG=1")   # from the main loop
    notifier.notify("STATUS=in-flight, heading azimuth 231.2 deg")
    notifier.notify("STOPPING=1")              # on shutdown
"""
from __future__ import annotations

import os
import socket
from collections.abc import Mapping


def _address(notify_socket: str) -> str | bytes:
    if notify_socket.startswith("@"):
        return b"\0" + notify_socket[1:].encode()
    return notify_socket


def watchdog_interval_s(env: Mapping[str, str] | None = None) -> float | None:
    """Half of $WATCHDOG_USEC in seconds (the recommended ping period), or None when systemd
    runs no watchdog for us (unset, malformed, 0, or WATCHDOG_PID naming another process)."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    return value / 2e6


class Notifier:
    """Holds the socket address and the watchdog schedule; ``notify`` never raises on I/O."""

    def __init__(self, notify_socket: str | None, watchdog_period_s: float | None = None):
        self.address = _address(notify_socket) if notify_socket else None
        self.watchdog_period_s = watchdog_period_s
        self._next_watchdog_s: float | None = None
        self.errors = 0

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Notifier:
        env = os.environ if env is None else env
        return cls(env.get("NOTIFY_SOCKET") or None, watchdog_interval_s(env))

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, state: str) -> bool:
        """Send one state string (e.g. "READY=1", "WATCHDOG=1", "STATUS=text"); lines may be
        joined with newlines. Returns True when sent, False when disabled or the send failed."""
        if self.address is None:
            return False
        if not state:
            raise ValueError("sd_notify state must be a non-empty string like 'READY=1'")
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.sendto(state.encode(), self.address)
        except OSError:
            self.errors += 1
            return False
        return True

    def watchdog_due(self, now_s: float) -> bool:
        """True once per watchdog period (monotonic ``now_s``), always False without a watchdog."""
        if self.watchdog_period_s is None:
            return False
        if self._next_watchdog_s is None or now_s >= self._next_watchdog_s:
            self._next_watchdog_s = now_s + self.watchdog_period_s
            return True
        return False


def notify(state: str) -> bool:
    """One-shot ``sd_notify(0, state)`` using the current environment; no-op outside systemd."""
    return Notifier.from_env().notify(state)
