"""``[launch] vehicle = "auto"``: the take-off model (service/phases.py VEHICLES) from what the FC says.

The FC's HEARTBEAT names its MAV_TYPE; for a fixed wing, how it leaves the ground is in its own
take-off parameters (read once with the daemon's other FC parameters, mavlink_io/params.py):

| HEARTBEAT type                                  | autopilot | parameter that decides          | vehicle     |
|-------------------------------------------------|-----------|---------------------------------|-------------|
| quad/hexa/octo/tri/coaxial/heli/dodeca/deca/generic multirotor | any | -                    | multicopter |
| VTOL_* (19-25), VTOL_GYRODYNE (47)              | any       | -                               | vtol        |
| ROCKET (9)                                      | any       | -                               | launcher    |
| FIXED_WING (1)                                  | ardupilot | Q_ENABLE 1 (a QuadPlane: ArduPlane 4.7 sends FIXED_WING for it, flown) | vtol |
|                                                 | ardupilot | TKOFF_THR_MINACC > 0 (hand/catapult/bungee launch: its take-off waits for that forward acceleration) | launcher |
|                                                 | px4       | FW_LAUN_DETCN_ON 1 (catapult/hand launch detection on) | launcher |
|                                                 | any       | none of the above (or not answered) | runway  |
| anything else (rover, boat, GCS, ...)           | any       | -                               | None: no take-off model; set [launch] vehicle |

Nothing is chosen before the HEARTBEAT, nor for a fixed wing before its parameters are answered
or given up (``params_wait_s`` after the HEARTBEAT, receive clock: a log replayed without the FC's
parameters decides on the HEARTBEAT alone). An explicit ``[launch] vehicle`` is used as configured.
Pure state: no I/O; the caller passes the times and reads the parameters ``param_names`` lists.
"""
from __future__ import annotations

from dataclasses import dataclass

AUTO = "auto"
MAV_TYPE_FIXED_WING = 1
MAV_TYPE_ROCKET = 9
MULTIROTOR_TYPES = {2: "quadrotor", 3: "coaxial", 4: "helicopter", 13: "hexarotor", 14: "octorotor",
                    15: "tricopter", 29: "dodecarotor", 35: "decarotor", 43: "generic multirotor"}
VTOL_TYPES = {19: "VTOL duorotor tailsitter", 20: "VTOL quadrotor tailsitter", 21: "VTOL tiltrotor",
              22: "VTOL fixed rotor", 23: "VTOL tailsitter", 24: "VTOL tiltwing", 25: "VTOL", 47: "VTOL gyrodyne"}
PARAMS = {"ardupilot": ("Q_ENABLE", "TKOFF_THR_MINACC"), "px4": ("FW_LAUN_DETCN_ON",)}
"""The FC parameters that say how a fixed wing takes off, per autopilot."""


def param_names(autopilot: str | None) -> tuple[str, ...]:
    """The parameters to read from this autopilot (read with the others: only a fixed wing waits on them)."""
    return PARAMS.get(autopilot or "", ())


@dataclass(frozen=True)
class VehicleChoice:
    vehicle: str | None
    """A phases.VEHICLES name; None: this FC type has no take-off model (the operator must set one)."""
    reason: str


def choose_vehicle(mav_type: int, autopilot: str, params: dict) -> VehicleChoice:
    """The take-off model for a HEARTBEAT ``mav_type`` of ``autopilot`` with the FC ``params``
    read so far (name -> value; an absent name was not answered)."""
    if mav_type in MULTIROTOR_TYPES:
        return VehicleChoice("multicopter", f"HEARTBEAT type {mav_type} ({MULTIROTOR_TYPES[mav_type]})")
    if mav_type in VTOL_TYPES:
        return VehicleChoice("vtol", f"HEARTBEAT type {mav_type} ({VTOL_TYPES[mav_type]})")
    if mav_type == MAV_TYPE_ROCKET:
        return VehicleChoice("launcher", f"HEARTBEAT type {mav_type} (rocket)")
    if mav_type != MAV_TYPE_FIXED_WING:
        return VehicleChoice(None, f"HEARTBEAT type {mav_type} has no take-off model: set [launch] vehicle")
    head = f"HEARTBEAT type 1 (fixed wing, {autopilot})"
    if autopilot == "ardupilot":
        if params.get("Q_ENABLE", 0.0) >= 1.0:
            return VehicleChoice("vtol", f"{head}, Q_ENABLE {params['Q_ENABLE']:g} (a QuadPlane)")
        acc = params.get("TKOFF_THR_MINACC", 0.0)
        if acc > 0.0:
            return VehicleChoice("launcher", f"{head}, TKOFF_THR_MINACC {acc:g} m/s^2 (a hand/catapult launch)")
    elif autopilot == "px4" and params.get("FW_LAUN_DETCN_ON", 0.0) >= 1.0:
        return VehicleChoice("launcher", f"{head}, FW_LAUN_DETCN_ON 1 (catapult/hand launch detection)")
    said = ", ".join(f"{n} {params[n]:g}" for n in param_names(autopilot) if n in params)
    unanswered = [n for n in param_names(autopilot) if n not in params]
    tail = (f", {said}" if said else "") + (f" ({', '.join(unanswered)} not answered)" if unanswered else "")
    return VehicleChoice("runway", f"{head}{tail}: a runway take-off")


class VehicleResolver:
    """Holds the configured value and, for ``auto``, waits for what ``choose_vehicle`` needs."""

    def __init__(self, configured: str, params_wait_s: float = 5.0):
        if not params_wait_s > 0.0:
            raise ValueError(f"params_wait_s must be > 0, got {params_wait_s!r}")
        self.configured = configured
        self.params_wait_s = params_wait_s
        self.choice: VehicleChoice | None = None if configured == AUTO else VehicleChoice(configured, "configured")
        self._hb: tuple[int, str] | None = None
        self._hb_rx_s: float | None = None
        self._params: dict = {}
        self._params_done = False

    @property
    def pending(self) -> bool:
        return self.choice is None

    def on_heartbeat(self, mav_type: int, autopilot: str, time_rx_s: float) -> VehicleChoice | None:
        """The FC's HEARTBEAT; the choice when made now (once), else None."""
        if self._hb is None:
            self._hb, self._hb_rx_s = (int(mav_type), autopilot), time_rx_s
        return self._decide(time_rx_s)

    def on_params(self, values: dict, done: bool, time_rx_s: float) -> VehicleChoice | None:
        """The FC's parameters read so far; ``done``: every asked one answered or given up."""
        self._params = {n: float(v) for n, v in values.items()}
        self._params_done = self._params_done or done
        return self._decide(time_rx_s)

    def poll(self, time_rx_s: float) -> VehicleChoice | None:
        return self._decide(time_rx_s)

    def _decide(self, now_s: float) -> VehicleChoice | None:
        if self.choice is not None or self._hb is None:
            return None
        mav_type, autopilot = self._hb
        names = param_names(autopilot) if mav_type == MAV_TYPE_FIXED_WING else ()
        have_all = all(n in self._params for n in names)
        if names and not (have_all or self._params_done or now_s - self._hb_rx_s >= self.params_wait_s):
            return None
        self.choice = choose_vehicle(mav_type, autopilot, self._params)
        return self.choice
