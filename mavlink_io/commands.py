"""The MAVLink command protocol: COMMAND_LONG / COMMAND_INT, COMMAND_ACK awaited, retried, reported.

A pure-ish state machine with no clock and no socket of its own: the daemon's loop drives it with
``poll(now_s)`` and ``on_command_ack(ack, now_s)`` and injects ``send(msg)`` (``link.send``) and
the target (the autopilot's system/component, known once the link has seen its HEARTBEAT).

Rules (MAVLink "Command Protocol", https://mavlink.io/en/services/command.html):
* one command in flight at a time; further commands wait in a short queue (``max_queue``, the
  oldest queued one is dropped as ``superseded`` when it is full); a command equal to one already
  queued or in flight (same ``key``) is not queued twice;
* a try that gets no COMMAND_ACK within ``ack_timeout_s`` (+ ``input_delay_s``, how late the caller
  reads its input) is resent, up to ``max_tries`` tries;
  COMMAND_LONG retries carry ``confirmation`` = 1, 2, ... (0 on the first try); COMMAND_INT has
  no such field and is resent as is;
* MAV_RESULT_IN_PROGRESS: the autopilot is working on it; no resend; the final ACK is awaited
  for up to ``in_progress_timeout_s`` (each progress ACK restarts that wait);
* MAV_RESULT_TEMPORARILY_REJECTED: retried after ``ack_timeout_s`` while tries remain, then
  reported ``denied`` with that result;
* ACCEPTED -> ``accepted``; DENIED, UNSUPPORTED, FAILED, CANCELLED, ... -> ``denied`` (result kept);
  no ACK after the last try -> ``timeout``; dropped by ``submit(..., supersede=True)`` or a full
  queue -> ``superseded``.
Every finished command yields exactly one :class:`CommandOutcome`, returned by ``poll``,
``on_command_ack`` or ``submit`` and also passed to the optional ``on_outcome`` callback.

Sends are paced: never two sends closer than ``min_send_interval_s`` (no flood even if a peer
answers every try with TEMPORARILY_REJECTED at once).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_IN_PROGRESS = 5
MAV_RESULT_NAMES = {0: "accepted", 1: "temporarily_rejected", 2: "denied", 3: "unsupported", 4: "failed",
                    5: "in_progress", 6: "cancelled", 7: "command_long_only", 8: "command_int_only",
                    9: "unsupported_mav_frame"}

MAV_CMD_NAV_RETURN_TO_LAUNCH = mavlink2.MAV_CMD_NAV_RETURN_TO_LAUNCH        # 20
MAV_CMD_DO_SET_MODE = mavlink2.MAV_CMD_DO_SET_MODE                          # 176
MAV_CMD_DO_REPOSITION = mavlink2.MAV_CMD_DO_REPOSITION                      # 192
MAV_CMD_DO_FLIGHTTERMINATION = mavlink2.MAV_CMD_DO_FLIGHTTERMINATION        # 185
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT  # 6
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED  # 1
MAV_DO_REPOSITION_FLAGS_CHANGE_MODE = 1


@dataclass(frozen=True)
class CommandSpec:
    """One command to send. COMMAND_LONG: params p1..p7. COMMAND_INT (use_int): p1..p4, then
    x, y as integers (degE7 for global frames), z as float, in ``frame``."""
    name: str
    """What it is for (``rtl``, ``reposition``...): appears in outcomes and logs."""
    command: int
    params: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    use_int: bool = False
    frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def __post_init__(self):
        if not isinstance(self.command, int) or isinstance(self.command, bool) or not 0 <= self.command <= 65535:
            raise ValueError(f"CommandSpec.command must be an integer MAV_CMD, got {self.command!r}")
        if len(self.params) != 7:
            raise ValueError(f"CommandSpec.params must have 7 values, got {len(self.params)}")
        for i, p in enumerate(self.params):
            if not isinstance(p, (int, float)) or isinstance(p, bool):
                raise ValueError(f"CommandSpec.params[{i}] must be a number, got {p!r}")
            if self.use_int and i in (4, 5):
                if not (math.isfinite(p) and float(p).is_integer() and -2**31 <= p < 2**31):
                    raise ValueError(f"CommandSpec.params[{i}] (COMMAND_INT x/y) must be an int32, got {p!r}")

    @property
    def key(self) -> tuple:
        return (self.command, self.use_int, self.frame, tuple(repr(float(p)) for p in self.params))  # NaN-safe


@dataclass(frozen=True)
class CommandOutcome:
    name: str
    command: int
    status: str
    """accepted | denied | timeout | superseded"""
    result: int | None
    """The MAV_RESULT of the final ACK (None for timeout / superseded)."""
    tries: int
    submitted_s: float
    finished_s: float
    detail: str = ""

    @property
    def result_name(self) -> str:
        return "-" if self.result is None else MAV_RESULT_NAMES.get(self.result, f"result_{self.result}")


@dataclass(frozen=True)
class CommandProtocolParams:
    ack_timeout_s: float = 1.0
    """Wait per try for the COMMAND_ACK (local monotonic seconds)."""
    max_tries: int = 5
    in_progress_timeout_s: float = 10.0
    """After MAV_RESULT_IN_PROGRESS, how long to wait for the next ACK."""
    max_queue: int = 4
    min_send_interval_s: float = 0.05

    def __post_init__(self):
        for name in ("ack_timeout_s", "in_progress_timeout_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 < v <= 600):
                raise ValueError(f"CommandProtocolParams.{name} must be in (0, 600] s, got {v!r}")
        if not (isinstance(self.min_send_interval_s, (int, float)) and 0 <= self.min_send_interval_s < self.ack_timeout_s):
            raise ValueError("CommandProtocolParams.min_send_interval_s must be in [0, ack_timeout_s), got "
                             f"{self.min_send_interval_s!r}")
        for name, hi in (("max_tries", 20), ("max_queue", 16)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
                raise ValueError(f"CommandProtocolParams.{name} must be an integer in [1, {hi}], got {v!r}")


@dataclass
class _InFlight:
    spec: CommandSpec
    submitted_s: float
    tries: int = 0
    deadline_s: float = 0.0
    in_progress: bool = False
    last_result: int | None = None
    resend_due: bool = False


@dataclass
class CommandStats:
    sent: int = 0
    retries: int = 0
    acks: int = 0
    acks_unmatched: int = 0
    outcomes: dict = field(default_factory=dict)


class CommandProtocol:
    """One command in flight, a short de-duplicated queue, retries with a timeout, outcomes."""

    def __init__(self, send: Callable[[object], object], target: Callable[[], tuple[int | None, int | None]],
                 params: CommandProtocolParams = CommandProtocolParams(),
                 on_outcome: Callable[[CommandOutcome], None] | None = None):
        """send(msg): sends a pymavlink message (link.send). target(): (system, component) of the
        autopilot, None while unknown (nothing is sent until it is known; the try is not counted)."""
        self._send = send
        self._target = target
        self.params = params
        self._on_outcome = on_outcome
        self._queue: deque[tuple[CommandSpec, float]] = deque()
        self._cur: _InFlight | None = None
        self._last_send_s = -math.inf
        self.stats = CommandStats()
        self.input_delay_s = 0.0
        """How late the caller is reading its input (s; the geofence monitor's input age): an ACK
        the FC sent promptly sits behind that backlog, so a try times out only after
        ack_timeout_s + input_delay_s (a late daemon does not escalate on ACKs it has not read yet:
        with ``terminate`` configured that would end a flight the FC had already diverted)."""

    # --- state -----------------------------------------------------------------------------

    @property
    def in_flight(self) -> CommandSpec | None:
        return None if self._cur is None else self._cur.spec

    @property
    def pending(self) -> list[CommandSpec]:
        return [s for s, _ in self._queue]

    @property
    def idle(self) -> bool:
        return self._cur is None and not self._queue

    def next_due_s(self) -> float | None:
        """When poll() next has something to do (None: nothing in flight)."""
        if self._cur is None:
            return None
        if self._cur.tries == 0 or self._cur.resend_due:
            return self._last_send_s + self.params.min_send_interval_s
        return self._cur.deadline_s + self.input_delay_s

    # --- inputs ----------------------------------------------------------------------------

    def submit(self, spec: CommandSpec, now_s: float, supersede: bool = False) -> list[CommandOutcome]:
        """Queue a command (sent at once if nothing is in flight). supersede=True drops the
        command in flight and every queued one first (reported ``superseded``). A command equal to
        the one in flight or a queued one is ignored. Returns the outcomes this caused."""
        out: list[CommandOutcome] = []
        if supersede:
            out.extend(self.cancel_all(now_s, f"superseded by {spec.name}"))
        elif (self._cur is not None and self._cur.spec.key == spec.key) or any(s.key == spec.key for s, _ in self._queue):
            return out
        if len(self._queue) >= self.params.max_queue:
            old, t0 = self._queue.popleft()
            out.append(self._finish_spec(old, t0, "superseded", None, 0, now_s, "queue full"))
        self._queue.append((spec, now_s))
        out.extend(self.poll(now_s))
        return out

    def cancel_all(self, now_s: float, why: str = "cancelled") -> list[CommandOutcome]:
        out = []
        if self._cur is not None:
            cur, self._cur = self._cur, None
            out.append(self._finish_spec(cur.spec, cur.submitted_s, "superseded", None, cur.tries, now_s, why))
        while self._queue:
            spec, t0 = self._queue.popleft()
            out.append(self._finish_spec(spec, t0, "superseded", None, 0, now_s, why))
        return out

    def on_command_ack(self, ack, now_s: float) -> list[CommandOutcome]:
        """A COMMAND_ACK (mavlink_io.samples.CommandAck or the raw pymavlink message) addressed to
        us; the link has already filtered the sender and the target."""
        self.stats.acks += 1
        cur = self._cur
        if cur is None or int(ack.command) != cur.spec.command or cur.tries == 0:
            self.stats.acks_unmatched += 1
            return []
        result = int(ack.result)
        cur.last_result = result
        if result == MAV_RESULT_IN_PROGRESS:
            cur.in_progress = True
            cur.deadline_s = now_s + self.params.in_progress_timeout_s
            return []
        if result == MAV_RESULT_TEMPORARILY_REJECTED and cur.tries < self.params.max_tries:
            cur.resend_due = False
            cur.deadline_s = now_s + self.params.ack_timeout_s  # retry at the deadline, not at once
            return []
        status = "accepted" if result == MAV_RESULT_ACCEPTED else "denied"
        self._cur = None
        out = [self._finish_spec(cur.spec, cur.submitted_s, status, result, cur.tries, now_s,
                                 MAV_RESULT_NAMES.get(result, f"result {result}"))]
        out.extend(self.poll(now_s))
        return out

    def poll(self, now_s: float) -> list[CommandOutcome]:
        """Send, resend or give up as the clock says; start the next queued command."""
        out: list[CommandOutcome] = []
        for _ in range(self.params.max_queue + 2):
            cur = self._cur
            if cur is None:
                if not self._queue:
                    return out
                spec, t0 = self._queue.popleft()
                self._cur = cur = _InFlight(spec, t0)
            if cur.tries == 0 or cur.resend_due:
                if not self._try_send(cur, now_s):
                    return out
                return out
            if now_s < cur.deadline_s + self.input_delay_s:
                return out
            if cur.tries >= self.params.max_tries or cur.in_progress:
                self._cur = None
                if cur.in_progress:
                    detail = "no final ACK after IN_PROGRESS"
                elif cur.last_result == MAV_RESULT_TEMPORARILY_REJECTED:
                    detail = f"temporarily rejected, then no ACK; {cur.tries} tries"
                else:
                    detail = f"no COMMAND_ACK after {cur.tries} tries"
                status, result = "timeout", None
                out.append(self._finish_spec(cur.spec, cur.submitted_s, status, result, cur.tries, now_s, detail))
                continue
            cur.resend_due = True
            if not self._try_send(cur, now_s):
                return out
            return out
        return out

    # --- internals -------------------------------------------------------------------------

    def _try_send(self, cur: _InFlight, now_s: float) -> bool:
        if now_s - self._last_send_s < self.params.min_send_interval_s:
            cur.resend_due = True
            return False
        tgt_sys, tgt_comp = self._target()
        if tgt_sys is None or tgt_comp is None:
            cur.resend_due = True  # the autopilot is not known yet: nothing to address
            return False
        msg = self._encode(cur.spec, cur.tries, tgt_sys, tgt_comp)
        self._send(msg)
        self.stats.sent += 1
        if cur.tries > 0:
            self.stats.retries += 1
        cur.tries += 1
        cur.resend_due = False
        cur.deadline_s = now_s + self.params.ack_timeout_s
        self._last_send_s = now_s
        return True

    @staticmethod
    def _encode(spec: CommandSpec, confirmation: int, tgt_sys: int, tgt_comp: int):
        p = [float(x) for x in spec.params]
        if spec.use_int:
            return mavlink2.MAVLink_command_int_message(tgt_sys, tgt_comp, spec.frame, spec.command, 0, 0,
                                                        p[0], p[1], p[2], p[3], int(spec.params[4]),
                                                        int(spec.params[5]), p[6])
        return mavlink2.MAVLink_command_long_message(tgt_sys, tgt_comp, spec.command, min(confirmation, 255), *p)

    def _finish_spec(self, spec: CommandSpec, t0: float, status: str, result: int | None, tries: int,
                     now_s: float, detail: str) -> CommandOutcome:
        o = CommandOutcome(spec.name, spec.command, status, result, tries, t0, now_s, detail)
        self.stats.outcomes[status] = self.stats.outcomes.get(status, 0) + 1
        if self._on_outcome is not None:
            self._on_outcome(o)
        return o


# --- command builders (what the geofence sends) ---------------------------------------------

ARDUPILOT_RTL_MODE = {"plane": 11, "copter": 6, "rover": 11, "sub": 19}
PX4_MAIN_AUTO, PX4_SUB_RTL, PX4_SUB_LOITER = 4, 5, 3
ARDUPILOT_LOITER_MODE = {"plane": 12, "copter": 5, "rover": 5, "sub": 16}

_PLANE_TYPES = {1, 16, 19, 20, 21, 22, 23, 24, 25, 28}  # fixed wing and VTOL types
_ROVER_TYPES = {10, 11}
_SUB_TYPES = {12}


def ardupilot_frame(vehicle_type: int) -> str:
    if vehicle_type in _PLANE_TYPES:
        return "plane"
    if vehicle_type in _ROVER_TYPES:
        return "rover"
    if vehicle_type in _SUB_TYPES:
        return "sub"
    return "copter"


def cmd_rtl() -> CommandSpec:
    """MAV_CMD_NAV_RETURN_TO_LAUNCH (COMMAND_LONG, no parameters)."""
    return CommandSpec("rtl", MAV_CMD_NAV_RETURN_TO_LAUNCH)


def cmd_set_mode(mode: str, autopilot: str | None, vehicle_type: int) -> CommandSpec:
    """MAV_CMD_DO_SET_MODE to RTL or LOITER: param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
    ArduPilot param2 = the vehicle's mode number; PX4 param2 = main mode AUTO (4), param3 = sub
    mode (5 RTL, 3 LOITER)."""
    if mode not in ("rtl", "loiter"):
        raise ValueError(f"mode must be rtl or loiter, got {mode!r}")
    if autopilot == "px4":
        sub = PX4_SUB_RTL if mode == "rtl" else PX4_SUB_LOITER
        params = (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(PX4_MAIN_AUTO), float(sub), 0.0, 0.0, 0.0, 0.0)
    else:
        table = ARDUPILOT_RTL_MODE if mode == "rtl" else ARDUPILOT_LOITER_MODE
        params = (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(table[ardupilot_frame(vehicle_type)]),
                  0.0, 0.0, 0.0, 0.0, 0.0)
    return CommandSpec(f"{mode}_mode", MAV_CMD_DO_SET_MODE, params)


def cmd_reposition(lat_deg: float, lon_deg: float, alt_rel_m: float, ground_speed_m_s: float = -1.0) -> CommandSpec:
    """MAV_CMD_DO_REPOSITION as COMMAND_INT in MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: param1 ground
    speed (-1 default), param2 flag CHANGE_MODE (switch to guided/hold as needed), param4 yaw NaN
    (keep), x/y degE7, z metres above home."""
    for name, v, lo, hi in (("lat_deg", lat_deg, -90, 90), ("lon_deg", lon_deg, -180, 180),
                            ("alt_rel_m", alt_rel_m, -1000, 20000)):
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"{name} must be in [{lo}, {hi}], got {v!r}")
    return CommandSpec("reposition", MAV_CMD_DO_REPOSITION,
                       (float(ground_speed_m_s), float(MAV_DO_REPOSITION_FLAGS_CHANGE_MODE), 0.0, float("nan"),
                        int(round(lat_deg * 1e7)), int(round(lon_deg * 1e7)), float(alt_rel_m)),
                       use_int=True, frame=MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)


def cmd_terminate() -> CommandSpec:
    """MAV_CMD_DO_FLIGHTTERMINATION param1 = 1 (terminate now). Only ever as an explicit opt-in."""
    return CommandSpec("terminate", MAV_CMD_DO_FLIGHTTERMINATION, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


MAV_SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5, "info": 6,
                "debug": 7}


def statustext_message(severity: str, text: str):
    """A STATUSTEXT (#253) message: severity name (MAV_SEVERITY), text cut to 50 characters."""
    if severity not in MAV_SEVERITY:
        raise ValueError(f"severity must be one of {', '.join(MAV_SEVERITY)}, got {severity!r}")
    raw = text.encode("ascii", "replace")[:50]
    return mavlink2.MAVLink_statustext_message(MAV_SEVERITY[severity], raw)


__all__ = ["CommandSpec", "CommandOutcome", "CommandProtocolParams", "CommandProtocol", "CommandStats",
           "cmd_rtl", "cmd_set_mode", "cmd_reposition", "cmd_terminate", "statustext_message",
           "MAV_RESULT_NAMES", "ardupilot_frame"]
