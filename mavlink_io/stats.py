"""Link statistics: what arrived, how fast, and everything that went wrong (counted, never raised)."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


@dataclass(slots=True)
class RateWindow:
    """Message rate over a sliding window of local receive times.

    rate = (n - 1) / (t_newest - t_oldest) over the arrivals within ``window_s`` of the newest;
    0 when fewer than two arrivals, or when the newest is older than ``window_s`` at ``now_s``.
    """
    window_s: float
    times_s: deque = field(default_factory=deque)

    def add(self, t_s: float) -> None:
        self.times_s.append(t_s)
        self._trim(t_s)

    def _trim(self, now_s: float) -> None:
        lo = now_s - self.window_s
        while self.times_s and self.times_s[0] < lo:
            self.times_s.popleft()

    def rate_hz(self, now_s: float | None = None) -> float:
        if now_s is not None:
            self._trim(now_s)
        n = len(self.times_s)
        if n < 2:
            return 0.0
        span = self.times_s[-1] - self.times_s[0]
        return (n - 1) / span if span > 0 else 0.0


@dataclass(slots=True)
class FcRateWindow:
    """Message rate in the SENDER's clock: rate = (n - 1) / (t_newest - t_oldest) over the FC time
    stamps within ``window_s`` of the newest. A daemon that reads a burst late (the machine busy)
    gives one receive time to many messages; their FC stamps still say how fast the FC sends.
    A stamp that goes back (an FC reboot) starts the window again."""
    window_s: float
    times_s: deque = field(default_factory=deque)

    def add(self, t_fc_s: float) -> None:
        if self.times_s and t_fc_s < self.times_s[-1]:
            self.times_s.clear()
        self.times_s.append(t_fc_s)
        lo = t_fc_s - self.window_s
        while self.times_s and self.times_s[0] < lo:
            self.times_s.popleft()

    def rate_hz(self) -> float:
        n = len(self.times_s)
        span = self.times_s[-1] - self.times_s[0] if n >= 2 else 0.0
        return (n - 1) / span if span > 0 else 0.0


@dataclass(slots=True)
class LinkStats:
    """Counters of one MavlinkLink. ``as_dict()`` gives a JSON-ready copy; ``rates_hz()`` the
    per-message rates: in the FC's clock for messages that carry a time stamp (over the last
    ``rate_window_s`` of FC time, while the stream is alive in local time), else over the last
    ``rate_window_s`` seconds of local receive time."""
    rate_window_s: float = 2.0
    bytes_received: int = 0
    messages_received: int = 0
    """All decoded frames (any source), bad data excluded."""
    messages_by_type: dict[str, int] = field(default_factory=dict)
    """Accepted messages from the autopilot, by type."""
    accepted: int = 0
    crc_errors: int = 0
    framing_errors: int = 0
    """Bytes that are not MAVLink frames (bad magic, bad length, bad flags, signature)."""
    unknown_ids: int = 0
    unknown_id_set: set[int] = field(default_factory=set)
    seq_lost: int = 0
    """Packets lost on the autopilot's stream, from gaps in the MAVLink sequence number."""
    seq_duplicates: int = 0
    seq_reordered: int = 0
    non_finite_rejects: dict[str, int] = field(default_factory=dict)
    """Samples dropped because a required field was NaN/inf, by message type."""
    non_finite_optional: int = 0
    """Optional fields (mag, diff pressure, temperature) that were non-finite and became None."""
    stale_time_drops: int = 0
    """Samples dropped because their FC time did not advance (reordered/duplicated)."""
    own_echoes: int = 0
    foreign_messages: int = 0
    """Messages from other systems/components (GCS, gimbal, other companions): ignored."""
    time_gaps: int = 0
    time_wraps: int = 0
    fc_reboots: int = 0
    input_backlogs: int = 0
    """Samples whose FC time lagged the local clock by over 1 s with the FC clock continuous: a
    stalled sender or a queued read (mavlink_io/timebase.py), not an FC reboot."""
    link_losses: int = 0
    reconnects: int = 0
    transport_errors: int = 0
    parser_errors: int = 0
    """Unexpected exceptions inside the MAVLink parser (the parser is reset, nothing raised)."""
    subscriber_errors: int = 0
    """Exceptions raised by MavlinkLink.subscribe() callbacks (caught; see link.last_error)."""
    messages_sent: int = 0
    send_errors: int = 0
    send_no_peer: int = 0
    """Sends skipped because a listening transport has no peer yet (not an error)."""
    heartbeats_sent: int = 0
    rate_requests_sent: int = 0
    signed_accepted: int = 0
    """Signed frames whose signature and timestamp verified with our key."""
    signature_bad: int = 0
    """Signed frames dropped: signature mismatch (wrong key, altered or forged frame)."""
    signature_replay: int = 0
    """Signed frames dropped: timestamp not after the stream's last (replay), or a new stream more
    than 60 s behind our timestamp."""
    unsigned_rejected: int = 0
    """Unsigned frames dropped by the require_signed policy (all types, commands included)."""
    unsigned_commands_rejected: int = 0
    """Of unsigned_rejected: COMMAND_LONG/COMMAND_INT addressed to us (policy "commands" or "all")."""
    commands_received: int = 0
    """COMMAND_LONG/COMMAND_INT addressed to our component, yielded as IncomingCommand."""
    commands_broadcast_ignored: int = 0
    """Commands with a broadcast target (system or component 0): the FC acts on them, we do not."""
    datagram_resets: int = 0
    """UDP: parser resets at a datagram that starts with a MAVLink magic byte while the parser
    held a partial frame (a damaged frame cannot swallow the next datagram's frames)."""
    udp_split_frames_seen: int = 0
    """UDP: frames completed across datagrams (the sender splits frames, e.g. a serial-to-UDP
    bridge); after the first, per-datagram resets are off for this link until it is reopened."""
    kernel_rx_drops: int | None = None
    """UDP datagrams the kernel dropped because our receive buffer was full (None when the
    transport cannot tell); refreshed about once a second by poll()."""
    rate_results: dict[str, str] = field(default_factory=dict)
    """Last SET_MESSAGE_INTERVAL outcome per message: accepted, denied, unsupported, failed,
    no_ack, data_stream (fallback REQUEST_DATA_STREAM)."""
    _rates: dict[str, RateWindow] = field(default_factory=dict)
    _fc_rates: dict[str, FcRateWindow] = field(default_factory=dict)
    _now_s: float = 0.0

    def count_message(self, msg_type: str, rx_s: float, fc_s: float | None = None) -> None:
        """One accepted message received at local ``rx_s``; ``fc_s`` its FC time stamp (s) if it has one."""
        self.accepted += 1
        self.messages_by_type[msg_type] = self.messages_by_type.get(msg_type, 0) + 1
        w = self._rates.get(msg_type)
        if w is None:
            w = self._rates[msg_type] = RateWindow(self.rate_window_s)
        w.add(rx_s)
        if fc_s is not None and fc_s == fc_s:
            f = self._fc_rates.get(msg_type)
            if f is None:
                f = self._fc_rates[msg_type] = FcRateWindow(self.rate_window_s)
            f.add(fc_s)
        self._now_s = max(self._now_s, rx_s)

    def set_now(self, now_s: float) -> None:
        """Advance the clock the rates are evaluated at (rates decay to 0 when nothing arrives)."""
        self._now_s = max(self._now_s, now_s)

    def rates_hz(self) -> dict[str, float]:
        """Message rates (Hz) by type: the FC-clock rate where the messages carry a stamp, else the
        local one; 0 once nothing has arrived for ``rate_window_s`` of local time."""
        out = {}
        for k, w in self._rates.items():
            local = w.rate_hz(self._now_s)
            f = self._fc_rates.get(k)
            alive = bool(w.times_s) and self._now_s - w.times_s[-1] <= self.rate_window_s
            out[k] = (f.rate_hz() if alive else 0.0) if f is not None and len(f.times_s) >= 2 else local
        return out

    def count_non_finite(self, msg_type: str) -> None:
        self.non_finite_rejects[msg_type] = self.non_finite_rejects.get(msg_type, 0) + 1

    def as_dict(self) -> dict:
        out = {}
        for name in self.__slots__:
            if name.startswith("_"):
                continue
            v = getattr(self, name)
            if isinstance(v, set):
                v = sorted(v)
            elif isinstance(v, dict):
                v = dict(v)
            out[name] = v
        out["rates_hz"] = self.rates_hz()
        out["bad_data"] = self.crc_errors + self.framing_errors
        out["non_finite_rejects_total"] = sum(self.non_finite_rejects.values())
        return out
