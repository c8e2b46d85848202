"""The azimuth solver worker cannot start or restart: the daemon solves inline, says so, runs on."""
from __future__ import annotations

import concurrent.futures as cf
import logging

from service import solver as solver_mod


class _NoPool:
    def __init__(self, *a, **k):
        raise BrokenPipeError(32, "Broken pipe")  # what a dead multiprocessing resource tracker gives


def test_worker_unavailable_at_start_falls_back_to_inline(monkeypatch, caplog):
    monkeypatch.setattr(cf, "ProcessPoolExecutor", _NoPool)
    with caplog.at_level(logging.ERROR, logger="azimuthd.solver"):
        s = solver_mod.make_solver(True)
    assert isinstance(s, solver_mod.InlineSolver)
    assert "solving in the main loop" in caplog.text
    assert isinstance(solver_mod.make_solver(False), solver_mod.InlineSolver)


def test_worker_that_cannot_be_restarted_goes_inline(monkeypatch, caplog):
    calls = []
    monkeypatch.setattr(solver_mod, "_solve_job", lambda state, t, *kernels: calls.append((state, t)) or ("solved", t))
    s = solver_mod.BackgroundSolver()
    try:
        monkeypatch.setattr(cf, "ProcessPoolExecutor", _NoPool)
        with caplog.at_level(logging.ERROR, logger="azimuthd.solver"):
            s._restart(cf.process.BrokenProcessPool("worker killed"))
        assert "cannot be restarted" in caplog.text
        assert s.submit("state", 12.0) is True
        assert s.poll() == ("solved", 12.0) and calls == [("state", 12.0)]
        assert s.poll() is None
    finally:
        s.close()
