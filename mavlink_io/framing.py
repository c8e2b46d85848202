"""Bytes -> pymavlink messages, and lost packets from MAVLink sequence numbers.

:class:`FrameParser` parses what one read returned, with the datagram rules of a UDP link (a
datagram that starts with a magic byte resets a half frame left by the previous one; a sender that
splits frames across datagrams is detected and then parsed as a byte stream). With ``split_imu``
on, CRC-checked unsigned RAW_IMU frames come back as :class:`~mavlink_io.frame_scan.RawImuFrame`
(:mod:`mavlink_io.frame_scan`: the link decodes them itself), everything else as pymavlink messages, in order; a
sender that splits frames keeps the pymavlink-only path. :class:`SeqTracker`
counts sequence gaps as lost packets. Neither ever raises on bad bytes: errors are counted in the
link's :class:`~mavlink_io.stats.LinkStats`.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.frame_scan import AVAILABLE as SPLIT_AVAILABLE
from mavlink_io.frame_scan import RawImuFrame, split_raw_imu
from mavlink_io.stats import LinkStats

MAGIC_BYTES = (0xFD, 0xFE)


class FrameParser:
    """One incoming byte stream. It has its own MAVLink object WITHOUT a key: pymavlink's own
    signature check records a stream's timestamp before comparing the signature (one forged
    far-future frame blocks the genuine stream); incoming signatures are verified by
    mavlink_io.signing instead (mavlink_io.security).

    ``on_split_sender(rx_s, items)`` is called once when a UDP sender is found to split frames;
    ``on_error(text)`` with a parser exception (counted, never raised)."""

    def __init__(self, stats: LinkStats, on_split_sender: Callable[[float, list], None],
                 on_error: Callable[[str], None]):
        self.stats = stats
        self._on_split_sender = on_split_sender
        self._on_error = on_error
        self._rx_mav = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
        self._rx_mav.robust_parsing = True
        self.udp_split_sender = False
        """A datagram transport whose sender splits frames across datagrams: no per-datagram reset."""
        self._split_seen = False
        self.split_imu = False
        """Hand unsigned RAW_IMU frames back as RawImuFrame (the link without a signing key); needs fastcrc."""
        self.scan = split_raw_imu
        """frame_scan.split_raw_imu, or the compiled core's copy (MavlinkLink's ``frame_scan``)."""

    def reset(self) -> None:
        """A new byte stream: drop any half frame of the old one (pymavlink has no reset method)."""
        rx = self._rx_mav
        rx.buf = bytearray()
        rx.buf_index = 0
        rx.expected_length = mavlink2.HEADER_LEN_V1 + 2
        rx.have_prefix_error = False

    def new_stream(self) -> None:
        """The transport was (re)opened: reset, and learn the sender's datagram habits again."""
        self.reset()
        self.udp_split_sender = False

    def parse_chunk(self, data: bytes, datagram: bool, rx_s: float, items: list) -> list:
        """Parse one read. On a datagram transport a datagram normally holds whole frames (ArduPilot,
        PX4, mavlink-router, pymavlink), so a partial frame left by the previous datagram is a
        damaged frame whose length byte lies: if this datagram starts with a magic byte, the parser
        is reset first, so the damaged frame cannot swallow this datagram's intact frames. A sender
        that splits frames across datagrams (a serial-to-UDP bridge: socat, ser2net) shows itself
        when a datagram that does not start with a magic byte completes a held frame that decodes
        (CRC with CRC_EXTRA): from then on this link parses UDP as a byte stream (no resets) until
        the transport is reopened."""
        rx = self._rx_mav
        held = len(rx.buf) - rx.buf_index   # rx.buf_len() without the call
        if not datagram or held == 0:
            return self._parse_split(data, held) if self.split_imu and SPLIT_AVAILABLE else self._parse(data)
        if not self.udp_split_sender and data[:1] and data[0] in MAGIC_BYTES:
            self.reset()
            self.stats.datagram_resets += 1
            return self._parse_split(data, 0) if self.split_imu and SPLIT_AVAILABLE else self._parse(data)
        out = self._parse(data, held=held)
        if self._split_seen and not self.udp_split_sender:
            self.udp_split_sender = True
            self._on_split_sender(rx_s, items)
        return out

    def _parse_split(self, data: bytes, held: int) -> list:
        """``_parse`` with the RAW_IMU frames set apart. A frame the parser holds from the previous
        read (``held`` bytes, a byte stream) is taken back and scanned with this read: pymavlink holds
        nothing but those bytes (always a frame's start: it never holds a bad prefix), so this is the same."""
        if held:
            rx = self._rx_mav
            data = bytes(rx.buf[rx.buf_index:]) + data
            self.reset()
        parts = self.scan(data)
        if len(parts) == 1 and type(parts[0]) is RawImuFrame:
            return parts   # the usual datagram: one RAW_IMU frame
        out = []
        for part in parts:
            if type(part) is RawImuFrame:
                out.append(part)
            else:
                out.extend(self._parse(part))
        return out

    def _parse(self, data: bytes, held: int = 0) -> list:
        """All messages in the parser after adding ``data``. ``held``: bytes the parser held before
        (a partial frame): a frame that decodes and began in them sets ``_split_seen``."""
        out = []
        self._split_seen = False
        rx = self._rx_mav
        total = held + len(data)
        try:
            m = rx.parse_char(data)
            while m is not None:
                out.append(m)
                if held:
                    end = total - rx.buf_len()  # offset after m, counted from the held bytes' start
                    if end - len(getattr(m, "_msgbuf", b"")) < held:
                        mtype = m.get_type()
                        if mtype != "BAD_DATA" and not mtype.startswith("UNKNOWN_"):
                            self.stats.udp_split_frames_seen += 1
                            self._split_seen = True
                    else:
                        held = 0  # past the boundary
                m = rx.parse_char(b"")
        except Exception as exc:  # noqa: BLE001 - the transport never dies on bad bytes
            self.stats.parser_errors += 1
            self._on_error(f"parser: {exc}")
            self.reset()
        return out


class SeqTracker:
    """Lost packets from MAVLink sequence gaps, per source (system, component)."""

    def __init__(self, stats: LinkStats):
        self.stats = stats
        self._seq: dict[tuple[int, int], int] = {}
        self._seq_back: dict[tuple[int, int], int] = {}

    def track(self, src: tuple[int, int], seq: int) -> None:
        """A jump of 1..127 counts as lost packets; a step back is a duplicate or a reordered
        packet (not lost). Three steps back in a row mean the sender restarted its counter (FC
        reboot): resynchronise."""
        last = self._seq.get(src)
        if last is not None:
            diff = (seq - last - 1) % 256
            if diff >= 128:
                self._seq_back[src] = self._seq_back.get(src, 0) + 1
                if self._seq_back[src] < 3:
                    if diff == 255:
                        self.stats.seq_duplicates += 1
                    else:
                        self.stats.seq_reordered += 1
                    return
                diff = 0
            self.stats.seq_lost += diff
        self._seq_back[src] = 0
        self._seq[src] = seq
