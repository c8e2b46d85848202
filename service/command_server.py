"""Commands addressed to our component: what we do with them and what we answer.

A ground station reaches the companion computer through the flight controller, which routes a
COMMAND_LONG / COMMAND_INT whose target component is ours (191) to the port it heard our HEARTBEAT
on. The link (mavlink_io.link) has already applied the signing policy: with a key and
``require_signed`` = "commands", an unsigned command never gets here. This module decides, the
daemon acts and sends the COMMAND_ACK (MAVLink command protocol: one ACK per command received,
retries included).

What we act on:
- MAV_CMD_REQUEST_MESSAGE (512), param1 = message id: HEARTBEAT, ATTITUDE, ATTITUDE_QUATERNION
  (the latter two from the current solution; TEMPORARILY_REJECTED before there is one);
- MAV_CMD_DO_FENCE_ENABLE (207), param1 = 0 / 1: stop / resume the geofence divert monitor
  (DENIED without a [geofence] section; param1 = 2, "disable floor only", is UNSUPPORTED: we
  have no floor).
Everything else is UNSUPPORTED; with ``accept_commands = false`` everything is DENIED.

A COMMAND_LONG retry (``confirmation`` > 0, same command, source and parameters within
``RETRY_WINDOW_S``) is answered again with the first answer and not acted on twice: the first
ACK was lost, the command was not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink2

from mavlink_io.samples import IncomingCommand

RETRY_WINDOW_S = 5.0
MSG_HEARTBEAT = mavlink2.MAVLINK_MSG_ID_HEARTBEAT
MSG_ATTITUDE = mavlink2.MAVLINK_MSG_ID_ATTITUDE
MSG_ATTITUDE_QUATERNION = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
REQUESTABLE_IDS = (MSG_HEARTBEAT, MSG_ATTITUDE, MSG_ATTITUDE_QUATERNION)

RESULT_NAMES = {mavlink2.MAV_RESULT_ACCEPTED: "ACCEPTED", mavlink2.MAV_RESULT_TEMPORARILY_REJECTED: "TEMPORARILY_REJECTED",
                mavlink2.MAV_RESULT_DENIED: "DENIED", mavlink2.MAV_RESULT_UNSUPPORTED: "UNSUPPORTED",
                mavlink2.MAV_RESULT_FAILED: "FAILED"}


def command_name(command: int) -> str:
    entry = mavlink2.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD_{command}"


@dataclass(frozen=True)
class Decision:
    result: int
    """MAV_RESULT for the COMMAND_ACK."""
    action: str | None
    """What the daemon does: "request_message", "fence_enable", "fence_disable", or None."""
    message_id: int | None
    reason: str
    """One line for the log and the events topic (names the command, the source, signed or not)."""
    repeat: bool = False
    """A retry of a command already answered: ACK again, do not act again."""

    @property
    def result_name(self) -> str:
        return RESULT_NAMES.get(self.result, str(self.result))


class CommandServer:
    """Decides on each IncomingCommand. State: the recent answers (for retries) only."""

    def __init__(self, accept_commands: bool, fence_configured: bool):
        self.accept_commands = accept_commands
        self.fence_configured = fence_configured
        self._recent: dict[tuple, tuple[float, Decision]] = {}
        self.counts: dict[str, int] = {}

    def decide(self, cmd: IncomingCommand, now_s: float, have_solution: bool) -> Decision:
        key = (cmd.source_system, cmd.source_component, cmd.command, cmd.is_int, _params_key(cmd.params))
        self._recent = {k: v for k, v in self._recent.items() if now_s - v[0] <= RETRY_WINDOW_S}
        if not cmd.is_int and cmd.confirmation > 0 and key in self._recent:
            first = self._recent[key][1]
            d = Decision(first.result, None, first.message_id, first.reason + " (retry, answered again)", repeat=True)
        else:
            d = self._decide(cmd, have_solution)
            self._recent[key] = (now_s, d)
        self.counts[d.result_name] = self.counts.get(d.result_name, 0) + 1
        return d

    def revise(self, d: Decision, result: int, why: str) -> Decision:
        """The daemon could not do what was decided: the answer becomes ``result`` (for retries too)."""
        new = Decision(result, None, d.message_id, f"{d.reason.split(':')[0]}: {why}", d.repeat)
        self.counts[d.result_name] -= 1
        self.counts[new.result_name] = self.counts.get(new.result_name, 0) + 1
        for k, (t, old) in self._recent.items():
            if old is d:
                self._recent[k] = (t, new)
        return new

    def _decide(self, cmd: IncomingCommand, have_solution: bool) -> Decision:
        who = (f"{command_name(cmd.command)} from {cmd.source_system}/{cmd.source_component} "
               f"({'signed' if cmd.signed else 'unsigned'})")
        p1 = cmd.params[0] if cmd.params else float("nan")
        if not self.accept_commands:
            return Decision(mavlink2.MAV_RESULT_DENIED, None, None, f"{who}: denied (accept_commands = false)")
        if cmd.command == mavlink2.MAV_CMD_REQUEST_MESSAGE:
            if not _is_int_value(p1) or int(p1) not in REQUESTABLE_IDS:
                return Decision(mavlink2.MAV_RESULT_DENIED, None, None,
                                f"{who}: message id {p1!r} not provided (we answer {', '.join(map(str, REQUESTABLE_IDS))})")
            mid = int(p1)
            if mid != MSG_HEARTBEAT and not have_solution:
                return Decision(mavlink2.MAV_RESULT_TEMPORARILY_REJECTED, None, mid, f"{who}: no solution yet")
            return Decision(mavlink2.MAV_RESULT_ACCEPTED, "request_message", mid, f"{who}: message {mid} sent")
        if cmd.command == mavlink2.MAV_CMD_DO_FENCE_ENABLE:
            if not self.fence_configured:
                return Decision(mavlink2.MAV_RESULT_DENIED, None, None, f"{who}: no [geofence] configured")
            if p1 == 0:
                return Decision(mavlink2.MAV_RESULT_ACCEPTED, "fence_disable", None,
                                f"{who}: geofence divert monitor DISABLED")
            if p1 == 1:
                return Decision(mavlink2.MAV_RESULT_ACCEPTED, "fence_enable", None,
                                f"{who}: geofence divert monitor enabled")
            return Decision(mavlink2.MAV_RESULT_UNSUPPORTED, None, None, f"{who}: param1 {p1!r} not supported (0 or 1)")
        return Decision(mavlink2.MAV_RESULT_UNSUPPORTED, None, None, f"{who}: not supported by azimuthd")


def _is_int_value(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and float(x) == int(x)


def _params_key(params: tuple) -> tuple:
    # NaN != NaN: compare parameters by their text so that a retry with NaN fields still matches
    return tuple(repr(p) for p in params)
