"""MAVLink 2 message signing: verification of incoming frames, in the order that resists forgery.

The signing spec (mavlink.io "Message Signing"): a signed MAVLink 2 frame has incompat flag 0x01
and ends with a 13-byte signature block

    link_id (1 byte) | timestamp (6 bytes, little endian, 10 us units since 2015-01-01 00:00 UTC)
    | signature (6 bytes) = SHA-256(secret_key (32 bytes) + header + payload + CRC + link_id
                                    + timestamp)[:6]

A receiver keeps the last timestamp of each stream (link_id, source system, source component) and
rejects a frame whose timestamp is not greater; a stream it has not seen is accepted when its
timestamp is at most 60 s (6 000 000 units) behind the receiver's own current timestamp.

Order (why this module exists): pymavlink's ``MAVLink.check_signature`` stores the stream's
timestamp BEFORE it compares the signature, so one forged frame carrying a far-future timestamp
makes every genuine later frame of that stream look replayed (a denial of service by anyone who
can inject one frame). Here the signature is compared first (constant time, ``hmac.compare_digest``),
then the timestamp rule, and the stream's timestamp is stored only when both pass
(:meth:`SignatureVerifier.verify`). A stream entry is therefore only ever created by a holder of
the key, so the table cannot be flooded either.

Pure: no sockets, no clocks; the caller passes its own current timestamp. Nothing here ever puts
key bytes or signature bytes into a message, an exception or a repr.
"""
from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass, field

IFLAG_SIGNED = 0x01
"""MAVLink 2 incompat flag: the frame carries a signature block."""
SIGNATURE_BLOCK_LEN = 13
SIGNATURE_LEN = 6
KEY_LEN = 32
MAGIC_V2 = 0xFD
EPOCH_2015_UNIX_S = 1_420_070_400
"""2015-01-01 00:00:00 UTC as a Unix time, s."""
TIMESTAMP_UNITS_PER_S = 100_000
"""Signing timestamps count 10 us units."""
NEW_STREAM_MAX_BEHIND = 6_000_000
"""A new stream's timestamp may be at most 60 s (in 10 us units) behind ours."""
TIMESTAMP_MAX = (1 << 48) - 1

REASON_OK = "ok"
REASON_BAD_SIGNATURE = "bad_signature"
REASON_OLD_TIMESTAMP = "old_timestamp"
REASON_STALE_NEW_STREAM = "stale_new_stream"
REASON_MALFORMED = "malformed"
REPLAY_REASONS = (REASON_OLD_TIMESTAMP, REASON_STALE_NEW_STREAM)


def timestamp_from_unix_s(unix_s: float) -> int:
    """Unix time (s) -> signing timestamp (10 us units since 2015-01-01 UTC), clamped to
    [0, 2^48 - 1] (a clock before 2015, e.g. a board without RTC at 1970, gives 0)."""
    ts = int((unix_s - EPOCH_2015_UNIX_S) * TIMESTAMP_UNITS_PER_S)
    return min(max(ts, 0), TIMESTAMP_MAX)


def check_key(key: object, name: str = "signing_key") -> bytes:
    """The key as bytes, or ValueError naming its type/length (never its bytes)."""
    if not isinstance(key, (bytes, bytearray)):
        raise ValueError(f"{name} must be {KEY_LEN} bytes, got {type(key).__name__}")
    if len(key) != KEY_LEN:
        raise ValueError(f"{name} must be exactly {KEY_LEN} bytes, got {len(key)} bytes")
    return bytes(key)


def is_signed_frame(frame: bytes | bytearray) -> bool:
    """True for a MAVLink 2 frame whose incompat flags carry the signed bit."""
    return len(frame) >= 3 and frame[0] == MAGIC_V2 and bool(frame[2] & IFLAG_SIGNED)


def signature(key: bytes, signed_part: bytes | bytearray) -> bytes:
    """The 6-byte signature of ``signed_part`` = header + payload + CRC + link_id + timestamp."""
    return hashlib.sha256(bytes(key) + bytes(signed_part)).digest()[:SIGNATURE_LEN]


def signature_fields(frame: bytes | bytearray) -> tuple[int, int]:
    """(link_id, timestamp) of a signed frame's signature block (no validity check)."""
    block = frame[-SIGNATURE_BLOCK_LEN:]
    return block[0], int.from_bytes(bytes(block[1:7]), "little")


@dataclass(frozen=True, slots=True)
class Verdict:
    """Outcome of :meth:`SignatureVerifier.verify`.

    reason: ``ok``, ``bad_signature`` (HMAC mismatch: wrong key or altered frame),
    ``old_timestamp`` (not after the stream's last: a replay), ``stale_new_stream`` (a new stream
    more than 60 s behind our timestamp), ``malformed`` (too short or not a signed v2 frame)."""
    ok: bool
    reason: str
    link_id: int = 0
    timestamp: int = 0

    @property
    def replay(self) -> bool:
        return self.reason in REPLAY_REASONS


@dataclass(slots=True)
class SignatureVerifier:
    """Per-stream timestamps of signed frames accepted with one key.

    ``verify(frame, src_system, src_component, own_timestamp)`` checks, in this order:
    1. the signature, constant-time (``hmac.compare_digest``);
    2. the timestamp: greater than the stream's last one; or, for a new stream, at most
       NEW_STREAM_MAX_BEHIND behind ``own_timestamp``;
    and only when both pass records the stream's timestamp. A rejected frame changes nothing."""
    key: bytes = field(repr=False, compare=False)
    streams: dict[tuple[int, int, int], int] = field(default_factory=dict)
    """(link_id, src system, src component) -> last accepted timestamp (10 us units)."""

    def __post_init__(self) -> None:
        self.key = check_key(self.key, "SignatureVerifier.key")

    def verify(self, frame: bytes | bytearray, src_system: int, src_component: int,
               own_timestamp: int) -> Verdict:
        if not is_signed_frame(frame) or len(frame) < 10 + 2 + SIGNATURE_BLOCK_LEN:
            return Verdict(False, REASON_MALFORMED)
        link_id, ts = signature_fields(frame)
        expected = signature(self.key, frame[:-SIGNATURE_LEN])
        if not hmac.compare_digest(expected, bytes(frame[-SIGNATURE_LEN:])):
            return Verdict(False, REASON_BAD_SIGNATURE, link_id, ts)
        stream = (link_id, src_system, src_component)
        last = self.streams.get(stream)
        if last is not None:
            if ts <= last:
                return Verdict(False, REASON_OLD_TIMESTAMP, link_id, ts)
        elif ts + NEW_STREAM_MAX_BEHIND < own_timestamp:
            return Verdict(False, REASON_STALE_NEW_STREAM, link_id, ts)
        self.streams[stream] = ts
        return Verdict(True, REASON_OK, link_id, ts)
