"""The daemon's loop and Python's cyclic garbage collector (issue 19, the daemon's own CPU at 400 Hz).

What the daemon builds before its loop (the modules, pymavlink's dialects, the Pipeline, the link:
~80k objects) lives as long as the process. Left in the collector's generations, every full
collection in flight walks all of it (a pause, and CPU at 400 Hz that does no work); frozen once
the daemon is up (gc.freeze), the collections walk only what the loop made."""
from __future__ import annotations

import gc
import signal
import socket

from service.config import validate
from service.daemon import Daemon


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_daemon_freezes_what_it_built_before_its_loop(tmp_path):
    # GIVEN a daemon on a UDP port no FC talks to, and a heap with nothing frozen
    site = {"lat_deg": 48.14, "lon_deg": 11.58, "alt_m": 520.0, "decimal_year": 2026.42}
    d = Daemon(validate({"site": site, "mavlink": {"url": f"udpin:127.0.0.1:{_free_udp_port()}"},
                         "zenoh": {"enabled": False}, "service": {"state_dir": str(tmp_path)},
                         "outputs": {"status_interval_s": 0.0}}))
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    gc.unfreeze()
    seen = {}
    step = d.step

    def first_step(timeout_s: float) -> None:
        seen.setdefault("frozen", gc.get_freeze_count())
        seen.setdefault("pipeline", any(o is d.pipeline for o in gc.get_objects()))
        step(timeout_s)

    d.step = first_step
    try:
        # WHEN it runs its loop
        d.run(duration_s=0.05)
    finally:
        gc.unfreeze()
        for sig, h in handlers.items():
            signal.signal(sig, h)
    # THEN by its first step the objects it built are frozen, out of the collector's generations
    assert seen["frozen"] > 10_000
    assert seen["pipeline"] is False
