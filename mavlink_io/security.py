"""The link's security policy: MAVLink 2 signing in and out, and commands addressed to us.

Incoming, per frame (:meth:`LinkSecurity.admit`): a signed frame is verified by
:mod:`mavlink_io.signing` (signature first, then the timestamp; pymavlink never checks incoming
signatures here: its check lets one forged far-future frame block a stream) and dropped when it
fails; an unsigned frame is dropped by the ``require_signed`` policy ("commands": COMMAND_LONG/INT
addressed to us; "all"; "none"). Drops are counted and reported as ``signature_rejected`` /
``unsigned_command_rejected`` LinkEvents: the first, then at most one per
SECURITY_REPORT_PERIOD_S per kind with the count in between; they name source, message type and
reason, never key or signature bytes.

Commands (:meth:`LinkSecurity.command_in`): COMMAND_LONG/INT addressed exactly to our component,
from any source, become IncomingCommand; broadcast ones are counted, not yielded (the FC acts on them).

Outgoing: the sending MAVLink object signs with pymavlink's own signer; its timestamp starts above
max(signing_timestamp_floor, wall clock), is pulled up to the wall clock by
:meth:`refresh_timestamp` (about once a second) and to the newest verified incoming timestamp (a
board without a real-time clock follows the FC), and never goes back.
"""
from __future__ import annotations

from typing import Callable

from mavlink_io.link_config import LinkConfig
from mavlink_io.samples import IncomingCommand
from mavlink_io.signing import IFLAG_SIGNED, TIMESTAMP_MAX, SignatureVerifier, timestamp_from_unix_s
from mavlink_io.stats import LinkStats

COMMAND_TYPES = ("COMMAND_LONG", "COMMAND_INT")
SECURITY_REPORT_PERIOD_S = 10.0
"""signature_rejected / unsigned_command_rejected: the first one, then at most one per this period
per kind, with the count since the last report (a flood of forged frames is not a log flood)."""


class ReportLimiter:
    """The first report of a kind, then at most one per ``period_s``, carrying the count of the
    ones held back since the previous report; ``due()`` flushes a held-back count once the period
    has passed even if nothing new arrives."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._last_s: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._held_detail: dict[str, str] = {}

    def report(self, kind: str, detail: str, now: float) -> str | None:
        last = self._last_s.get(kind)
        if last is not None and now - last < self.period_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            self._held_detail[kind] = detail
            return None
        self._last_s[kind] = now
        n = self._held.pop(kind, 0)
        self._held_detail.pop(kind, None)
        return detail + (f" ({n} more since the last report)" if n else "")

    def due(self, now: float) -> list[tuple[str, str]]:
        out = []
        for kind, n in list(self._held.items()):
            if now - self._last_s[kind] >= self.period_s:
                out.append((kind, f"{n} more in {now - self._last_s[kind]:.0f} s, the last: "
                                  f"{self._held_detail.pop(kind)}"))
                del self._held[kind]
                self._last_s[kind] = now
        return out


class LinkSecurity:
    """Signing and command admission for one link.

    cfg: the link's settings; mav: the sending pymavlink MAVLink object (its signer and our
    srcSystem); wall_clock: Unix time, s (only for the outgoing signing timestamp);
    event(kind, detail, now, items): how a report reaches the link's output."""

    def __init__(self, cfg: LinkConfig, mav, stats: LinkStats, wall_clock: Callable[[], float],
                 event: Callable[[str, str, float, list | None], None]):
        self.cfg = cfg
        self.mav = mav
        self.stats = stats
        self.wall_clock = wall_clock
        self._event = event
        self.verifier: SignatureVerifier | None = None
        if cfg.signing_key is not None:
            self.verifier = SignatureVerifier(cfg.signing_key)
            sg = mav.signing
            sg.secret_key = bytes(cfg.signing_key)
            sg.link_id = cfg.signing_link_id
            sg.sign_outgoing = cfg.sign_outgoing
            sg.timestamp = max(cfg.signing_timestamp_floor, self._wall_timestamp()) + 1
        self._reports = ReportLimiter(SECURITY_REPORT_PERIOD_S)

    @property
    def timestamp(self) -> int | None:
        """Our current outgoing signing timestamp, None without a key."""
        return self.mav.signing.timestamp if self.verifier is not None else None

    def _wall_timestamp(self) -> int:
        try:
            return timestamp_from_unix_s(float(self.wall_clock()))
        except (TypeError, ValueError, OverflowError):  # a broken wall clock: keep our own count
            return 0

    def refresh_timestamp(self) -> None:
        """Outgoing timestamp = max(current, wall clock): never back (pymavlink adds 1 per frame)."""
        if self.verifier is not None:
            sg = self.mav.signing
            sg.timestamp = min(max(sg.timestamp, self._wall_timestamp()), TIMESTAMP_MAX)

    def reports_due(self, now: float, items: list) -> None:
        """Held-back report counts whose period has passed."""
        for kind, detail in self._reports.due(now):
            self._event(kind, detail, now, items)

    def to_us(self, msg, mtype: str) -> bool:
        """A command whose target is us: our system or broadcast, our component or broadcast."""
        return (mtype in COMMAND_TYPES and msg.target_system in (0, self.mav.srcSystem)
                and msg.target_component in (0, self.cfg.component_id))

    def _report(self, kind: str, detail: str, now: float, items: list) -> None:
        detail = self._reports.report(kind, detail, now)
        if detail is not None:
            self._event(kind, detail, now, items)

    def admit(self, msg, mtype: str, src: tuple[int, int], rx_s: float, items: list) -> bool | None:
        """None: drop the frame (counted, reported); else whether it carried a signature that
        verified with our key. Without a key everything passes as unsigned (False)."""
        if self.verifier is None:
            return False
        header = getattr(msg, "_header", None)
        frame = getattr(msg, "_msgbuf", None)
        if header is not None and frame is not None and header.incompat_flags & IFLAG_SIGNED:
            v = self.verifier.verify(frame, src[0], src[1], self.mav.signing.timestamp)
            if v.ok:
                self.stats.signed_accepted += 1
                # the spec's clock rule: our timestamp is at least the newest valid one seen (a
                # companion without a real-time clock follows the FC's)
                sg = self.mav.signing
                sg.timestamp = max(sg.timestamp, v.timestamp)
                return True
            if v.replay:
                self.stats.signature_replay += 1
                why = ("timestamp not after the last one of its stream (replay)" if v.reason == "old_timestamp"
                       else "new stream more than 60 s behind our timestamp (replay)")
            else:
                self.stats.signature_bad += 1
                why = "signature does not match our key" if v.reason == "bad_signature" else "malformed signature block"
            self._report("signature_rejected", f"{mtype} from system {src[0]} component {src[1]} "
                                               f"(link id {v.link_id}) dropped: {why}", rx_s, items)
            return None
        policy = self.cfg.require_signed
        is_cmd_to_us = self.to_us(msg, mtype)
        if policy == "all" or (policy == "commands" and is_cmd_to_us):
            self.stats.unsigned_rejected += 1
            if is_cmd_to_us:
                self.stats.unsigned_commands_rejected += 1
                self._report("unsigned_command_rejected",
                             f"unsigned {mtype} (command {msg.command}) from system {src[0]} "
                             f"component {src[1]} to {msg.target_system}/{msg.target_component} "
                             f"dropped: require_signed={policy}", rx_s, items)
            return None
        return False

    def command_in(self, msg, mtype: str, src: tuple[int, int], signed: bool, rx_s: float,
                   items: list) -> bool:
        """Yield an IncomingCommand for a command addressed exactly to our component; count a
        broadcast one (the FC acts on it; we must not act twice). True when it was for us."""
        if not self.to_us(msg, mtype):
            return False
        if msg.target_system != self.mav.srcSystem or msg.target_component != self.cfg.component_id:
            self.stats.commands_broadcast_ignored += 1
            return True
        if mtype == "COMMAND_LONG":
            params = tuple(float(getattr(msg, f"param{i}")) for i in range(1, 8))
            frame, confirmation, is_int = None, int(msg.confirmation), False
        else:
            params = (*(float(getattr(msg, f"param{i}")) for i in range(1, 5)), int(msg.x), int(msg.y), float(msg.z))
            frame, confirmation, is_int = int(msg.frame), 0, True
        self.stats.commands_received += 1
        items.append(IncomingCommand(time_rx_s=rx_s, command=int(msg.command), params=params, is_int=is_int,
                                     frame=frame, confirmation=confirmation, source_system=src[0],
                                     source_component=src[1], target_system=int(msg.target_system),
                                     target_component=int(msg.target_component), signed=signed))
        return True
