"""MAVLink 2 frames of the daemon's outputs packed without pymavlink's per-send objects (issue 19).

pymavlink's ``MAVLink.send(msg)`` packs the payload, builds a MAVLink_header object, copies the frame
into a bytearray twice and runs the CRC through an x25crc object: ~29 us per ATTITUDE under load, for
~4 us of work. :func:`send` writes the same bytes (unsigned MAVLink 2: trailing zero bytes of the
payload cut, CRC-16/MCRF4XX over header and payload with the message's CRC_EXTRA, fastcrc) and
advances the sender exactly as ``MAVLink.send`` does (sequence number, packet and byte counts). The
payload's values are read in wire order from the message class's own description
(``ordered_fieldnames``, ``array_lengths``; a char array from its ``_<name>_raw`` bytes, as the
generated ``pack`` does). Anything else (signing, a send callback, a type not in ``FAST_TYPES``,
MAVLink 1) goes through pymavlink unchanged: the same frame, the slow way.
"""
from __future__ import annotations

import operator

from pymavlink.dialects.v20 import ardupilotmega, common as mavlink2

try:
    from fastcrc import crc16 as _crc16
    _mcrf4xx = _crc16.mcrf4xx
except ImportError:  # pragma: no cover - fastcrc is a dependency; without it pymavlink packs
    _mcrf4xx = None


FAST_TYPES = tuple(getattr(mod, f"MAVLink_{name}_message") for mod in (mavlink2, ardupilotmega)
                   for name in ("attitude", "attitude_quaternion", "odometry", "named_value_float"))
"""The daemon's output messages (mavlink_io/outputs.py builds them from common, a receiver's dialect
from ardupilotmega: each generated module has classes of its own)."""


def _reader(cls):
    """The payload's values of a ``cls`` message, in wire order (its generated ``pack``'s arguments)."""
    types = dict(zip(cls.fieldnames, cls.fieldtypes))
    parts = [(f"_{name}_raw", 0) if n and types[name] == "char" else (name, n)
             for name, n in zip(cls.ordered_fieldnames, cls.array_lengths)]
    if not any(n for _a, n in parts):
        return operator.attrgetter(*(a for a, _n in parts))

    def values(msg) -> list:
        out = []
        for attr, n in parts:
            v = getattr(msg, attr)
            if n:
                out += v[:n]   # v[0] .. v[n-1], as pymavlink indexes it (too short: struct.error)
            else:
                out.append(v)
        return out
    return values


class _Kind:
    __slots__ = ("pack", "values", "crc_extra", "msgid")

    def __init__(self, cls):
        self.pack = cls.unpacker.pack
        self.values = _reader(cls)
        self.crc_extra = bytes((cls.crc_extra,))
        self.msgid = cls.id.to_bytes(3, "little")


_KINDS = {cls: _Kind(cls) for cls in FAST_TYPES} if _mcrf4xx is not None else {}
_V1 = {cls: float(mod.WIRE_PROTOCOL_VERSION) != 2.0 for mod in (mavlink2, ardupilotmega) for cls in FAST_TYPES
       if cls.__module__ == mod.__name__}
"""A class whose module packs MAVLink 1 (not with MAVLINK20 set, mavlink_io/__init__.py): pymavlink packs it."""


def frame(msg, seq: int, src_system: int, src_component: int) -> bytes:
    """The unsigned MAVLink 2 frame of ``msg`` (a FAST_TYPES message) as pymavlink packs it:
    0xFD, len, incompat 0, compat 0, seq, sysid, compid, msgid (3 bytes LE), payload, CRC (LE) =
    CRC-16/MCRF4XX(len .. payload, CRC_EXTRA)."""
    k = _KINDS[type(msg)]
    payload = k.pack(*k.values(msg))
    payload = payload.rstrip(b"\0") or payload[:1]   # MAVLink 2 truncation, never below one byte
    body = bytes((len(payload), 0, 0, seq, src_system, src_component)) + k.msgid + payload
    return b"\xfd" + body + _mcrf4xx(body + k.crc_extra, 0xFFFF).to_bytes(2, "little")


def send(mav, msg) -> None:
    """``mav.send(msg)`` (mav: a pymavlink MAVLink object): the frame packed here when it can be, with
    the same effects on ``mav``; raises what packing raises, as ``mav.send`` does."""
    if (type(msg) not in _KINDS or mav.signing.sign_outgoing or mav.send_callback is not None
            or _V1[type(msg)]):
        mav.send(msg)
        return
    buf = frame(msg, mav.seq, mav.srcSystem, mav.srcComponent)
    mav.file.write(buf)
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(buf)
