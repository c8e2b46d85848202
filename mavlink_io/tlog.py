"""Telemetry logs (.tlog, as MAVProxy / Mission Planner / QGroundControl record them) through the
same receive path as a live link.

A tlog is a sequence of records: an 8-byte big-endian timestamp (microseconds since the Unix
epoch, when the frame was received) followed by one raw MAVLink 1 or 2 frame. :func:`read_tlog`
yields ``(t_s, frame_bytes)``; a damaged record is skipped by scanning for the next plausible
timestamp + frame magic (and counted in ``TlogReader.skipped_bytes``).

:func:`replay_tlog` feeds the frames into a :class:`~mavlink_io.link.MavlinkLink` built on a
:class:`~mavlink_io.transport.NullTransport` whose clock is the log's receive time, so the items
are exactly those a live link would have produced (samples, events, stats), with
``time_rx_s`` = the log's receive time in seconds.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

if TYPE_CHECKING:
    from mavlink_io.link import MavlinkLink

_MAGIC_V1 = 0xFE
_MAGIC_V2 = 0xFD
_SIGNED = 0x01
_MAX_CLOCK_JUMP_S = 3 * 24 * 3600.0
"""A timestamp further than this from the previous one means we lost sync (pymavlink uses the same)."""


def _frame_len(buf: bytes, i: int) -> int | None:
    """Length of the MAVLink frame starting at buf[i], or None if it cannot be one."""
    if i + 3 > len(buf):
        return None
    magic, plen = buf[i], buf[i + 1]
    if magic == _MAGIC_V1:
        return 6 + plen + 2
    if magic == _MAGIC_V2:
        flags = buf[i + 2]
        return 10 + plen + 2 + (13 if flags & _SIGNED else 0)
    return None


class TlogReader:
    """Iterate ``(t_s, frame)`` over a tlog's bytes."""

    def __init__(self, data: bytes):
        self.data = data
        self.skipped_bytes = 0
        self.records = 0

    def __iter__(self) -> Iterator[tuple[float, bytes]]:
        buf = self.data
        i = 0
        n = len(buf)
        last_t: float | None = None
        while i + 8 < n:
            t_s = struct.unpack_from(">Q", buf, i)[0] * 1e-6
            flen = _frame_len(buf, i + 8)
            plausible = last_t is None or abs(t_s - last_t) <= _MAX_CLOCK_JUMP_S
            if flen is None or not plausible or i + 8 + flen > n:
                if flen is not None and plausible and i + 8 + flen > n:
                    break  # truncated last record
                i += 1
                self.skipped_bytes += 1
                continue
            yield t_s, buf[i + 8:i + 8 + flen]
            self.records += 1
            last_t = t_s
            i += 8 + flen


def read_tlog(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """Yield ``(receive time s since the epoch, raw frame)`` for each record of a tlog file."""
    return iter(TlogReader(Path(path).read_bytes()))


def replay_tlog(path: str | Path, **link_config) -> tuple[Iterator, "MavlinkLink"]:
    """Run a tlog through a MavlinkLink's receive path.

    link_config: LinkConfig fields (``url`` defaults to a placeholder; ``system_id`` etc. as live).
    Returns ``(items, link)``: an iterator over the items (samples and LinkEvents) in log order,
    and the link (its ``stats`` fill up as the iterator is consumed).
    """
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.transport import NullTransport

    link_config.setdefault("url", "udpin:127.0.0.1:0")  # never opened: NullTransport
    cfg = LinkConfig(**link_config)
    records = read_tlog(path)
    clock_s = [0.0]
    link = MavlinkLink(cfg, clock=lambda: clock_s[0], transport=NullTransport(None))

    def items():
        for t_s, frame in records:
            clock_s[0] = t_s
            yield from link.feed(frame, t_s)
            yield from link.poll(0.0)  # timers: link timeout, retries (sent nowhere)

    return items(), link
