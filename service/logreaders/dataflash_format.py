"""ArduPilot DataFlash (.bin) record format: a tolerant record walker.

A .bin file is a sequence of records ``0xA3 0x95 type payload``; record type 128 (FMT) defines the
others (type id, total length, 4-char name, a format string of one char per field, the
comma-separated column names). Every ArduPilot generation uses this; what changes is which
messages exist and their columns (TimeMS vs TimeUS, an instance column ``I`` or IMU2/MAG2...).

The walker never raises on bad bytes: an unknown type or a missing header is skipped byte by byte
to the next header (counted in ``skipped_bytes``); after such a skip a record is believed only when
the next one starts with a header too (or the file ends there); a FMT whose length disagrees with
its format string is ignored (counted); a last record cut short is counted in ``tail_bytes`` (a
truncated log). Field scaling follows the format chars: c/C/e/E are hundredths, L is 1e-7 degrees.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Iterator

HEAD1, HEAD2 = 0xA3, 0x95
FMT_TYPE = 128
_FMT_STRUCT = struct.Struct("<BB4s16s64s")
_FMT_RECORD_BYTES = 3 + _FMT_STRUCT.size  # 89

# format char -> (struct code, scale or None); 'a' (int16[32]) is kept as its 64 raw bytes
_CHARS = {"a": ("64s", None), "b": ("b", None), "B": ("B", None), "h": ("h", None), "H": ("H", None),
          "i": ("i", None), "I": ("I", None), "f": ("f", None), "d": ("d", None), "n": ("4s", None),
          "N": ("16s", None), "Z": ("64s", None), "c": ("h", 0.01), "C": ("H", 0.01), "e": ("i", 0.01),
          "E": ("I", 0.01), "L": ("i", 1e-7), "M": ("B", None), "q": ("q", None), "Q": ("Q", None)}


def _text(b: bytes) -> str:
    return b.split(b"\0", 1)[0].decode("ascii", "replace").strip()


@dataclass(frozen=True)
class Format:
    type_id: int
    name: str
    length: int
    """Whole record, header included (bytes)."""
    columns: tuple[str, ...]
    unpack: object
    scales: tuple
    """(index, scale) of the scaled fields."""
    texts: tuple
    """Indexes of the string fields."""

    def decode(self, data: bytes, pos: int) -> dict:
        vals = list(self.unpack(data, pos + 3))
        for i, k in self.scales:
            vals[i] = vals[i] * k
        for i in self.texts:
            vals[i] = _text(vals[i])
        return dict(zip(self.columns, vals))


def parse_fmt(payload: tuple) -> Format | None:
    """A Format from FMT's fields, or None when they do not agree with each other."""
    type_id, length, name_b, fmt_b, cols_b = payload
    name, fmt, cols = _text(name_b), _text(fmt_b), _text(cols_b)
    columns = tuple(c.strip() for c in cols.split(",")) if cols else ()
    if not name or not fmt or any(c not in _CHARS for c in fmt) or len(columns) != len(fmt):
        return None
    st = struct.Struct("<" + "".join(_CHARS[c][0] for c in fmt))
    if st.size + 3 != length:
        return None
    scales = tuple((i, _CHARS[c][1]) for i, c in enumerate(fmt) if _CHARS[c][1] is not None)
    texts = tuple(i for i, c in enumerate(fmt) if c in "nNZ")
    return Format(type_id, name, length, columns, st.unpack_from, scales, texts)


@dataclass
class WalkStats:
    records: int = 0
    skipped_bytes: int = 0
    """Bytes between records that are no record (damage)."""
    bad_formats: int = 0
    tail_bytes: int = 0
    """Bytes of a last record cut short (a truncated log)."""
    formats: dict = field(default_factory=dict)
    """Type id -> Format, as defined so far."""
    counts: dict = field(default_factory=dict)
    """Record name -> count."""

    def names(self) -> set[str]:
        return {f.name for f in self.formats.values()}


def walk(data: bytes, wanted: set[str], stats: WalkStats | None = None) -> Iterator[tuple[str, dict, int]]:
    """(name, fields, byte offset) of every record whose name is in ``wanted``, in file order."""
    st = stats if stats is not None else WalkStats()
    formats = st.formats
    counts = st.counts
    n = len(data)
    pos = 0
    recovering = False
    find = data.find
    while pos + 3 <= n:
        if data[pos] != HEAD1 or data[pos + 1] != HEAD2:
            nxt = find(b"\xa3\x95", pos + 1)
            nxt = n if nxt < 0 else nxt
            st.skipped_bytes += nxt - pos
            pos, recovering = nxt, True
            continue
        t = data[pos + 2]
        if t == FMT_TYPE:
            if pos + _FMT_RECORD_BYTES > n:
                st.tail_bytes = n - pos
                return
            f = parse_fmt(_FMT_STRUCT.unpack_from(data, pos + 3))
            if f is None or (f.type_id in formats and formats[f.type_id].columns != f.columns) \
                    or f.type_id == FMT_TYPE:
                if f is None or f.type_id != FMT_TYPE:
                    st.bad_formats += 1
            elif f.type_id not in formats:
                formats[f.type_id] = f
            pos += _FMT_RECORD_BYTES
            st.records += 1
            continue
        f = formats.get(t)
        if f is None:  # not a record we can size: damage, resync on the next header
            st.skipped_bytes += 1
            pos, recovering = pos + 1, True
            continue
        end = pos + f.length
        if end > n:
            st.tail_bytes = n - pos
            return
        if recovering and end + 2 <= n and (data[end] != HEAD1 or data[end + 1] != HEAD2):
            st.skipped_bytes += 1  # a header-like byte pair inside damage: not a record
            pos += 1
            continue
        recovering = False
        st.records += 1
        counts[f.name] = counts.get(f.name, 0) + 1
        if f.name in wanted:
            yield f.name, f.decode(data, pos), pos
        pos = end
    st.tail_bytes = n - pos if pos < n else 0
