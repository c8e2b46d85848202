"""The simulator's MAVLink ports: several endpoints served as one, and a serial port (HIL).

A flight controller has several MAVLink ports (TELEM1 to the radio, TELEM2 to the companion
computer, USB) and routes between them: what it sends goes out on every port, and a message that
arrives on one port and is not addressed to the FC itself is forwarded to the others (ArduPilot's
MAVLink routing), so a ground station on one port sees the companion computer's messages sent on
another. :class:`Ports` does the same for ``azimuthd sim --mavlink URL --mavlink URL ...``; it
looks to the autopilot like one pymavlink connection (``mav``, ``write``, ``recv_msg``, ``fd``).

:class:`SerialPort` is a serial device (or a pty, for hardware-in-the-loop tests) in raw mode
through termios: no pyserial needed.
"""
from __future__ import annotations

import os
import select
from collections import deque

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega

_READ_BYTES = 4096


class SerialPort:
    """A serial device in raw mode at ``baud``, non-blocking; pymavlink-like (mav, write, recv_msg)."""

    def __init__(self, device: str, baud: int, source_system: int, source_component: int):
        import termios
        import tty
        speed = getattr(termios, f"B{baud}", None)
        if speed is None:
            raise ValueError(f"serial baud rate {baud} is not supported by this system")
        self.fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(self.fd, termios.TCSANOW)
            attrs = termios.tcgetattr(self.fd)
            attrs[2] |= termios.CLOCAL | termios.CREAD          # ignore modem lines, enable the receiver
            attrs[2] &= ~getattr(termios, "CRTSCTS", 0)         # no hardware flow control
            attrs[4] = attrs[5] = speed                          # ispeed, ospeed
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except (OSError, termios.error):
            os.close(self.fd)
            raise
        self.device = device
        self.mav = ardupilotmega.MAVLink(self, srcSystem=source_system, srcComponent=source_component)
        self.mav.robust_parsing = True
        self._queue: deque = deque()
        self.dropped_writes = 0

    def write(self, buf: bytes) -> None:
        """Whole frame or nothing: a full output buffer drops the frame (and counts it)."""
        try:
            n = os.write(self.fd, bytes(buf))
        except BlockingIOError:
            self.dropped_writes += 1
            return
        if n < len(buf):  # the rest of a frame cut by a full buffer would corrupt the next one
            self.dropped_writes += 1

    def recv_msg(self):
        if not self._queue:
            try:
                data = os.read(self.fd, _READ_BYTES)
            except (BlockingIOError, InterruptedError):
                return None
            except OSError as exc:  # EIO: the other end of a pty closed
                raise OSError(f"serial port {self.device} failed: {exc}") from exc
            if data:
                self._queue.extend(self.mav.parse_buffer(data) or [])
        return self._queue.popleft() if self._queue else None

    def close(self) -> None:
        os.close(self.fd)


def open_endpoint(endpoint, source_system: int, source_component: int):
    """A parsed endpoint (mavlink_io.url.Endpoint) as a pymavlink-like connection."""
    if endpoint.kind == "serial":
        return SerialPort(endpoint.device, endpoint.baud, source_system, source_component)
    conn = mavutil.mavlink_connection(endpoint.pymavlink_url, source_system=source_system,
                                      source_component=source_component, dialect="ardupilotmega",
                                      autoreconnect=True)
    conn.mav.robust_parsing = True
    return conn


def _for_fc_only(msg, sysid: int, compid: int) -> bool:
    """Addressed to the FC itself (its system AND its component): not forwarded."""
    ts = getattr(msg, "target_system", None)
    tc = getattr(msg, "target_component", None)
    return ts == sysid and tc == compid


class Ports:
    """Several connections as one: ``write`` sends to all; ``recv_msg`` returns the next message
    from any, after forwarding it (raw bytes) to the others unless it is for the FC only.

    ``mav`` is the first connection's encoder: every port carries the same frames with the same
    sequence numbers (a real FC numbers each port's channel on its own; a receiver's loss count is
    per port either way)."""

    def __init__(self, conns: list, sysid: int, compid: int):
        if not conns:
            raise ValueError("Ports needs at least one connection")
        self.conns = conns
        self.sysid, self.compid = sysid, compid
        self.mav = conns[0].mav  # the encoder; each connection keeps its own parser
        self._poll = select.epoll()
        for c in conns:
            fd = getattr(c, "fd", None)
            if fd is not None:
                self._poll.register(fd, select.EPOLLIN)
        self.fd = self._poll.fileno()
        """One fd that is readable when any port is: select() on it waits for all of them."""
        self._next = 0
        self.forwarded = 0

    def write(self, buf: bytes) -> None:
        for c in self.conns:
            c.write(buf)

    def recv_msg(self):
        n = len(self.conns)
        for i in range(n):
            k = (self._next + i) % n
            msg = self.conns[k].recv_msg()
            if msg is None:
                continue
            self._next = (k + 1) % n  # round robin: a busy port cannot starve the others
            if msg.get_type() != "BAD_DATA" and not _for_fc_only(msg, self.sysid, self.compid):
                raw = msg.get_msgbuf()
                for j, other in enumerate(self.conns):
                    if j != k:
                        other.write(raw)
                        self.forwarded += 1
            return msg
        return None

    def close(self) -> None:
        self._poll.close()
        for c in self.conns:
            c.close()
