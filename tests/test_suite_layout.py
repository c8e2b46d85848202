"""The suite under two workers (make test: pytest-xdist -n 2 --dist loadfile, tests/conftest.py).

GIVEN the test modules WHEN one starts a process (the simulator, the daemon, ArduPilot SITL, a
browser, a subscriber) THEN it is either in conftest.REALTIME_MODULES (one unit of work, one worker,
one module after another: two real-time flights never compete for the 2 cores) or listed here as
light, with the reason it may run beside another; and every collected test is in the unit that says so.
"""
from __future__ import annotations

import re
from pathlib import Path

import conftest

TESTS = Path(__file__).resolve().parent
STARTS_A_PROCESS = re.compile(r"Popen\(|\bSitl\(|\brun_load\(|\bdaemon_flights\(|\brun_daemon\(|\baps\.fly\("
                              r"|\b_start\(|readme_commands\(|\bbusy_run\(")
"""How a module starts a live process: directly, or through a harness of bench/ or of another test."""

LIGHT = {
    "test_security_unprivileged": "one daemon start and its first frames, waited for while it works",
    "test_service_solver_orphan": "a solver worker and its parent, no stream",
    "test_sim_ports": "the simulator on a pty for a few seconds; counts in its own clock",
    "test_systemd_lifecycle": "short daemon runs without an FC stream",
    "test_systemd_start": "one daemon start to READY=1, its cost measured in CPU seconds",
    "test_zenoh_bus": "a subscriber or a liveliness holder for a few seconds",
    "test_reliability_zenoh_stall": "a stalled subscriber: what is asserted is that the publisher never blocks",
}
"""Modules that start processes but may run beside a real-time one (no stream that must keep pace)."""


def _modules() -> dict[str, str]:
    return {p.stem: p.read_text() for p in sorted(TESTS.glob("test_*.py")) if p.stem != Path(__file__).stem}


def test_every_module_that_starts_a_process_is_placed():
    modules = _modules()
    starting = {name for name, text in modules.items() if STARTS_A_PROCESS.search(text)}
    unplaced = starting - conftest.REALTIME_MODULES - LIGHT.keys()
    assert not unplaced, (f"{sorted(unplaced)} start processes: add each to conftest.REALTIME_MODULES, or to "
                          "LIGHT here with the reason it may run beside a real-time test")
    assert not conftest.REALTIME_MODULES & LIGHT.keys()
    assert conftest.REALTIME_MODULES <= modules.keys(), "a real-time module no longer exists"
    assert LIGHT.keys() & modules.keys() <= starting, "a LIGHT module no longer starts a process"


def test_each_collected_test_is_in_its_unit(request):
    # THEN a real-time module's tests are in the one real-time unit, any other test in its
    # module's own unit (its module fixtures are built once, on one worker)
    for item in request.session.items:
        unit = conftest.xdist_unit(item.nodeid)
        if item.path.stem in conftest.REALTIME_MODULES:
            assert unit == conftest.REALTIME_UNIT, item.nodeid
        else:
            assert unit == item.nodeid.split("::")[0] and unit.endswith(f"{item.path.stem}.py"), item.nodeid
