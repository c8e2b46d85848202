"""GIVEN a DataFlash or ULog log (no HEARTBEAT in it) and the example config's [launch] vehicle = "auto"
WHEN it is replayed THEN the take-off model comes from what the log says of its FC (its MAV_TYPE /
firmware parameters), is named with its source, and a take-off is detected (before this, "auto"
waited for a HEARTBEAT that a log never has: no take-off, silently)."""
from __future__ import annotations

from pathlib import Path

import pytest

from service.config import validate
from service.logreaders import open_log
from service.replay import run_replay

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SITE = {"site": {"lat_deg": 45.0, "lon_deg": 7.0, "alt_m": 300.0}}


def _need(name: str) -> Path:
    p = DATA / name
    if not p.exists():
        pytest.skip(f"{p} absent (the shared real logs)")
    return p


@pytest.mark.parametrize("name, mav_type, source", [
    ("arducopter-rtl-midflight.bin", 2, "PARM FRAME_CLASS"),      # no MSG in this log: its copter-only parameter
    ("px4-vtol-airspeed-small.ulg", 22, "parameter MAV_TYPE"),
    ("px4-quad-no-gnss.ulg", 2, "parameter MAV_TYPE"),
])
def test_reader_says_what_the_fc_is(name, mav_type, source):
    ident = open_log(_need(name)).summary.fc_identity
    assert ident is not None and ident.mav_type == mav_type and ident.source.startswith(source)


def test_vtol_log_replayed_with_auto_takes_off_near_the_logs_own_takeoff():
    reader = open_log(_need("px4-vtol-airspeed-small.ulg"))
    cfg = validate(SITE)
    assert cfg["launch"]["vehicle"] == "auto"
    res = run_replay(reader, cfg, None)
    vehicle = [d for _, k, d in res.events if k == "vehicle"]
    assert len(vehicle) == 1 and vehicle[0].startswith("vtol take-off (auto)") and "parameter MAV_TYPE" in vehicle[0]
    launch = [t for t, k, d in res.events if k == "phase" and d == "launch"]
    (log_takeoff,) = reader.takeoff_times_s()
    # measured: 23.68 s against the log's 22.67 s (its land detector is itself late by design)
    assert launch and 0.0 <= launch[0] - log_takeoff <= 2.0
