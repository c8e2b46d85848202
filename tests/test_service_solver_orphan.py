"""GIVEN a daemon with its azimuth solver worker WHEN the daemon is SIGKILLed (no close())
THEN the worker does not outlive it (an orphan would keep a core of the companion computer)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

CHILD = textwrap.dedent("""
    import os, sys
    from service.solver import BackgroundSolver
    s = BackgroundSolver()
    fut = s._pool.submit(os.getpid)          # starts the worker and tells its pid
    print(fut.result(timeout=120), flush=True)
    sys.stdin.read()                          # wait to be killed
""")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_solver_worker_ends_with_a_killed_daemon():
    p = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        worker_pid = int(p.stdout.readline())
        assert worker_pid != p.pid and _alive(worker_pid)
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
        # a hang bound, not a timing claim: the kernel delivers the death signal at once
        deadline = time.monotonic() + 60
        while _alive(worker_pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(worker_pid), f"solver worker {worker_pid} outlived its killed daemon"
    finally:
        if p.poll() is None:
            p.kill()
