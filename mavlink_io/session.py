"""The link's session: the transport up and down, our HEARTBEAT, and whether the autopilot is heard.

- Transport: (re)opened when down and its backoff has expired (tcp/serial/udp alike; the backoff
  doubles up to reconnect_backoff_max_s and resets once the transport is really up), a dead
  transport is closed and reported once per new failure (``transport_error``), a reopening once
  up (``reconnect``). UDP kernel drops are summed over reopened sockets.
- HEARTBEAT at heartbeat_hz from our identity (onboard controller, no autopilot, active); at once
  when a listening transport gets its peer (udpin: the FC talked; tcpin: a client connected).
- Liveness: ``link_lost`` when no message from the autopilot came for link_timeout_s (or the
  transport died while connected), ``link_restored`` when one comes again.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

import time
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link_config import LinkConfig
from mavlink_io.stats import LinkStats
from mavlink_io.transport import Transport, TransportDead
from mavlink_io.url import Endpoint


class Session:
    """Transport, heartbeat and liveness of one link. Never raises on I/O.

    send(msg): the link's send (our HEARTBEAT goes through it); event(kind, detail, now, items):
    the link's events (items None: held for the next poll); on_open(): a new byte stream began
    (the link resets its parser)."""

    def __init__(self, cfg: LinkConfig, endpoint: Endpoint, transport: Transport, stats: LinkStats, mav,
                 clock: Callable[[], float], send: Callable, event: Callable[[str, str, float, list | None], None],
                 on_open: Callable[[], None]):
        self.cfg = cfg
        self.endpoint = endpoint
        self.transport = transport
        self.stats = stats
        self.mav = mav
        self.clock = clock
        self._send = send
        self._event = event
        self._on_open = on_open
        self.last_error: str | None = None
        self.open_ok = False
        self.connected = False
        """The autopilot has been heard within link_timeout_s."""
        self.last_fc_rx_s: float | None = None
        self._ever_connected = False
        self._ever_opened = False
        self._announce_reconnect = False
        self._had_peer = False
        self._kernel_drops_closed = 0
        self._kernel_drops_socket = 0
        now = clock()
        self.next_heartbeat_s = now
        self._backoff_s = cfg.reconnect_backoff_s
        self.reopen_at_s = now

    # --- transport ----------------------------------------------------------------------------

    def try_open(self, now: float, items: list | None = None) -> None:
        try:
            self.transport.open()
        except OSError as exc:
            self.stats.transport_errors += 1
            err = f"cannot open {self.endpoint.url}: {exc}"
            if err != self.last_error:
                self._event("transport_error", f"{err}; retrying every <= {self.cfg.reconnect_backoff_max_s:g} s",
                            now, items)
            self.last_error = err
            self._schedule_reopen(now)
            return
        self.open_ok = True
        self._on_open()
        self._announce_reconnect = self._ever_opened
        self._ever_opened = True
        self.check_up(now, items)

    def _schedule_reopen(self, now: float) -> None:
        self.reopen_at_s = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.cfg.reconnect_backoff_max_s)

    def check_up(self, now: float, items: list | None) -> None:
        """Once the reopened transport is really up (TCP connect done): reset the backoff and
        report the reconnection."""
        if not self.transport.connected:
            return
        self._backoff_s = self.cfg.reconnect_backoff_s
        if self._announce_reconnect:
            self._announce_reconnect = False
            self.stats.reconnects += 1
            self._event("reconnect", f"{self.endpoint.url} reopened", now, items)
        self.last_error = None

    def dead(self, reason: str, now: float, items: list | None) -> None:
        """The transport failed: close it, report, reopen later with backoff."""
        self.bank_kernel_drops()
        self.transport.close()
        self.open_ok = False
        self.stats.transport_errors += 1
        err = f"{self.endpoint.url}: {reason}"
        if err != self.last_error:  # report each new failure once, not every retry
            self._event("transport_error", f"{err}; reopening with backoff (<= "
                                           f"{self.cfg.reconnect_backoff_max_s:g} s)", now, items)
        self.last_error = err
        self._schedule_reopen(now)
        if self.connected:
            self.lose(now, f"transport down ({reason})", items)

    def close(self) -> None:
        self.bank_kernel_drops()
        self.transport.close()
        self.open_ok = False

    def write(self, buf: bytes) -> None:
        """One encoded frame out (pymavlink's MAVLink object writes here). Counted, never raises."""
        if not self.open_ok:
            self.stats.send_errors += 1
            return
        if not self.transport.has_peer:
            self.stats.send_no_peer += 1  # udpin/tcpin before anyone talked: nothing to send to
            return
        try:
            ok = self.transport.write(buf)
        except TransportDead as exc:
            self.stats.send_errors += 1
            self.dead(str(exc), self.clock(), None)
            return
        except OSError as exc:
            self.stats.send_errors += 1
            self.last_error = f"{self.endpoint.url}: send failed: {exc}"
            return
        if ok:
            self.stats.messages_sent += 1
        else:
            self.stats.send_errors += 1

    def read(self, wait_s: float, items: list) -> list:
        """Wait up to ``wait_s`` for input, read all of it, push queued output; [(bytes, peer)]."""
        try:
            self.transport.wait(wait_s)
            chunks = self.transport.read()
        except TransportDead as exc:
            self.dead(str(exc), self.clock(), items)
            chunks = []
        except OSError as exc:
            self.dead(f"read failed: {exc}", self.clock(), items)
            chunks = []
        if self.open_ok:
            try:
                self.transport.flush()  # queued output of a slow stream transport
            except TransportDead as exc:
                self.dead(str(exc), self.clock(), items)
        if self._announce_reconnect and self.open_ok:
            self.check_up(self.clock(), items)
        return chunks

    def track_peer(self) -> None:
        """After a read: a listener that just got its peer (udpin: the FC talked; tcpin: a client
        connected) introduces us now rather than at the next 1 Hz tick."""
        has_peer = self.open_ok and self.transport.has_peer
        if has_peer and not self._had_peer:
            self.next_heartbeat_s = self.clock()
        self._had_peer = has_peer

    def sleep_closed(self, timeout_s: float, now: float) -> None:
        """The transport is down: wait for its reopening time, at most ``timeout_s``."""
        if timeout_s > 0:
            time.sleep(min(timeout_s, max(0.0, self.reopen_at_s - now)))

    def read_kernel_drops(self) -> None:
        """stats.kernel_rx_drops from the transport (UDP: datagrams the kernel dropped, our receive
        buffer full), summed over reopened sockets (the transport's count is per socket); None
        while the transport cannot tell."""
        fn = getattr(self.transport, "kernel_rx_drops", None)
        if fn is None or not self.open_ok:
            return
        try:
            n = fn()
        except OSError:
            return
        if n is not None:
            self._kernel_drops_socket = int(n)
            self.stats.kernel_rx_drops = self._kernel_drops_closed + self._kernel_drops_socket

    def bank_kernel_drops(self) -> None:
        """The socket is about to close: keep its last count in the total."""
        self.read_kernel_drops()
        self._kernel_drops_closed += self._kernel_drops_socket
        self._kernel_drops_socket = 0

    # --- heartbeat ----------------------------------------------------------------------------

    def heartbeat_message(self):
        """Our HEARTBEAT (onboard controller, no autopilot, active)."""
        return self.mav.heartbeat_encode(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID,
                                         0, 0, mavlink2.MAV_STATE_ACTIVE)

    def heartbeat_due(self, now: float) -> None:
        """Send our HEARTBEAT if it is due; the next one a period later (not bunched after a stall)."""
        if now < self.next_heartbeat_s:
            return
        if self.open_ok:
            before = self.stats.messages_sent
            self._send(self.heartbeat_message())
            if self.stats.messages_sent > before:
                self.stats.heartbeats_sent += 1
        period = 1.0 / self.cfg.heartbeat_hz
        self.next_heartbeat_s += period
        if self.next_heartbeat_s <= now:
            self.next_heartbeat_s = now + period

    # --- liveness -----------------------------------------------------------------------------

    def mark_alive(self, rx_s: float, items: list) -> bool:
        """A message from the autopilot. True when this restores a link that was lost (the link
        then re-requests its streams)."""
        self.last_fc_rx_s = rx_s
        if self.connected:
            return False
        self.connected = True
        restored = self._ever_connected
        if restored:
            self._event("link_restored", "autopilot messages are back", rx_s, items)
        self._ever_connected = True
        return restored

    def lose(self, now: float, why: str, items: list | None) -> None:
        self.connected = False
        self.stats.link_losses += 1
        self._event("link_lost", why, now, items)

    def check_timeout(self, now: float, items: list) -> None:
        if self.connected and now - self.last_fc_rx_s > self.cfg.link_timeout_s:
            self.lose(now, f"no message from the autopilot for {now - self.last_fc_rx_s:.2f} s "
                           f"(> {self.cfg.link_timeout_s:g} s)", items)

    def next_due_s(self) -> float:
        """The next heartbeat, or the link timeout if sooner."""
        due = self.next_heartbeat_s
        if self.connected and self.last_fc_rx_s is not None:
            due = min(due, self.last_fc_rx_s + self.cfg.link_timeout_s)
        return due
