"""The streams we ask the FC for: requests, achieved-rate checks, silent streams.

Rates are (re)requested when the autopilot is first seen, after an FC reboot, when the link comes
back (the link calls :meth:`StreamRates.request`), and when a requested stream stays silent
(:meth:`StreamRates.check_silent`). One round is :class:`~mavlink_io.rates.RateRequester`'s
SET_MESSAGE_INTERVAL state machine, with the legacy REQUEST_DATA_STREAM when nothing was accepted.
RATE_CHECK_DELAY_S after a round the achieved rates are measured (:meth:`check_achieved_due`): a
stream the FC accepted but does not deliver gets REQUEST_DATA_STREAM for its group, and one
``rates_limited`` event names the FC parameter to change.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

import math
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link_config import IMU_SOURCES, FcPeer, LinkConfig, message_id
from mavlink_io.rates import DATA_STREAM_OF, Finished, RateRequester, SendInterval, data_stream_requests
from mavlink_io.stats import LinkStats

# messages an autopilot family does not send: not requested from it
_NOT_SENT_BY = {"ardupilot": {"ESTIMATOR_STATUS"},
                "px4": {"RAW_IMU", "EKF_STATUS_REPORT"}}

_MAX_SILENT_REQUESTS = 3
RATE_CHECK_DELAY_S = 5.0
"""After a rate round, the achieved rates are measured over the link's rate window this much later."""
RATE_HONOURED_FRACTION = 0.5
"""An accepted stream measured below this fraction of its granted rate is not honoured: the legacy
REQUEST_DATA_STREAM is sent for its group."""
ARDUPILOT_RATE_PER_LOOP = 0.8
"""ArduPilot's SET_MESSAGE_INTERVAL refuses an interval below 1/(0.8 x SCHED_LOOP_RATE) (SITL,
SCHED_LOOP_RATE 50: RAW_IMU 50 Hz denied, 25 Hz accepted): the loop rate to advise."""
SCHED_LOOP_RATES_HZ = (50, 100, 200, 300, 400)
ARDUPILOT_STREAM_PARAM = {1: "RAW_SENS", 2: "EXT_STAT", 6: "POSITION", 10: "EXTRA1", 12: "EXTRA3"}
"""REQUEST_DATA_STREAM group -> the suffix of ArduPilot's stream-rate parameter (MAVn_ since 4.7,
SRn_ before)."""


class StreamRates:
    """Stream-rate requests for one link.

    fc: the autopilot (shared with the link, which learns it); seen_s: message name -> local time
    last received from the FC (shared, the link fills it); mav: the sending pymavlink object (its
    encoders); send(msg): the link's send; event(kind, detail, now, items): the link's events."""

    def __init__(self, cfg: LinkConfig, stats: LinkStats, fc: FcPeer, seen_s: dict[str, float], mav,
                 send: Callable, event: Callable[[str, str, float, list | None], None]):
        self.cfg = cfg
        self.stats = stats
        self.fc = fc
        self._seen_s = seen_s
        self.mav = mav
        self._send = send
        self._event = event
        self.requester = RateRequester(ack_timeout_s=cfg.ack_timeout_s, max_tries=cfg.request_tries,
                                       floor_hz=cfg.rate_floor_hz)
        self._rate_check_at_s: float | None = None
        self._data_stream_sent: set[int] = set()
        self.rate_refusal_text: str | None = None
        """The FC's last STATUSTEXT refusing a rate (ArduPilot: "... too fast. Increase SCHED_LOOP_RATE")."""
        self.rate_advice: str | None = None
        """The last rates_limited advice (which FC parameter to change), None while every rate is met."""
        self.wanted: list[tuple[str, int, float]] = []
        self._last_request_s: dict[str, float] = {}
        self._silent_requests: dict[str, int] = {}
        self._silent_not_before_s = -math.inf
        """``check_silent`` finds no stream silent before this local time (a lower bound from the last
        requests and receive times; -inf: not known). The loop wakes for every datagram: most wake-ups
        skip the walk over the streams."""
        self._silent_bound_at_s = -math.inf

    def next_due_s(self) -> float | None:
        """When a retry or the achieved-rate check is next due (None: nothing pending)."""
        due, check = self.requester.next_due_s(), self._rate_check_at_s   # every wake-up: no list
        if due is None or (check is not None and check < due):
            return check
        return due

    def report(self) -> dict[str, dict]:
        """Per requested stream: ``asked_hz``, ``granted_hz``, ``achieved_hz``, ``result``
        (MavlinkLink.stream_report)."""
        rates = self.stats.rates_hz()
        out = {}
        for name, _mid, rate in self.wanted:
            out[name] = {"asked_hz": rate, "granted_hz": self.requester.granted_hz.get(name),
                         "achieved_hz": float(rates.get(name, 0.0)),
                         "result": self.stats.rate_results.get(name, "requested")}
        return out

    def on_statustext(self, text: str) -> None:
        if "too fast" in text and "SCHED_LOOP_RATE" in text:
            self.rate_refusal_text = text

    def on_ack(self, command: int, result: int, now: float, items: list) -> None:
        self._run_actions(self.requester.on_ack(command, result, now), now, items)

    def poll_due(self, now: float, items: list) -> None:
        """Resend or give up on an unanswered request."""
        self._run_actions(self.requester.poll(now), now, items)

    def check_achieved_due(self, now: float, items: list) -> None:
        if self._rate_check_at_s is not None and now >= self._rate_check_at_s:
            self._rate_check_at_s = None
            self._check_achieved(now, items)

    def _wanted_rates(self) -> list[tuple[str, int, float]]:
        rates = dict(self.cfg.stream_rates_hz)
        autopilot = self.fc.autopilot
        if autopilot == "px4" and "EKF_STATUS_REPORT" in rates and "ESTIMATOR_STATUS" not in rates:
            rates["ESTIMATOR_STATUS"] = rates["EKF_STATUS_REPORT"]
        skip = set(_NOT_SENT_BY.get(autopilot, set()))
        if self.cfg.imu_source != "auto":
            skip |= set(IMU_SOURCES) - {self.cfg.imu_source}  # only the IMU stream we use
        elif autopilot == "ardupilot" and "RAW_IMU" in rates:
            skip.add("HIGHRES_IMU")  # one IMU stream is enough: RAW_IMU is ArduPilot's native one
        return [(n, message_id(n), float(r)) for n, r in rates.items() if n not in skip]

    def request(self, now: float, reason: str, items: list,
                only: list[tuple[str, int, float]] | None = None) -> None:
        """A new round for every wanted stream (``only``: just these, a silent-stream re-request)."""
        if not self.fc.known:
            return
        if only is None:
            self.wanted = self._wanted_rates()
            self._silent_requests.clear()
            self._data_stream_sent.clear()
            self._rate_check_at_s = None
        batch = self.wanted if only is None else only
        if not batch:
            return
        self._silent_not_before_s = -math.inf
        for n, _i, _r in batch:
            self._last_request_s[n] = now
        listing = ", ".join(f"{n} {r:g} Hz" for n, _i, r in batch)
        self._event("rates_requested", f"{reason}: SET_MESSAGE_INTERVAL {listing}", now, items)
        self._run_actions(self.requester.start(batch, now), now, items)

    def _run_actions(self, actions: list, now: float, items: list) -> None:
        for act in actions:
            if isinstance(act, SendInterval):
                msg = self.mav.command_long_encode(self.fc.system, self.fc.component,
                                                   mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, act.confirmation,
                                                   float(act.msg_id), float(act.interval_us), 0, 0, 0, 0, 0)
                self._send(msg)
                self.stats.rate_requests_sent += 1
            elif isinstance(act, Finished):
                self._finished(act.results, now, items)

    def _finished(self, results: dict, now: float, items: list) -> None:
        self.stats.rate_results.update(results)
        req = self.requester
        if self._rate_check_at_s is None:  # a re-request of a silent stream does not postpone it
            self._rate_check_at_s = now + max(RATE_CHECK_DELAY_S, self.cfg.rate_window_s)
        summary = ", ".join(f"{n}={r}" + (f" at {req.granted_hz[n]:g} Hz" if n in req.granted_hz
                                          and req.granted_hz[n] != req.asked_hz.get(n) else "")
                            for n, r in results.items())
        if any(r == "accepted" for r in results.values()):
            self._event("rates_acked", summary, now, items)
            return
        # nothing accepted (no ACK at all, or SET_MESSAGE_INTERVAL unsupported): legacy streams
        batch = [w for w in self.wanted if w[0] in results]
        streams = data_stream_requests(batch)
        for sid, hz in streams.items():
            self._send(self.mav.request_data_stream_encode(self.fc.system, self.fc.component, sid, hz, 1))
            self.stats.rate_requests_sent += 1
        for n, _i, _r in batch:
            if n in DATA_STREAM_OF and results.get(n) in ("no_ack", "unsupported", "not_tried"):
                self.stats.rate_results[n] = "data_stream"
        self._event("rates_requested", f"SET_MESSAGE_INTERVAL not accepted ({summary}); fallback "
                                       "REQUEST_DATA_STREAM " + ", ".join(f"stream {s} at {hz} Hz"
                                                                         for s, hz in streams.items()),
                    now, items)

    def _check_achieved(self, now: float, items: list) -> None:
        """After a rate round: what each stream gives, measured. A stream the FC accepted but does not
        deliver at half its granted rate gets the legacy REQUEST_DATA_STREAM for its group (once per
        round); every shortfall is told in one ``rates_limited`` event that names the FC parameter to
        change (SCHED_LOOP_RATE for a refused rate, the stream-rate parameter for one not honoured)."""
        report = self.report()
        short, groups = [], {}
        for name, r in report.items():
            granted, asked, got = r["granted_hz"], r["asked_hz"], r["achieved_hz"]
            expected = granted if granted is not None else asked
            honoured = got >= RATE_HONOURED_FRACTION * expected
            if granted is not None and granted >= asked and honoured:
                continue
            sid = DATA_STREAM_OF.get(name)
            if not honoured and sid is not None and sid not in self._data_stream_sent:
                groups[sid] = max(groups.get(sid, 0), max(1, int(round(expected))))
            short.append(f"{name} asked {asked:g} Hz, " + (f"granted {granted:g} Hz, " if granted is not None
                                                           else f"{r['result']}, ") + f"measured {got:.1f} Hz")
        for sid, hz in groups.items():
            self._data_stream_sent.add(sid)
            self._send(self.mav.request_data_stream_encode(self.fc.system, self.fc.component, sid, hz, 1))
            self.stats.rate_requests_sent += 1
        if not short:
            self.rate_advice = None
            return
        self.rate_advice = self._advice(report, groups)
        self._event("rates_limited", "; ".join(short) + (f" (FC said: \"{self.rate_refusal_text}\")"
                                                         if self.rate_refusal_text else "") + ". " + self.rate_advice,
                    now, items)

    def _advice(self, report: dict, groups: dict) -> str:
        """Which FC parameter to change, in one sentence."""
        refused = [n for n, r in report.items() if (r["granted_hz"] is not None and r["granted_hz"] < r["asked_hz"])
                   or r["result"] in ("denied", "failed")]
        parts = []
        ardupilot = self.fc.autopilot == "ardupilot"
        if refused and ardupilot:
            need = max(report[n]["asked_hz"] for n in refused) / ARDUPILOT_RATE_PER_LOOP
            loop = next((r for r in SCHED_LOOP_RATES_HZ if r >= need), SCHED_LOOP_RATES_HZ[-1])
            parts.append(f"set SCHED_LOOP_RATE >= {loop} on the FC (it refuses a stream faster than about "
                         f"{ARDUPILOT_RATE_PER_LOOP:g} x its loop rate), or lower [mavlink] imu_rate_hz/"
                         "attitude_rate_hz/pressure_rate_hz to what it grants")
        elif refused:
            parts.append("the FC refused the rate: raise its stream limits or lower the [mavlink] rates")
        if groups and ardupilot:
            names = sorted({ARDUPILOT_STREAM_PARAM[s] for s in groups if s in ARDUPILOT_STREAM_PARAM})
            parts.append("streams not delivered at the accepted rate: REQUEST_DATA_STREAM sent; set the port's "
                         + ", ".join(f"MAVn_{p}" for p in names) + " (SRn_ before ArduPilot 4.7) to the rate")
        elif groups:
            parts.append("streams not delivered at the accepted rate: REQUEST_DATA_STREAM sent")
        return "; ".join(parts) if parts else "the FC gives less than asked"

    def check_silent(self, now: float, items: list, connected: bool) -> None:
        """Re-request a requested stream that has gone silent (the FC dropped our interval, e.g.
        after a reboot we did not see). At most every stream_recheck_s, and at most
        _MAX_SILENT_REQUESTS times in a row for a stream that never comes (its count starts again
        once it comes).

        The loop calls this on every wake-up (every datagram): until the earliest time a stream can
        be silent (``_silent_not_before_s``) only the streams with a count are looked at."""
        if (self.cfg.stream_recheck_s <= 0 or not connected or self.requester.active
                or not self.wanted):
            return
        recheck_s, timeout_s = max(self.cfg.stream_recheck_s, self.cfg.link_timeout_s), self.cfg.link_timeout_s
        if self._silent_bound_at_s <= now < self._silent_not_before_s:
            for name in list(self._silent_requests):   # the full walk's reset of a count, for these alone
                if self.stats.rate_results.get(name) in ("denied", "unsupported", "failed") \
                        or now - self._last_request_s.get(name, now) < recheck_s:
                    continue
                seen_s = self._seen_s.get(name)
                if seen_s is not None and now - seen_s <= timeout_s:
                    del self._silent_requests[name]
                    self._silent_not_before_s = -math.inf   # it can go silent again
            return
        silent = []
        for name, msg_id, rate in self.wanted:
            if self.stats.rate_results.get(name) in ("denied", "unsupported", "failed"):
                continue
            if now - self._last_request_s.get(name, now) < recheck_s:
                continue
            seen_s = self._seen_s.get(name)
            if seen_s is not None and now - seen_s <= timeout_s:
                self._silent_requests.pop(name, None)
                continue
            if self._silent_requests.get(name, 0) >= _MAX_SILENT_REQUESTS:
                continue
            self._silent_requests[name] = self._silent_requests.get(name, 0) + 1
            silent.append((name, msg_id, rate))
        # the earliest a stream can be found silent: requests and receive times only move on (a stream
        # with its requests used up waits for its count to reset, above); a bit early is harmless
        bound = math.inf
        for name, _i, _r in self.wanted:
            last_s, seen_s = self._last_request_s.get(name), self._seen_s.get(name)
            if last_s is not None and self._silent_requests.get(name, 0) < _MAX_SILENT_REQUESTS:
                bound = min(bound, max(last_s + recheck_s, seen_s + timeout_s if seen_s is not None else -math.inf))
        self._silent_not_before_s, self._silent_bound_at_s = bound - 1e-6, now
        if silent:
            self.request(now, f"stream(s) silent: {', '.join(n for n, _i, _r in silent)}", items, only=silent)
