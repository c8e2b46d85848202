"""Test-session setup: single-threaded BLAS, as the daemon runs (service/cli.py).

The estimators multiply small matrices (3x3 to ~30x4500); a threaded OpenBLAS on a busy 2-core
machine spends its time in locking and spinning: one normal-equation build of method A took 51 ms per
call threaded (a 4500x27 Gram matrix: 144 ms threaded, 0.27 ms single-threaded on the loaded
development machine), and the 240 s method-D flight (tests/test_pipeline_deviation.py) took 106 s
against 22 s. pytest imports this file before any test module imports numpy.
"""
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# --- what a busy machine may change, and what it may not ---------------------------------------
# The machine running the suite is shared (load 10-17 on 2 cores): a process may be descheduled
# for seconds. A test asserts what holds at any speed: rates in the sender's own clock (its
# time stamps), counts relative to what the sender says it sent, losses accounted with their
# cause (e.g. the kernel's drop counter of the receiving socket). Wall-clock deadlines only
# detect a hang.
HANG_S = 300.0
"""A wall-clock deadline that only detects a hang: never a measure of speed."""


def udp_kernel_drops(sock) -> int:
    """Datagrams the kernel dropped for this UDP socket because its receive buffer was full (the
    ``drops`` column of /proc/self/net/udp for the socket's inode): the accounted loss of a
    receiver that fell behind. 0 when the table does not list it (not Linux)."""
    import socket as _socket
    from mavlink_io.transport import _udp_drops_from_table
    path = "/proc/self/net/udp6" if sock.family == _socket.AF_INET6 else "/proc/self/net/udp"
    try:
        with open(path, "rb") as f:
            table = f.read()
    except OSError:
        return 0
    return _udp_drops_from_table(table, os.fstat(sock.fileno()).st_ino) or 0


def udp_rx_queue_bytes(port: int) -> int | None:
    """Bytes waiting in the receive queue of the IPv4 UDP socket bound to ``port`` (any process of
    this network namespace; /proc/net/udp's ``rx_queue``), None when no such socket is listed.
    0 means its owner has read everything: wait for that, not for a guessed time."""
    try:
        with open("/proc/net/udp") as f:
            rows = f.read().splitlines()[1:]
    except OSError:
        return None
    for row in rows:
        cols = row.split()
        if int(cols[1].split(":")[1], 16) == port:
            return int(cols[4].split(":")[1], 16)
    return None
