"""Message-rate requests: MAV_CMD_SET_MESSAGE_INTERVAL one at a time, fallback REQUEST_DATA_STREAM.

The MAVLink command protocol allows one outstanding command of a given id per target, and an
ArduPilot COMMAND_ACK for SET_MESSAGE_INTERVAL does not say which message it is about, so the
requests go out strictly one after the other: send, wait for the COMMAND_ACK (or ``ack_timeout_s``),
resend up to ``max_tries`` times with ``confirmation`` incremented, then move on.

A refused rate (ACK DENIED or FAILED: ArduPilot denies an interval shorter than its main loop allows,
"Requested rate for message ID 27 too fast. Increase SCHED_LOOP_RATE") is asked again at half the
rate, down to ``floor_hz`` (None: no retry lower). Once a lower rate is accepted, ``BISECT_STEPS``
more requests halve the gap to the lowest refused one (accepted: the new rate holds; refused: the
FC keeps the last accepted interval), so a stock ArduPlane (50 Hz loop, streams up to 40 Hz) grants
37.5 Hz for a 200 Hz request instead of the 25 Hz halving alone finds. ``granted_hz`` keeps the
rate the FC accepted last and ``asked_hz`` the first one asked for, so the user can be told what
was refused and why.

When no request at all was accepted (no ACK, or every ACK UNSUPPORTED: old firmware), the link falls
back to the legacy REQUEST_DATA_STREAM (which has no ACK), one request per stream group.

Pure state machine: the caller passes the time and executes the returned actions.
"""
from __future__ import annotations

from dataclasses import dataclass, field

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_NAMES = {0: "accepted", 1: "temporarily_rejected", 2: "denied", 3: "unsupported",
                    4: "failed", 5: "in_progress", 6: "cancelled"}
MAV_RESULT_IN_PROGRESS = 5
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_FAILED = 4

# ArduPilot's legacy stream groups (GCS_MAVLink stream lists) for the REQUEST_DATA_STREAM fallback
DATA_STREAM_OF = {
    "RAW_IMU": 1,  # MAV_DATA_STREAM_RAW_SENSORS
    "SCALED_IMU": 1,
    "SCALED_PRESSURE": 1,
    "HIGHRES_IMU": 1,
    "SYS_STATUS": 2,  # MAV_DATA_STREAM_EXTENDED_STATUS
    "ATTITUDE": 10,  # MAV_DATA_STREAM_EXTRA1
    "EKF_STATUS_REPORT": 12,  # MAV_DATA_STREAM_EXTRA3
    "ESTIMATOR_STATUS": 12,
}


@dataclass(frozen=True, slots=True)
class SendInterval:
    """Action: send COMMAND_LONG(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)."""
    name: str
    msg_id: int
    interval_us: float
    confirmation: int


@dataclass(frozen=True, slots=True)
class Finished:
    """Action: the round is over; ``results`` maps message name -> outcome."""
    results: dict


BISECT_STEPS = 2
"""Requests between the accepted and the lowest refused rate after a refusal (see the docstring)."""


@dataclass(slots=True)
class _Pending:
    name: str
    msg_id: int
    interval_us: float
    tries: int
    sent_at_s: float
    refused_hz: float | None = None
    """Lowest rate the FC refused for this message in this round."""
    accepted_hz: float | None = None
    """Highest rate it accepted after a refusal (the interval it now uses)."""
    bisect_left: int = BISECT_STEPS


@dataclass(slots=True)
class RateRequester:
    ack_timeout_s: float = 0.5
    max_tries: int = 3
    give_up_after: int = 2
    """End the round early when this many messages in a row got no ACK at all and none was
    accepted yet: the FC does not speak SET_MESSAGE_INTERVAL, go to the fallback without waiting
    for every message's timeouts (the rest are marked "not_tried")."""
    floor_hz: float | None = None
    """A DENIED/FAILED rate is asked again at half the rate while that stays >= this (Hz);
    None: a refusal is final."""
    active: bool = False
    no_ack_streak: int = 0
    asked_hz: dict = field(default_factory=dict)
    """Message name -> the rate first asked for in this round (Hz)."""
    granted_hz: dict = field(default_factory=dict)
    """Message name -> the rate the FC accepted (Hz), after any retries lower."""
    queue: list = field(default_factory=list)
    current: _Pending | None = None
    results: dict = field(default_factory=dict)
    finished_at_s: float | None = None

    def start(self, wanted: list[tuple[str, int, float]], now_s: float) -> list:
        """wanted: [(message name, message id, rate Hz)]. Restarts any round in progress."""
        self.queue = list(wanted)
        self.results = {}
        for name, _msg_id, rate_hz in wanted:
            self.asked_hz[name] = float(rate_hz)
            self.granted_hz.pop(name, None)
        self.current = None
        self.active = True
        self.no_ack_streak = 0
        return self._next(now_s)

    def _next(self, now_s: float) -> list:
        if not self.queue:
            self.active = False
            self.current = None
            self.finished_at_s = now_s
            return [Finished(dict(self.results))]
        name, msg_id, rate_hz = self.queue.pop(0)
        self.current = _Pending(name, msg_id, 1e6 / rate_hz, 1, now_s)
        return [SendInterval(name, msg_id, self.current.interval_us, 0)]

    def on_ack(self, command: int, result: int, now_s: float) -> list:
        if not self.active or self.current is None or command != MAV_CMD_SET_MESSAGE_INTERVAL:
            return []
        if result in (MAV_RESULT_IN_PROGRESS, MAV_RESULT_TEMPORARILY_REJECTED):
            return []  # keep waiting; the timeout resends
        cur = self.current
        self.no_ack_streak = 0
        rate_hz = 1e6 / cur.interval_us
        refused = result in (MAV_RESULT_DENIED, MAV_RESULT_FAILED)
        if refused and self.floor_hz is not None:
            cur.refused_hz = rate_hz if cur.refused_hz is None else min(cur.refused_hz, rate_hz)
            if cur.accepted_hz is None and rate_hz / 2.0 >= self.floor_hz:
                # refused as too fast: ask for half (ArduPilot grants up to 0.8 x its loop rate)
                return self._ask(cur, rate_hz / 2.0, now_s)
            if cur.accepted_hz is not None:  # refused while bisecting up: the last accepted holds
                return self._bisect_or_finish(cur, now_s)
        if result == 0 and cur.refused_hz is not None and self.floor_hz is not None:
            cur.accepted_hz = rate_hz
            return self._bisect_or_finish(cur, now_s)
        self.results[cur.name] = MAV_RESULT_NAMES.get(result, f"result_{result}")
        if result == 0:
            self.granted_hz[cur.name] = rate_hz
        return self._next(now_s)

    def _ask(self, cur: _Pending, rate_hz: float, now_s: float) -> list:
        cur.interval_us, cur.tries, cur.sent_at_s = 1e6 / rate_hz, 1, now_s
        return [SendInterval(cur.name, cur.msg_id, cur.interval_us, 0)]

    def _bisect_or_finish(self, cur: _Pending, now_s: float) -> list:
        """After a refusal and an acceptance: one more step halfway up, or the accepted rate stands."""
        if cur.bisect_left > 0:
            cur.bisect_left -= 1
            return self._ask(cur, 0.5 * (cur.accepted_hz + cur.refused_hz), now_s)
        self.results[cur.name] = "accepted"
        self.granted_hz[cur.name] = cur.accepted_hz
        return self._next(now_s)

    def next_due_s(self) -> float | None:
        if not self.active or self.current is None:
            return None
        return self.current.sent_at_s + self.ack_timeout_s

    def poll(self, now_s: float) -> list:
        due = self.next_due_s()
        if due is None or now_s < due:
            return []
        cur = self.current
        if cur.tries < self.max_tries:
            cur.tries += 1
            cur.sent_at_s = now_s
            return [SendInterval(cur.name, cur.msg_id, cur.interval_us, cur.tries - 1)]
        if cur.accepted_hz is not None:  # no answer to a step up: the accepted rate stands
            cur.bisect_left = 0
            return self._bisect_or_finish(cur, now_s)
        self.results[cur.name] = "no_ack"
        self.no_ack_streak += 1
        if self.no_ack_streak >= self.give_up_after and "accepted" not in self.results.values():
            for name, _msg_id, _rate in self.queue:
                self.results[name] = "not_tried"
            self.queue = []
        return self._next(now_s)


def data_stream_requests(wanted: list[tuple[str, int, float]]) -> dict[int, int]:
    """REQUEST_DATA_STREAM fallback: stream id -> rate Hz (uint16, the max over its messages)."""
    out: dict[int, int] = {}
    for name, _msg_id, rate_hz in wanted:
        sid = DATA_STREAM_OF.get(name)
        if sid is None:
            continue
        out[sid] = max(out.get(sid, 0), max(1, min(65535, int(round(rate_hz)))))
    return out
