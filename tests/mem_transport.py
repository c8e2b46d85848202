"""An in-memory Transport for MavlinkLink tests (not a test module: imported by them).

``inbox``: datagrams (or stream chunks) the next ``read()`` returns; ``sent``: frames written;
``die``: the next ``read()`` raises TransportDead; ``drops``: what ``kernel_rx_drops()`` says.
"""
from __future__ import annotations

from mavlink_io.transport import Transport, TransportDead


class MemTransport(Transport):
    def __init__(self, datagram: bool = True, drops=None):
        super().__init__(None)
        self.datagram = datagram
        self.inbox: list[bytes] = []
        self.sent: list[bytes] = []
        self.die = False
        self.drops = drops

    def open(self):
        pass

    def close(self):
        pass

    def fileno(self):
        return None

    def read(self):
        if self.die:
            self.die = False
            raise TransportDead("test: socket gone")
        out, self.inbox = [(d, ("fc", 0)) for d in self.inbox], []
        return out

    def write(self, buf):
        self.sent.append(bytes(buf))
        return True

    def wait(self, timeout_s):
        pass

    @property
    def connected(self):
        return True

    @property
    def has_peer(self):
        return True


class DropsTransport(MemTransport):
    def kernel_rx_drops(self):
        return self.drops
