"""Set unsigned RAW_IMU frames apart from a read, CRC-checked, decoded without pymavlink (issue 19 item 3).

:func:`split_raw_imu` walks the bytes of a read frame by frame with pymavlink's own framing rules,
so every byte it does not take goes to pymavlink exactly as pymavlink would have framed it:

- a MAVLink 2 frame (magic 0xFD) is ``len + 12`` bytes, ``+ 13`` with the signed flag; a MAVLink 1
  frame (0xFE) ``len + 8``; a frame is consumed whole whatever its CRC (pymavlink then says
  BAD_DATA);
- bytes that are not a magic byte run, up to the next magic byte, into one "bad prefix" BAD_DATA;
- a frame cut by the end of the read stays with pymavlink (it holds it for the next read).

A frame is taken when it is MAVLink 2, id 27 (RAW_IMU), its incompatibility flags are 0 (unsigned)
and its CRC-16/MCRF4XX over header and payload plus RAW_IMU's CRC_EXTRA matches: the frames pymavlink
would decode into a RAW_IMU message. Everything else (other messages, signed frames, bad CRCs,
garbage) comes back as byte segments, in order, for pymavlink. The CRC is ``fastcrc``'s compiled
MCRF4XX (the one pymavlink's dialects use when it is importable); without ``fastcrc`` the split
is off (:data:`AVAILABLE`) and everything goes through pymavlink.

:func:`split_raw_imu` is the reference: the compiled core has a copy (core/mavlink_frames.hpp,
core/bindings_link.cpp: the same walk, CRC and RawImuFrames; tests/test_link_core.py holds them equal on
recorded flights and a fault corpus). mavlink_io imports nothing above it, so the service hands the core's
to the link (``MavlinkLink(frame_scan=...)``, service/link_core.py).
"""
from __future__ import annotations

import re
from typing import NamedTuple

try:
    from fastcrc.crc16 import mcrf4xx
    AVAILABLE = True
except ImportError:  # pragma: no cover - fastcrc is a dependency; the link falls back to pymavlink
    mcrf4xx = None
    AVAILABLE = False

MAGIC_V2, MAGIC_V1 = 0xFD, 0xFE
IFLAG_SIGNED = 0x01
RAW_IMU_ID = 27
RAW_IMU_CRC_EXTRA = bytes([144])
_HEADER_V2 = 10
_MAGIC_RE = re.compile(b"[\xfd\xfe]")


class RawImuFrame(NamedTuple):
    """One CRC-checked unsigned RAW_IMU frame: its header fields, its payload (as sent: MAVLink 2
    may have cut trailing zero bytes) and the payload's time_usec and id (a cut field's missing bytes
    are zeros)."""
    src_system: int
    src_component: int
    seq: int
    payload: bytes
    time_usec: int
    imu_id: int


def frame_length(header: bytes) -> int | None:
    """Total length of the frame whose first bytes (magic, len, flags: at least 3) are ``header``,
    as pymavlink counts it; None when fewer than 3 bytes are known."""
    if len(header) < 3:
        return None
    if header[0] == MAGIC_V2:
        return header[1] + 12 + (13 if header[2] & IFLAG_SIGNED else 0)
    return header[1] + 8


def _raw_imu_ok(data: bytes, pos: int, plen: int) -> bool:
    end = pos + _HEADER_V2 + plen
    crc = mcrf4xx(RAW_IMU_CRC_EXTRA, mcrf4xx(data[pos + 1:end], 0xFFFF))
    return crc == data[end] | (data[end + 1] << 8)


def split_raw_imu(data: bytes) -> list[bytes | RawImuFrame]:
    """The read ``data`` (pymavlink's parser holding nothing before it) as byte segments for
    pymavlink and RawImuFrames, in the order they came. Segments are never merged across a taken
    frame, so pymavlink reports each bad run on its own, as it would have."""
    out: list[bytes | RawImuFrame] = []
    n = len(data)
    pos = seg = 0
    while pos < n:
        b = data[pos]
        if b != MAGIC_V2 and b != MAGIC_V1:  # bad prefix: up to the next magic byte
            m = _MAGIC_RE.search(data, pos + 1)
            pos = n if m is None else m.start()
            continue
        length = frame_length(data[pos:pos + 3])
        if length is None or pos + length > n:
            break  # cut by the end of the read: pymavlink holds it
        if (b == MAGIC_V2 and data[pos + 2] == 0 and data[pos + 7] == RAW_IMU_ID and data[pos + 8] == 0
                and data[pos + 9] == 0 and _raw_imu_ok(data, pos, data[pos + 1])):
            if seg < pos:
                out.append(data[seg:pos])
            p = data[pos + _HEADER_V2:pos + _HEADER_V2 + data[pos + 1]]
            out.append(RawImuFrame(data[pos + 5], data[pos + 6], data[pos + 4], p,
                                   int.from_bytes(p[:8], "little"), p[26] if len(p) > 26 else 0))
            seg = pos + length
        pos += length
    if seg < n:
        out.append(data[seg:])
    return out
