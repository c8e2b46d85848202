"""Test-session setup: single-threaded BLAS, as the daemon runs (service/cli.py).

The estimators multiply small matrices (3x3 to ~30x4500); a threaded OpenBLAS on a busy 2-core
machine spends its time in locking and spinning: one normal-equation build of method A took 51 ms per
call threaded (a 4500x27 Gram matrix: 144 ms threaded, 0.27 ms single-threaded on the loaded
development machine), and the 240 s method-D flight (tests/test_pipeline_deviation.py) took 106 s
against 22 s. pytest imports this file before any test module imports numpy.
"""
import os
import time

import pytest

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

@pytest.fixture(scope="session", autouse=True)
def _simulated_flights_under_basetemp(tmp_path_factory):
    """A simulated flight's work folder (bench/sitl.py: logs, truth, the daemon's state), when a
    test gives none, goes under pytest's base folder, which pytest prunes to its last three runs: a
    suite run leaves no flight folders behind in /tmp. (Not every temporary file: a test that runs
    the daemon as an unprivileged user needs a folder that user can reach.)"""
    before = os.environ.get("AZIMUTHD_SITL_TMPDIR")
    os.environ["AZIMUTHD_SITL_TMPDIR"] = str(tmp_path_factory.mktemp("sitl", numbered=False))
    yield
    if before is None:
        os.environ.pop("AZIMUTHD_SITL_TMPDIR", None)
    else:
        os.environ["AZIMUTHD_SITL_TMPDIR"] = before


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


def wait_progressing(cond, progress, what, stall_s: float = 60.0, hang_s: float = HANG_S,
                     poll_s: float = 0.1, stall_ok: bool = False):
    """Wait until ``cond()`` is truthy and return its value, for as long as the watched processes
    make progress: ``progress()`` returns a value that changes while they work (a count of samples
    they processed, a log's size, their CPU time). A busy machine only slows the progress down; it
    fails (AssertionError: ``what``, a str or a callable giving one, e.g. a log's tail) when
    nothing changed for ``stall_s`` or after ``hang_s`` in all: both only detect a hang, never a
    measure of speed. ``stall_ok``: a stall ends the wait instead (returns the falsy ``cond()``),
    e.g. a drain that ends when the process has nothing more to give."""
    t0 = t_seen = time.monotonic()
    last = progress()
    while True:
        got = cond()
        if got:
            return got
        now = time.monotonic()
        seen = progress()
        if seen != last:
            last, t_seen = seen, now
        if stall_ok and now - t_seen > stall_s:
            return cond()
        if now - t_seen > stall_s or now - t0 > hang_s:
            why = (f"no progress for {stall_s:g} s" if now - t_seen > stall_s
                   else f"not after {hang_s:g} s although still progressing")
            raise AssertionError(f"{what() if callable(what) else what}\n({why}; progress {last!r})")
        time.sleep(poll_s)


def cpu_seconds(*procs) -> float:
    """CPU time (s) used so far by these processes (subprocess.Popen or pids) and their children,
    exited ones counting 0: what ``wait_progressing`` watches for processes that work while a
    test waits for them (importing, computing, catching up)."""
    import psutil
    total = 0.0
    for p in procs:
        try:
            ps = psutil.Process(p if isinstance(p, int) else p.pid)
            for q in (ps, *ps.children(recursive=True)):
                t = q.cpu_times()
                total += t.user + t.system
        except (psutil.NoSuchProcess, psutil.ZombieProcess, psutil.AccessDenied):
            continue
    return round(total, 2)


# --- two workers (make test: pytest-xdist -n 2 --dist loadfile) ------------------------------
REALTIME_MODULES = frozenset({
    "test_ardupilot_sitl", "test_e2e_heading", "test_e2e_sitl", "test_first_run", "test_geofence_sitl",
    "test_mavlink_sim_faults", "test_mavproxy_e2e", "test_outputs_mavsdk", "test_reliability_link",
    "test_reliability_load", "test_reliability_overflow", "test_reliability_restart",
    "test_reliability_restart_in_flight", "test_security_signing_e2e", "test_sim_live", "test_speed_busy",
    "test_web_dashboard",
})
"""Test modules whose processes (the simulator, the daemon, ArduPilot SITL, a browser) run in real
time against the wall clock. Under xdist they are one unit of work, run one after another on one
worker, so two of them never compete for the 2 cores; the CPU-bound rest runs beside them on the
other worker. tests/test_suite_layout.py keeps this list in step with the modules that start
such a process."""
REALTIME_UNIT = "realtime"


def xdist_unit(nodeid: str) -> str:
    """The unit of work a test belongs to under ``--dist loadfile``: its module (the module's
    fixtures, e.g. a simulated flight several tests share, are built once, on one worker), or
    REALTIME_UNIT for every test of REALTIME_MODULES."""
    path = nodeid.split("::", 1)[0]
    return REALTIME_UNIT if os.path.splitext(os.path.basename(path))[0] in REALTIME_MODULES else path


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    # xdist's own loadgroup marks groups by rewriting item._nodeid, which pytest 9.2's nodeid no
    # longer reads: loadfile's scheduler with the real-time modules merged into one unit instead
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class RealtimeAsOneUnit(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_unit(nodeid)
    return RealtimeAsOneUnit(config, log)


def pytest_collection_modifyitems(config, items):
    if hasattr(config, "workerinput"):  # an xdist worker: the real-time unit first in the queue
        items.sort(key=lambda it: xdist_unit(it.nodeid) != REALTIME_UNIT)


CPU_BOUND_NICE = 10
"""Under xdist the real-time unit shares the 2 cores with the other worker's CPU-bound modules. As
root, a worker runs CPU-bound modules at this nice and the real-time ones at 0 (both workers are one
CPU group, so nice orders them): the processes a real-time test starts inherit 0, as the systemd
unit's Nice= puts the daemon ahead of the companion computer's other work (CPU_BOUND_NICE 10 vs 0:
weight 110 vs 1024). Not root: nothing changes (a nice once raised could not be lowered again)."""


def pytest_runtest_setup(item):
    if not hasattr(item.config, "workerinput") or os.geteuid() != 0:
        return
    want = 0 if xdist_unit(item.nodeid) == REALTIME_UNIT else CPU_BOUND_NICE
    if os.getpriority(os.PRIO_PROCESS, 0) != want:
        os.setpriority(os.PRIO_PROCESS, 0, want)
