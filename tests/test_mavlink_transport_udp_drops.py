"""UdpTransport: SO_RCVBUF request and the kernel's per-socket drop counter (issue 10).

Loopback UDP delivers synchronously: when sendto() returns, the datagram is either queued on the
receiving socket or counted in its ``drops``. So with a tiny receive buffer and no reading in
between, received + kernel_rx_drops() must equal what was sent, exactly."""
import os
import shutil
import socket
import subprocess
import sys
import textwrap

import pytest

from mavlink_io.transport import (UDP_RCVBUF_BYTES_DEFAULT, Transport, UdpTransport,
                                  _udp_drops_from_table, make_transport)
from mavlink_io.url import parse_url

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/net/udp is Linux")


def _rmem_max() -> int | None:
    try:
        with open("/proc/sys/net/core/rmem_max") as f:
            return int(f.read())
    except OSError:
        return None


def _ipv6_loopback() -> bool:
    if not socket.has_ipv6:
        return False
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


def _open(url: str, **kw) -> UdpTransport:
    t = make_transport(parse_url(url), **kw)
    assert isinstance(t, UdpTransport)
    t.open()
    return t


def _read_all(t: UdpTransport) -> list:
    out = []
    while True:
        chunk = t.read()
        if not chunk:
            return out
        out += chunk


def _flood(t: UdpTransport, n: int, family: int, payload_len: int = 40) -> None:
    with socket.socket(family, socket.SOCK_DGRAM) as tx:
        addr = t.local_address[:2]
        for i in range(n):
            tx.sendto(i.to_bytes(4, "little") + bytes(payload_len - 4), addr)


def test_datagram_flag():
    assert UdpTransport.datagram is True and Transport.datagram is False
    assert make_transport(parse_url("tcp:127.0.0.1:5760")).datagram is False
    assert make_transport(parse_url("udpout:127.0.0.1:14550")).datagram is True


@linux_only
@pytest.mark.parametrize("url,family", [
    ("udpin:127.0.0.1:0", socket.AF_INET),
    pytest.param("udpin:[::1]:0", socket.AF_INET6,
                 marks=pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback")),
])
def test_kernel_drops_account_for_every_datagram(url, family):
    n_sent = 300
    t = _open(url, rcvbuf_bytes=4096)
    try:
        assert t.kernel_rx_drops() == 0  # fresh socket
        _flood(t, n_sent, family)
        got = _read_all(t)
        drops = t.kernel_rx_drops()
        # the buffer (8 KiB granted) holds only a few small datagrams: most are dropped
        assert 0 < len(got) < n_sent // 4
        assert drops == n_sent - len(got)
        # the ones kept are the first ones, in order (drops happen at the tail of a full queue)
        seq = [int.from_bytes(d[:4], "little") for d, _peer in got]
        assert seq == list(range(len(got)))
        # reading emptied the buffer: the next datagrams arrive, the counter does not move
        _flood(t, 3, family)
        assert len(_read_all(t)) == 3 and t.kernel_rx_drops() == drops
    finally:
        t.close()
    assert t.kernel_rx_drops() is None  # closed


@linux_only
def test_counter_is_per_socket_and_restarts_after_reopen():
    t = _open("udpin:127.0.0.1:0", rcvbuf_bytes=4096)
    try:
        _flood(t, 100, socket.AF_INET)
        _read_all(t)
        assert t.kernel_rx_drops() > 0
        other = _open("udpin:127.0.0.1:0", rcvbuf_bytes=4096)  # another socket is unaffected
        assert other.kernel_rx_drops() == 0
        other.close()
        t.close()
        t.open()
        assert t.kernel_rx_drops() == 0
    finally:
        t.close()


@linux_only
def test_rcvbuf_granted_is_what_the_kernel_reports():
    small = _open("udpin:127.0.0.1:0", rcvbuf_bytes=4096)
    dflt = _open("udpin:127.0.0.1:0")  # make_transport(endpoint) keeps working: 4 MiB asked
    out = _open("udpout:127.0.0.1:9", rcvbuf_bytes=65536)
    try:
        assert small.rcvbuf_bytes_granted == 2 * 4096  # Linux doubles the request
        assert out.rcvbuf_bytes_granted == 2 * 65536
        assert dflt.rcvbuf_bytes == UDP_RCVBUF_BYTES_DEFAULT == 4 * 1024 * 1024
        rmem_max = _rmem_max()
        if rmem_max is not None:  # unprivileged: capped at net.core.rmem_max, never forced
            assert dflt.rcvbuf_bytes_granted == 2 * min(UDP_RCVBUF_BYTES_DEFAULT, rmem_max)
    finally:
        small.close()
        dflt.close()
        out.close()
    assert small.rcvbuf_bytes_granted is None


@pytest.mark.parametrize("bad", [0, -1, 2**31, 4096.0, True, None, "4096"])
def test_rcvbuf_bytes_validated(bad):
    with pytest.raises(ValueError, match="rcvbuf_bytes"):
        UdpTransport(parse_url("udpin:127.0.0.1:0"), rcvbuf_bytes=bad)


def test_table_parser_matches_only_the_inode_column():
    header = (b"   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt"
              b"   uid  timeout inode ref pointer drops\n")
    # row 1 has 4242 as its uid (not the inode); row 2 is the socket
    row1 = b"  1: 0100007F:3039 00000000:0000 07 00000000:00000000 00:00000000 00000000  4242        0 777 2 0000000000000000 5\n"
    row2 = b"  2: 0100007F:303A 00000000:0000 07 00000000:00000000 00:00000000 00000000  1000        0 4242 2 0000000000000000 17"
    table = header + row1 + row2
    assert _udp_drops_from_table(table, 4242) == 17
    assert _udp_drops_from_table(table, 777) == 5
    assert _udp_drops_from_table(table, 999) is None


@linux_only
@pytest.mark.skipif(shutil.which("unshare") is None, reason="needs util-linux unshare")
def test_readable_under_procsubset_pid():
    """systemd's ProcSubset=pid + ProtectProc=invisible mount /proc with subset=pid,hidepid=
    invisible: /proc/net disappears but /proc/self/net/udp stays, so the counter still works.
    Reproduced here in an unprivileged user+mount+pid namespace (skipped where not allowed)."""
    script = textwrap.dedent("""
        import os, socket
        from mavlink_io.transport import make_transport
        from mavlink_io.url import parse_url
        assert not os.path.exists("/proc/net/udp"), "subset=pid should hide /proc/net"
        t = make_transport(parse_url("udpin:127.0.0.1:0"), rcvbuf_bytes=4096)
        t.open()
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for _ in range(50):
            tx.sendto(bytes(40), t.local_address)
        n = 0
        while True:
            c = t.read()
            if not c:
                break
            n += len(c)
        print(50 - n, t.kernel_rx_drops())
    """)
    cmd = ["unshare", "-Urmpf", "--mount-proc", "sh", "-c",
           'mount -t proc -o subset=pid,hidepid=invisible proc /proc && exec "$0" -c "$1"',
           sys.executable, script]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=30, cwd=os.getcwd())
    if r.returncode != 0 and ("Operation not permitted" in r.stderr or "unshare failed" in r.stderr
                              or "mount:" in r.stderr):
        pytest.skip(f"user namespaces / proc subset=pid not available here: {r.stderr.strip()[:200]}")
    assert r.returncode == 0, r.stderr
    expected, reported = r.stdout.split()
    assert int(expected) > 0 and reported == expected
