"""Where the heavy least-squares re-solves of method A run.

The per-sample path must stay cheap: a re-solve of psi_s with distortions over ~1000
magnetometer samples costs tens to hundreds of milliseconds, which would stall the MAVLink loop
(every IMU sample behind it waits). ``BackgroundSolver`` runs the pure ``azimuth_solve`` on a
snapshot of the state in one worker process; the result is merged into the then-current state
(``azimuth_apply_solve``) when it is ready. ``InlineSolver`` runs it at once, for replay and
tests, where the result must not depend on timing. The Pipeline hands the state with its samples as one
packed array (estimators.azimuth.PackedSamples, service/hot_path.py SamplePack): a worker gets one ndarray,
not up to 1,500 pickled MagRecords, and solves it the same.
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os

log = logging.getLogger("azimuthd.solver")


def _die_with_daemon(daemon_pid: int) -> None:
    """Worker initializer: the worker ends when the daemon does, even a SIGKILLed daemon (no
    close() then). Its parent is the forkserver, not the daemon, and the forkserver stays up while
    any worker holds its pipe: PR_SET_PDEATHSIG cannot see the daemon go, so a watcher thread waits
    on a pidfd of the daemon (Linux >= 5.3) or, where there is none, checks it every 2 s."""
    import os
    import select
    import threading

    def watch() -> None:
        try:
            fd = os.pidfd_open(daemon_pid)
        except (AttributeError, OSError):
            fd = None
        if fd is not None:
            select.select([fd], [], [])               # readable when the daemon has exited
        else:
            import time
            while True:
                try:
                    os.kill(daemon_pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    pass
                time.sleep(2.0)
        os._exit(0)

    threading.Thread(target=watch, name="daemon-watch", daemon=True).start()


def _new_pool() -> cf.ProcessPoolExecutor:
    # forkserver: the worker does not inherit the daemon's sockets and threads (zenoh)
    return cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver"),
                                  initializer=_die_with_daemon, initargs=(os.getpid(),))


def _solve_job(state, time_s, *kernels):
    """``kernels``: the solve's implementations, (fit_psi, orientation_diversity) of the Pipeline's backend
    (estimators.azimuth_fit's or estimators.core's: module functions, so a worker process unpickles them
    by name); none given: the reference."""
    from estimators.azimuth import azimuth_solve, azimuth_solve_result
    return azimuth_solve_result(azimuth_solve(state, time_s, *kernels))


class InlineSolver:
    """Solves at once; ``poll`` returns the result at the next call."""
    background = False

    def __init__(self):
        self._result = None

    def busy(self) -> bool:
        return False

    def submit(self, state, time_s: float, *kernels) -> bool:
        self._result = _solve_job(state, time_s, *kernels)
        return True

    def poll(self):
        r, self._result = self._result, None
        return r

    def ready(self) -> bool:
        """``poll`` would return a result now (the Pipeline's hot path leaves such a sample to Python)."""
        return self._result is not None

    def close(self) -> None:
        pass


class BackgroundSolver:
    """One worker process; at most one solve in flight (a newer snapshot waits for it)."""
    background = True

    def __init__(self):
        self._pool = _new_pool()
        self._future: cf.Future | None = None
        self._inline: InlineSolver | None = None
        self.failures = 0

    def busy(self) -> bool:
        return self._future is not None and not self._future.done()

    def submit(self, state, time_s: float, *kernels) -> bool:
        if self._pool is None:  # the worker could not be restarted: inline from now on
            return self._inline.submit(state, time_s, *kernels)
        if self.busy():
            return False
        try:
            self._future = self._pool.submit(_solve_job, state, time_s, *kernels)
        except (RuntimeError, cf.process.BrokenProcessPool) as exc:
            self._restart(exc)
            return False
        return True

    def poll(self):
        if self._pool is None:
            return self._inline.poll()
        f = self._future
        if f is None or not f.done():
            return None
        self._future = None
        try:
            return f.result()
        except cf.process.BrokenProcessPool as exc:
            self._restart(exc)
        except Exception as exc:  # the solve itself failed: report it, keep flying on the last solution
            self.failures += 1
            log.error("azimuth solve failed", extra={"fields": {"error": repr(exc)}})
        return None

    def ready(self) -> bool:
        """``poll`` would return a result (or a failure to report) now."""
        if self._pool is None:
            return self._inline.ready()
        return self._future is not None and self._future.done()

    def _restart(self, exc: BaseException) -> None:
        self.failures += 1
        log.error("azimuth solver process died; restarting it", extra={"fields": {"error": repr(exc)}})
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._future = None
        try:
            self._pool = _new_pool()
        except OSError as exc2:
            self._pool = None
            self._inline = InlineSolver()
            log.error("azimuth solver process cannot be restarted; solving in the main loop from now on",
                      extra={"fields": {"error": repr(exc2)}})

    def close(self) -> None:
        """Stop the worker at once (a solve in flight is not waited for) and wait for the pool's
        own thread: shutdown(wait=False) left it running, and CPython's exit hook then wrote to the
        pool's closed wake-up pipe (an 'OSError: Bad file descriptor' traceback at a daemon's stop)."""
        if self._pool is None:
            return
        for proc in list((getattr(self._pool, "_processes", None) or {}).values()):
            proc.terminate()
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_solver(background: bool):
    """The daemon's solver: a worker process if asked and possible, else inline (with the reason
    logged: e.g. an interpreter or /dev/shm the service user may not use). Inline solves cost the
    loop tens to hundreds of milliseconds each, a degraded but working mode."""
    if not background:
        return InlineSolver()
    try:
        return BackgroundSolver()
    except OSError as exc:
        log.error("azimuth solver process unavailable; solving in the main loop",
                  extra={"fields": {"error": repr(exc)}})
        return InlineSolver()
