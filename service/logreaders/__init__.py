"""Flight-log readers for ``azimuthd replay``: a log in, the typed samples of mavlink_io.samples out.

Every reader yields, in time order, the same items the daemon's link hands to the Pipeline:
``ImuSample`` (sensor frame as the FC logs it, SI units, magnetometer in gauss held from the
last magnetometer sample as RAW_IMU carries it), ``PressureSample`` (absolute Pa, differential Pa
or None, K), ``FcAttitude`` (the log's own attitude estimate: the reference of the replay), and
for telemetry logs also what the link produces (LinkEvent, FcHeartbeat, FcEkfStatus, ...).

=========== ============================ ===========================================================
extension   reader                       streams used
=========== ============================ ===========================================================
.tlog       logreaders.tlog              RAW_IMU | HIGHRES_IMU | SCALED_IMU, SCALED_PRESSURE,
                                         ATTITUDE (through mavlink_io.link: the daemon's decoder)
.bin        logreaders.dataflash         IMU, MAG, BARO, ARSP, ATT (pymavlink DFReader)
.ulg        logreaders.ulog              sensor_combined, vehicle_magnetometer, vehicle_air_data,
                                         differential_pressure | airspeed, vehicle_attitude (pyulog)
=========== ============================ ===========================================================

A stream the log does not have is reported in ``missing`` (never guessed, never zero-filled).
Common interface (duck-typed, see ``LogReader``); bad input raises :class:`LogError` with a
message naming the file and the problem, in one line (a damaged or truncated file is read up to
the damage and says so in ``summary.notes``; a reader never lets a parser's exception out).

``items(imu_batches=True)`` may give a run of consecutive IMU samples as one
``mavlink_io.imu_batch.ImuBatch`` (IMU_RECORD rows: the same values as the ImuSamples it stands
for; the tlog reader passes on its link's batches, the ULog reader decodes its whole log into rows,
the DataFlash reader gives ImuSamples either way): what ``azimuthd replay`` hands the Pipeline.

Readers also yield ``FcFlightState`` (the FC's own armed / landed state from the log's records),
the Pipeline's phase evidence; ``takeoff_times_s()`` gives the log's own take-off times from the
same records, a reference for scoring only (the Pipeline never sees it).
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Protocol


class LogError(ValueError):
    """A log that cannot be replayed (unknown extension, not a log, truncated, no IMU)."""


@dataclass(frozen=True)
class LogSite:
    """Where the log says the vehicle was (first valid GNSS fix or home), for the field model."""
    lat_deg: float
    lon_deg: float
    alt_m: float
    source: str
    """Which message gave it, e.g. "GPS_RAW_INT (fix 3)"."""


@dataclass(frozen=True)
class FcIdentity:
    """What a log says of its FC where it carries no HEARTBEAT (DataFlash, ULog): its MAV_TYPE, its
    autopilot and its take-off parameters (service/vehicle_type.py), for ``[launch] vehicle = "auto"``."""
    mav_type: int
    autopilot: str
    params: dict
    source: str
    """Where it was read, for the user (e.g. "PARM FRAME_CLASS", "vehicle_status.system_type")."""


@dataclass
class LogSummary:
    """What a reader found: per-stream sample counts, missing streams, notes for the user."""
    kind: str
    autopilot: str | None = None
    counts: dict = field(default_factory=dict)
    missing: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    fc_identity: FcIdentity | None = None
    params: dict = field(default_factory=dict)
    """Every FC parameter the log carries (name -> value; one set again during the log keeps its
    last value); empty where the format keeps none (a tlog)."""


class LogReader(Protocol):
    path: Path
    summary: LogSummary

    def site(self) -> LogSite | None: ...
    def decimal_year(self) -> float | None: ...
    def items(self, imu_batches: bool = False) -> Iterator: ...
    def progress(self) -> float: ...
    def takeoff_times_s(self) -> list[float]: ...


EXTENSIONS = {".tlog": "tlog", ".bin": "dataflash", ".ulg": "ulog"}


def open_log(path: str | Path) -> "LogReader":
    """The reader for ``path`` by its extension; LogError for an unknown extension or bad file."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in EXTENSIONS:
        raise LogError(f"{p}: unknown log type {ext or '(no extension)'!r}; "
                       f"expected one of {', '.join(EXTENSIONS)} (MAVLink telemetry, ArduPilot "
                       "DataFlash, PX4 ULog)")
    if not p.is_file():
        raise LogError(f"{p}: no such file")
    if p.stat().st_size == 0:
        raise LogError(f"{p}: empty file")
    if ext == ".tlog":
        from service.logreaders.tlog import TlogLogReader
        return TlogLogReader(p)
    if ext == ".bin":
        from service.logreaders.dataflash import DataflashReader
        return DataflashReader(p)
    from service.logreaders.ulog import UlogReader
    return UlogReader(p)


def decimal_year_from_unix(t_s: float) -> float | None:
    """Decimal year of a Unix time (UTC); None when it is not a plausible date (1990..2100)."""
    if not math.isfinite(t_s) or not 631152000 <= t_s <= 4102444800:
        return None
    d = _dt.datetime.fromtimestamp(t_s, tz=_dt.timezone.utc)
    start = _dt.datetime(d.year, 1, 1, tzinfo=_dt.timezone.utc)
    end = _dt.datetime(d.year + 1, 1, 1, tzinfo=_dt.timezone.utc)
    return d.year + (d - start).total_seconds() / (end - start).total_seconds()


GPS_EPOCH_UNIX_S = 315964800
"""1980-01-06 00:00:00 UTC, the GPS week origin, as Unix time."""
GPS_LEAP_S = 18
"""GPS - UTC since 2017 (good to a few seconds for a date: all the field model needs)."""


def one_line(exc: BaseException) -> str:
    """An exception as one short line (type and message), for a LogError's text."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:160]}" if text else type(exc).__name__


class FlightStateTrack:
    """The FC's armed / landed state as a log states it, record by record, and its take-offs.

    ``update(t_s, armed=..., landed=..., arming_event=...)`` takes what one record says (None: it
    says nothing about that) and returns the combined state (armed, landed), each carried from the
    last record that said it. A take-off is a landed -> in-air transition while armed (or while
    the log never says): from "landed" said before, or from no landed state at all after an
    arming seen in the log (an arming record, or armed after disarmed: a vehicle arms on the
    ground). A log that starts in the air has no take-off until it lands again."""

    def __init__(self) -> None:
        self.armed: bool | None = None
        self.landed: bool | None = None
        self.takeoffs_s: list[float] = []
        self._armed_on_ground = False

    def update(self, t_s: float, armed: bool | None = None, landed: bool | None = None,
               arming_event: bool = False) -> tuple[bool | None, bool | None]:
        if armed is not None:
            if armed and (arming_event or self.armed is False):
                self._armed_on_ground = self.landed is not False
            elif not armed:
                self._armed_on_ground = False
            self.armed = armed
        if landed is False and self.landed is not False and self.armed is not False \
                and (self.landed is True or self._armed_on_ground):
            self.takeoffs_s.append(t_s)
        if landed is not None:
            self._armed_on_ground = False
            self.landed = landed
        return self.armed, self.landed
