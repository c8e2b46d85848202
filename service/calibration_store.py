"""Persistent store for the synthetic AHRS magnetometer calibration (KF1), METHODS.md B2.

What it keeps (one JSON file in the state directory, e.g. systemd's StateDirectory):
- ``current``: the estimate being learnt in the current flight (saved periodically, so a restart
  in flight resumes it);
- ``completed``: the estimates of the last ``keep_completed`` finished flights, newest last.

The rule (seed AU756340B2, B2): the estimator is handed an estimate **at least one flight
old** (``estimate_for_flight``): the newest completed flight whose id is below the current
flight's. A reference that failed silently in this flight can therefore never poison the
calibration this flight uses.

A flight ends implicitly when a new one begins (vehicles are powered off after landing, so an
explicit "landed" may never come): ``begin_flight`` moves an older ``current`` into
``completed``; a ``current`` with the same flight id is resumed (restart in flight).

File safety:
- atomic writes (service/state_file.py): a temp file in the same directory, flush + fsync, ``os.replace`` over
  the old file, fsync the directory. A crash leaves either the old or the new file.
- the payload is checked by a SHA-256 over its canonical JSON and a format/version header;
  a truncated, corrupted or unknown-version file is renamed ``<name>.corrupt[.N]`` and the store
  starts empty (status says why) instead of crashing the daemon.

File I/O lives here (service/), not in estimators/ (pure); the estimate itself is serialised by
``estimators.mag_error_kf.kf1_to_dict`` / ``kf1_from_dict``.

Use in the daemon::

    store = CalibrationStore(state_dir / "synthetic_ahrs_kf1.json")
    hist = store.load()                          # hist.status says if a file was set aside
    fid = next_flight_id(hist)                   # or hist.current.flight_id when restarting in flight
    hist = begin_flight(hist, fid, time.time())
    use = estimate_for_flight(hist, fid)         # at least one flight old, or None
    state = synthetic_ahrs_init(params, kf1_learn=learning_start(hist, fid),
                                kf1_applied=None if use is None else use.kf1)
    ...  # every ~30 s and at shutdown:
    hist = update_current(hist, fid, state.kf1_learn, time.time()); store.save(hist)
"""
from __future__ import annotations

import json
import pathlib
from dataclasses import dataclass, field, replace

from estimators.mag_error_kf import Kf1State, kf1_from_dict, kf1_to_dict
from service import state_file

FILE_FORMAT = "azimuthd-synthetic-ahrs-calibration"
FILE_VERSION = 1


@dataclass(frozen=True)
class FlightEstimate:
    flight_id: int
    kf1: Kf1State
    wall_time_s: float
    """Wall-clock time (s since the epoch) this estimate was saved / its flight completed."""


@dataclass(frozen=True)
class CalibrationHistory:
    current: FlightEstimate | None = None
    completed: tuple[FlightEstimate, ...] = ()
    """Newest last."""
    status: str = "empty"
    """How the history was obtained: empty | loaded | missing | corrupt: <why>."""


def _fe_to_dict(fe: FlightEstimate) -> dict:
    return {"flight_id": fe.flight_id, "wall_time_s": fe.wall_time_s, "kf1": kf1_to_dict(fe.kf1)}


def _fe_from_dict(d: dict) -> FlightEstimate:
    try:
        return FlightEstimate(flight_id=int(d["flight_id"]), wall_time_s=float(d["wall_time_s"]),
                              kf1=kf1_from_dict(d["kf1"]))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"flight estimate malformed: {exc}") from exc


def history_to_document(history: CalibrationHistory) -> dict:
    payload = {"current": None if history.current is None else _fe_to_dict(history.current),
               "completed": [_fe_to_dict(fe) for fe in history.completed]}
    return state_file.document(FILE_FORMAT, FILE_VERSION, payload)


def _history_from_payload(payload: dict) -> CalibrationHistory:
    cur = payload.get("current")
    completed = payload.get("completed")
    if not isinstance(completed, list):
        raise ValueError("'completed' is not a list")
    return CalibrationHistory(current=None if cur is None else _fe_from_dict(cur),
                              completed=tuple(_fe_from_dict(d) for d in completed),
                              status="loaded")


def history_from_document(doc: object) -> CalibrationHistory:
    """Validate a parsed file; ValueError saying what is wrong."""
    return _history_from_payload(state_file.payload_from_document(doc, FILE_FORMAT, FILE_VERSION, "calibration"))


# --- the rules (pure) -----------------------------------------------------------------------

def next_flight_id(history: CalibrationHistory) -> int:
    ids = [fe.flight_id for fe in history.completed]
    if history.current is not None:
        ids.append(history.current.flight_id)
    return max(ids, default=0) + 1


def begin_flight(history: CalibrationHistory, flight_id: int, wall_time_s: float,
                 keep_completed: int = 3) -> CalibrationHistory:
    """Start (or resume) flight ``flight_id``: an older ``current`` becomes completed."""
    cur = history.current
    if cur is not None and cur.flight_id == flight_id:
        return history
    completed = list(history.completed)
    if cur is not None:
        if cur.flight_id > flight_id:
            raise ValueError(f"flight id {flight_id} is older than the stored current flight {cur.flight_id}")
        kf1 = replace(cur.kf1, flight_count=cur.kf1.flight_count + 1)
        completed.append(FlightEstimate(cur.flight_id, kf1, wall_time_s))
    return replace(history, current=None, completed=tuple(completed[-keep_completed:]))


def update_current(history: CalibrationHistory, flight_id: int, kf1: Kf1State,
                   wall_time_s: float) -> CalibrationHistory:
    """Record this flight's (learning) estimate."""
    if history.current is not None and history.current.flight_id != flight_id:
        raise ValueError(f"call begin_flight({flight_id}) first (current is flight {history.current.flight_id})")
    return replace(history, current=FlightEstimate(flight_id, kf1, wall_time_s))


def estimate_for_flight(history: CalibrationHistory, flight_id: int) -> FlightEstimate | None:
    """The estimate the estimator may use in flight ``flight_id``: the newest completed flight
    with an id below it (at least one flight old); None when there is none."""
    older = [fe for fe in history.completed if fe.flight_id < flight_id]
    return max(older, key=lambda fe: fe.flight_id) if older else None


def learning_start(history: CalibrationHistory, flight_id: int) -> Kf1State | None:
    """Where KF1 starts learning in flight ``flight_id``: the resumed current-flight estimate
    after a restart, else the newest completed one (learning continues across flights)."""
    if history.current is not None and history.current.flight_id == flight_id:
        return history.current.kf1
    fe = estimate_for_flight(history, flight_id)
    return None if fe is None else fe.kf1


# --- the file -------------------------------------------------------------------------------

@dataclass
class CalibrationStore:
    path: pathlib.Path
    keep_completed: int = 3
    last_error: str = field(default="", init=False)

    def __post_init__(self):
        self.path = pathlib.Path(self.path)
        if self.keep_completed < 1:
            raise ValueError(f"keep_completed must be >= 1, got {self.keep_completed}")

    def load(self) -> CalibrationHistory:
        """Read the file; a damaged one is set aside as *.corrupt and an empty history returned."""
        payload, status = state_file.read_document(self.path, FILE_FORMAT, FILE_VERSION, "calibration")
        if payload is None:
            return CalibrationHistory(status=status)
        try:
            return _history_from_payload(payload)
        except ValueError as exc:
            return CalibrationHistory(status=f"corrupt: {exc}; moved to {state_file.set_aside(self.path)}")

    def save(self, history: CalibrationHistory) -> bool:
        """Atomic write; False (and ``last_error``) on an OS error, never a partial file."""
        data = json.dumps(history_to_document(history), indent=1, allow_nan=False).encode("utf-8")
        self.last_error = state_file.atomic_write_bytes(self.path, data)
        return not self.last_error
