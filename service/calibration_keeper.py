"""The daemon's side of the calibration store: which flight this is, what to load, when to save.

A flight is one run of the daemon, unless the daemon restarts while a flight is going on: then
the stored ``current`` estimate is resumed (saved less than ``resume_within_s`` ago, e.g. systemd
restarted us after a crash or the watchdog). Otherwise a new flight begins and the previous one's
estimate becomes "completed"; method B is handed the newest estimate at least one flight old
(service/calibration_store.py has the rule and the file safety).
"""
from __future__ import annotations

import logging
import pathlib
import time

from estimators.mag_error_kf import Kf1State
from service.calibration_store import (CalibrationStore, begin_flight, estimate_for_flight,
                                       learning_start, next_flight_id, update_current)

log = logging.getLogger("azimuthd.calibration")

CALIBRATION_FILE = "synthetic_ahrs_calibration.json"


class CalibrationKeeper:
    def __init__(self, state_dir: pathlib.Path, clock=time.time, resume_within_s: float = 120.0):
        self.store = CalibrationStore(pathlib.Path(state_dir) / CALIBRATION_FILE)
        self.clock = clock
        self.resume_within_s = resume_within_s
        self.history = None
        self.flight_id: int | None = None

    def start(self) -> tuple[Kf1State | None, Kf1State | None]:
        """Load the file (a damaged one is set aside), choose the flight; (kf1_learn, kf1_applied)."""
        hist = self.store.load()
        if hist.status.startswith("corrupt"):
            log.error("calibration file damaged, set aside; starting without it",
                      extra={"fields": {"status": hist.status}})
        now = self.clock()
        cur = hist.current
        if cur is not None and now - cur.wall_time_s < self.resume_within_s:
            self.flight_id = cur.flight_id
            log.info("resuming the calibration of the flight in progress", extra={"fields": {"flight": cur.flight_id}})
        else:
            self.flight_id = next_flight_id(hist)
        self.history = begin_flight(hist, self.flight_id, now)
        applied = estimate_for_flight(self.history, self.flight_id)
        log.info("calibration loaded", extra={"fields": {
            "flight": self.flight_id, "file": str(self.store.path), "status": hist.status,
            "applied_from_flight": applied.flight_id if applied else "none"}})
        return learning_start(self.history, self.flight_id), applied.kf1 if applied else None

    def save(self, kf1: Kf1State | None, final: bool = False) -> bool:
        if kf1 is None or self.history is None:
            return False
        self.history = update_current(self.history, self.flight_id, kf1, self.clock())
        ok = self.store.save(self.history)
        if not ok:
            log.error("calibration not saved", extra={"fields": {"error": self.store.last_error}})
        elif final:
            log.info("calibration saved", extra={"fields": {"file": str(self.store.path), "flight": self.flight_id}})
        return ok
