"""Byte transports for MAVLink: UDP in/out, TCP client/server, serial (termios). Non-blocking.

Our own thin transports instead of pymavlink's ``mavutil`` ones, because the link must never
block, print or raise out of its poll loop: pymavlink's TCP client sleeps and retries inside
``connect``, its serial port needs pyserial, and both print to stdout on errors. pymavlink is
still what frames, parses and encodes every message (mavlink_io.link).

Contract for every transport:
- ``open()`` may raise ``OSError`` (the link retries with backoff);
- ``read()`` returns a list of ``(bytes, peer)`` chunks available now (``[]`` if none) and raises
  :class:`TransportDead` when the connection is gone (EOF, reset, device unplugged);
- ``write(buf)`` returns True if handed to the OS, False if there is nobody to send to yet, and
  may raise ``OSError``;
- ``wait(timeout_s)`` blocks until readable (or connected) or the timeout.

UDP receive buffer and kernel drops (issue 10)
----------------------------------------------
A datagram that arrives while the socket's receive buffer is full is dropped by the kernel, before
any of our code sees it. :class:`UdpTransport` therefore asks for a larger buffer
(``rcvbuf_bytes``, default :data:`UDP_RCVBUF_BYTES_DEFAULT` = 4 MiB, ``SO_RCVBUF`` at open) and
reports what the kernel dropped for its socket (:meth:`UdpTransport.kernel_rx_drops`).

The daemon runs unprivileged, so the request is silently capped at the sysctl
``net.core.rmem_max`` (often 212992 bytes); ``SO_RCVBUFFORCE`` would need CAP_NET_ADMIN and is not
used. :attr:`UdpTransport.rcvbuf_bytes_granted` is what the kernel reports back: on Linux twice the
effective request (the kernel doubles it for its bookkeeping), i.e. ``2 * min(rcvbuf_bytes,
rmem_max)``. For the full 4 MiB an operator raises the cap once, as root::

    # /etc/sysctl.d/90-azimuthd.conf
    net.core.rmem_max = 4194304

then ``sysctl --system`` (or reboot). The daemon cannot do this itself (ProtectKernelTunables).

``kernel_rx_drops()`` reads the ``drops`` column of ``/proc/self/net/udp`` and ``udp6`` (the
per-process view of the socket tables, which stays visible under systemd's ``ProcSubset=pid``;
the top-level ``/proc/net`` link is hidden there and is only a fallback). The counter belongs to
the socket: after a close/reopen it starts again from 0, so the caller (the link) accumulates.
"""
from __future__ import annotations

import errno
import os
import select
import socket
import sys
import time

from mavlink_io.url import Endpoint

_READ_CHUNK = 65536
_MAX_CHUNKS_PER_READ = 512
"""Bound the work of one read() so that a flood cannot starve the caller's timers."""


UDP_RCVBUF_BYTES_DEFAULT = 4 * 1024 * 1024
"""Receive buffer a UDP transport asks for (SO_RCVBUF), bytes; capped by net.core.rmem_max."""

_PROC_UDP_TABLES = {
    socket.AF_INET: ("/proc/self/net/udp", "/proc/net/udp"),
    socket.AF_INET6: ("/proc/self/net/udp6", "/proc/net/udp6"),
}
"""Where the kernel lists the UDP sockets of our network namespace, per address family: the
per-process path first (visible under ProcSubset=pid), then the classic top-level one."""

_PROC_UDP_INODE_COL = 9
_PROC_UDP_DROPS_COL = 12
"""Whitespace-separated columns of /proc/net/udp{,6}: sl local rem st tx:rx tr:when retrnsmt uid
timeout inode ref pointer drops (net/ipv4/udp.c udp4_format_sock, net/ipv6/datagram.c)."""


def _udp_drops_from_table(table: bytes, inode: int) -> int | None:
    """The ``drops`` column of the row whose ``inode`` column equals ``inode``, else None.

    Searches the raw bytes for `` INODE `` (C speed) and checks the candidate row's columns, so
    a number that happens to equal the inode in another column cannot match."""
    needle = b" %d " % inode
    start = 0
    while True:
        i = table.find(needle, start)
        if i < 0:
            return None
        line_start = table.rfind(b"\n", 0, i) + 1
        line_end = table.find(b"\n", i)
        cols = table[line_start:line_end if line_end >= 0 else len(table)].split()
        if len(cols) > _PROC_UDP_DROPS_COL and cols[_PROC_UDP_INODE_COL] == needle.strip():
            try:
                return int(cols[_PROC_UDP_DROPS_COL])
            except ValueError:
                return None
        start = i + 1


def _read_proc_file(path: str) -> bytes | None:
    try:
        with open(path, "rb", buffering=0) as f:
            chunks = []
            while True:
                b = f.read(65536)
                if not b:
                    return b"".join(chunks)
                chunks.append(b)
    except OSError:
        return None


class TransportDead(Exception):
    """The connection is gone; the link closes the transport and reopens it with backoff."""


OUT_QUEUE_LIMIT_BYTES = 65536
"""Stream transports queue outgoing frames up to this much; beyond, whole frames are dropped."""


class _OutQueue:
    """Outgoing bytes of a stream transport. Frames enter whole or not at all, so a full kernel
    buffer (slow serial link) never puts half a frame on the wire; the rest goes out on flush."""

    def __init__(self, limit: int = OUT_QUEUE_LIMIT_BYTES):
        self.buf = bytearray()
        self.limit = limit
        self.dropped_frames = 0

    def push(self, frame: bytes) -> bool:
        if len(self.buf) + len(frame) > self.limit:
            self.dropped_frames += 1
            return False
        self.buf += frame
        return True

    def flush(self, send) -> None:
        """send(memoryview) -> bytes written; OSError other than EAGAIN propagates."""
        while self.buf:
            try:
                n = send(memoryview(self.buf))
            except (BlockingIOError, InterruptedError):
                return
            if not n:
                return
            del self.buf[:n]

    def clear(self) -> None:
        self.buf.clear()


class Transport:
    endpoint: Endpoint
    datagram: bool = False
    """True when each chunk returned by :meth:`read` is exactly one datagram (UDP), so the link
    may treat a chunk as a unit; False for byte streams (TCP, serial), where a chunk boundary
    means nothing and a frame may span chunks."""

    def __init__(self, endpoint: Endpoint):
        self.endpoint = endpoint

    def open(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def fileno(self) -> int | None:  # pragma: no cover - interface
        raise NotImplementedError

    def read(self) -> list[tuple[bytes, object]]:  # pragma: no cover - interface
        raise NotImplementedError

    def write(self, buf: bytes) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def set_peer(self, peer: object) -> None:
        """Tell a datagram transport where the autopilot's packets come from (reply address)."""

    def flush(self) -> None:
        """Push queued outgoing bytes (stream transports); may raise TransportDead."""

    def _pending_out(self) -> bool:
        return False

    @property
    def local_address(self) -> tuple | None:
        return None

    @property
    def connected(self) -> bool:
        """The byte stream is up (TCP connect finished; serial open; UDP socket open)."""
        return self.fileno() is not None

    @property
    def has_peer(self) -> bool:
        """There is somebody to send to (udpin: a peer has talked; tcpin: a client is connected)."""
        return self.connected

    def _want_write(self) -> bool:
        return False

    def wait(self, timeout_s: float) -> None:
        fd = self.fileno()
        if timeout_s <= 0:
            return
        if fd is None:
            time.sleep(min(timeout_s, 0.05))
            return
        wl = [fd] if (self._want_write() or self._pending_out()) else []
        try:
            select.select([fd], wl, [], timeout_s)
        except (OSError, ValueError):
            pass


def _family(host: str) -> int:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _resolve(host: str, port: int, kind: int) -> tuple:
    infos = socket.getaddrinfo(host, port, type=kind)
    # prefer IPv4 when the name resolves to both, like most MAVLink tools
    infos.sort(key=lambda i: 0 if i[0] == socket.AF_INET else 1)
    return infos[0][0], infos[0][4]


class UdpTransport(Transport):
    """udpin (bind and reply to the autopilot's address) or udpout (send to a fixed address)."""

    datagram = True

    def __init__(self, endpoint: Endpoint, rcvbuf_bytes: int = UDP_RCVBUF_BYTES_DEFAULT):
        """rcvbuf_bytes: receive buffer to ask for (SO_RCVBUF at open), bytes, > 0; the kernel
        caps it at net.core.rmem_max (see the module docstring) and reports the result in
        :attr:`rcvbuf_bytes_granted`."""
        if isinstance(rcvbuf_bytes, bool) or not isinstance(rcvbuf_bytes, int) or rcvbuf_bytes <= 0:
            raise ValueError(f"rcvbuf_bytes must be a positive int (bytes), got {rcvbuf_bytes!r}")
        if rcvbuf_bytes > 2**31 - 1:
            raise ValueError(f"rcvbuf_bytes must be <= 2147483647 (int SO_RCVBUF), got {rcvbuf_bytes}")
        super().__init__(endpoint)
        self.rcvbuf_bytes = rcvbuf_bytes
        self.sock: socket.socket | None = None
        self.peer: tuple | None = None
        self._fixed_peer = endpoint.kind == "udpout"
        self._inode: int | None = None
        self._family: int | None = None

    def open(self) -> None:
        ep = self.endpoint
        if ep.kind == "udpin":
            sock = socket.socket(_family(ep.host), socket.SOCK_DGRAM)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                # before bind: no datagram can arrive into the small default buffer
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf_bytes)
                sock.bind((ep.host, ep.port))
            except OSError:
                sock.close()
                raise
        else:
            fam, addr = _resolve(ep.host, ep.port, socket.SOCK_DGRAM)
            sock = socket.socket(fam, socket.SOCK_DGRAM)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf_bytes)
                sock.bind(("::" if fam == socket.AF_INET6 else "0.0.0.0", 0))
            except OSError:
                sock.close()
                raise
            self.peer = addr
        sock.setblocking(False)
        self.sock = sock
        self._family = sock.family
        try:
            self._inode = os.fstat(sock.fileno()).st_ino
        except OSError:
            self._inode = None

    @property
    def rcvbuf_bytes_granted(self) -> int | None:
        """SO_RCVBUF as the kernel reports it now, bytes (Linux: 2 * min(request, rmem_max));
        None when the socket is closed."""
        if self.sock is None:
            return None
        try:
            return self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        except OSError:
            return None

    def kernel_rx_drops(self) -> int | None:
        """Datagrams the kernel dropped for this socket since it was opened (receive buffer full),
        from the ``drops`` column of /proc/self/net/udp{,6} for the socket's inode.

        None when the socket is closed, not on Linux, or the table is not readable / does not
        list the socket. Per socket: after close() and open() it starts again from 0, so a
        caller that wants a total over reconnects accumulates.

        Cost: one read of the UDP socket table of the network namespace, made by the kernel
        one page per read(): measured ~25-30 us per call with a handful of UDP sockets and
        ~2.5 ms with 1000 (about 2.4 us per socket listed) on a 2-core x86 VM. Fine once a
        second; not for every datagram."""
        if self.sock is None or self._inode is None or not sys.platform.startswith("linux"):
            return None
        for path in _PROC_UDP_TABLES.get(self._family, ()):
            table = _read_proc_file(path)
            if table is None:
                continue
            return _udp_drops_from_table(table, self._inode)
        return None

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self._inode = None
        if not self._fixed_peer:
            self.peer = None

    def fileno(self) -> int | None:
        return None if self.sock is None else self.sock.fileno()

    @property
    def local_address(self) -> tuple | None:
        return None if self.sock is None else self.sock.getsockname()

    @property
    def has_peer(self) -> bool:
        return self.sock is not None and self.peer is not None

    def set_peer(self, peer: object) -> None:
        if not self._fixed_peer and peer is not None:
            self.peer = peer  # type: ignore[assignment]

    def read(self) -> list[tuple[bytes, object]]:
        if self.sock is None:
            raise TransportDead("socket closed")
        out = []
        for _ in range(_MAX_CHUNKS_PER_READ):
            try:
                data, addr = self.sock.recvfrom(_READ_CHUNK)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                continue  # ICMP port unreachable from an earlier send: the peer is not up yet
            except OSError as exc:
                raise TransportDead(f"UDP receive failed: {exc}") from exc
            if self.peer is None:
                self.peer = addr
            out.append((data, addr))
        return out

    def write(self, buf: bytes) -> bool:
        if self.sock is None or self.peer is None:
            return False
        try:
            self.sock.sendto(buf, self.peer)
        except ConnectionRefusedError:
            return False
        return True


class TcpClientTransport(Transport):
    """tcp:HOST:PORT, non-blocking connect."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.sock: socket.socket | None = None
        self.connecting = False
        self.out = _OutQueue()

    def _pending_out(self) -> bool:
        return bool(self.out.buf)

    def open(self) -> None:
        fam, addr = _resolve(self.endpoint.host, self.endpoint.port, socket.SOCK_STREAM)
        sock = socket.socket(fam, socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        rc = sock.connect_ex(addr)
        if rc not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY):
            sock.close()
            raise OSError(rc, f"connect to {addr[0]}:{addr[1]} failed: {os.strerror(rc)}")
        self.sock = sock
        self.connecting = rc != 0

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self.connecting = False
        self.out.clear()

    def fileno(self) -> int | None:
        return None if self.sock is None else self.sock.fileno()

    def _want_write(self) -> bool:
        return self.connecting

    @property
    def connected(self) -> bool:
        return self.sock is not None and not self.connecting

    def _check_connected(self) -> bool:
        if not self.connecting:
            return True
        _, wl, _ = select.select([], [self.sock], [], 0)
        if not wl:
            return False
        err = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err != 0:
            raise TransportDead(f"TCP connect failed: {os.strerror(err)}")
        self.connecting = False
        return True

    def read(self) -> list[tuple[bytes, object]]:
        if self.sock is None:
            raise TransportDead("socket closed")
        if not self._check_connected():
            return []
        out = []
        for _ in range(_MAX_CHUNKS_PER_READ):
            try:
                data = self.sock.recv(_READ_CHUNK)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                raise TransportDead(f"TCP receive failed: {exc}") from exc
            if data == b"":
                raise TransportDead("TCP connection closed by peer")
            out.append((data, None))
        return out

    def write(self, buf: bytes) -> bool:
        if self.sock is None or not self._check_connected():
            return False
        if not self.out.push(buf):
            return False  # queue full: drop this frame rather than block the loop
        self.flush()
        return True

    def flush(self) -> None:
        if self.sock is None or self.connecting or not self.out.buf:
            return
        try:
            self.out.flush(self.sock.send)
        except OSError as exc:
            raise TransportDead(f"TCP send failed: {exc}") from exc


class TcpServerTransport(Transport):
    """tcpin:HOST:PORT: listen, serve one client at a time (a new client replaces the old)."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.listener: socket.socket | None = None
        self.client: socket.socket | None = None
        self.out = _OutQueue()

    def _pending_out(self) -> bool:
        return self.client is not None and bool(self.out.buf)

    def open(self) -> None:
        ep = self.endpoint
        sock = socket.socket(_family(ep.host), socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((ep.host, ep.port))
            sock.listen(1)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self.listener = sock

    def close(self) -> None:
        self._drop_client()
        if self.listener is not None:
            self.listener.close()
            self.listener = None

    def _drop_client(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        self.out.clear()

    def fileno(self) -> int | None:
        if self.client is not None:
            return self.client.fileno()
        return None if self.listener is None else self.listener.fileno()

    @property
    def local_address(self) -> tuple | None:
        return None if self.listener is None else self.listener.getsockname()

    @property
    def has_peer(self) -> bool:
        return self.client is not None

    def _accept(self) -> None:
        try:
            conn, _addr = self.listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            raise TransportDead(f"TCP accept failed: {exc}") from exc
        self._drop_client()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = conn

    def read(self) -> list[tuple[bytes, object]]:
        if self.listener is None:
            raise TransportDead("listener closed")
        self._accept()
        if self.client is None:
            return []
        out = []
        for _ in range(_MAX_CHUNKS_PER_READ):
            try:
                data = self.client.recv(_READ_CHUNK)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._drop_client()  # the client went away: keep listening
                break
            if data == b"":
                self._drop_client()
                break
            out.append((data, None))
        return out

    def write(self, buf: bytes) -> bool:
        if self.client is None or not self.out.push(buf):
            return False
        self.flush()
        return self.client is not None

    def flush(self) -> None:
        if self.client is None or not self.out.buf:
            return
        try:
            self.out.flush(self.client.send)
        except OSError:
            self._drop_client()  # the client went away: keep listening


class SerialTransport(Transport):
    """A serial port (or pty) in raw mode via termios; no pyserial needed."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.fd: int | None = None
        self.out = _OutQueue()

    def _pending_out(self) -> bool:
        return bool(self.out.buf)

    def open(self) -> None:
        import termios
        import tty
        speed = getattr(termios, f"B{self.endpoint.baud}", None)
        if speed is None:
            raise OSError(errno.EINVAL, f"baud {self.endpoint.baud} not supported on this system")
        fd = os.open(self.endpoint.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(fd, termios.TCSANOW)
            attrs = termios.tcgetattr(fd)
            attrs[2] |= termios.CLOCAL | termios.CREAD  # cflag: ignore modem lines, enable receiver
            attrs[2] &= ~getattr(termios, "CRTSCTS", 0)
            attrs[4] = attrs[5] = speed  # ispeed, ospeed
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except (OSError, termios.error) as exc:
            os.close(fd)
            raise OSError(errno.EIO, f"cannot configure {self.endpoint.device}: {exc}") from exc
        self.fd = fd

    def close(self) -> None:
        if self.fd is not None:
            try:
                os.close(self.fd)
            except OSError:
                pass
            self.fd = None
        self.out.clear()

    def fileno(self) -> int | None:
        return self.fd

    def read(self) -> list[tuple[bytes, object]]:
        if self.fd is None:
            raise TransportDead("serial port closed")
        out = []
        for _ in range(_MAX_CHUNKS_PER_READ):
            try:
                data = os.read(self.fd, _READ_CHUNK)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                raise TransportDead(f"serial read failed: {exc}") from exc
            if data == b"":
                if out:
                    break
                # select said readable but nothing came: hangup (device unplugged, pty closed)
                r, _, _ = select.select([self.fd], [], [], 0)
                if r:
                    raise TransportDead("serial port hung up")
                break
            out.append((data, None))
        return out

    def write(self, buf: bytes) -> bool:
        if self.fd is None or not self.out.push(buf):
            return False
        self.flush()
        return True

    def flush(self) -> None:
        if self.fd is None or not self.out.buf:
            return
        fd = self.fd
        try:
            self.out.flush(lambda mv: os.write(fd, mv))
        except OSError as exc:
            raise TransportDead(f"serial write failed: {exc}") from exc


class NullTransport(Transport):
    """No wire: nothing to read, writes are accepted and dropped. For replaying recorded bytes
    through the link's receive path (:meth:`MavlinkLink.feed`, mavlink_io.tlog)."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.written = 0

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def fileno(self) -> int | None:
        return None

    @property
    def connected(self) -> bool:
        return True

    def read(self) -> list[tuple[bytes, object]]:
        return []

    def wait(self, timeout_s: float) -> None:
        pass

    def write(self, buf: bytes) -> bool:
        self.written += 1
        return True


def make_transport(endpoint: Endpoint, *, rcvbuf_bytes: int = UDP_RCVBUF_BYTES_DEFAULT) -> Transport:
    """The transport for an endpoint. rcvbuf_bytes: UDP receive buffer to ask for (bytes; see
    :class:`UdpTransport`); ignored by the stream transports."""
    if endpoint.kind in ("udpin", "udpout"):
        return UdpTransport(endpoint, rcvbuf_bytes=rcvbuf_bytes)
    if endpoint.kind == "tcp":
        return TcpClientTransport(endpoint)
    if endpoint.kind == "tcpin":
        return TcpServerTransport(endpoint)
    if endpoint.kind == "serial":
        return SerialTransport(endpoint)
    raise ValueError(f"no transport for endpoint kind {endpoint.kind!r}")
