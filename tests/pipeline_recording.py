"""A flight through the daemon's Pipeline with a chosen core backend, for the compiled core's parity
tests (tests/test_core_polar_attitude.py, tests/test_core_polar_heading.py): a simulated flight fed as
the daemon feeds it, a real log replayed as ``azimuthd replay`` runs it.

``fly(name, sims, inputs, data_dir, no_site=())`` runs one flight and returns what it gave;
``run_with_backend(fly_one, name, backend)`` runs ``fly_one(name)`` with ``backend`` as every Pipeline's
core backend and returns (what it gave, the Pipeline that ran)."""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import feed_pipeline  # noqa: E402

REPLAY_KEYS = ("time_s", "phase", "cols", "heading_source", "roll_sigma_deg", "pitch_sigma_deg", "events",
               "phases", "imu_samples")
NO_SITE_GIVEN = "47.37,8.54"
"""The site given to a log without a GNSS fix, as `azimuthd replay --site` does (where it flew is
unknown: the field model is Zurich's; parity does not depend on it)."""


def fly(name: str, sims: dict, inputs: dict, data_dir: Path, no_site=()) -> dict:
    """Run the flight through ``service.pipeline.Pipeline`` as looked up now: ``sims[name]()`` gives
    (config, items) of a simulated flight (cached in ``inputs``), fed as bench/sitl.feed_pipeline feeds
    the daemon (its solutions and events); any other name is a real log in ``data_dir`` replayed by
    service/replay.run_replay (its rows and events; skipped when absent)."""
    import service.pipeline as sp
    if name in sims:
        if name not in inputs:
            inputs[name] = sims[name]()
        cfg, items = inputs[name]
        events: list = []
        sols = list(feed_pipeline(sp.Pipeline(cfg), items, events))
        return {"solutions": sols, "events": events}
    from service.logreaders import open_log
    from service.replay import build_config, run_replay
    path = data_dir / name
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    log = open_log(path)
    site = NO_SITE_GIVEN if name in no_site else None
    cfg, _ = build_config(SimpleNamespace(config=None, site=site, exclude_fc_yaw=False), log)
    res = run_replay(log, cfg, None)
    return {k: getattr(res, k) for k in REPLAY_KEYS}



def select_core_backend(monkeypatch):
    """The compiled core's backend as the daemon selects it (AZIMUTHD_CORE unset): the parity tests'
    "core" side; fails when the core is not what select() gives."""
    from service import core_backend as cb
    monkeypatch.delenv("AZIMUTHD_CORE", raising=False)
    backend = cb.select()
    assert backend.name == "core"
    return backend

def run_with_backend(fly_one, name: str, backend):
    """(what ``fly_one(name)`` returns, the Pipeline it ran) with ``backend`` as the Pipeline's core backend."""
    import service.pipeline as sp
    made: list = []

    class Kept(sp.Pipeline):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: backend)
        mp.setattr(sp, "Pipeline", Kept)
        out = fly_one(name)
    finally:
        mp.undo()
    return out, made[-1]
